"""The paper's Table 3 on a KITTI-format folder: recall of REEB and of the classical baselines.

Rows are methods, columns are recall (%) at IoU 0.3 / 0.5 / 0.7 for the top 500 / 1000 /
2000 proposals, then milliseconds per image. Methods (``--methods``, keys in brackets):

- BING [bing], Selective Search [selective-search], Edge Boxes [edgeboxes]: OpenCV contrib,
  see :mod:`reeb_torch.eval.baselines`;
- Ours* [reeb-default-no-regions], Ours** [reeb-training-free]: REEB without a learned part
  (the ``training-free`` preset), without / with region enhancement;
- Ours** + learned ranking [reeb-default]: the package default, REEB's windows ordered by the
  shipped model (``ranker='kitti'``; fitted on the 106 dev frames, so on those frames its row
  is no estimate: ``reeb fit`` cross-validates it);
- Ours** + learned ranking, cross-validated [reeb-default-cv, with ``--cross-validate FOLDS``]:
  the default with, for each block of frames, a ranking fitted on the other blocks of the
  frames measured (``reeb fit``'s folds, options and seed: no drive neighbour of a block on
  the training side): an estimate on labelled frames the shipped model saw; the other rows are
  then paired with ``training-free`` (the default's own row is in sample there);
- Ours** + learned ranking, fitted on the other folders [reeb-default-lofo, with
  ``--leave-folder-out``]: the same with one block per ``--data`` folder (another drive, another
  camera set-up): how a model holds on frames unlike those it was fitted on;
- REEB as printed [reeb-paper-no-regions, reeb-paper]: the ``paper`` preset.

Recall counts every non-DontCare object of the four classes (Car, Pedestrian, Cyclist,
Truck). Tables, for the selected frames:

1. micro recall over all objects (all objects pooled) - the headline, as Table 3;
2. micro recall over KITTI-*moderate* objects (box height >= 25 px, occlusion <= 1,
   truncation <= 0.3: the usual protocol of KITTI proposal papers,
   :data:`reeb_torch.eval.metrics.KITTI_DIFFICULTIES`);
3. the mean of the per-class recalls (all objects);
4. per-class recall at 2000 proposals, IoU 0.7, over all and over moderate objects;
5. average recall (AR, IoU 0.5:0.05:0.95) at each k;
6. the headline (2000 proposals, IoU 0.7, all objects) with its 95 % frame-bootstrap
   interval (:func:`reeb_torch.eval.metrics.recall_interval`): on 60 frames about ±6 points,
   on 20 about ±10, so the paper's 72.1 % is told apart only from figures well outside it;
   and each method paired with the package default (``reeb-default``, or the first method
   run) on the same objects: objects only it recalls, objects only the default recalls,
   and the exact sign test (:func:`reeb_torch.eval.metrics.compare_recall`).

``--frames 0:39 40:59`` selects frames by numeric id (both ends included); with two or more
ranges, tables 1, 2, 4 and 6 are repeated for each range (the proposals are computed once).

Timing is the wall time of the proposal call alone (images are decoded beforehand), one
image at a time, after one untimed warm-up call; REEB is also timed in batches of
``--batch`` images (reported separately, total time / images).

Writes into ``--out`` (default ``runs/table3``): ``table3.txt`` (what is printed),
``table3.csv`` (one row per method x frames x objects x average), ``table3.json`` (every
number, the settings and the machine), and ``recall_vs_proposals_iou0.7.png`` /
``recall_vs_iou_k2000.png`` (with matplotlib, the ``extras``).

Run: ``reeb eval DIR``, ``python -m reeb_torch.eval --data DIR [--limit N] [--frames A:B ...]
[--methods ...] [--cross-validate FOLDS] [--leave-folder-out]``, or from code ``main(argv)``
(returns the JSON record).
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from .metrics import (
    AR_IOUS,
    KITTI_DIFFICULTIES,
    RecallResult,
    compare_recall,
    kitti_difficulty_mask,
    object_hits,
    recall_interval,
    recall_table,
    recall_vs_iou,
    recall_vs_proposals,
    select_objects,
)
from .common import (add_data_option, add_frames_option, environment, first_few, folder_splits, load_folders,
                     rerun_line)

__all__ = [
    "KS",
    "IOUS",
    "HEADLINE",
    "PAPER_TABLE3",
    "Method",
    "METHODS",
    "run_method",
    "recall_tables",
    "format_table",
    "main",
]

KS = (500, 1000, 2000)
IOUS = (0.3, 0.5, 0.7)
HEADLINE = (2000, 0.7)
"""``(k, IoU)`` of the per-class table."""
CURVE_IOUS = tuple(round(0.3 + 0.05 * i, 2) for i in range(15))  # 0.3 .. 1.0
OBJECT_SETS = ("all", "moderate")
"""Which objects are counted: every object, or KITTI-moderate ones only."""
CROSS_VALIDATED = "reeb-default-cv"
"""The key of the cross-validated row (``--cross-validate``; not a ``--methods`` choice)."""
LEAVE_FOLDER_OUT = "reeb-default-lofo"
"""The key of the row ranked by models fitted on the other folders (``--leave-folder-out``)."""

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
    """One row of the table."""

    key: str
    label: str
    build: Callable[..., Callable[[torch.Tensor], dict]]
    """``build(max_proposals, **options)`` -> a callable on one uint8 (3, H, W) image."""
    batched: bool = False
    """Accepts a list of images (REEB), so batch timing applies."""
    preset: str | None = None
    """The REEB preset of a REEB row (its ranking model, if any, is checked against the frames)."""
    cross_validated: bool = False
    """Ranked by models fitted on the measured frames' other blocks (``--cross-validate``):
    its boxes come from :func:`cross_validated_boxes`, not from ``build``."""


def _reeb(preset: str) -> Callable[..., Callable]:
    def build(max_proposals: int, **_: Any) -> Callable:
        from .. import ProposalGenerator, get_preset

        gen = ProposalGenerator(get_preset(preset), top_k=max_proposals)
        gen.eval()
        return gen

    return build


def _baseline(name: str) -> Callable[..., Callable]:
    def build(max_proposals: int, bing_model: str | os.PathLike | None = None, **_: Any) -> Callable:
        from .baselines import BASELINES

        if name == "bing" and bing_model is not None:
            return BASELINES[name](max_proposals=max_proposals, model_dir=bing_model)
        return BASELINES[name](max_proposals=max_proposals)

    return build


METHODS: dict[str, Method] = {
    m.key: m
    for m in [
        Method("bing", "BING", _baseline("bing")),
        Method("selective-search", "Selective Search", _baseline("selective-search")),
        Method("edgeboxes", "Edge Boxes (Sobel)", _baseline("edgeboxes")),
        Method("reeb-default-no-regions", "Ours* (training-free, no regions)", _reeb("training-free-no-regions"),
               True, "training-free-no-regions"),
        Method("reeb-training-free", "Ours** (training-free)", _reeb("training-free"), True, "training-free"),
        Method("reeb-default", "Ours** + learned ranking (default)", _reeb("default"), True, "default"),
        Method(CROSS_VALIDATED, "Ours** + learned ranking (cross-validated)", _reeb("default"), True,
               cross_validated=True),
        Method(LEAVE_FOLDER_OUT, "Ours** + learned ranking (fitted on the other folders)", _reeb("default"), True,
               cross_validated=True),
        Method("reeb-paper-no-regions", "REEB paper preset, no regions", _reeb("paper-no-regions"), True,
               "paper-no-regions"),
        Method("reeb-paper", "REEB paper preset", _reeb("paper"), True, "paper"),
    ]
}


def _call(method: Method, model: Callable, images: list[torch.Tensor]) -> list[dict]:
    """Proposals for a list of images: one call for REEB, one call per image otherwise."""
    if method.batched:
        return model(images)
    return [model(im) for im in images]


def run_method(
    method: Method,
    images: list[torch.Tensor],
    max_proposals: int,
    batch: int,
    **options: Any,
) -> tuple[list[torch.Tensor], dict[str, Any]]:
    """Run one method over the images; return its ranked boxes per image (``Tensor[N_i, 4]``,
    CPU, at most ``max_proposals``) and its timings (ms per image)."""
    from tqdm import tqdm

    model = method.build(max_proposals, **options)
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


# -- recall ----------------------------------------------------------------------------------


def moderate_masks(items: Sequence[dict[str, Any]]) -> list[torch.Tensor]:
    """Per frame, ``bool Tensor[N_i]``: which objects are KITTI-moderate."""
    return [kitti_difficulty_mask(it["boxes"], it["occluded"], it["truncated"], "moderate") for it in items]


def recall_tables(
    boxes: Sequence[torch.Tensor],
    items: Sequence[dict[str, Any]],
    classes: Sequence[str],
    objects: str = "all",
) -> tuple[RecallResult, RecallResult]:
    """Recall of ranked ``boxes`` (one ``Tensor[P_i, 4]`` per item) against the items'
    ground truth, over ``objects`` ``"all"`` or ``"moderate"``.

    Returns:
        ``(table, ar_table)``: recall at :data:`KS` x :data:`IOUS`, and at :data:`KS` x
        :data:`reeb_torch.eval.metrics.AR_IOUS` (its mean over IoUs is the average recall).
    """
    gts = [it["boxes"] for it in items]
    labels: list[torch.Tensor] | None = [it["labels"] for it in items]
    if objects == "moderate":
        gts, labels = select_objects(gts, labels, moderate_masks(items))
    elif objects != "all":
        raise ValueError(f"objects must be one of {OBJECT_SETS}, got {objects!r}")
    table = recall_table(boxes, gts, labels, classes, ks=KS, ious=IOUS)
    ar = recall_table(boxes, gts, labels, classes, ks=KS, ious=AR_IOUS)
    return table, ar


def _ar_dict(ar: RecallResult) -> dict[str, Any]:
    """AR per k (``str(k)`` keys): micro, class mean and per class; ``None`` = undefined."""

    def row(t: torch.Tensor) -> dict[str, float | None]:
        return {str(k): (None if math.isnan(v) else v) for k, v in zip(ar.ks, t.mean(dim=-1).tolist())}

    return {
        "micro": row(ar.micro),
        "class_mean": row(ar.class_mean),
        "per_class": {c: row(ar.per_class[ci]) for ci, c in enumerate(ar.class_names)},
    }


# -- output ----------------------------------------------------------------------------------


def _fmt(v: float | None, digits: int = 1) -> str:
    return "-" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.{digits}f}"


def _pct(v: float | None) -> float:
    return float("nan") if v is None else 100.0 * v


def format_table(title: str, rows: list[tuple[str, list[float], str]], note: str = "") -> str:
    """Plain-text table in Table 3's layout: ``rows`` are (name, 9 recalls in %, time)."""
    name_w = max([30, *(len(r[0]) for r in rows)])
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


