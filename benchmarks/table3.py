"""The paper's Table 3 on a KITTI-format folder: recall of REEB and of the classical baselines.

Rows are methods, columns are recall (%) at IoU 0.3 / 0.5 / 0.7 for the top 500 / 1000 /
2000 proposals, then milliseconds per image. Methods (``--methods``, keys in brackets):

- BING [bing], Selective Search [selective-search], Edge Boxes [edgeboxes]: OpenCV contrib,
  see :mod:`reeb_torch.baselines`;
- Ours* [reeb-default-no-regions], Ours** [reeb-default]: REEB with the package default
  config, without / with region enhancement;
- REEB as printed [reeb-paper-no-regions, reeb-paper]: the ``paper`` preset.

Recall counts every non-DontCare object of the four classes (Car, Pedestrian, Cyclist,
Truck); the headline table is micro recall (all objects pooled), a second table the mean of
the per-class recalls (NOTES #16). Also reported: average recall (AR, IoU 0.5:0.05:0.95) at
each k. Timing is the wall time of the proposal call alone (images are decoded beforehand),
one image at a time, after one untimed warm-up call; REEB is also timed in batches of
``--batch`` images (reported separately, total time / images).

Writes into ``--out`` (default ``runs/table3``): ``table3.txt`` (what is printed),
``table3.csv``, ``table3.json`` (every number, the settings and the machine), and
``recall_vs_proposals_iou0.7.png`` / ``recall_vs_iou_k2000.png``.

Rerun: ``python benchmarks/table3.py [--data DIR] [--limit N] [--methods ...]``; from code,
``main(argv)`` (returns the JSON record).
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

import torch

try:  # imported as benchmarks.table3
    from ._common import REPO_ROOT, default_kitti_dir, environment, rerun_line
except ImportError:  # run as a script, or loaded from its file
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from _common import REPO_ROOT, default_kitti_dir, environment, rerun_line  # type: ignore[no-redef]

    # The checkout's package first: run from benchmarks/, an editable install made before
    # reeb_torch/__init__.py existed resolves `reeb_torch` as an empty namespace package.
    if "reeb_torch" not in sys.modules:
        sys.path.insert(0, str(REPO_ROOT))

KS = (500, 1000, 2000)
IOUS = (0.3, 0.5, 0.7)
CURVE_IOUS = tuple(round(0.3 + 0.05 * i, 2) for i in range(15))  # 0.3 .. 1.0

# The paper's Table 3 (KITTI training set, all 7481 frames; micro or class mean is not said).
PAPER_TABLE3: dict[str, tuple[list[float], float]] = {
    "BING [14]": ([55.5, 41.5, 33.1, 73.3, 58.3, 49.8, 78.7, 66.0, 56.5], 30),
    "Selective Search [16]": ([73.0, 47.5, 30.0, 84.0, 61.1, 42.2, 89.7, 73.0, 54.8], 4300),
    "Edge Boxes [20]": ([66.6, 55.8, 48.6, 68.4, 57.0, 49.0, 87.6, 79.4, 70.0], 27),
    "Ours*": ([54.9, 45.0, 37.8, 68.5, 57.5, 49.8, 80.9, 71.0, 63.4], 40),
    "Ours**": ([67.3, 53.0, 43.1, 75.2, 61.3, 56.0, 89.5, 81.0, 72.1], 15),
}


@dataclass(frozen=True)
class Method:
    key: str
    label: str
    build: Callable[[int], Callable[[torch.Tensor], dict]]
    """``build(max_proposals)`` -> a callable on one uint8 (3, H, W) image."""
    batched: bool = False
    """Accepts a list of images (REEB), so batch timing applies."""


def _reeb(preset: str) -> Callable[[int], Callable]:
    def build(max_proposals: int) -> Callable:
        import reeb_torch

        gen = reeb_torch.ProposalGenerator(reeb_torch.get_preset(preset), top_k=max_proposals)
        gen.eval()
        return gen

    return build


def _baseline(name: str) -> Callable[[int], Callable]:
    def build(max_proposals: int) -> Callable:
        from reeb_torch.baselines import BASELINES

        return BASELINES[name](max_proposals=max_proposals)

    return build


METHODS: dict[str, Method] = {
    m.key: m
    for m in [
        Method("bing", "BING", _baseline("bing")),
        Method("selective-search", "Selective Search", _baseline("selective-search")),
        Method("edgeboxes", "Edge Boxes (Sobel)", _baseline("edgeboxes")),
        Method("reeb-default-no-regions", "Ours* (default, no regions)", _reeb("default-no-regions"), True),
        Method("reeb-default", "Ours** (default)", _reeb("default"), True),
        Method("reeb-paper-no-regions", "REEB paper preset, no regions", _reeb("paper-no-regions"), True),
        Method("reeb-paper", "REEB paper preset", _reeb("paper"), True),
    ]
}


def _call(method: Method, model: Callable, images: list[torch.Tensor]) -> list[dict]:
    """Proposals for a list of images: one call for REEB, one call per image otherwise."""
    if method.batched:
        return model(images)
    return [model(im) for im in images]


def run_method(
    method: Method, images: list[torch.Tensor], max_proposals: int, batch: int
) -> tuple[list[torch.Tensor], dict[str, Any]]:
    """Run one method over the images; return its ranked boxes per image and its timings."""
    from tqdm import tqdm

    model = method.build(max_proposals)
    _call(method, model, images[:1])  # warm-up, untimed (lazy allocations, caches)
    boxes: list[torch.Tensor] = []
    seconds: list[float] = []
    for im in tqdm(images, desc=f"{method.label:<30}", unit="img", file=sys.stderr, dynamic_ncols=True):
        t0 = time.perf_counter()
        (out,) = _call(method, model, [im])
        seconds.append(time.perf_counter() - t0)
        boxes.append(out["boxes"].detach().cpu()[:max_proposals])
    timing: dict[str, Any] = {
        "ms_per_img": 1000.0 * sum(seconds) / len(seconds),
        "ms_median": 1000.0 * sorted(seconds)[len(seconds) // 2],
        "batch_size": 1,
    }
    if method.batched and batch > 1 and len(images) > 1:
        t0 = time.perf_counter()
        for i in tqdm(range(0, len(images), batch), desc=f"{method.label[:21]:<21} batch {batch}",
                      unit="batch", file=sys.stderr, dynamic_ncols=True):
            _call(method, model, images[i : i + batch])
        timing[f"ms_per_img_batch{batch}"] = 1000.0 * (time.perf_counter() - t0) / len(images)
    timing["num_proposals_mean"] = sum(b.shape[0] for b in boxes) / len(boxes)
    return boxes, timing


# -- output ----------------------------------------------------------------------------------


def _fmt(v: float | None, digits: int = 1) -> str:
    return "-" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.{digits}f}"


def format_table(title: str, rows: list[tuple[str, list[float], str]], note: str = "") -> str:
    """Plain-text table in Table 3's layout: ``rows`` are (name, 9 recalls in %, time)."""
    name_w = max(30, *(len(r[0]) for r in rows))
    group = " ".join(f"{f'IoU {t:g}':>8}" for t in IOUS)
    head1 = f"{'':<{name_w}} | " + " | ".join(f"{f'{k} proposals':^{len(group)}}" for k in KS) + " | time"
    head2 = f"{'Method':<{name_w}} | " + " | ".join(group for _ in KS) + " | ms/img"
    lines = [title, head1, head2, "-" * len(head2)]
    for name, vals, t in rows:
        groups = [" ".join(f"{_fmt(v):>8}" for v in vals[3 * i : 3 * i + 3]) for i in range(len(KS))]
        lines.append(f"{name:<{name_w}} | " + " | ".join(groups) + f" | {t}")
    if note:
        lines.append(note)
    return "\n".join(lines)


