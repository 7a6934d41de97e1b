"""Typed all the way: library code reads its settings as attributes of the validated schema objects, never
by key with a default of its own; one list of policy variants; the config files state no schema default.

- ``test_library_reads_no_config_key_by_string``: an AST scan of ``findview/`` and ``findview_baselines/``
  for ``<config>.get("<key>"...)``, ``getattr(<config>, "<key>", default)``, ``section_get(...)``,
  ``OmegaConf.select(...)`` and ``_get(<config>, ...)``, where ``<config>`` is a name that holds a config
  (``cfg``, ``conf``, ``config``, ``section``, ``agent``, ``trainer``, ``sim``, ``task``, ``dataset``,
  ``corruption`` or ``*_cfg`` / ``*_conf`` / ``*_config``, also as the last attribute: ``self.config``).
  :data:`ALLOWED` names the few places that read *data* by key (a checkpoint's stored run config, the
  config file of a finished run folder), each with its reason.
- ``test_one_list_of_policy_variants``: the schema checks ``agent.variant`` against ``rl/policy.VARIANTS``.
- ``test_config_files_state_no_schema_default``: a value in a group file (agent, trainer, sim, task,
  corruption, dataset) equal to its schema default is a second statement of that default; the schemas in
  findview/config.py and findview_baselines/config.py are the one place defaults live.
"""

from __future__ import annotations

import ast
from pathlib import Path
from typing import Any, Iterator

import pytest

REPO = Path(__file__).resolve().parents[1]
LIBRARY = ("findview", "findview_baselines")

CONFIG_NAMES = {"cfg", "conf", "config", "section", "agent", "trainer", "sim", "task", "dataset", "corruption"}
CONFIG_SUFFIXES = ("_cfg", "_conf", "_config")

#: (file, enclosing function, receiver name) -> why reading by key is right there
ALLOWED: dict[tuple[str, str, str], str] = {
    ("findview_baselines/evaluation/run_info.py", "_checkpoint_info", "conf"):
        "the run config a checkpoint stores (a plain dict written by any earlier version, maybe without the key)",
    ("findview_baselines/evaluation/run_info.py", "_checkpoint_info", "trainer"):
        "the trainer section of that stored run config",
    ("findview_baselines/evaluation/run_info.py", "run_settings", "config"):
        "the resolved config YAML of a finished run folder (data on disk, any earlier version)",
    ("findview_baselines/evaluation/run_info.py", "run_settings", "agent"):
        "the agent section of that run-folder YAML (a plain dict)",
    ("findview_baselines/agents/ppo_agent.py", "from_checkpoint", "run_conf"):
        "the run config a checkpoint stores: its memory setting and FoV when the caller gives none (absent in "
        "checkpoints made outside a run)",
    ("findview_baselines/evaluation/evaluate.py", "apply_checkpoint_config", "run_conf"):
        "the run config a checkpoint stores (sim, agent sections; absent in checkpoints made outside a run)",
    ("findview_baselines/evaluation/harness.py", "run_episodes", "agent"):
        "the agent object (not a config): its display name, which a bare Agent subclass may lack",
    ("findview_baselines/evaluation/collect.py", "learned", "config"):
        "collect_results reads the config YAML of finished run folders (data on disk, any earlier version)",
    ("findview_baselines/evaluation/collect.py", "title", "config"):
        "as above: a run folder's config YAML",
    ("findview_baselines/evaluation/collect.py", "title", "agent_cfg"):
        "as above: the agent section of a run folder's config YAML",
    ("findview_baselines/evaluation/collect.py", "corruption_of", "cfg"):
        "as above: a run folder's config YAML",
    ("findview_baselines/evaluation/collect.py", "find_runs", "cfg"):
        "as above: a run folder's config YAML",
    ("findview_baselines/evaluation/collect.py", "find_runs", "agent_cfg"):
        "as above: its agent section",
    ("findview_baselines/evaluation/collect.py", "find_runs", "dataset_cfg"):
        "as above: its dataset section",
    ("findview_baselines/training/resume.py", "rank_trainer_state", "trainer"):
        "the trainer state stored in a resume checkpoint (world_size absent in single-process checkpoints)",
}


