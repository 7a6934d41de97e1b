"""findview baselines: agents (rule-based, oracle, learned), training (PPO, DAgger), evaluation."""

import findview  # noqa: F401  (first: the CPU thread policy must be set before torch loads)