def format_per_class(title: str, rows: list[tuple[str, dict[str, dict]]], classes: Sequence[str]) -> str:
    """Per-class recall at :data:`HEADLINE`: one row per method, for all and moderate
    objects a column "all" (micro) then one per class. ``rows`` are
    ``(name, {objects: recall dict})`` with recall dicts as :meth:`RecallResult.to_dict`."""
    k, t = str(HEADLINE[0]), f"{HEADLINE[1]:g}"
    first = rows[0][1] if rows else {}
    cols: list[tuple[str, str, str | None]] = []  # (header, objects, class or None = micro)
    for objects in OBJECT_SETS:
        if objects not in first:
            continue
        n = first[objects]["num_objects"]
        cols.append((f"all ({n})", objects, None))
        for c in classes:
            cols.append((f"{c} ({first[objects]['num_per_class'].get(c, 0)})", objects, c))
    width = max(11, *(len(h) for h, _, _ in cols)) if cols else 11
    name_w = max(30, *(len(r[0]) for r in rows)) if rows else 30
    groups = []
    for objects in OBJECT_SETS:
        n_cols = sum(1 for _, o, _ in cols if o == objects)
        if n_cols:
            label = "all objects" if objects == "all" else "KITTI-moderate objects"
            groups.append(f"{label:^{n_cols * (width + 1) - 1}}")
    head1 = f"{'':<{name_w}} | " + " | ".join(groups)
    head2 = f"{'Method':<{name_w}} | " + " | ".join(
        " ".join(f"{h:>{width}}" for h, o, _ in cols if o == objects) for objects in OBJECT_SETS
        if any(o == objects for _, o, _ in cols))
    lines = [title, head1, head2, "-" * len(head2)]
    for name, rec in rows:
        cells = []
        for objects in OBJECT_SETS:
            if objects not in rec:
                continue
            r = rec[objects]
            vals = [r["micro"][k][t]] + [r["per_class"][c][k][t] for c in classes]
            cells.append(" ".join(f"{_fmt(_pct(v)):>{width}}" for v in vals))
        lines.append(f"{name:<{name_w}} | " + " | ".join(cells))
    return "\n".join(lines)


