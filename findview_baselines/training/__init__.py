"""The training layer: a run of a learned agent (build, resume, seeding, ranks, the loop and its callbacks),
above the algorithms (``rl``), the agents and the evaluation harness it validates with.

- :mod:`.run`: :func:`train` (what ``tools/train.py`` calls) and :class:`TrainResult`;
- :mod:`.build`: data, environments, policy and trainer from the typed config;
- :mod:`.resume`: ``latest.pth`` -> this rank's trainer state;
- :mod:`.loop`: :func:`learn`, :class:`RunContext`, :class:`Callback`;
- :mod:`.callbacks`: progress bar, TensorBoard (:func:`tb_tag`), validation + ``best.pth``, ``latest.pth``,
  the corruption-severity ramp.
"""

from findview_baselines.training.build import select_val_episodes, seed_everything
from findview_baselines.training.callbacks import tb_tag
from findview_baselines.training.loop import Callback, RunContext, TrainingDiverged, learn
from findview_baselines.training.run import TrainResult, train

__all__ = ["train", "TrainResult", "TrainingDiverged", "learn", "Callback", "RunContext", "tb_tag",
           "select_val_episodes", "seed_everything"]
