"""Speed of ``findview.corruptions`` against the reference ``imagecorruptions`` 1.1.2, in the same run.

    python benchmarks/bench_corruptions.py --reference-python /path/to/refvenv/bin/python \\
        [--threads 2] [--batch 16] [--size 256] [--repeats 2] [--device cpu]

The reference package needs its own virtual environment (its ``opencv-python`` clashes with the
headless build findview uses, and 1.1.2 calls ``skimage.filters.gaussian(multichannel=True)``,
which scikit-image >= 0.20 rejects), e.g.::

    python -m venv refvenv && refvenv/bin/pip install "numpy<2" "scipy<1.14" scikit-image==0.20.0 \\
        "opencv-python-headless<4.9" pillow "setuptools<70" && refvenv/bin/pip install --no-deps imagecorruptions==1.1.2

The reference runs in a worker subprocess with that interpreter; for scikit-image >= 0.20 the worker
maps ``multichannel=True`` to the equivalent ``channel_axis=-1`` (same computation). The two sides
alternate corruption by corruption, so both see the same machine load. Both use ``--threads``
threads (torch and OpenCV; the reference's numpy code is single-threaded), under findview's thread
policy (``findview.runtime``: OpenMP threads sleep rather than spin when idle). Each figure is the
per-image time averaged over severities 1-5 (ours: one batched call of ``--batch`` images per
severity; reference: the images one by one, stopping after ``--ref-budget`` seconds per severity
with at least 2 images, which only matters for glass blur), best of ``--repeats``. Without
``--reference-python`` only our column is printed. Images: central crops of the panoramas in
``$FINDVIEW_SUN360_MINI`` (or ``--data``), else smooth random images.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import findview  # noqa: F401  (first: sets OMP_WAIT_POLICY=PASSIVE before torch loads; findview.runtime)
import numpy as np
import torch

from findview.corruptions import NAMES, corrupt
from findview.runtime import configure_threads

DEFAULT_DATA = Path(os.environ.get("FINDVIEW_SUN360_MINI", "") or "/nonexistent")  # a folder of SUN360 panoramas

WORKER = r'''
import json, sys, time, warnings
import numpy as np
warnings.filterwarnings("ignore")
threads = int(sys.argv[2])
import cv2
cv2.setNumThreads(threads)
import skimage.filters
import imagecorruptions.corruptions as ref
from imagecorruptions import corrupt
_gaussian = skimage.filters.gaussian
def _compat_gaussian(image, *args, multichannel=None, **kwargs):
    if multichannel is not None:
        kwargs.setdefault("channel_axis", -1 if multichannel else None)
    return _gaussian(image, *args, **kwargs)
ref.gaussian = _compat_gaussian
images = np.load(sys.argv[1])
np.random.seed(0)
print(json.dumps({"ready": True}), flush=True)
for line in sys.stdin:
    name, repeats, budget = line.split()
    best = []
    for severity in range(1, 6):
        corrupt(images[0], severity, name)  # warm-up
        times = []
        for _ in range(int(repeats)):
            t = time.perf_counter()
            n = 0
            for img in images:  # all images, or as many as fit in the budget (at least 2)
                corrupt(img, severity, name)
                n += 1
                if n >= 2 and time.perf_counter() - t > float(budget):
                    break
            times.append((time.perf_counter() - t) / n)
        best.append(min(times))
    print(json.dumps({"name": name, "s_per_image": float(np.mean(best))}), flush=True)
'''


def load_images(data: Path, batch: int, size: int) -> np.ndarray:
    """``(batch, size, size, 3)`` uint8: central crops of real panoramas, else smooth random images."""
    files = sorted(data.rglob("pano_*.jpg")) if data.is_dir() else []
    if files:
        from findview.imageio import load_panorama

        out = []
        for f in (files * batch)[:batch]:
            p = load_panorama(f)
            h, w = p.shape[:2]
            t, l = (h - size) // 2, (w - size) // 2
            out.append(p[t : t + size, l : l + size])
        return np.stack(out)
    rng = np.random.default_rng(0)
    low = rng.integers(0, 256, (batch, 3, size // 16, size // 16)).astype(np.float32)
    up = torch.nn.functional.interpolate(torch.from_numpy(low), size=(size, size), mode="bilinear")
    return up.permute(0, 2, 3, 1).round().clamp(0, 255).to(torch.uint8).numpy()


def time_ours(x: torch.Tensor, name: str, repeats: int) -> float:
    """Seconds per image of ``corrupt`` on the batch, averaged over severities, best of ``repeats``."""
    g = torch.Generator(device=x.device).manual_seed(0)
    per_sev = []
    for severity in range(1, 6):
        corrupt(x, name, severity, g)  # warm-up (caches, kernels)
        times = []
        for _ in range(repeats):
            if x.is_cuda:
                torch.cuda.synchronize()
            t = time.perf_counter()
            corrupt(x, name, severity, g)
            if x.is_cuda:
                torch.cuda.synchronize()
            times.append((time.perf_counter() - t) / x.shape[0])
        per_sev.append(min(times))
    return float(np.mean(per_sev))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--reference-python", type=str, default=None, help="interpreter with imagecorruptions 1.1.2")
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--device", type=str, default="cpu")
    ap.add_argument("--names", type=str, default="all", help="comma-separated subset of the 16 names")
    ap.add_argument("--ref-budget", type=float, default=5.0,
                    help="seconds per severity and repeat after which the reference stops (>= 2 images)")
    args = ap.parse_args()
    configure_threads(args.threads, opencv_threads=args.threads)
    names = NAMES if args.names == "all" else tuple(args.names.split(","))
    images = load_images(args.data, args.batch, args.size)
    x = torch.from_numpy(images).permute(0, 3, 1, 2).contiguous().to(args.device)

    worker = None
    tmpdir = tempfile.TemporaryDirectory()
    if args.reference_python:
        npy = os.path.join(tmpdir.name, "images.npy")
        np.save(npy, images)
        script = os.path.join(tmpdir.name, "worker.py")
        Path(script).write_text(WORKER)
        env = dict(os.environ, OMP_NUM_THREADS=str(args.threads))
        worker = subprocess.Popen(
            [args.reference_python, script, npy, str(args.threads)],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env,
        )
        json.loads(worker.stdout.readline())
    else:
        print("no --reference-python given: reference column skipped")

    print(f"batch {args.batch} x {args.size}x{args.size}, device {args.device}, {args.threads} threads; "
          f"ms per image (mean over severities 1-5)")
    print(f"{'corruption':18s} {'findview':>9s} {'reference':>10s} {'speed-up':>9s}")
    ours_total = ref_total = 0.0
    for name in names:
        ours = time_ours(x, name, args.repeats)
        ours_total += ours
        ref_s = None
        if worker is not None:
            worker.stdin.write(f"{name} {args.repeats} {args.ref_budget}\n")
            worker.stdin.flush()
            ref_s = json.loads(worker.stdout.readline())["s_per_image"]
            ref_total += ref_s
        ref_txt = f"{ref_s * 1e3:10.2f}" if ref_s is not None else f"{'-':>10s}"
        ratio = f"{ref_s / ours:8.1f}x" if ref_s is not None else f"{'-':>9s}"
        print(f"{name:18s} {ours * 1e3:9.2f} {ref_txt} {ratio}", flush=True)
    if worker is not None:
        worker.stdin.close()
        worker.wait()
        print(f"{'all 16 (sum)':18s} {ours_total * 1e3:9.2f} {ref_total * 1e3:10.2f} {ref_total / ours_total:8.1f}x")
    else:
        print(f"{'all (sum)':18s} {ours_total * 1e3:9.2f}")
    tmpdir.cleanup()


if __name__ == "__main__":
    sys.exit(main())
