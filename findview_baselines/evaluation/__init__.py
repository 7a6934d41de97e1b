"""Evaluation of agents on static FindView episodes: the harness (:func:`run_episodes`), one run's result
files (``results``), its agent title and non-default settings (``run_info``), the threshold-search and
corruption tables of a multirun (``collect``) and episode pictures / videos (``viz``, imported on demand)."""

from findview_baselines.evaluation.harness import Runtime, TraceRecorder, TrajectoryRecorder, run_episodes

__all__ = ["Runtime", "TraceRecorder", "TrajectoryRecorder", "run_episodes"]