def _style(label: str, in_sample: bool = False) -> str:
    return ":" if in_sample else "--" if "no regions" in label else "-"


def _plot(curves: dict[str, dict], out: Path, in_sample: Sequence[str] = ()) -> list[str]:
    """The two recall plots, a line per method (``curves`` by label); the methods labelled
    ``in_sample`` (ranked by a model fitted on these frames) dotted, and said so."""
    try:
        import matplotlib
    except ImportError:
        print("plots skipped: matplotlib is not installed (pip install 'reeb-torch[extras]')", flush=True)
        return []
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    files: list[str] = []

    def line_plot(x: str, y: str, xlabel: str, ylabel: str, title: str, name: str, log: bool) -> None:
        fig, ax = plt.subplots(figsize=(6.4, 4.4))
        for label, c in curves.items():
            seen = label in in_sample
            ax.plot(c[x], [100 * r for r in c[y]], label=label + (" - in sample, no estimate" if seen else ""),
                    ls=_style(label, seen))
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


def build_parser(prog: str = "python -m reeb_torch.eval",
                 default_data: Sequence[Path] | Path | None = None) -> argparse.ArgumentParser:
    """The command line of :func:`main`. ``default_data``: the ``--data`` default, one folder
    or several (without one, ``--data`` is required)."""
    p = argparse.ArgumentParser(
        prog=prog,
        description="Reproduce the paper's Table 3 (recall vs proposals and IoU, ms/img) on KITTI.",
    )
    if isinstance(default_data, (str, Path)):
        default_data = [Path(default_data)]
    add_data_option(p, default_data)
    p.add_argument("--limit", type=int, default=None, help="use only the first N frames (after --frames)")
    add_frames_option(p)
    p.add_argument("--out", type=Path, default=Path("runs/table3"), help="output folder; default: %(default)s")
    chosen = [k for k, m in METHODS.items() if not m.cross_validated]
    p.add_argument("--methods", nargs="+", default=chosen, choices=chosen, metavar="METHOD",
                   help=f"methods to run, in table order; choose from {', '.join(chosen)} (default: all)")
    p.add_argument("--max-proposals", type=int, default=max(KS), help="proposals per image; default: %(default)s")
    p.add_argument("--batch", type=int, default=8,
                   help="also time REEB in batches of this many images (0 or 1: skip); default: %(default)s")
    p.add_argument("--exclude-fitted", action="store_true",
                   help="leave out the frames a learned ranking among the methods was fitted on (the same "
                        "pictures, whatever their names: reeb_torch.ranker.fitted_frames), so that every row "
                        "is an estimate (the shipped model saw KITTI training frames)")
    p.add_argument("--cross-validate", type=int, default=0, metavar="FOLDS",
                   help="also the default ranked, on each block of frames, by a model fitted on the other "
                        "blocks (FOLDS folds of blocks of frames, no drive neighbours on both sides, reeb fit's "
                        "options and seed): an estimate on labelled frames the shipped model saw. Fits FOLDS "
                        "models (about a minute for 100 frames); the rows are then paired with training-free")
    p.add_argument("--leave-folder-out", action="store_true",
                   help="also the default ranked, on each --data folder, by a model fitted on the other folders "
                        "(as --cross-validate, a block per folder): how a model holds on another drive")
    p.add_argument("--bing-model", type=Path, default=None,
                   help="folder of BING's nine ObjNessB2W8*.yml.gz files; default: the package's "
                        "default (reeb_torch.eval.baselines.default_bing_model_dir), else bing_model/ "
                        "beside the --data folder")
    return p