def _grid(result, average: str) -> list[float]:
    """Nine recalls in % in column order (k major, IoU minor)."""
    return [100.0 * result.at(k, t, None if average == "micro" else "mean") for k in KS for t in IOUS]


def _style(label: str) -> str:
    return "--" if "no regions" in label else "-"


def _plot(curves: dict[str, dict], out: Path) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    files: list[str] = []

    def line_plot(x: str, y: str, xlabel: str, ylabel: str, title: str, name: str, log: bool) -> None:
        fig, ax = plt.subplots(figsize=(6.4, 4.4))
        for label, c in curves.items():
            ax.plot(c[x], [100 * r for r in c[y]], label=label, ls=_style(label))
        if log:
            ax.set_xscale("log")
        ax.set_xlabel(xlabel)
        ax.set_ylabel(ylabel)
        ax.set_ylim(0, 100)
        ax.grid(True, which="both" if log else "major", alpha=0.3)
        ax.legend(fontsize=8)
        ax.set_title(title)
        fig.tight_layout()
        fig.savefig(out / name, dpi=120)
        plt.close(fig)
        files.append(name)

    line_plot("ks", "recall_vs_k", "number of proposals", "recall at IoU 0.7 (%)",
              "Recall vs number of proposals (KITTI, IoU 0.7)", "recall_vs_proposals_iou0.7.png", log=True)
    line_plot("ious", "recall_vs_iou", "IoU threshold", "recall of the top 2000 (%)",
              "Recall vs IoU (KITTI, 2000 proposals)", "recall_vs_iou_k2000.png", log=False)
    return files


