"""Moved to :mod:`findview_baselines.rl.search_memory` (the learned agents' search memory); re-exported here."""

from findview_baselines.rl.search_memory import SEARCH_KEYS, RevisitPenalty, make_revisit_penalty, search_settings

__all__ = ["RevisitPenalty", "SEARCH_KEYS", "search_settings", "make_revisit_penalty"]