def _bing_model(args: argparse.Namespace) -> Path | None:
    if args.bing_model is not None:
        return args.bing_model
    from .baselines import default_bing_model_dir

    if default_bing_model_dir().is_dir():
        return None
    beside = Path(args.data[0]).resolve().parent / "bing_model"
    return beside if beside.is_dir() else None


def _class_counts(labels: list[torch.Tensor], n: int) -> list[int]:
    if not labels:
        return [0] * n
    return torch.bincount(torch.cat(labels).to(torch.int64), minlength=n).tolist()


def _frame_span(ids: Sequence[str]) -> str:
    return f"{ids[0]}-{ids[-1]}" if ids else "none"


@dataclass
class _Frames:
    """The selected frames of the KITTI folder, decoded."""

    items: list[dict]
    classes: tuple[str, ...]
    images: list[torch.Tensor]
    gts: list[torch.Tensor]
    labels: list[torch.Tensor]
    ids: list[str]
    n_obj: int


def main(
    argv: Sequence[str] | None = None,
    *,
    prog: str = "python -m reeb_torch.eval",
    default_data: Path | None = None,
) -> dict[str, Any]:
    """Run the benchmark (``argv`` as on the command line) and return the JSON record.

    ``prog`` names the command in ``--help`` and in the rerun line; ``default_data`` is the
    ``--data`` default. Bad options or unusable data exit with code 2 and a message.
    """
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser(prog, default_data)
    args = _parse_args(parser, argv)
    rerun = rerun_line(prog, argv)
    print(f"Rerun: {rerun}   (from {os.getcwd()})", flush=True)
    frames = _load_frames(args, parser)
    excluded: dict[str, str] = {}
    if args.exclude_fitted:
        frames, excluded = _without_fitted(frames, [k for k in args.methods if METHODS[k].preset], args, parser)
    if args.cross_validate > len(frames.images):
        parser.exit(2, f"{parser.prog}: error: --cross-validate {args.cross_validate} needs at least as many "
                       f"frames, got {len(frames.images)}\n")
    splits = _splits(args, frames)
    bing_model = _bing_model(args)
    args.out.mkdir(parents=True, exist_ok=True)
    results, curves, hits = _run_methods(args, frames, splits, bing_model)
    done = [k for k in args.methods if "recall" in results[k]]
    reference = _reference(done)
    _pair_with_reference(results, hits, splits, done, reference)
    env = environment()
    # after --exclude-fitted no frame left was seen: no need to hash them again
    seen = {} if args.exclude_fitted else in_sample_frames([k for k in done if METHODS[k].preset], frames)
    text = _report(args, rerun, env, frames, splits, results, done, reference, seen)
    print("\n" + text, flush=True)
    (args.out / "table3.txt").write_text(text)
    _write_csv(args.out / "table3.csv", results, done, splits, frames.classes, args.batch)
    plots = _plot(curves, args.out, [results[k]["label"] for k in seen]) if curves else []
    record = _record(args, rerun, env, frames, splits, results, plots)
    record["in_sample"] = seen
    record["excluded_fitted"] = excluded
    (args.out / "table3.json").write_text(json.dumps(record, indent=1))
    print(f"wrote {args.out}/table3.txt, table3.csv, table3.json"
          + (f", {', '.join(plots)}" if plots else ""), flush=True)
    return record


def _reference(done: Sequence[str]) -> str | None:
    """The row every row is paired with on the same objects: the package default; where a
    cross-validated row ran (the frames are labelled ones the shipped model may have seen),
    ``training-free``; else the first row run."""
    held_out = any(METHODS[k].cross_validated for k in done)
    order = ["reeb-training-free", "reeb-default"] if held_out else ["reeb-default"]
    return next((k for k in order if k in done), done[0] if done else None)


def _parse_args(parser: argparse.ArgumentParser, argv: list[str]) -> argparse.Namespace:
    args = parser.parse_args(argv)
    if args.max_proposals < max(KS):
        parser.error(f"--max-proposals must be >= {max(KS)} for Table 3's columns, got {args.max_proposals}")
    if args.limit is not None and args.limit < 1:
        parser.error(f"--limit must be >= 1, got {args.limit}")
    if args.cross_validate and args.cross_validate < 2:
        parser.error(f"--cross-validate needs at least 2 folds, got {args.cross_validate}")
    if args.leave_folder_out and len(args.data) < 2:
        parser.error("--leave-folder-out needs two or more --data folders")
    held_out = [k for k, on in ((CROSS_VALIDATED, args.cross_validate), (LEAVE_FOLDER_OUT, args.leave_folder_out))
                if on]
    at = args.methods.index("reeb-default") + 1 if "reeb-default" in args.methods else len(args.methods)
    args.methods = [*args.methods[:at], *held_out, *args.methods[at:]]
    return args


def _load_frames(args: argparse.Namespace, parser: argparse.ArgumentParser) -> _Frames:
    """The selected frames, decoded; a usage error when there are none or they hold no object."""
    t0 = time.perf_counter()
    try:
        items, classes = load_folders(args.data, limit=args.limit, frames=args.frames)
    except (ValueError, FileNotFoundError) as e:  # unusable data: one line, exit 2 (no usage block)
        parser.exit(2, f"{parser.prog}: error: {' '.join(str(e).split())}\n")
    gts = [it["boxes"] for it in items]
    frames = _Frames(items, classes, [it["image"] for it in items], gts, [it["labels"] for it in items],
                     [it["image_id"] for it in items], sum(int(g.shape[0]) for g in gts))
    if frames.n_obj == 0:
        parser.exit(2, f"{parser.prog}: error: {_data_text(args)}: the {len(items)} selected frames hold no "
                       f"object of {', '.join(classes)}; recall is undefined\n")
    print(f"{len(frames.images)} frames from {_data_text(args)} ({frames.n_obj} objects of {', '.join(classes)}), "
          f"decoded in {time.perf_counter() - t0:.1f} s", flush=True)
    return frames