def _parse(argv: Sequence[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(
        prog="benchmarks/table3.py",
        description="Reproduce the paper's Table 3 (recall vs proposals and IoU, ms/img) on KITTI.",
    )
    p.add_argument("--data", type=Path, default=default_kitti_dir(),
                   help="KITTI-format folder (images/ + labels/, or image_2/ + label_2/); default: %(default)s")
    p.add_argument("--limit", type=int, default=None, help="use only the first N frames")
    p.add_argument("--out", type=Path, default=Path("runs/table3"), help="output folder; default: %(default)s")
    p.add_argument("--methods", nargs="+", default=list(METHODS), choices=list(METHODS), metavar="METHOD",
                   help=f"methods to run, in table order; choose from {', '.join(METHODS)} (default: all)")
    p.add_argument("--max-proposals", type=int, default=max(KS), help="proposals per image; default: %(default)s")
    p.add_argument("--batch", type=int, default=8,
                   help="also time REEB in batches of this many images (0 or 1: skip); default: %(default)s")
    return p.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    """Run the benchmark (``argv`` as on the command line) and return the JSON record."""
    from reeb_torch.data import KittiDataset
    from reeb_torch.metrics import average_recall, recall_table, recall_vs_iou, recall_vs_proposals

    argv = list(sys.argv[1:] if argv is None else argv)
    args = _parse(argv)
    if args.max_proposals < max(KS):
        raise SystemExit(f"--max-proposals must be >= {max(KS)} for Table 3's columns")
    rerun = rerun_line("benchmarks/table3.py", argv)
    print(f"Rerun: {rerun}   (from {REPO_ROOT})", flush=True)

    ds = KittiDataset(args.data, limit=args.limit)
    if len(ds) == 0:
        raise SystemExit(f"{args.data}: no frames")
    t0 = time.perf_counter()
    items = [ds[i] for i in range(len(ds))]
    images = [it["image"] for it in items]
    gts = [it["boxes"] for it in items]
    labels = [it["labels"] for it in items]
    classes = tuple(ds.classes)
    n_obj = sum(int(g.shape[0]) for g in gts)
    print(f"{len(images)} frames from {args.data} ({n_obj} objects of {', '.join(classes)}), "
          f"decoded in {time.perf_counter() - t0:.1f} s", flush=True)

    args.out.mkdir(parents=True, exist_ok=True)
    results: dict[str, Any] = {}
    curves: dict[str, dict] = {}
    for key in args.methods:
        method = METHODS[key]
        try:
            boxes, timing = run_method(method, images, args.max_proposals, args.batch)
        except (FileNotFoundError, ImportError) as e:  # e.g. the BING model folder is absent
            print(f"skipped {method.label}: {e}", flush=True)
            results[key] = {"label": method.label, "skipped": str(e)}
            continue
        table = recall_table(boxes, gts, labels, classes, ks=KS, ious=IOUS)
        ar_micro = average_recall(boxes, gts, ks=KS)
        ar_class = average_recall(boxes, gts, ks=KS, gt_labels=labels, class_names=classes, average="class")
        ks_curve, r_k = recall_vs_proposals(boxes, gts, iou=0.7, max_k=args.max_proposals)
        ious_curve, r_iou = recall_vs_iou(boxes, gts, k=max(KS), ious=CURVE_IOUS)
        curves[method.label] = {"ks": ks_curve.tolist(), "recall_vs_k": r_k.tolist(),
                                "ious": ious_curve.tolist(), "recall_vs_iou": r_iou.tolist()}
        results[key] = {
            "label": method.label,
            "recall": table.to_dict(),
            "ar_micro": dict(zip(map(str, KS), ar_micro.tolist())),
            "ar_class_mean": dict(zip(map(str, KS), ar_class.tolist())),
            "timing": timing,
            "curves": curves[method.label],
        }
        print(f"  {method.label}: recall@2000 IoU0.7 micro {100 * table.at(2000, 0.7):.1f} %, "
              f"{timing['ms_per_img']:.0f} ms/img", flush=True)

    done = [k for k in args.methods if "recall" in results[k]]

    def time_cell(k: str) -> str:
        t = results[k]["timing"]
        s = f"{t['ms_per_img']:.0f}"
        bk = f"ms_per_img_batch{args.batch}"
        return s + (f" ({t[bk]:.0f} @b{args.batch})" if bk in t else "")

    blocks = []
    for average, title in (("micro", "Recall (%) over all objects (micro) - headline, as Table 3"),
                           ("class", "Recall (%), mean of the per-class recalls (Car, Pedestrian, Cyclist, Truck)")):
        rows = []
        for k in done:
            r = results[k]["recall"]
            grid = r["micro"] if average == "micro" else r["class_mean"]
            vals = [100.0 * grid[str(kk)][f"{t:g}"] if grid[str(kk)][f"{t:g}"] is not None else float("nan")
                    for kk in KS for t in IOUS]
            rows.append((results[k]["label"], vals, time_cell(k)))
        blocks.append(format_table(title, rows))
    ar_lines = ["Average recall (%, IoU 0.5:0.05:0.95)   micro @500 / @1000 / @2000  |  class mean @500 / @1000 / @2000"]
    for k in done:
        a, c = results[k]["ar_micro"], results[k]["ar_class_mean"]
        ar_lines.append(f"{results[k]['label']:<30} " + " / ".join(f"{100 * a[str(kk)]:5.1f}" for kk in KS)
                        + "  |  " + " / ".join(_fmt(100 * c[str(kk)] if c[str(kk)] == c[str(kk)] else None)
                                               for kk in KS))
    blocks.append("\n".join(ar_lines))
    blocks.append(format_table(
        "The paper's Table 3 (7481 KITTI frames, C++ on an i7-8750H; its Edge Boxes uses SE edges)",
        [(n, v, f"{t:,}") for n, (v, t) in PAPER_TABLE3.items()]))
    env = environment()
    counts = ", ".join(f"{c} {n}" for c, n in zip(classes, _class_counts(labels, len(classes))))
    header = (f"Table 3 on {len(images)} frames of {args.data} ({n_obj} objects: {counts}).\n"
              f"Time: wall ms per image of the proposal call only (decoding excluded), batch size 1"
              f"{f'; REEB also at batch {args.batch} (@b{args.batch})' if args.batch > 1 else ''}; "
              f"{env['processor']}, {env['cpu_count']} cores, torch threads {env['torch_threads']}, "
              f"OpenCV threads {env['opencv_threads']}, CUDA {'yes' if env['cuda'] else 'no'}.")
    text = "\n\n".join([f"Rerun: {rerun}", header, *blocks]) + "\n"
    print("\n" + text, flush=True)
    (args.out / "table3.txt").write_text(text)

    with open(args.out / "table3.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["method", "label", "average"] + [f"R@{k}_IoU{t:g}" for k in KS for t in IOUS]
                   + [f"AR@{k}" for k in KS] + ["ms_per_img", f"ms_per_img_batch{args.batch}"])
        for k in done:
            r = results[k]
            for average in ("micro", "class_mean"):
                grid = r["recall"][average]
                ar = r["ar_micro"] if average == "micro" else r["ar_class_mean"]
                w.writerow([k, r["label"], average]
                           + [_fmt(None if grid[str(kk)][f'{t:g}'] is None else 100 * grid[str(kk)][f'{t:g}'], 2)
                              for kk in KS for t in IOUS]
                           + [_fmt(100 * ar[str(kk)], 2) for kk in KS]
                           + [f"{r['timing']['ms_per_img']:.1f}",
                              _fmt(r["timing"].get(f"ms_per_img_batch{args.batch}"), 1)])

    plots = _plot(curves, args.out) if curves else []
    record = {
        "rerun": rerun,
        "data": str(args.data),
        "num_images": len(images),
        "image_ids": [it["image_id"] for it in items],
        "num_objects": n_obj,
        "classes": list(classes),
        "ks": list(KS),
        "ious": list(IOUS),
        "max_proposals": args.max_proposals,
        "batch": args.batch,
        "environment": env,
        "methods": results,
        "paper_table3": {n: {"recall": v, "ms_per_img": t} for n, (v, t) in PAPER_TABLE3.items()},
        "plots": plots,
    }
    (args.out / "table3.json").write_text(json.dumps(record, indent=1))
    print(f"wrote {args.out}/table3.txt, table3.csv, table3.json, {', '.join(plots)}", flush=True)
    return record


def _class_counts(labels: list[torch.Tensor], n: int) -> list[int]:
    if not labels:
        return [0] * n
    return torch.bincount(torch.cat(labels).to(torch.int64), minlength=n).tolist()


if __name__ == "__main__":
    main()
