"""The five FindView actions."""

from __future__ import annotations

from enum import IntEnum


class Action(IntEnum):
    """Action ids. Moves change pitch or yaw by ``step_deg`` (1 degree); ``STOP`` ends the episode."""

    UP = 0  # pitch + 1 (look up)
    DOWN = 1  # pitch - 1
    LEFT = 2  # yaw - 1 (pan left)
    RIGHT = 3  # yaw + 1 (pan right)
    STOP = 4


NUM_ACTIONS = len(Action)
ACTION_NAMES = tuple(a.name.lower() for a in Action)