def _without_fitted(frames: _Frames, keys: Sequence[str], args: argparse.Namespace,
                    parser: argparse.ArgumentParser) -> tuple[_Frames, dict[str, str]]:
    """``--exclude-fitted``: ``frames`` less those a learned ranking of the REEB rows ``keys``
    was fitted on, and those left out (``{id: the model's name for it}``); a usage error when
    nothing with an object is left."""
    left: dict[str, str] = {}
    for seen in in_sample_frames(keys, frames).values():
        left.update(seen)
    keep = [i for i, f in enumerate(frames.ids) if f not in left]
    pick = lambda xs: [xs[i] for i in keep]  # noqa: E731
    out = _Frames(pick(frames.items), frames.classes, pick(frames.images), pick(frames.gts), pick(frames.labels),
                  pick(frames.ids), sum(int(frames.gts[i].shape[0]) for i in keep))
    if out.n_obj == 0:
        parser.exit(2, f"{parser.prog}: error: --exclude-fitted leaves {len(keep)} of the {len(frames.ids)} frames "
                       f"of {_data_text(args)}, with no object: the learned ranking was fitted on the others\n")
    print(f"--exclude-fitted: left out {len(left)} frames the learned ranking was fitted on"
          + (f" ({first_few(list(left))})" if left else ""), flush=True)
    return out, left


def _data_text(args: argparse.Namespace) -> str:
    """The data folders as the tables name them."""
    return " + ".join(str(d) for d in args.data)


def _splits(args: argparse.Namespace, frames: _Frames) -> list[tuple[str, list[int]]]:
    """Frame splits: the whole selection, then each data folder when there are several, then
    each ``--frames`` range when there are several."""
    ids = frames.ids
    splits: list[tuple[str, list[int]]] = [("all", list(range(len(ids))))]
    splits += folder_splits(frames.items)
    if len(args.frames) > 1:
        for r in args.frames:
            idx = [i for i, f in enumerate(ids) if int(f) in r]
            splits.append((r.text, idx))
    return splits


def _run_methods(args: argparse.Namespace, frames: _Frames, splits: list[tuple[str, list[int]]],
                 bing_model: Path | None) -> tuple[dict[str, Any], dict[str, dict], dict[str, list[torch.Tensor]]]:
    """Each method's proposals and their record: ``(results, curves, hits)``, keyed by method
    (curves by label; hits: per-frame headline hits, for the pairing)."""
    results: dict[str, Any] = {}
    curves: dict[str, dict] = {}
    hits: dict[str, list[torch.Tensor]] = {}  # method -> per-frame headline hits
    prepared: dict[str, Any] = {}  # the held-out rows' frames and candidates, taken once
    for key in args.methods:
        method = METHODS[key]
        try:
            if method.cross_validated:
                folds = (args.cross_validate if key == CROSS_VALIDATED
                         else [idx for _, idx in folder_splits(frames.items)])
                boxes, timing = cross_validated_boxes(frames, args.data, folds, args.max_proposals, prepared)
            else:
                boxes, timing = run_method(method, frames.images, args.max_proposals, args.batch,
                                           bing_model=bing_model)
        except (FileNotFoundError, ImportError) as e:  # e.g. the BING model folder is absent
            print(f"skipped {method.label}: {e}", flush=True)
            results[key] = {"label": method.label, "skipped": str(e)}
            continue
        ks_curve, r_k = recall_vs_proposals(boxes, frames.gts, iou=0.7, max_k=args.max_proposals)
        ious_curve, r_iou = recall_vs_iou(boxes, frames.gts, k=max(KS), ious=CURVE_IOUS)
        curves[method.label] = {"ks": ks_curve.tolist(), "recall_vs_k": r_k.tolist(),
                                "ious": ious_curve.tolist(), "recall_vs_iou": r_iou.tolist()}
        hits[key] = object_hits(boxes, frames.gts, *HEADLINE)  # once; each split takes its frames' hits
        results[key] = _method_record(method, boxes, timing, hits[key], curves[method.label], frames, splits)
        whole = results[key]["splits"]["all"]
        hk, ht = HEADLINE
        mod = whole["moderate"]["recall"]["micro"][str(hk)][f"{ht:g}"]
        micro = whole["all"]["recall"]["micro"][str(hk)][f"{ht:g}"]
        print(f"  {method.label}: recall@2000 IoU0.7 micro {_fmt(_pct(micro))} %, "
              f"moderate {_fmt(_pct(mod))} %, {_fmt(timing['ms_per_img'], 0)} ms/img", flush=True)
    return results, curves, hits


