"""Perspective rendering from equirectangular panoramas (the mapping of docs/TASK.md)."""

from findview.sim.bank import PanoramaBank
from findview.sim.equi2pers import MODES, camera_rays, equi2pers, pitch_grid
from findview.sim.simulator import Simulator, resolve_device

__all__ = ["equi2pers", "camera_rays", "pitch_grid", "MODES", "PanoramaBank", "Simulator", "resolve_device"]
