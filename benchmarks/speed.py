"""Speed of REEB per stage, in the layout of the paper's Table 2, with and without region
enhancement.

End to end from decoded tensors (uint8, already in memory) to ranked boxes, at a given
batch size and proposal count, on the frames of a KITTI-format folder. Each configuration
is warmed up once (window grids are cached per image size; the first call also compiles
the numba NMS kernel, or loads it from numba's cache) and that first call is reported
apart; then all frames are timed and the median over ``--repeats`` passes is reported, at
``--batch`` and at batch 1 (the latency a detector sees calling one image at a time).
Beside the table: an OpenCV pass (grey, Gaussian blur, Sobel x and y) over the same
images, the floor the paper compares with (15 ms total vs about 3 ms for edges), and the
ratio of REEB's total to it.

Rerun: ``python benchmarks/speed.py [--data DIR] [--limit N] [--batch 8] [--top-k 2000] [--threads N]``
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import default_kitti_dir, environment, rerun_line  # noqa: E402

from reeb_torch import ProposalGenerator, get_preset  # noqa: E402
from reeb_torch.eval.data import KittiDataset  # noqa: E402
from reeb_torch.io import read_image  # noqa: E402

STAGES = [
    ("Edge detection (resize, blur, Sobel, thinning)", "edges"),
    ("Edge groups (Sec. 3.7)", "groups"),
    ("Road segmentation (Sec. 3.5)", "road"),
    ("Regions and entropy (Sec. 3.6, eqs. 2, 9)", "regions"),
    ("Proposal scoring (windows, eqs. 1, 10-12, ranking)", "scoring"),
    ("Edge Boxes' refinement (preset refined only)", "refine"),
    ("NMS (eq. 13)", "nms"),
]


def measure(preset: str, images: list[torch.Tensor], batch: int, top_k: int, repeats: int,
            device: str) -> dict:
    gen = ProposalGenerator(get_preset(preset), top_k=top_k).to(device)
    imgs = [im.to(device) for im in images]
    t0 = time.perf_counter()
    gen(imgs[:batch])  # warm-up: numba compile (or cache load), window grids
    first_ms = (time.perf_counter() - t0) * 1000
    totals, stages = [], []
    for _ in range(repeats):
        gen.stage_times = {}
        t0 = time.perf_counter()
        for i in range(0, len(imgs), batch):
            gen(imgs[i: i + batch])
        if device.startswith("cuda"):
            torch.cuda.synchronize()
        totals.append((time.perf_counter() - t0) * 1000 / len(imgs))
        stages.append({k: v * 1000 / len(imgs) for k, v in gen.stage_times.items()})
    best = min(range(repeats), key=lambda r: abs(totals[r] - statistics.median(totals)))
    return {"total": statistics.median(totals), "stages": stages[best], "all_totals": totals,
            "first_call_ms": first_ms}


def opencv_floor(images: list[torch.Tensor], sigma: float, repeats: int) -> float:
    """Median ms per image of an OpenCV grey + Gaussian blur + Sobel x/y pass over ``images``
    (``uint8 (3, H, W)`` RGB tensors, converted to arrays outside the timing)."""
    arrays = [np.ascontiguousarray(im.permute(1, 2, 0).cpu().numpy()) for im in images]
    times = []
    for _ in range(max(repeats, 1)):
        t0 = time.perf_counter()
        for a in arrays:
            g = cv2.cvtColor(a, cv2.COLOR_RGB2GRAY).astype(np.float32)
            g = cv2.GaussianBlur(g, (0, 0), sigma)
            cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3)
            cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3)
        times.append((time.perf_counter() - t0) * 1000 / len(arrays))
    return statistics.median(times)


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=default_kitti_dir())
    ap.add_argument("--limit", type=int, default=None)
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--latency-batch", type=int, default=1, help="second batch size timed (0: skip)")
    ap.add_argument("--top-k", type=int, default=2000)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--threads", type=int, default=None, help="torch intra-op threads (default: torch's)")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--presets", nargs="*", default=["default", "default-no-regions"])
    ap.add_argument("--out", type=Path, default=Path("runs/speed"))
    args = ap.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    print("# rerun:", rerun_line("benchmarks/speed.py", argv if argv is not None else sys.argv[1:]))
    files = KittiDataset(args.data, limit=args.limit).image_paths  # either KITTI layout
    images = [read_image(f) for f in files]
    print(f"# {len(images)} frames of {args.data}, batch {args.batch}, top-{args.top_k}, device {args.device}, "
          f"torch threads {torch.get_num_threads()}; median of {args.repeats} passes, ms per image")
    res = {p: measure(p, images, args.batch, args.top_k, args.repeats, args.device) for p in args.presets}
    lat = {}
    if args.latency_batch and args.latency_batch != args.batch:
        lat = {p: measure(p, images, args.latency_batch, args.top_k, args.repeats, args.device)
               for p in args.presets}
    floor = opencv_floor(images, get_preset("default").blur_sigma, args.repeats)
    head = f"{'Process':52s}" + "".join(f"{p:>22s}" for p in args.presets)
    lines = [head, "-" * len(head)]
    for label, key in STAGES:
        lines.append(f"{label:52s}" + "".join(f"{res[p]['stages'].get(key, 0.0):22.1f}" for p in args.presets))
    lines.append("-" * len(head))
    lines.append(f"{'Total (end to end, median)':52s}" + "".join(f"{res[p]['total']:22.1f}" for p in args.presets))
    lines.append(f"{'Paper, Table 2 (C++, i7-8750H, Sobel)':52s}" + "".join(
        f"{(15.0 if 'no-regions' not in p else 40.0):22.1f}" for p in args.presets))
    lines.append(f"{'OpenCV grey+blur+Sobel pass, same images':52s}" + "".join(
        f"{floor:22.2f}" for p in args.presets))
    lines.append(f"{'Total / OpenCV pass (paper: about 5)':52s}" + "".join(
        f"{res[p]['total'] / floor:22.1f}" for p in args.presets))
    for p_lat in ([lat] if lat else []):
        lines.append(f"{f'Total at batch {args.latency_batch} (latency, median)':52s}" + "".join(
            f"{p_lat[p]['total']:22.1f}" for p in args.presets))
    lines.append(f"{'First call (numba compile/cache load; not above), ms':52s}" + "".join(
        f"{res[p]['first_call_ms']:22.0f}" for p in args.presets))
    table = "\n".join(lines)
    print(table)
    args.out.mkdir(parents=True, exist_ok=True)
    record = {"results": res, "latency": lat, "opencv_floor_ms": floor, "table": table, "args": {k: str(v) for k, v in vars(args).items()}, "env": environment()}
    (args.out / "speed.json").write_text(json.dumps(record, indent=2))
    (args.out / "speed.txt").write_text(table + "\n")
    return record


if __name__ == "__main__":
    main()