def cross_validated_boxes(frames: _Frames, roots: Sequence[Path], folds: int | Sequence[Sequence[int]],
                          max_proposals: int,
                          prepared: dict[str, Any] | None = None) -> tuple[list[torch.Tensor], dict[str, Any]]:
    """The default's ranked boxes (``Tensor[N_i, 4]``, at most ``max_proposals``) on each of
    ``frames`` (read from the folders ``roots``), each ranked by a model fitted without the
    frame's block of ``folds`` (a number of blocks, or the blocks: the frame indices of each;
    :func:`reeb_torch.eval.fit.held_out_outputs`, with ``reeb fit``'s default options and seed:
    the same models as ``reeb fit ROOTS --folds FOLDS``), and the
    seconds it took (``fit_s``: candidates, fits, proposals; no ms per image: the row runs the
    default's code, whose row times it). ``prepared``: a dict kept between calls on the same
    frames, which holds their candidates and training rows after the first (then not timed
    again)."""
    from tqdm import tqdm

    from .. import get_preset
    from .common import folder_names
    from .fit import FitFrames, FitOptions, frame_samples, held_out_outputs, other_boxes
    from .tune import FrameCache

    def bar(desc: str) -> Callable:
        return lambda items: tqdm(items, desc=f"{'cross-validated: ' + desc:<30}", file=sys.stderr, dynamic_ncols=True)

    t0 = time.perf_counter()
    cfg, opts = get_preset("default").replace(top_k=max_proposals), FitOptions()
    prepared = {} if prepared is None else prepared
    if not prepared:
        root_of = dict(zip(folder_names(roots), roots))
        folders = [it["folder"] for it in frames.items]
        ignore: list[torch.Tensor] = [torch.zeros(0, 4)] * len(frames.ids)
        for name, idx in folder_splits(frames.items) or [(folders[0], list(range(len(folders))))]:
            for i, box in zip(idx, other_boxes(root_of[name], [frames.ids[i] for i in idx])):
                ignore[i] = box
        cache = FrameCache(FitFrames(frames.images, frames.gts, frames.labels, frames.classes, frames.ids, folders,
                                     ignore))
        prepared.update(cache=cache, samples=frame_samples(cache, cfg, opts, progress=bar("candidates")))
    outputs = held_out_outputs(prepared["cache"], cfg, prepared["samples"], opts, folds, progress=bar("folds"))
    boxes = [o["boxes"][:max_proposals] for o in outputs]
    timing = {"ms_per_img": None, "fit_s": time.perf_counter() - t0,
              "folds": folds if isinstance(folds, int) else len(folds), "batch_size": 1,
              "num_proposals_mean": sum(b.shape[0] for b in boxes) / len(boxes)}
    return boxes, timing


def _method_record(method: Method, boxes: list[torch.Tensor], timing: dict, hits: list[torch.Tensor], curve: dict,
                   frames: _Frames, splits: list[tuple[str, list[int]]]) -> dict[str, Any]:
    """One method's entry of the JSON record: its recall tables per split and object set."""
    split_records: dict[str, Any] = {}
    for name, idx in splits:
        rec: dict[str, Any] = {"frames": [frames.ids[i] for i in idx]}
        for objects in OBJECT_SETS:
            table, ar = recall_tables([boxes[i] for i in idx], [frames.items[i] for i in idx], frames.classes,
                                      objects)
            rec[objects] = {"recall": table.to_dict(), "ar": _ar_dict(ar)}
        ci = recall_interval([hits[i] for i in idx])
        rec["headline_interval"] = {"recall": ci.recall, "low": ci.low, "high": ci.high, "level": ci.level}
        split_records[name] = rec
    whole = split_records["all"]
    hk, ht = HEADLINE
    return {
        "label": method.label,
        # kept as before: all objects of all selected frames
        "recall": whole["all"]["recall"],
        "ar_micro": whole["all"]["ar"]["micro"],
        "ar_class_mean": whole["all"]["ar"]["class_mean"],
        "recall_moderate": whole["moderate"]["recall"],
        "per_class_headline": {
            objects: {c: whole[objects]["recall"]["per_class"][c][str(hk)][f"{ht:g}"] for c in frames.classes}
            for objects in OBJECT_SETS
        },
        "splits": split_records,
        "timing": timing,
        "curves": curve,
    }


def _pair_with_reference(results: dict[str, Any], hits: dict[str, list[torch.Tensor]],
                         splits: list[tuple[str, list[int]]], done: list[str], reference: str | None) -> None:
    """Each method's objects found and lost against ``reference``, with the sign test, per split."""
    if reference is None:
        return
    for k in done:
        for split, idx in splits:
            c = compare_recall([hits[reference][i] for i in idx], [hits[k][i] for i in idx])
            results[k]["splits"][split]["versus_reference"] = {
                "reference": reference, "gained": c.gained, "lost": c.lost, "p_value": c.p_value}


def in_sample_frames(keys: Sequence[str], frames: _Frames) -> dict[str, dict[str, str]]:
    """For each REEB row ``keys`` whose preset ranks with a learned model: the frames that model
    was fitted on (the same pictures, :func:`~reeb_torch.ranker.fitted_frames`), ``{frame id:
    the model's name for it}``; rows whose model saw none of them are left out. Its recall
    there is in-sample, not an estimate."""
    from .. import get_preset
    from ..ranker import fitted_frames, load_ranker

    out: dict[str, dict[str, str]] = {}
    looked: dict[str, dict[str, str]] = {}
    for k in keys:
        spec = get_preset(METHODS[k].preset or "default").ranker
        if spec == "none":
            continue
        if spec not in looked:
            names = fitted_frames(load_ranker(spec), frames.images)
            looked[spec] = {i: n for i, n in zip(frames.ids, names) if n is not None}
        if looked[spec]:
            out[k] = looked[spec]
    return out


def _in_sample_note(seen: dict[str, dict[str, str]], frames: _Frames, results: dict[str, Any]) -> str:
    if not seen:
        return ""
    ids = next(iter(seen.values()))
    rows = ", ".join(results[k]["label"] for k in seen)
    return (f"In-sample: {len(ids)} of these {len(frames.images)} frames are pictures the learned ranking was "
            f"fitted on ({first_few(list(ids))}; table3.json: in_sample), so the rows ranked by it ({rows}) are not an "
            "estimate there; --exclude-fitted leaves them out.")