def _holds_config(name: str) -> bool:
    return name in CONFIG_NAMES or name.endswith(CONFIG_SUFFIXES)


def _name_of(node: ast.AST) -> str | None:
    """``cfg`` for ``cfg``, ``config`` for ``self.config`` (the last name of a receiver), else None."""
    if isinstance(node, ast.Name):
        return node.id
    if isinstance(node, ast.Attribute):
        return node.attr
    return None


def _is_literal(node: ast.AST) -> bool:
    return isinstance(node, ast.Constant) and isinstance(node.value, str)


class _Scan(ast.NodeVisitor):
    """Collects ``(function, receiver, line, what)`` for every read of a config key by string."""

    def __init__(self) -> None:
        self.stack: list[str] = ["<module>"]
        self.hits: list[tuple[str, str, int, str]] = []

    def _scoped(self, node: ast.AST) -> None:
        self.stack.append(node.name)  # type: ignore[attr-defined]
        self.generic_visit(node)
        self.stack.pop()

    visit_FunctionDef = visit_AsyncFunctionDef = visit_ClassDef = _scoped

    def _hit(self, node: ast.AST, receiver: str, what: str) -> None:
        scope = next((s for s in reversed(self.stack) if not s[:1].isupper()), self.stack[-1])
        self.hits.append((scope, receiver, node.lineno, what))  # type: ignore[attr-defined]

    def visit_Attribute(self, node: ast.Attribute) -> None:
        receiver = _name_of(node.value)
        if node.attr == "get" and receiver is not None and _holds_config(receiver):
            self._hit(node, receiver, f"{receiver}.get")  # called with a key, or aliased (get = cfg.get)
        self.generic_visit(node)

    def visit_Call(self, node: ast.Call) -> None:
        func = node.func
        fname = _name_of(func)
        first = node.args[0] if node.args else None
        if fname == "section_get":
            self._hit(node, "section_get", "section_get(...)")
        elif fname == "select" and isinstance(func, ast.Attribute) and _name_of(func.value) == "OmegaConf":
            self._hit(node, "OmegaConf", "OmegaConf.select(...)")
        elif fname == "_get" and first is not None and _name_of(first) and _holds_config(_name_of(first)):
            self._hit(node, _name_of(first), "_get(<config>, ...)")
        elif (fname == "getattr" and isinstance(func, ast.Name) and len(node.args) == 3 and first is not None
              and _name_of(first) and _holds_config(_name_of(first)) and _is_literal(node.args[1])):
            self._hit(node, _name_of(first), f"getattr(<config>, {node.args[1].value!r}, default)")
        self.generic_visit(node)


def _library_files() -> Iterator[Path]:
    for package in LIBRARY:
        yield from sorted((REPO / package).rglob("*.py"))


def scan(path: Path) -> list[tuple[str, str, int, str]]:
    """The config reads by string in one file: ``(function, receiver, line, what)``."""
    visitor = _Scan()
    visitor.visit(ast.parse(path.read_text(), str(path)))
    return visitor.hits


def test_the_scan_finds_reads_by_string() -> None:
    code = (
        "def f(cfg, self, agent_cfg):\n"
        "    a = cfg.get('fov', 90)\n"
        "    b = section_get(cfg, 'x', 1)\n"
        "    c = OmegaConf.select(cfg, 'sim.fov')\n"
        "    d = _get(cfg, 'sim.fov', 90)\n"
        "    e = self.config.get('agent')\n"
        "    g = agent_cfg.get\n"
        "    h = getattr(cfg, 'fov', 90)\n"
        "    ok = state.get('rng'), header.get('fov'), cfg.sim.fov\n"
    )
    visitor = _Scan()
    visitor.visit(ast.parse(code))
    assert [line for _, _, line, _ in visitor.hits] == [2, 3, 4, 5, 6, 7, 8]


