"""Evaluation of agents on static FindView episodes: the harness (:func:`run_episodes`), result files,
threshold-search tables and episode pictures / videos (``viz``, imported on demand)."""

from findview_baselines.evaluation.harness import Runtime, TrajectoryRecorder, run_episodes

__all__ = ["Runtime", "TrajectoryRecorder", "run_episodes"]