def _report(args: argparse.Namespace, rerun: str, env: dict, frames: _Frames, splits: list[tuple[str, list[int]]],
            results: dict[str, Any], done: list[str], reference: str | None,
            seen: dict[str, dict[str, str]] | None = None) -> str:
    """The text of ``table3.txt``: the rerun line, the header (with a note where a learned
    ranking was fitted on some of the frames: ``seen``, :func:`in_sample_frames`), then the
    tables of each split, the AR lines and the paper's Table 3."""
    blocks = []
    for split, idx in splits:
        blocks += _split_blocks(args, frames, split, idx, len(splits), results, done, reference)
    ar_lines = ["Average recall (%, IoU 0.5:0.05:0.95, all objects)   micro @500 / @1000 / @2000  |  "
                "class mean @500 / @1000 / @2000"]
    width = _label_width(results, done)
    for k in done:
        a, c = results[k]["ar_micro"], results[k]["ar_class_mean"]
        ar_lines.append(f"{results[k]['label']:<{width}} " + " / ".join(f"{_fmt(_pct(a[str(kk)])):>5}" for kk in KS)
                        + "  |  " + " / ".join(f"{_fmt(_pct(c[str(kk)])):>5}" for kk in KS))
    blocks.append("\n".join(ar_lines))
    blocks.append(format_table(
        "The paper's Table 3 (7481 KITTI frames, C++ on an i7-8750H; its Edge Boxes uses SE edges)",
        [(n, v, f"{t:,}") for n, (v, t) in PAPER_TABLE3.items()]))
    counts = ", ".join(f"{c} {n}" for c, n in zip(frames.classes, _class_counts(frames.labels, len(frames.classes))))
    frames_note = f", --frames {' '.join(r.text for r in args.frames)}" if args.frames else ""
    if args.exclude_fitted:
        frames_note += ", --exclude-fitted: frames a learned ranking was fitted on left out"
    header = (f"Table 3 on {len(frames.images)} frames of {_data_text(args)} ({_frame_span(frames.ids)}{frames_note}; "
              f"{frames.n_obj} objects: {counts}).\n"
              f"Time: wall ms per image of the proposal call only (decoding excluded), batch size 1"
              f"{f'; REEB also at batch {args.batch} (@b{args.batch})' if args.batch > 1 else ''}; "
              f"{env['processor']}, {env['cpu_count']} cores, torch threads {env['torch_threads']}, "
              f"OpenCV threads {env['opencv_threads']}, CUDA {'yes' if env['cuda'] else 'no'}.")
    notes = [n for n in (_in_sample_note(seen or {}, frames, results), _held_out_note(results, done)) if n]
    return "\n\n".join([f"Rerun: {rerun}", header, *notes, *blocks]) + "\n"


def _held_out_note(results: dict[str, Any], done: Sequence[str]) -> str:
    """What the rows ranked by held-out models (--cross-validate, --leave-folder-out) are."""
    lines = []
    for k in (CROSS_VALIDATED, LEAVE_FOLDER_OUT):
        if k not in done:
            continue
        t, label = results[k]["timing"], results[k]["label"]
        lines.append(
            f"Cross-validated: the row {label} ranks each of {t['folds']} blocks of these frames with a model fitted "
            "on the other blocks (no drive neighbour or near-copy of a block on the training side; reeb fit's "
            f"options and seed, the same models as reeb fit --folds {t['folds']}; {t['fit_s']:.0f} s in all)."
            if k == CROSS_VALIDATED else
            f"Other folders: the row {label} ranks each data folder's frames with a model fitted on the other "
            f"folders (reeb fit's options and seed; {t['fit_s']:.0f} s in all).")
    if lines:
        lines.append(f"These rows are estimates; every row is paired with {results[_reference(done) or done[0]]['label']}.")
    return "\n".join(lines)


def _split_blocks(args: argparse.Namespace, frames: _Frames, split: str, idx: list[int], n_splits: int,
                  results: dict[str, Any], done: list[str], reference: str | None) -> list[str]:
    """The tables of one split of the frames: micro, moderate (and, for all frames, the
    class mean), the headline with its interval and pairings, the per-class table."""
    def time_cell(k: str) -> str:
        t = results[k]["timing"]
        if t["ms_per_img"] is None:
            return f"(fit {t['fit_s']:.0f} s)"
        s = f"{t['ms_per_img']:.0f}"
        bk = f"ms_per_img_batch{args.batch}"
        return s + (f" ({t[bk]:.0f} @b{args.batch})" if bk in t else "")

    def grid_rows(objects: str, average: str) -> list[tuple[str, list[float], str]]:
        rows = []
        for k in done:
            grid = results[k]["splits"][split][objects]["recall"][average]
            vals = [_pct(grid[str(kk)][f"{t:g}"]) for kk in KS for t in IOUS]
            rows.append((results[k]["label"], vals, time_cell(k)))
        return rows

    mod_rule = KITTI_DIFFICULTIES["moderate"]
    mod_text = (f"height >= {mod_rule.min_height:g} px, occlusion <= {mod_rule.max_occlusion}, "
                f"truncation <= {mod_rule.max_truncation:g}")
    blocks = []
    span = f"{len(idx)} frames {_frame_span([frames.ids[i] for i in idx])}"
    name = _split_name(split)
    where = span if split == "all" else f"{name} ({span})"
    if n_splits > 1:
        blocks.append(f"=== {'all selected frames' if split == 'all' else name}: {span} ===")
    any_rec = results[done[0]]["splits"][split] if done else None
    n_all = any_rec["all"]["recall"]["num_objects"] if any_rec else 0
    n_mod = any_rec["moderate"]["recall"]["num_objects"] if any_rec else 0
    blocks.append(format_table(
        f"Recall (%) over all objects (micro, {n_all} objects, {where}) - headline, as Table 3",
        grid_rows("all", "micro")))
    blocks.append(format_table(
        f"Recall (%) over KITTI-moderate objects (micro, {n_mod} objects: {mod_text})",
        grid_rows("moderate", "micro")))
    if split == "all":
        blocks.append(format_table(
            f"Recall (%), mean of the per-class recalls ({', '.join(frames.classes)}; all objects)",
            grid_rows("all", "class_mean")))
    blocks.append(_interval_block(split, results, done, reference))
    blocks.append(format_per_class(
        f"Per-class recall (%) at {HEADLINE[0]} proposals, IoU {HEADLINE[1]:g} ({where})",
        [(results[k]["label"], {o: results[k]["splits"][split][o]["recall"] for o in OBJECT_SETS})
         for k in done], frames.classes))
    return blocks


