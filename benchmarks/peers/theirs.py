"""One row of ``benchmarks/bench_peers.py`` on the authors' code (look_around: LookAround + findview_baselines).

    ../la_venv/bin/python benchmarks/peers/theirs.py --look-around ../look_around --row orb --panoramas DIR

Prints one JSON line ``{"row", "value", "unit", ...}``. Runs with an interpreter that has look_around's
requirements; reads only local files (no network). A venv that reuses the installed torch (never
``pip install torch`` into it: another torch pulls the CUDA wheels)::

    python -m venv --system-site-packages ../la_venv
    ../la_venv/bin/pip install --no-deps mmengine pyequilib==0.5.8   # mmengine's deps would add opencv-python
    ../la_venv/bin/pip install addict termcolor yapf rich imageio numba scikit-image "numpy==<the installed one>"

(gymnasium, scipy, attrs, tqdm, tensorboard, Pillow come from the system site-packages here; install them
too where they do not.) Each row uses the authors' classes the way their own scripts do:

- ``orb`` / ``sift``: ``FindViewEnv.from_config`` (static episodes, ``np.float32`` views: their
  ``benchmarks/orb.py`` / ``sift.py`` configs) + ``FeatureMatchingAgent.from_config``, the loop of
  ``FindViewBenchmark.evaluate`` without its video writing: ``agent.act`` + ``env.step`` per decision
  (``env.reset`` + ``agent.reset`` when an episode ends), decisions/s.
- ``ppo``: their ``PPOTrainer`` (``_init_rlenvs`` -> ``construct_envs``: 16 ``InverseFindViewRLEnv`` in their
  default ``ThreadedVecEnv``, ``torch.float32`` views; ``_setup_actor_critic_agent``: ``FindViewBaselinePolicy``
  = ``FindViewBaselineNet``, a 6-channel SimpleCNN on view + target and a separate SimpleCNN goal encoder
  on the target, GRU 512; ``PPO``, ``RolloutStorage``), one update = ``num_steps`` x ``_collect_rollout_step``
  + ``_update_agent`` (+ the lr / clip decay and episode stats of ``train``; no TensorBoard, validation or
  checkpoints), env steps/s over ``--updates`` updates after one warm-up update.
- ``env16``: ``construct_envs`` (16 RL envs, ThreadedVecEnv) + random moves, env steps/s.
- ``env1``: one RL env from their ``make_rl_env_fn`` stepped directly, random moves, env steps/s.
- ``reset16``: seconds for ``construct_envs`` (16 RL envs) + the first ``envs.reset()`` (the config file is
  parsed before the clock starts).

Substitutions, each reported in the JSON line:

- look_around's HEAD (merge 03f569e of cde50b4 "update", 2025-10-17) holds a half-done refactor:
  ``findview_baselines`` imports ``findview_baselines.rl.models.base_policy``, which does not exist, so
  neither the trainer nor the agents package imports. When the checkout has no ``findview_baselines/rl/ppo/``,
  ``findview_baselines/`` and ``configs/`` are taken from ``--baselines-rev`` (default ``ad2abbb``, the
  merge's other parent, 2023-09-18: the code from before the refactor) with ``git archive`` into a
  temporary folder; ``LookAround/`` (simulator, envs, vec env) is the checkout's own (byte-identical at both
  commits, as are ``agents/feature_matching.py`` and ``common/``).
- ``findview_baselines/agents/__init__.py`` imports ``agents/ppo.py``, whose default argument
  ``torch.device(0)`` raises on a torch without an accelerator: ``feature_matching.py`` is loaded from
  its file, without the package ``__init__``.
- ``LookAround/core/improc.py`` imports ``torchvision.transforms`` (``ToTensor`` for the float loader).
  PyPI's torchvision wheel needs CUDA torch; when ``import torchvision`` fails, an in-process stand-in with
  torchvision's ``ToTensor`` arithmetic (uint8 HWC -> float CHW / 255) is used.
- Data: their dataset JSON files (pseudo-episodes for ``train``, episodes for ``test``) are written to a
  temporary folder from ``--panoramas``; the config's ``data_root`` / ``dataset_root`` point there.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import subprocess
import sys
import tempfile
import time
import types
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from peerlib import (  # noqa: E402
    AGENT_MAX_STEPS,
    FOV,
    VIEW,
    PeerError,
    Timer,
    emit,
    episode_tuples,
    panorama_files,
    rate,
    shortest_steps,
    thread_env,
)

DEFAULT_BASELINES_REV = "ad2abbb"  # HEAD's other parent (2023-09-18): findview_baselines before the 2025 refactor
TRAIN_CONFIG = "configs/findview/sun360/alpha/indoor/training/inverse_1.py"
AGENT_CONFIG = "configs/findview/sun360/alpha/indoor/benchmarks/{name}.py"


# ------------------------------------------------------------------------------------------------- setup
def check_checkout(path: str) -> Path:
    la = Path(path).expanduser().resolve()
    if not (la / "LookAround" / "FindView" / "sim.py").is_file() or not (la / "findview_baselines").is_dir():
        raise PeerError(f"--look-around {la}: not a look_around checkout (no LookAround/FindView/sim.py "
                        "or findview_baselines/ there; git clone the authors' repository)")
    return la


def git_rev(la: Path, rev: str = "HEAD") -> str | None:
    try:
        out = subprocess.run(["git", "-C", str(la), "rev-parse", "--short", rev], capture_output=True, text=True)
    except OSError:
        return None
    return out.stdout.strip() if out.returncode == 0 else None


def baselines_source(la: Path, rev: str, tmp: Path) -> tuple[Path, str]:
    """The folder holding the ``findview_baselines/`` and ``configs/`` to run, and a description of it."""
    if (la / "findview_baselines" / "rl" / "ppo" / "policy.py").is_file():
        return la, f"checkout ({git_rev(la) or 'no git'})"
    dest = tmp / "baselines"
    dest.mkdir()
    cmd = ["git", "-C", str(la), "archive", "--format=tar", rev, "findview_baselines", "configs"]
    try:
        archive = subprocess.run(cmd, capture_output=True)
    except OSError as e:
        raise PeerError(f"--look-around {la}: its findview_baselines does not import (no rl/ppo/) and git is "
                        f"not available to take it from commit {rev}: {e}") from None
    if archive.returncode != 0:
        raise PeerError(f"--look-around {la}: its findview_baselines does not import (no rl/ppo/) and "
                        f"'git archive {rev}' failed: {archive.stderr.decode(errors='replace').strip()} "
                        "(pass a full clone, or --baselines-rev)")
    subprocess.run(["tar", "-x", "-C", str(dest)], input=archive.stdout, check=True)
    return dest, f"git archive {git_rev(la, rev) or rev} (checkout at {git_rev(la) or '?'})"


def ensure_torchvision() -> str:
    """``torchvision.transforms`` for ``LookAround.core.improc``: the real one, else a stand-in (see docstring)."""
    try:
        import torchvision.transforms  # noqa: F401
        import torchvision

        return torchvision.__version__
    except Exception as e:  # not installed, or a wheel built for CUDA torch (RuntimeError / OSError)
        reason = f"{type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}"
    for name in [m for m in sys.modules if m == "torchvision" or m.startswith("torchvision.")]:
        del sys.modules[name]
    import numpy as np
    import torch

    class Compose:
        def __init__(self, transforms):
            self.transforms = transforms

        def __call__(self, img):
            for t in self.transforms:
                img = t(img)
            return img

    class ToTensor:  # torchvision.transforms.functional.to_tensor for PIL images (uint8 modes)
        def __call__(self, pic):
            img = torch.from_numpy(np.array(pic, np.uint8, copy=True))
            img = img.view(pic.size[1], pic.size[0], len(pic.getbands())).permute((2, 0, 1)).contiguous()
            return img.to(dtype=torch.get_default_dtype()).div(255)

    class ToPILImage:  # used by no row
        def __call__(self, pic):
            raise NotImplementedError("torchvision stand-in: ToPILImage")

    tv = types.ModuleType("torchvision")
    tr = types.ModuleType("torchvision.transforms")
    tr.Compose, tr.ToTensor, tr.ToPILImage = Compose, ToTensor, ToPILImage
    tv.transforms = tr
    tv.__version__ = "stand-in"
    sys.modules["torchvision"] = tv
    sys.modules["torchvision.transforms"] = tr
    return f"stand-in ToTensor ({reason})"


def load_feature_matching(src: Path):
    """``findview_baselines/agents/feature_matching.py`` without ``agents/__init__.py`` (see docstring)."""
    path = src / "findview_baselines" / "agents" / "feature_matching.py"
    spec = importlib.util.spec_from_file_location("findview_baselines.agents.feature_matching", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def write_dataset(tmp: Path, files: list[str], panoramas: Path, n_episodes: int) -> tuple[Path, Path]:
    """Their dataset layout under ``tmp``: ``data/sun360/`` (the data_dir they check) and
    ``dataset/sun360/alpha/indoor/{train,test}.json`` (absolute image paths). Returns (data_root, dataset_root)."""
    data_root, dataset_root = tmp / "data", tmp / "dataset"
    (data_root / "sun360").mkdir(parents=True)
    split_dir = dataset_root / "sun360" / "alpha" / "indoor"
    split_dir.mkdir(parents=True)

    def names(path: str) -> dict:
        p = Path(path)
        rel = p.relative_to(panoramas) if p.is_relative_to(panoramas) else Path(p.name)
        parts = rel.parent.parts
        return {
            "img_name": rel.with_suffix("").as_posix().replace("/", "_"),
            "path": path,
            "label": parts[0] if parts else "indoor",
            "sub_label": parts[-1] if parts else "none",
        }

    (split_dir / "train.json").write_text(json.dumps([names(f) for f in files]))
    eps = []
    for i, (img, ip, iy, tp, ty) in enumerate(episode_tuples(files, n_episodes)):
        eps.append({
            "episode_id": i,
            **names(img),
            "initial_rotation": {"roll": 0, "pitch": ip, "yaw": iy},
            "target_rotation": {"roll": 0, "pitch": tp, "yaw": ty},
            "difficulty": "easy",
            "steps_for_shortest_path": shortest_steps(ip, iy, tp, ty),
        })
    (split_dir / "test.json").write_text(json.dumps(eps))
    return data_root, dataset_root


def load_config(src: Path, rel: str, data_root: Path, dataset_root: Path, args):
    from mmengine import Config

    cfg = Config.fromfile(str(src / rel))
    cfg.data_root = str(data_root)
    cfg.dataset_root = str(dataset_root)
    cfg.sim.height = cfg.sim.width = VIEW
    cfg.sim.fov = FOV
    cfg.dataset.fov = FOV
    cfg.episode_iterator_kwargs.cycle = True  # static episodes: never run out
    if "trainer" in cfg:
        cfg.trainer.num_envs = 16
        if args.vec_type:
            cfg.trainer.vec_type = args.vec_type
    if "ppo" in cfg:
        cfg.ppo.num_steps = args.rollout_steps
        cfg.ppo.ppo_epoch = 4
        cfg.ppo.num_mini_batch = 1
    return cfg


# -------------------------------------------------------------------------------------------------- rows
def row_agent(name: str, ctx: dict, args) -> dict:
    import numpy as np
    import torch

    from LookAround.FindView.env import FindViewEnv

    cfg = load_config(ctx["src"], AGENT_CONFIG.format(name=name), ctx["data_root"], ctx["dataset_root"], args)
    cfg.dataset.max_steps = AGENT_MAX_STEPS
    assert cfg.benchmark.dtype == "np.float32", cfg.benchmark.dtype  # their orb / sift benchmark configs
    fm = load_feature_matching(ctx["src"])
    env = FindViewEnv.from_config(cfg=cfg, split="test", dtype=np.float32, device=torch.device("cpu"))
    agent = fm.FeatureMatchingAgent.from_config(cfg)
    _after_build(args)
    state = {"obs": None, "episodes": 0}

    def play(n: int) -> None:
        obs = state["obs"]
        for _ in range(n):
            if obs is None or env.episode_over:
                obs = env.reset()
                agent.reset()
                state["episodes"] += 1
            action = agent.act(obs)
            obs = env.step(action)
        state["obs"] = obs

    play(args.warmup_decisions)
    with Timer() as t:
        play(args.decisions)
    env.close()
    return {"value": rate(args.decisions, t.s), "seconds": t.s, "decisions": args.decisions,
            "episodes_started": state["episodes"], "classes": "FindViewEnv(np.float32) + FeatureMatchingAgent",
            "cv2_threads": _cv2_threads(), "torch_threads": torch.get_num_threads()}


def _after_build(args) -> None:
    """``--torch-threads``: override the torch thread count their env factories set (see the option)."""
    if args.torch_threads:
        import torch

        torch.set_num_threads(args.torch_threads)


def _cv2_threads() -> int:
    import cv2

    return cv2.getNumThreads()


def _vec_envs(cfg):
    import torch

    from LookAround.FindView.vec_env import construct_envs

    return construct_envs(cfg, split="train", is_rlenv=True, dtype=torch.float32, device=torch.device("cpu"),
                          vec_type=cfg.trainer.vec_type)


def row_reset16(ctx: dict, args) -> dict:
    import torch

    import findview_baselines.common  # noqa: F401  (registers their RL envs, 'inverse' among them)

    cfg = load_config(ctx["src"], TRAIN_CONFIG, ctx["data_root"], ctx["dataset_root"], args)  # parsed untimed
    with Timer() as t:
        envs = _vec_envs(cfg)
        envs.reset()
    vec = type(envs).__name__
    envs.close()
    return {"value": t.s, "seconds": t.s, "vec_env": vec, "num_envs": cfg.trainer.num_envs,
            "classes": f"construct_envs -> {vec} of InverseFindViewRLEnv (torch.float32)",
            "torch_threads": torch.get_num_threads()}


def row_env16(ctx: dict, args) -> dict:
    import random

    import torch

    import findview_baselines.common  # noqa: F401

    cfg = load_config(ctx["src"], TRAIN_CONFIG, ctx["data_root"], ctx["dataset_root"], args)
    envs = _vec_envs(cfg)
    _after_build(args)
    envs.reset()
    n = envs.num_envs
    rng = random.Random(0)
    acts = [[rng.randrange(4) for _ in range(n)] for _ in range(64)]  # up, down, right, left (no stop)
    for i in range(args.warmup_steps):
        envs.step(acts[i % 64])
    with Timer() as t:
        for i in range(args.env_steps):
            envs.step(acts[i % 64])
    vec = type(envs).__name__
    envs.close()
    return {"value": rate(args.env_steps * n, t.s), "seconds": t.s, "steps": args.env_steps, "num_envs": n,
            "vec_env": vec, "classes": f"construct_envs -> {vec} of InverseFindViewRLEnv (torch.float32)",
            "torch_threads": torch.get_num_threads()}


def row_env1(ctx: dict, args) -> dict:
    import random

    import torch

    import findview_baselines.common  # noqa: F401
    from LookAround.FindView.vec_env import make_rl_env_fn

    cfg = load_config(ctx["src"], TRAIN_CONFIG, ctx["data_root"], ctx["dataset_root"], args)
    env = make_rl_env_fn(cfg=cfg, filter_fn=None, split="train", rank=0, dtype=torch.float32,
                         device=torch.device("cpu"))
    _after_build(args)
    env.reset()
    rng = random.Random(0)
    acts = [rng.randrange(4) for _ in range(256)]
    for i in range(args.warmup_steps):
        env.step(action=acts[i % 256])
    with Timer() as t:
        for i in range(args.env1_steps):
            env.step(action=acts[i % 256])
    env.close()
    return {"value": rate(args.env1_steps, t.s), "seconds": t.s, "steps": args.env1_steps,
            "classes": f"make_rl_env_fn -> {type(env).__name__} (torch.float32), stepped directly",
            "torch_threads": torch.get_num_threads()}


def row_ppo(ctx: dict, args) -> dict:
    from collections import defaultdict, deque

    import torch
    from torch.optim.lr_scheduler import LambdaLR

    from findview_baselines.common import RolloutStorage
    from findview_baselines.rl.ppo.trainer import PPOTrainer
    from findview_baselines.utils.common import batch_obs

    cfg = load_config(ctx["src"], TRAIN_CONFIG, ctx["data_root"], ctx["dataset_root"], args)
    cfg.trainer.num_updates = 1 + args.updates
    trainer = PPOTrainer(cfg=cfg)
    trainer.device = torch.device("cpu")
    ppo_cfg = cfg.ppo
    # PPOTrainer.train() up to its loop (no log file, TensorBoard, validator or checkpoints)
    trainer._init_rlenvs()
    _after_build(args)
    trainer._setup_actor_critic_agent()
    params = sum(p.numel() for p in trainer.agent.parameters())
    trainer.rollouts = RolloutStorage(
        num_steps=ppo_cfg.num_steps, num_envs=trainer.envs.num_envs, observation_space=trainer.obs_space,
        action_space=trainer.policy_action_space, recurrent_hidden_state_size=ppo_cfg.hidden_size,
        num_recurrent_layers=trainer.actor_critic.net.num_recurrent_layers, action_shape=None,
        discrete_actions=True,
    )
    trainer.rollouts.to(trainer.device)
    observations = trainer.envs.reset()
    trainer.rollouts.buffers["observations"][0] = batch_obs(observations=observations, device=trainer.device,
                                                            cache=trainer._obs_batching_cache)
    trainer.current_episode_reward = torch.zeros(trainer.envs.num_envs, 1)
    trainer.running_episode_stats = dict(count=torch.zeros(trainer.envs.num_envs, 1),
                                         reward=torch.zeros(trainer.envs.num_envs, 1))
    trainer.window_episode_stats = defaultdict(lambda: deque(maxlen=ppo_cfg.reward_window_size))
    trainer.env_time = trainer.pth_time = 0.0
    lr_scheduler = LambdaLR(optimizer=trainer.agent.optimizer, lr_lambda=lambda x: 1 - trainer.percent_done())

    def one_update() -> float:
        """The body of PPOTrainer.train()'s loop (less logging / checkpoints); returns the update's seconds."""
        if ppo_cfg.use_linear_clip_decay:
            trainer.agent.clip_param = ppo_cfg.clip_param * (1 - trainer.percent_done())
        trainer.agent.eval()
        count = 0
        for _ in range(trainer.rollouts.num_steps):
            count += trainer._collect_rollout_step()
        t0 = time.perf_counter()
        value_loss, action_loss, dist_entropy = trainer._update_agent()
        dt = time.perf_counter() - t0
        if ppo_cfg.use_linear_lr_decay:
            lr_scheduler.step()
        trainer.num_updates_done += 1
        trainer._coalesce_post_step(dict(value_loss=value_loss, action_loss=action_loss,
                                         dist_entorpy=dist_entropy), count)
        return dt

    one_update()  # warm-up
    env0 = trainer.env_time
    update_s = 0.0
    with Timer() as t:
        for _ in range(args.updates):
            update_s += one_update()
    env_s = trainer.env_time - env0
    steps = args.updates * trainer.rollouts.num_steps * trainer.envs.num_envs
    vec = type(trainer.envs).__name__
    net = type(trainer.actor_critic.net).__name__
    trainer.envs.close()
    return {"value": rate(steps, t.s), "seconds": t.s, "updates": args.updates, "env_steps": steps,
            "env_s": env_s, "net_s": t.s - env_s, "update_s": update_s, "rollout_net_s": t.s - env_s - update_s,
            "params": params, "network": f"{type(trainer.actor_critic).__name__} ({net}, hidden 512)",
            "vec_env": vec, "classes": f"PPOTrainer + PPO + RolloutStorage + {net}, {vec} of InverseFindViewRLEnv",
            "torch_threads": torch.get_num_threads()}


ROW_FUNCS = {
    "orb": lambda ctx, a: row_agent("orb", ctx, a),
    "sift": lambda ctx, a: row_agent("sift", ctx, a),
    "ppo": row_ppo,
    "env16": row_env16,
    "env1": row_env1,
    "reset16": row_reset16,
}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--look-around", required=True, help="a clone of the authors' look_around repository")
    ap.add_argument("--row", required=True, choices=sorted(ROW_FUNCS))
    ap.add_argument("--panoramas", default=os.environ.get("FINDVIEW_SUN360_MINI"),
                    help="folder of panoramas (default: $FINDVIEW_SUN360_MINI)")
    ap.add_argument("--baselines-rev", default=DEFAULT_BASELINES_REV,
                    help="commit whose findview_baselines/ + configs/ run when the checkout's do not import")
    ap.add_argument("--vec-type", default=None, help="their vec env type (default: the config's, 'threaded')")
    ap.add_argument("--decisions", type=int, default=200)
    ap.add_argument("--warmup-decisions", type=int, default=20)
    ap.add_argument("--env-steps", type=int, default=60, help="env16: steps of the 16 envs")
    ap.add_argument("--env1-steps", type=int, default=300)
    ap.add_argument("--warmup-steps", type=int, default=5)
    ap.add_argument("--updates", type=int, default=2, help="ppo: timed updates (after one warm-up update)")
    ap.add_argument("--rollout-steps", type=int, default=16)
    ap.add_argument("--torch-threads", type=int, default=None,
                    help="torch.set_num_threads(N) once the envs are built (their make_env_fn / make_rl_env_fn set "
                         "1 for the whole process); default: leave their setting")
    args = ap.parse_args(argv)

    started_env = thread_env()
    la = check_checkout(args.look_around)
    files = panorama_files(args.panoramas)
    with tempfile.TemporaryDirectory(prefix="bench_peers_theirs_") as tmp_s:
        tmp = Path(tmp_s)
        src, src_desc = baselines_source(la, args.baselines_rev, tmp)
        sys.path.insert(0, str(la))
        if src != la:
            sys.path.insert(0, str(src))  # findview_baselines from src; LookAround only exists in la
        import findview_baselines

        if not Path(findview_baselines.__file__).resolve().is_relative_to(src.resolve()):
            raise PeerError(f"findview_baselines resolves to {findview_baselines.__file__}, not to {src} "
                            "(another package of that name shadows theirs; check PYTHONPATH / installs)")
        tv = ensure_torchvision()
        data_root, dataset_root = write_dataset(tmp, files, Path(args.panoramas).expanduser().resolve(), 4000)
        ctx = {"src": src, "data_root": data_root, "dataset_root": dataset_root}
        res = ROW_FUNCS[args.row](ctx, args)
        import torch

        value = res.pop("value")
        emit(args.row, value, side="theirs", look_around=git_rev(la) or str(la), baselines=src_desc,
             torch_threads_override=args.torch_threads,
             torchvision=tv, torch=torch.__version__, panoramas=len(files), env_at_start=started_env, **res)


if __name__ == "__main__":
    main()
