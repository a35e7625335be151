"""The paper's Table 3 on KITTI-format folders, computed: recall of REEB and of the classical baselines.

The rows and the options are :mod:`reeb_torch.eval.methods`' (:data:`~reeb_torch.eval.methods.METHODS`,
:class:`~reeb_torch.eval.methods.Table3Options`); :func:`compute` runs them.

Recall counts every non-DontCare object of the four classes (Car, Pedestrian, Cyclist,
Truck), over all objects and over KITTI-*moderate* objects (box height >= 25 px, occlusion
<= 1, truncation <= 0.3: :data:`reeb_torch.metrics.recall.KITTI_DIFFICULTIES`); micro, class
mean and per class; average recall (AR, IoU 0.5:0.05:0.95); the headline (2000 proposals,
IoU 0.7, all objects) with its 95 % frame-bootstrap interval
(:func:`reeb_torch.metrics.recall.recall_interval`); and each method paired with a reference row
on the same objects (:func:`reeb_torch.metrics.recall.compare_recall`). Every number is given for
all selected frames, for each data folder when there are several, and for each frame range
when there are several.

Timing is the wall time of the proposal call alone (images are decoded beforehand), one
image at a time, after one untimed warm-up call; REEB is also timed in batches of ``batch``
images (reported separately, total time / images).

>>> from reeb_torch.eval.methods import Table3Options
>>> from reeb_torch.eval.table3 import compute
>>> table = compute(Table3Options(data=["kitti/"], limit=10, methods=["reeb-default"]))
>>> table.results["reeb-default"]["recall"]["micro"]["2000"]["0.7"]

:mod:`reeb_torch.eval.report` renders a :class:`Table3` (text, CSV, JSON, plots through
:mod:`reeb_torch.eval.plots`); :mod:`reeb_torch.eval.command` is ``reeb eval``.
"""

from __future__ import annotations

import math
import os
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import torch