def test_library_reads_no_config_key_by_string() -> None:
    found, used = [], set()
    for path in _library_files():
        rel = path.relative_to(REPO).as_posix()
        for scope, receiver, line, what in scan(path):
            key = (rel, scope, receiver)
            if key in ALLOWED:
                used.add(key)
                continue
            found.append(f"{rel}:{line} ({scope}): {what}")
    assert not found, (
        "library code reads config keys by string (read the typed section's attributes instead; the schemas "
        "hold the defaults), or add a reasoned entry to ALLOWED for data read by key:\n  " + "\n  ".join(found)
    )
    stale = sorted(set(ALLOWED) - used)
    assert not stale, f"ALLOWED entries that match nothing any more (remove them): {stale}"


def test_one_list_of_policy_variants() -> None:
    from findview_baselines import config
    from findview_baselines.config import ConfigError, PPOAgentConfig
    from findview_baselines.rl import policy

    assert config.POLICY_VARIANTS is policy.VARIANTS
    for variant in policy.VARIANTS:
        kw: dict[str, Any] = {"fine_shifts": 1} if variant in policy.FINE_VARIANTS else {}
        assert PPOAgentConfig(variant=variant, **kw).variant == variant
    with pytest.raises(ConfigError, match="agent.variant"):
        PPOAgentConfig(variant="no_such_variant")


# ---- the config files state no schema default ------------------------------------------------------------

#: keys that select the schema or the option rather than set a value (allowed to equal the default)
SELECTORS = {"name", "kind", "algorithm"}
GROUPS = ("agent", "trainer", "sim", "task", "corruption", "dataset")
#: files not checked yet, each with its reason
PENDING: dict[str, str] = {}


def _schemas() -> dict[str, type]:
    from findview.config import CorruptionConfig, DatasetConfig, SimConfig, TaskConfig
    from findview_baselines import config as c

    return {
        "base_sim": SimConfig, "base_task": TaskConfig, "base_dataset": DatasetConfig,
        "base_corruption": CorruptionConfig, "base_trainer": c.TrainerConfig, "base_random": c.RandomAgentConfig,
        "base_oracle": c.OracleAgentConfig, "base_feature": c.FeatureAgentConfig,
        "base_rotation": c.RotationAgentConfig, "base_ppo": c.PPOAgentConfig,
    }


def _schema_of(path: Path) -> type:
    """The schema a group file names, directly (``/base_<x>@_here_``) or through a sibling it extends."""
    from omegaconf import OmegaConf

    for entry in OmegaConf.to_container(OmegaConf.load(path)).get("defaults", []):
        if isinstance(entry, str) and entry != "_self_":
            base = entry.split("@", 1)[0].lstrip("/")
            return _schemas()[base] if base.startswith("base_") else _schema_of(path.parent / f"{base}.yaml")
    raise AssertionError(f"{path} names no schema in its defaults list")


def _leaves(node: Any, prefix: str = "") -> Iterator[tuple[str, Any]]:
    if isinstance(node, dict) and node and prefix != "d_thresh":
        for k, v in node.items():
            yield from _leaves(v, f"{prefix}.{k}" if prefix else str(k))
    else:
        yield prefix, node


def _default_at(defaults: dict, key: str) -> Any:
    node: Any = defaults
    for part in key.split("."):
        if not isinstance(node, dict) or part not in node:
            return KeyError
        node = node[part]
    return node


@pytest.mark.parametrize("group", GROUPS)
def test_config_files_state_no_schema_default(group: str) -> None:
    from omegaconf import OmegaConf

    restated = []
    for path in sorted((REPO / "configs" / group).glob("*.yaml")):
        if path.relative_to(REPO).as_posix() in PENDING:
            continue
        schema = _schema_of(path)
        defaults = OmegaConf.to_container(OmegaConf.structured(schema), resolve=False)
        raw = OmegaConf.to_container(OmegaConf.load(path), resolve=False)
        raw.pop("defaults", None)
        for key, value in _leaves(raw):
            if key.split(".")[-1] in SELECTORS:
                continue
            default = _default_at(defaults, key)
            if default is not KeyError and value == default:
                restated.append(f"configs/{group}/{path.name}: {key}: {value!r} (the {schema.__name__} default)")
    assert not restated, "values equal to the schema default (delete them; the schema documents them):\n  " + \
        "\n  ".join(restated)
