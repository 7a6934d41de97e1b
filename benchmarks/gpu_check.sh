#!/usr/bin/env bash
# One GPU check, for the rare occasion a GPU is lent: at most 8 minutes in total, run from the repo root.
#
#   bash benchmarks/gpu_check.sh [OUT_DIR]                     # on the GPU machine (OUT_DIR default: $OUT)
#   bash benchmarks/gpu_check.sh --device cpu --quick /tmp/gc  # dry run of every stage on a CPU
#
# Stages (each under `timeout`, each given what is left of the 8-minute budget, at most its own cap):
#   0. the machine: nvidia-smi, Python / torch / CUDA / cuDNN versions       -> env.txt
#   1. packages: `pip install -e .[dev]` only when findview or its deps do not import -> install.log
#   2. the CUDA tests (tests that skip without CUDA: `-k cuda`, and the device-parametrised ones of
#      tests/test_gpu_path.py)                                                -> tests.log
#   3. the throughput curve over 16 ... 1024 envs, fp32 and bf16+channels_last -> scale/scale.csv (+ .png)
#   4. a short training run of the paper's network on the synthetic dataset   -> train.log, train/ (TensorBoard)
# Every stage's output and exit status is written under OUT_DIR; summary.txt lists them. The script
# always exits 0 once it has written summary.txt (read the statuses there).
set -u

DEVICE=cuda
QUICK=0
OUT_DIR=""
while [ $# -gt 0 ]; do
  case "$1" in
    --device) DEVICE="$2"; shift 2 ;;
    --quick) QUICK=1; shift ;;
    -h|--help) sed -n '2,17p' "$0"; exit 0 ;;
    *) OUT_DIR="$1"; shift ;;
  esac
done
OUT_DIR="${OUT_DIR:-${OUT:-outputs/gpu_check}}"
mkdir -p "$OUT_DIR"
OUT_DIR="$(cd "$OUT_DIR" && pwd)"
[ -f setup.py ] && [ -d findview ] || { echo "run from the repository root" >&2; exit 2; }

PY="${PYTHON:-python}"
command -v "$PY" >/dev/null || PY=python3
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"  # findview imports even when not pip-installed
export PYTHONUNBUFFERED=1
START=$(date +%s)
BUDGET=${GPU_CHECK_BUDGET_S:-470}  # seconds for all stages (8 minutes, minus a margin)
SUMMARY="$OUT_DIR/summary.txt"
: > "$SUMMARY"

left() { echo $(( BUDGET - ($(date +%s) - START) )); }

# stage NAME CAP_SECONDS LOG COMMAND...: run under timeout(min(CAP, time left)); record status and duration
stage() {
  local name="$1" cap="$2" log="$3"; shift 3
  local t; t=$(left)
  [ "$t" -gt "$cap" ] && t="$cap"
  if [ "$t" -lt 10 ]; then
    echo "$name: skipped (budget spent)" | tee -a "$SUMMARY"
    return 0
  fi
  local s0; s0=$(date +%s)
  echo "== $name (timeout ${t}s): $*" | tee -a "$log"
  timeout -s INT -k 15 "$t" "$@" >> "$log" 2>&1
  local rc=$?
  local note=""
  [ "$rc" -eq 124 ] || [ "$rc" -eq 130 ] && note=" (stopped by the ${t}s timeout)"
  echo "$name: exit $rc$note after $(( $(date +%s) - s0 ))s; log $(basename "$log")" | tee -a "$SUMMARY"
}