from ..datasets.folders import folder_names, folder_splits, load_folders
from .common import first_few
from ..metrics.recall import (
    AR_IOUS,
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
from .methods import (
    CROSS_VALIDATED,
    HEADLINE,
    IOUS,
    KS,
    METHODS,
    WHOLE_DRIVES,
    Method,
    Table3Error,
    Table3Options,
)

__all__ = [
    "CURVE_IOUS",
    "OBJECT_SETS",
    "PAPER_TABLE3",
    "Frames",
    "Table3",
    "compute",
    "load_frames",
    "run_method",
    "recall_tables",
    "moderate_masks",
    "in_sample_frames",
    "cross_validated_boxes",
]

CURVE_IOUS = tuple(round(0.3 + 0.05 * i, 2) for i in range(15))  # 0.3 .. 1.0
OBJECT_SETS = ("all", "moderate")
"""Which objects are counted: every object, or KITTI-moderate ones only."""

# The paper's Table 3 (KITTI training set, all 7481 frames; micro or class mean is not said).
PAPER_TABLE3: dict[str, tuple[list[float], float]] = {
    "BING [14]": ([55.5, 41.5, 33.1, 73.3, 58.3, 49.8, 78.7, 66.0, 56.5], 30),
    "Selective Search [16]": ([73.0, 47.5, 30.0, 84.0, 61.1, 42.2, 89.7, 73.0, 54.8], 4300),
    "Edge Boxes [20]": ([66.6, 55.8, 48.6, 68.4, 57.0, 49.0, 87.6, 79.4, 70.0], 27),
    "Ours*": ([54.9, 45.0, 37.8, 68.5, 57.5, 49.8, 80.9, 71.0, 63.4], 40),
    "Ours**": ([67.3, 53.0, 43.1, 75.2, 61.3, 56.0, 89.5, 81.0, 72.1], 15),
}


def _call(method: Method, model: Callable, images: list[torch.Tensor]) -> list[dict]:
    """Proposals for a list of images: one call for REEB, one call per image otherwise."""
    if method.batched:
        return model(images)
    return [model(im) for im in images]


def run_method(
    method: Method,
    images: list[torch.Tensor],
    top_k: int,
    batch: int,
    **options: Any,
) -> tuple[list[torch.Tensor], dict[str, Any]]:
    """Run one method over the images (uint8 ``Tensor[3, H, W]`` each); return its ranked
    boxes per image (``Tensor[N_i, 4]``, CPU, at most ``top_k``) and its timings (ms
    per image)."""
    from tqdm import tqdm

    model = method.build(top_k, **options)
    _call(method, model, images[:1])  # warm-up, untimed (lazy allocations, caches)
    boxes: list[torch.Tensor] = []
    seconds: list[float] = []
    for im in tqdm(images, desc=f"{method.label:<30}", unit="img", file=sys.stderr, dynamic_ncols=True):
        t0 = time.perf_counter()
        (out,) = _call(method, model, [im])
        seconds.append(time.perf_counter() - t0)
        boxes.append(out["boxes"].detach().cpu()[:top_k])
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
        :data:`reeb_torch.metrics.recall.AR_IOUS` (its mean over IoUs is the average recall).
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


# -- what to compute -------------------------------------------------------------------------


@dataclass
class Frames:
    """The selected frames of the data folders, decoded: per frame its dataset item (see
    :func:`reeb_torch.datasets.folders.load_kitti`), image (uint8 ``Tensor[3, H, W]``), boxes
    (``Tensor[N_i, 4]``), labels (int64 ``Tensor[N_i]``) and id; ``n_obj`` objects in all."""

    items: list[dict]
    classes: tuple[str, ...]
    images: list[torch.Tensor]
    gts: list[torch.Tensor]
    labels: list[torch.Tensor]
    ids: list[str]
    n_obj: int

    def subset(self, keep: Sequence[int]) -> Frames:
        """The frames at the indices ``keep``, in that order."""
        def pick(xs: list) -> list:
            return [xs[i] for i in keep]

        return Frames(pick(self.items), self.classes, pick(self.images), pick(self.gts), pick(self.labels),
                      pick(self.ids), sum(int(self.gts[i].shape[0]) for i in keep))


@dataclass
class Table3:
    """The computed table: every method's record (:attr:`results`, keyed by method; what
    ``table3.json``'s ``methods`` holds) and what the report needs beside it."""

    options: Table3Options
    frames: Frames
    splits: list[tuple[str, list[int]]]
    """``(name, frame indices)``: ``"all"``, then each folder, then each frame range."""
    results: dict[str, Any]
    done: list[str]
    """The rows that ran (not skipped), in table order."""
    reference: str | None
    """The row every row is paired with on the same objects."""
    curves: dict[str, dict] = field(default_factory=dict)
    """Recall against k and against IoU, keyed by label."""
    in_sample: dict[str, dict[str, str]] = field(default_factory=dict)
    """:func:`in_sample_frames` of the REEB rows run."""
    excluded: dict[str, str] = field(default_factory=dict)
    """The frames ``exclude_fitted`` left out, ``{id: the model's name for it}``."""


def compute(options: Table3Options) -> Table3:
    """Decode the frames, run every method of ``options`` and compute its tables.

    Raises:
        Table3Error: no usable frame (not a KITTI folder, no labels, no object, every frame
            left out), or more folds than frames.
    """
    frames = load_frames(options)
    excluded: dict[str, str] = {}
    if options.exclude_fitted:
        frames, excluded = _without_fitted(frames, [k for k in options.rows if options.ranker_of(k)], options)
    if options.cross_validate > len(frames.images):
        raise Table3Error(f"--cross-validate {options.cross_validate} needs at least as many frames, "
                          f"got {len(frames.images)}")
    splits = frame_splits(options, frames)
    results, curves, hits = _run_methods(options, frames, splits)
    done = [k for k in options.rows if "recall" in results[k]]
    reference = reference_row(done)
    _pair_with_reference(results, hits, splits, done, reference)
    # after exclude_fitted no frame left was seen: no need to hash them again
    ranked = {k: options.ranker_of(k) for k in done if options.ranker_of(k)}
    seen = {} if options.exclude_fitted else in_sample_frames(list(ranked), frames, ranked)
    return Table3(options, frames, splits, results, done, reference, curves, seen, excluded)


def reference_row(done: Sequence[str]) -> str | None:
    """The row every row is paired with on the same objects: the package default; where a
    cross-validated row ran (the frames are labelled ones the shipped model may have seen),
    ``training-free``; else the first row run."""
    held_out = any(METHODS[k].cross_validated for k in done)
    order = ["reeb-training-free", "reeb-default"] if held_out else ["reeb-default"]
    return next((k for k in order if k in done), done[0] if done else None)


def load_frames(options: Table3Options) -> Frames:
    """The selected frames, decoded (:func:`reeb_torch.datasets.folders.load_folders`).

    Raises:
        Table3Error: unusable data, or the selected frames hold no object.
    """
    t0 = time.perf_counter()
    try:
        items, classes = load_folders(options.data, limit=options.limit, frames=options.frames)
    except (ValueError, FileNotFoundError) as e:
        raise Table3Error(" ".join(str(e).split())) from None
    gts = [it["boxes"] for it in items]
    frames = Frames(items, classes, [it["image"] for it in items], gts, [it["labels"] for it in items],
                    [it["image_id"] for it in items], sum(int(g.shape[0]) for g in gts))
    if frames.n_obj == 0:
        raise Table3Error(f"{options.data_text}: the {len(items)} selected frames hold no object of "
                          f"{', '.join(classes)}; recall is undefined")
    print(f"{len(frames.images)} frames from {options.data_text} ({frames.n_obj} objects of {', '.join(classes)}), "
          f"decoded in {time.perf_counter() - t0:.1f} s", flush=True)
    return frames


def _without_fitted(frames: Frames, keys: Sequence[str], options: Table3Options) -> tuple[Frames, dict[str, str]]:
    """``exclude_fitted``: ``frames`` less those a learned ranking of the REEB rows ``keys``
    was fitted on, and those left out (``{id: the model's name for it}``); a
    :class:`Table3Error` when nothing with an object is left."""
    left: dict[str, str] = {}
    for seen in in_sample_frames(keys, frames, {k: options.ranker_of(k) for k in keys}).values():
        left.update(seen)
    out = frames.subset([i for i, f in enumerate(frames.ids) if f not in left])
    if out.n_obj == 0:
        raise Table3Error(f"--exclude-fitted leaves {len(out.ids)} of the {len(frames.ids)} frames of "
                          f"{options.data_text}, with no object: the learned ranking was fitted on the others")
    print(f"--exclude-fitted: left out {len(left)} frames the learned ranking was fitted on"
          + (f" ({first_few(list(left))})" if left else ""), flush=True)
    return out, left


def frame_splits(options: Table3Options, frames: Frames) -> list[tuple[str, list[int]]]:
    """Frame splits: the whole selection, then each data folder when there are several, then
    each frame range when there are several."""
    ids = frames.ids
    splits: list[tuple[str, list[int]]] = [("all", list(range(len(ids))))]
    splits += folder_splits(frames.items)
    if len(options.frames) > 1:
        for r in options.frames:
            splits.append((r.text, [i for i, f in enumerate(ids) if int(f) in r]))
    return splits


def _pct_text(v: float | None, digits: int = 1) -> str:
    return "-" if v is None or math.isnan(v) else f"{100 * v:.{digits}f}"


def _run_methods(options: Table3Options, frames: Frames, splits: list[tuple[str, list[int]]]
                 ) -> tuple[dict[str, Any], dict[str, dict], dict[str, list[torch.Tensor]]]:
    """Each method's proposals and their record: ``(results, curves, hits)``, keyed by method
    (curves by label; hits: per-frame headline hits, for the pairing)."""
    results: dict[str, Any] = {}
    curves: dict[str, dict] = {}
    hits: dict[str, list[torch.Tensor]] = {}  # method -> per-frame headline hits
    prepared: dict[str, Any] = {}  # the held-out rows' frames and candidates, taken once
    for key in options.rows:
        method = METHODS[key]
        try:
            if method.cross_validated:
                folds = (options.cross_validate if key in (CROSS_VALIDATED, WHOLE_DRIVES)
                         else [idx for _, idx in folder_splits(frames.items)])
                boxes, timing = cross_validated_boxes(frames, options.data, folds, options.top_k, prepared,
                                                      whole_drives=key == WHOLE_DRIVES)
            else:
                boxes, timing = run_method(method, frames.images, options.top_k, options.batch,
                                           bing_model=options.bing_model, config=options.config,
                                           device=options.device)
        except (FileNotFoundError, ImportError) as e:  # e.g. no BING model folder
            print(f"skipped {method.label}: {e}", flush=True)
            results[key] = {"label": method.label, "skipped": str(e)}
            continue
        ks_curve, r_k = recall_vs_proposals(boxes, frames.gts, iou=0.7, max_k=options.top_k)
        ious_curve, r_iou = recall_vs_iou(boxes, frames.gts, k=max(KS), ious=CURVE_IOUS)
        curves[method.label] = {"ks": ks_curve.tolist(), "recall_vs_k": r_k.tolist(),
                                "ious": ious_curve.tolist(), "recall_vs_iou": r_iou.tolist()}
        hits[key] = object_hits(boxes, frames.gts, *HEADLINE)  # once; each split takes its frames' hits
        results[key] = _method_record(method, boxes, timing, hits[key], curves[method.label], frames, splits)
        whole = results[key]["splits"]["all"]
        hk, ht = str(HEADLINE[0]), f"{HEADLINE[1]:g}"
        ms = timing["ms_per_img"]
        print(f"  {method.label}: recall@2000 IoU0.7 micro {_pct_text(whole['all']['recall']['micro'][hk][ht])} %, "
              f"moderate {_pct_text(whole['moderate']['recall']['micro'][hk][ht])} %, "
              f"{'-' if ms is None else f'{ms:.0f}'} ms/img", flush=True)
    return results, curves, hits


def cross_validated_boxes(frames: Frames, roots: Sequence[str | os.PathLike], folds: int | Sequence[Sequence[int]],
                          top_k: int,
                          prepared: dict[str, Any] | None = None,
                          whole_drives: bool = False) -> tuple[list[torch.Tensor], dict[str, Any]]:
    """The default's ranked boxes (``Tensor[N_i, 4]``, at most ``top_k``) on each of
    ``frames`` (read from the folders ``roots``), each ranked by a model fitted without the
    frame's block of ``folds`` (a number of blocks, or the blocks: the frame indices of each;
    :func:`reeb_torch.ranker.cv.held_out_outputs`, with ``reeb fit``'s default options and seed:
    the same models as ``reeb fit ROOTS --folds FOLDS``; ``whole_drives``: without any frame
    of the block's drives either, as ``reeb fit --whole-drives``), and the
    seconds it took (``fit_s``: candidates, fits, proposals; no ms per image: the row runs the
    default's code, whose row times it). ``prepared``: a dict kept between calls on the same
    frames, which holds their candidates and training rows after the first (then not timed
    again)."""
    from tqdm import tqdm

    from .. import get_preset
    from ..ranker.fit import FitOptions
    from ..ranker.frames import FitFrames, frame_samples, other_boxes
    from ..ranker.cv import held_out_outputs
    from ..tuning import FrameCache

    def bar(desc: str) -> Callable:
        return lambda items: tqdm(items, desc=f"{'cross-validated: ' + desc:<30}", file=sys.stderr, dynamic_ncols=True)

    t0 = time.perf_counter()
    cfg, opts = get_preset("default").replace(top_k=top_k), FitOptions()
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
    # reeb fit's gaps: drive frames within 2 of a held-out block stay out, or (whole drives) all of them
    gap = len(frames.ids) if whole_drives else 2
    outputs = held_out_outputs(prepared["cache"], cfg, prepared["samples"], opts, folds, gap,
                               progress=bar("whole drives" if whole_drives else "folds"))
    boxes = [o["boxes"][:top_k] for o in outputs]
    timing = {"ms_per_img": None, "fit_s": time.perf_counter() - t0,
              "folds": folds if isinstance(folds, int) else len(folds), "whole_drives": whole_drives,
              "batch_size": 1,
              "num_proposals_mean": sum(b.shape[0] for b in boxes) / len(boxes)}
    return boxes, timing


def _method_record(method: Method, boxes: list[torch.Tensor], timing: dict, hits: list[torch.Tensor], curve: dict,
                   frames: Frames, splits: list[tuple[str, list[int]]]) -> dict[str, Any]:
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
        # the headline entries: all objects of all selected frames
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


def in_sample_frames(keys: Sequence[str], frames: Frames,
                     rankers: Mapping[str, str | None] | None = None) -> dict[str, dict[str, str]]:
    """For each REEB row ``keys`` whose preset ranks with a learned model: the frames that model
    was fitted on (the same pictures, :func:`~reeb_torch.ranker.fitted_frames`), ``{frame id:
    the model's name for it}``; rows whose model saw none of them are left out. Its recall
    there is in-sample, not an estimate. ``rankers``: each row's model where it is not its
    preset's (:meth:`~reeb_torch.eval.methods.Table3Options.ranker_of`)."""
    from .. import get_preset
    from ..ranker import fitted_frames, load_ranker

    out: dict[str, dict[str, str]] = {}
    looked: dict[str, dict[str, str]] = {}
    for k in keys:
        spec = (rankers or {}).get(k) or get_preset(METHODS[k].preset or "default").ranker
        if spec == "none":
            continue
        if spec not in looked:
            names = fitted_frames(load_ranker(spec), frames.images)
            looked[spec] = {i: n for i, n in zip(frames.ids, names) if n is not None}
        if looked[spec]:
            out[k] = looked[spec]
    return out