def _label_width(results: dict[str, Any], done: Sequence[str]) -> int:
    """The width of the label column of the one-line-per-method blocks."""
    return max([30, *(len(results[k]["label"]) for k in done)])


def _split_name(split: str) -> str:
    """How the tables name a split: ``frames 0:39`` for a frame range, ``folder kitti`` for a
    data folder."""
    return f"frames {split}" if split.replace(":", "").isdigit() else f"folder {split}"


def _interval_block(split: str, results: dict[str, Any], done: list[str], reference: str | None) -> str:
    """The headline of each method with its 95 % interval, and its pairing with the reference."""
    ci_rows = []
    width = _label_width(results, done)
    for k in done:
        ci = results[k]["splits"][split]["headline_interval"]
        ci_rows.append(f"{results[k]['label']:<{width}} {100 * ci['recall']:5.1f}   {100 * ci['low']:5.1f} - "
                       f"{100 * ci['high']:5.1f}")
    for k in done:
        if reference is not None and k != reference:
            v = results[k]["splits"][split]["versus_reference"]
            ci_rows.append(f"{results[k]['label']:<{width}} vs {results[reference]['label']}: +{v['gained']} / "
                           f"-{v['lost']} objects, p = {v['p_value']:.2g}")
    return "\n".join([f"Recall (%) at {HEADLINE[0]} proposals, IoU {HEADLINE[1]:g}, all objects, with its "
                      "95 % interval (frames drawn with replacement, 4000 draws); each row paired with "
                      "the reference on the same objects (+ found by the row only / - by the reference "
                      "only, exact two-sided sign test)", *ci_rows])


def _write_csv(path: Path, results: dict[str, Any], done: list[str], splits: list[tuple[str, list[int]]],
               classes: Sequence[str], batch: int) -> None:
    """``table3.csv``: one row per method × frames × objects × average."""
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["method", "label", "frames", "objects", "average", "num_objects"]
                   + [f"R@{k}_IoU{t:g}" for k in KS for t in IOUS]
                   + [f"AR@{k}" for k in KS] + ["ms_per_img", f"ms_per_img_batch{batch}"])
        for k in done:
            r = results[k]
            for split, _ in splits:
                for objects in OBJECT_SETS:
                    rec = r["splits"][split][objects]
                    rows = [("micro", rec["recall"]["micro"], rec["ar"]["micro"], rec["recall"]["num_objects"]),
                            ("class_mean", rec["recall"]["class_mean"], rec["ar"]["class_mean"], "")]
                    rows += [(c, rec["recall"]["per_class"][c], rec["ar"]["per_class"][c],
                              rec["recall"]["num_per_class"][c]) for c in classes]
                    for average, grid, ar, n in rows:
                        w.writerow([k, r["label"], split, objects, average, n]
                                   + [_fmt(_pct(grid[str(kk)][f"{t:g}"]), 2) for kk in KS for t in IOUS]
                                   + [_fmt(_pct(ar[str(kk)]), 2) for kk in KS]
                                   + [_fmt(r["timing"]["ms_per_img"], 1),
                                      _fmt(r["timing"].get(f"ms_per_img_batch{batch}"), 1)])


def _record(args: argparse.Namespace, rerun: str, env: dict, frames: _Frames, splits: list[tuple[str, list[int]]],
            results: dict[str, Any], plots: list[str]) -> dict[str, Any]:
    """The JSON record ``main`` returns and writes to ``table3.json``."""
    mod_rule = KITTI_DIFFICULTIES["moderate"]
    return {
        "rerun": rerun,
        "data": [str(d) for d in args.data],
        "num_images": len(frames.images),
        "image_ids": frames.ids,
        "frames": [r.text for r in args.frames],
        "splits": {name: [frames.ids[i] for i in idx] for name, idx in splits},
        "num_objects": frames.n_obj,
        "classes": list(frames.classes),
        "ks": list(KS),
        "ious": list(IOUS),
        "moderate": {"min_height": mod_rule.min_height, "max_occlusion": mod_rule.max_occlusion,
                     "max_truncation": mod_rule.max_truncation},
        "max_proposals": args.max_proposals,
        "batch": args.batch,
        "environment": env,
        "methods": results,
        "paper_table3": {n: {"recall": v, "ms_per_img": t} for n, (v, t) in PAPER_TABLE3.items()},
        "plots": plots,
    }