# 0. the machine
{
  echo "date: $(date -u +%FT%TZ)"; echo "host: $(hostname)"; echo "device: $DEVICE quick=$QUICK"
  echo "git: $(git rev-parse HEAD 2>/dev/null || echo unknown) $(git status --porcelain 2>/dev/null | wc -l) changed files"
  nvidia-smi 2>&1 || echo "nvidia-smi: not available"
  "$PY" - <<'EOF' 2>&1
import platform, sys
print("python", sys.version.split()[0], platform.platform())
try:
    import torch
    print("torch", torch.__version__, "cuda", torch.version.cuda, "cudnn", torch.backends.cudnn.version(),
          "available", torch.cuda.is_available())
    if torch.cuda.is_available():
        p = torch.cuda.get_device_properties(0)
        print("gpu", p.name, f"{p.total_memory / 2**30:.1f} GiB", "bf16", torch.cuda.is_bf16_supported())
except Exception as e:  # noqa: BLE001
    print("torch: not importable:", e)
EOF
  "$PY" -m pip list 2>/dev/null | grep -iE "^(torch|numpy|opencv|hydra|omegaconf|kornia|pytest|matplotlib|tensorboard) " || true
} > "$OUT_DIR/env.txt" 2>&1
echo "env: see env.txt" >> "$SUMMARY"

# 1. packages, only when something is missing (the machine may have no network: then this fails fast)
if "$PY" -c "import findview, findview_baselines, torch, cv2, hydra, pytest" 2>/dev/null; then
  echo "install: not needed (everything imports)" | tee -a "$SUMMARY"
else
  stage install 150 "$OUT_DIR/install.log" "$PY" -m pip install --disable-pip-version-check -e ".[dev]"
fi

# 2. the CUDA tests (on a CPU dry run they all skip: that checks the selection)
stage tests 120 "$OUT_DIR/tests.log" "$PY" -m pytest -q -rs -s -p no:cacheprovider \
  tests/test_gpu_path.py tests/test_env.py tests/test_sim.py tests/test_policy.py tests/test_ppo.py -k cuda

# 3. the throughput curve
if [ "$QUICK" -eq 1 ]; then
  SCALE_ARGS=(--quick --threads 1)
else
  SCALE_ARGS=(--time-budget-s 130 --updates 2)
fi
stage scale 190 "$OUT_DIR/scale.log" "$PY" benchmarks/bench_scale.py --device "$DEVICE" \
  --configs fp32 bf16+cl "${SCALE_ARGS[@]}" --out "$OUT_DIR/scale"

# 4. a short training run: the paper's network and view size, many envs, the speed options on. The
# synthetic dataset (40 procedural panoramas, generated on first use) and the run folder live in a scratch
# folder (checkpoints of the 512-unit network are 50-150 MB); logs and TensorBoard events are copied back.
WORK="${TMPDIR:-/tmp}/findview_gpu_check"
rm -rf "$WORK/train"
if [ "$QUICK" -eq 1 ]; then
  TRAIN_ARGS=(+experiment=quickstart trainer.num_updates=2 trainer.num_envs=2 trainer.ppo.rollout_steps=4
              trainer.val_episodes=6 trainer.val_interval=0)
else
  TRAIN_ARGS=(+experiment=quickstart sim.height=256 sim.width=256 agent.hidden_size=512 trainer.num_envs=256
              trainer.ppo.rollout_steps=64 trainer.ppo.num_mini_batches=2 trainer.num_updates=40 trainer.val_interval=20
              trainer.val_episodes=48 trainer.log_interval=1 agent.precision=bf16 agent.channels_last=true)
fi
stage train 150 "$OUT_DIR/train.log" "$PY" tools/train.py "${TRAIN_ARGS[@]}" sim.device="$DEVICE" \
  trainer.progress=false "hydra.run.dir=$WORK/train" "dataset.root=$WORK/synthetic/images" \
  "dataset.out_dir=$WORK/synthetic"
mkdir -p "$OUT_DIR/train"
cp -r "$WORK/train/tb" "$WORK/train/cli.log" "$WORK/train/resolved_config.yaml" "$OUT_DIR/train/" 2>/dev/null
ls -l "$WORK/train/checkpoints" > "$OUT_DIR/train/checkpoints.txt" 2>&1

echo "total: $(( $(date +%s) - START ))s of a ${BUDGET}s budget; results in $OUT_DIR" | tee -a "$SUMMARY"
exit 0
