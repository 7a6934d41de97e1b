"""findview: the FindView look-around task (Ishikawa & Aoki, 2022) as a batched, device-agnostic framework.

Core modules (never import ``findview_baselines``):

- :mod:`findview.sim`      perspective rendering from equirectangular panoramas, panorama bank
- :mod:`findview.task`     the batched FindView environment, rewards, a Gymnasium-style wrapper
- :mod:`findview.dataset`  panorama discovery, splits, difficulties, static episodes, synthetic scenes
- :mod:`findview.metrics`  per-episode records and the paper's aggregate metrics
"""

__version__ = "0.1.0"
