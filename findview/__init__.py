"""findview: the FindView look-around task (Ishikawa & Aoki, 2022) as a batched, device-agnostic framework.

Core modules (never import ``findview_baselines``):

- :mod:`findview.sim`      perspective rendering from equirectangular panoramas, panorama bank
- :mod:`findview.task`     the batched FindView environment, rewards, a Gymnasium-style wrapper
- :mod:`findview.dataset`  panorama discovery, splits, difficulties, static episodes, synthetic scenes
- :mod:`findview.metrics`  per-episode records and the paper's aggregate metrics
- :mod:`findview.runtime`  the CPU thread policy (:func:`findview.runtime.configure_threads`)

Importing findview sets ``OMP_WAIT_POLICY=PASSIVE`` (unless already set) while torch is not loaded yet,
so that torch's OpenMP threads sleep instead of spin-waiting on a busy CPU (see :mod:`findview.runtime`).
"""

from findview.runtime import set_wait_policy as _set_wait_policy

_set_wait_policy()  # before anything imports torch

__version__ = "0.1.0"
