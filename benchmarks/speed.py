"""Speed of REEB per stage, in the layout of the paper's Table 2, with and without region
enhancement, for uint8 and float input, at two batch sizes.

End to end from decoded tensors (already in memory) to ranked boxes, at a given batch size
and proposal count, on the frames of a KITTI-format folder, for both inputs a caller may
hand over: ``uint8`` as decoded and float32 RGB in [0, 1] (``uint8 / 255``, what
torchvision detectors pass). The first call of each (input, batch) is timed apart (the
very first one compiles the numba kernels, or loads them from their cache), and so is the
first image of each other size (window grids and tables are built once per size); then
passes over all frames, every (column, input, batch) once per pass in a rotating order
(interleaved across the columns too: a slow spell of the machine hits all alike), and the
median over ``--repeats`` passes is reported, at ``--batch`` and at ``--latency-batch`` (1: the latency a detector sees
calling one image at a time). Beside the table: an OpenCV pass (grey, Gaussian blur,
Sobel x and y) over the same images, timed in the same rotation (once per pass), the floor
the paper compares with (15 ms total vs about 3 ms for edges), and the ratio of REEB's
total to it, with the lowest and highest pass beside the medians (for the ratio, each
pass's total over the same pass's OpenCV time: the short OpenCV pass swings more than
REEB's, so these spread wider than the ratio of the medians).

Rerun: ``python benchmarks/speed.py [--data DIR] [--limit N] [--batch 8] [--top-k 2000] [--threads N]
[--presets NAME ...] [--variant LABEL "FIELD=VALUE;..."]``
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
from _common import default_kitti_dir, environment, rerun_line, settings_config  # noqa: E402

from reeb_torch import ProposalGenerator, ReebConfig, get_preset  # noqa: E402
from reeb_torch.datasets.kitti import KittiDataset  # noqa: E402
from reeb_torch.io import read_image  # noqa: E402

STAGES = [
    ("Edge detection (resize, blur, Sobel, thinning)", "edges"),
    ("Edge groups (Sec. 3.7)", "groups"),
    ("Road segmentation (Sec. 3.5)", "road"),
    ("Regions and entropy (Sec. 3.6, eqs. 2, 9)", "regions"),
    ("Proposal scoring (windows, eqs. 1, 10-12, region cut)", "scoring"),
    ("Learned ranking (prefilter, features, model; default)", "ranker"),
    ("  of it: the prefilter and its cut", "ranker.prefilter"),
    ("  of it: the features of the kept candidates", "ranker.features"),
    ("  of it: the MLP", "ranker.model"),
    ("  of it: the class head (hints; class_quota)", "ranker.class_head"),
    ("NMS (eq. 13)", "nms"),
]


INPUTS = ("uint8", "float")


def as_input(images: list[torch.Tensor], kind: str) -> list[torch.Tensor]:
    """The frames as a caller hands them over: ``uint8`` as decoded, or ``float`` RGB in
    [0, 1] (``uint8 / 255``, float32, as torchvision detectors and ``ReebRPN`` pass them);
    converted outside the timing."""
    return images if kind == "uint8" else [im.float().div_(255.0) for im in images]


def _timed_pass(gen: ProposalGenerator, imgs: list[torch.Tensor], batch: int, device: str) -> tuple[float, dict]:
    """One pass over ``imgs`` in batches of ``batch``: ms per image, and per stage."""
    gen.stage_times = {}
    t0 = time.perf_counter()
    for i in range(0, len(imgs), batch):
        gen(imgs[i: i + batch])
    if device.startswith("cuda"):
        torch.cuda.synchronize()
    total = (time.perf_counter() - t0) * 1000 / len(imgs)
    return total, {k: v * 1000 / len(imgs) for k, v in gen.stage_times.items()}


def measure(preset: str | ReebConfig, images: list[torch.Tensor], batches: list[int], top_k: int, repeats: int,
            device: str) -> dict:
    """:func:`measure_all` of one preset (or config)."""
    return measure_all({"_": preset}, images, batches, top_k, repeats, device)["_"]


def measure_all(columns: dict[str, str | ReebConfig], images: list[torch.Tensor], batches: list[int], top_k: int,
                repeats: int, device: str) -> dict[str, dict]:
    """Time each column (a preset name or a config) on every (input kind, batch size),
    interleaved: each pass runs every (column, input, batch) once, in an order that rotates
    from pass to pass, so that a slow spell of the machine hits them all alike (columns timed
    one after the other were compared across spells); the OpenCV pass (:func:`opencv_pass`)
    is one more entry, so that the ratio to it compares runs of the same spell. The first
    call of each is timed apart (the very first one compiles the numba kernels, or loads
    them from their cache), and so are the first calls at the other image sizes
    (:func:`_other_sizes`). Returns per column, per variant ``"uint8/b8"``: the median ms per
    image, the per-stage ms of the pass nearest the median, all passes' totals, each pass's
    total over the same pass's OpenCV time (``"to_opencv"``), the first call's ms and the
    other sizes' mean first-call ms; and ``"opencv_ms"`` (median) and ``"opencv_all"`` for
    the OpenCV pass (the same for every column), and ``"regions"``, whether the column's config
    uses the region enhancement."""
    inputs = {k: [im.to(device) for im in as_input(images, k)] for k in INPUTS}
    variants = [(k, b) for b in batches for k in INPUTS]
    gens, first, new_size = {}, {}, {}
    for name, preset in columns.items():
        config = get_preset(preset) if isinstance(preset, str) else preset
        gens[name] = gen = ProposalGenerator(config, top_k=top_k).to(device)
        for k, b in variants:
            t0 = time.perf_counter()
            gen(inputs[k][:b])  # warm-up: numba compile (or cache load), window grids
            first[(name, k, b)] = (time.perf_counter() - t0) * 1000
            new_size[(name, k, b)] = _other_sizes(gen, inputs[k])
    runs: dict = {(name, *v): [] for name in columns for v in variants}
    arrays = [np.ascontiguousarray(im.permute(1, 2, 0).cpu().numpy()) for im in images]
    sigma, floors = get_preset("default").blur_sigma, []
    rotation = [*runs, "opencv"]
    for r in range(repeats):
        for j in range(len(rotation)):
            v = rotation[(j + r) % len(rotation)]
            if v == "opencv":
                floors.append(opencv_pass(arrays, sigma))
            else:
                name, k, b = v
                runs[v].append(_timed_pass(gens[name], inputs[k], b, device))
    out: dict[str, dict] = {name: {"opencv_ms": statistics.median(floors), "opencv_all": floors,
                                   "regions": gens[name].config.use_regions} for name in columns}
    for (name, k, b), passes in runs.items():
        totals = [t for t, _ in passes]
        med = statistics.median(totals)
        best = min(range(len(passes)), key=lambda i: abs(totals[i] - med))
        out[name][f"{k}/b{b}"] = {"total": med, "stages": passes[best][1], "all_totals": totals,
                                  "to_opencv": [t / f for t, f in zip(totals, floors)],
                                  "first_call_ms": first[(name, k, b)], "new_size_ms": new_size[(name, k, b)]}
    return out


def _other_sizes(gen: ProposalGenerator, imgs: list[torch.Tensor]) -> float | None:
    """The first call at each image size after the first (the window grid, score plan and
    NMS tables of a size are built once, then cached), one image each, so that no timed
    pass pays them: their mean ms, ``None`` where all frames share one size."""
    seen = {tuple(imgs[0].shape)}
    times = []
    for im in imgs:
        if tuple(im.shape) not in seen:
            seen.add(tuple(im.shape))
            t0 = time.perf_counter()
            gen([im])
            times.append((time.perf_counter() - t0) * 1000)
    return statistics.mean(times) if times else None


def opencv_pass(arrays: list[np.ndarray], sigma: float) -> float:
    """ms per image of one OpenCV grey + Gaussian blur + Sobel x/y pass over ``arrays``
    (``uint8 (H, W, 3)`` RGB)."""
    t0 = time.perf_counter()
    for a in arrays:
        g = cv2.cvtColor(a, cv2.COLOR_RGB2GRAY).astype(np.float32)
        g = cv2.GaussianBlur(g, (0, 0), sigma)
        cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3)
        cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3)
    return (time.perf_counter() - t0) * 1000 / len(arrays)


def _table(res: dict, presets: list[str], batches: list[int]) -> str:
    """The stage table (uint8 at the first batch size), then the totals of every input kind
    and batch size, the float / uint8 ratios and the first calls."""
    main_v = f"uint8/b{batches[0]}"
    head = f"{'Process (uint8, batch ' + str(batches[0]) + ')':52s}" + "".join(f"{p:>22s}" for p in presets)
    row = lambda label, vals, fmt="22.1f": f"{label:52s}" + "".join(f"{v:{fmt}}" for v in vals)  # noqa: E731
    lines = [head, "-" * len(head)]
    for label, key in STAGES:
        lines.append(row(label, [res[p][main_v]["stages"].get(key, 0.0) for p in presets]))
    lines.append("-" * len(head))
    spread = lambda label, key: f"{label:52s}" + "".join(  # noqa: E731
        f"{f'{min(res[p][main_v][key]):.1f}-{max(res[p][main_v][key]):.1f}':>22s}" for p in presets)
    lines.append(row("Total (end to end, median)", [res[p][main_v]["total"] for p in presets]))
    lines.append(spread("  lowest-highest pass", "all_totals"))
    lines.append(row("Paper, Table 2 (C++, i7-8750H, Sobel)", [15.0 if res[p]["regions"] else 40.0 for p in presets]))
    lines.append(row("OpenCV grey+blur+Sobel pass, same images, same passes", [res[p]["opencv_ms"] for p in presets],
                     "22.2f"))
    lines.append(row("Total / OpenCV pass (medians; paper: about 5)", [res[p][main_v]["total"] / res[p]["opencv_ms"]
                                                                       for p in presets]))
    lines.append(spread("  per pass, lowest-highest", "to_opencv"))
    lines.append("-" * len(head))
    for b in batches:
        for k in INPUTS:
            lines.append(row(f"Total, {k} input, batch {b} (median)", [res[p][f"{k}/b{b}"]["total"] for p in presets]))
        lines.append(row(f"  float / uint8 at batch {b}", [res[p][f"float/b{b}"]["total"] / res[p][f"uint8/b{b}"]["total"]
                                                         for p in presets], "22.2f"))
    lines.append("-" * len(head))
    for b in batches:
        for k in INPUTS:
            lines.append(row(f"First call, {k}, batch {b} (not above), ms", [res[p][f"{k}/b{b}"]["first_call_ms"]
                                                                         for p in presets], "22.0f"))
    sizes = [res[p][f"uint8/b{batches[0]}"]["new_size_ms"] for p in presets]
    if all(v is not None for v in sizes):
        lines.append(row("First call at each other image size (not above), ms", sizes, "22.0f"))
    return "\n".join(lines)


def columns(presets: list[str], variants: list[tuple[str, str]]) -> dict[str, str | ReebConfig]:
    """The table's columns: each preset by its name, then each ``(label, "FIELD=VALUE;...")``
    variant of the default (as ``reeb propose --set``) under its label."""
    out: dict[str, str | ReebConfig] = {p: p for p in presets}
    for label, settings in variants:
        out[label] = settings_config(settings)
    return out


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
    ap.add_argument("--presets", nargs="*", default=["default", "training-free"])
    ap.add_argument("--variant", nargs=2, action="append", default=[], metavar=("LABEL", "SETTINGS"),
                    help="one more column: the default with SETTINGS (FIELD=VALUE;..., as reeb propose --set)")
    ap.add_argument("--out", type=Path, default=Path("runs/speed"))
    args = ap.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    print("# rerun:", rerun_line("benchmarks/speed.py", argv if argv is not None else sys.argv[1:]))
    files = KittiDataset(args.data, limit=args.limit).image_paths  # either KITTI layout
    images = [read_image(f) for f in files]
    print(f"# {len(images)} frames of {args.data}, batch {args.batch}, top-{args.top_k}, device {args.device}, "
          f"torch threads {torch.get_num_threads()}; median of {args.repeats} passes, ms per image")
    batches = [args.batch] + ([args.latency_batch] if args.latency_batch and args.latency_batch != args.batch else [])
    try:
        configs = columns(args.presets, args.variant)
    except ValueError as e:  # a field or value reeb propose --set would refuse
        raise SystemExit(f"--variant: {e}") from None
    res = measure_all(configs, images, batches, args.top_k, args.repeats, args.device)
    table = _table(res, list(configs), batches)
    print(table)
    args.out.mkdir(parents=True, exist_ok=True)
    record = {"results": res, "table": table, "args": {k: str(v) for k, v in vars(args).items()}, "env": environment()}
    (args.out / "speed.json").write_text(json.dumps(record, indent=2))
    (args.out / "speed.txt").write_text(table + "\n")
    return record


if __name__ == "__main__":
    main()
