"""KITTI's 2D detection AP (AP|R40), as the object devkit computes it, with frame-bootstrap
intervals.

The protocol of KITTI's ``evaluate_object.cpp`` (and its Python port in the ``kitti_eval``
of SECOND / OpenPCDet), for one class and one difficulty level:

- **Ground truth.** An object of the class counts (``ignored_gt = 0``) unless its box is at
  most ``min_height`` px tall, or more occluded or truncated than the level allows; then it
  is ignored (1). Objects of the neighbouring class (``Van`` for ``Car``,
  ``Person_sitting`` for ``Pedestrian``) are ignored too; every other object is left out
  (-1). ``DontCare`` boxes are kept apart.
- **Detections** of the class lower than ``min_height`` px are ignored (1): they are neither
  true nor false positives.
- **Matching**, per frame: each object, in file order, takes the still unassigned
  detection above the score threshold with overlap > ``min_overlap`` (strictly; IoU) —
  the highest-scoring one in the first pass, the best-overlapping non-ignored one when
  counting false positives. A detection on an ignored object or an ignored detection is
  neither. Unassigned detections are false positives unless more than ``min_overlap`` of
  their area lies in a ``DontCare`` box.
- **Curve.** The first pass collects the scores of the true positives; 41 thresholds are
  picked from them at recall steps of 1/40 (``get_thresholds``); precision and recall are
  counted at each, precision is made non-increasing from the right, and AP|R40 is the mean
  of the 40 precisions at indices 1..40 (index 0, recall 0, is left out).

Deviations: none in the rules above. The difficulty bounds are
:data:`reeb_torch.metrics.recall.KITTI_DIFFICULTIES` (moderate: taller than 25 px, occlusion
<= 1, truncation <= 0.3); the devkit ignores an object exactly 25.00 px tall, as done here,
where :func:`~reeb_torch.metrics.recall.kitti_difficulty_mask` (recall) keeps it.

Boxes: ``(x1, y1, x2, y2)`` pixels, float, the frame of the label files; the overlap is
``inter / union`` with no ``+1`` (the devkit's ``boxoverlap``).

>>> stats = evaluate(gts, detections, ("Car", "Pedestrian", "Cyclist"))
>>> ap = {c: average_precision(s) for c, s in stats.items()}
>>> bootstrap(stats, samples=1000)["Car"]          # (low, high)
>>> paired_bootstrap(stats_a, stats_b)["mAP"].diff    # B - A, the same frames drawn for both
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from ..datasets.kitti import KittiObject
from .recall import KITTI_DIFFICULTIES, KittiDifficulty

__all__ = [
    "MIN_OVERLAP",
    "NEIGHBOURS",
    "N_SAMPLE_PTS",
    "FrameStats",
    "frame_stats",
    "evaluate",
    "get_thresholds",
    "average_precision",
    "kitti_ap",
    "bootstrap",
    "PairedDifference",
    "paired_bootstrap",
]

MIN_OVERLAP: dict[str, float] = {"Car": 0.7, "Pedestrian": 0.5, "Cyclist": 0.5}
"""KITTI's IoU threshold per class for 2D AP."""
NEIGHBOURS: dict[str, str] = {"Car": "Van", "Pedestrian": "Person_sitting"}
"""Objects of these classes are ignored (never a false negative, never make a false positive)."""
N_SAMPLE_PTS = 41
"""Recall points of the devkit's curve; AP|R40 averages points 1..40."""
_NO_DETECTION = -10000000.0


@dataclass(frozen=True)
class FrameStats:
    """One frame, one class: what the devkit counts there, for every score threshold.

    Attributes:
        tp_scores: ``float64 [T]``: scores of the first pass's true positives.
        num_gt: objects that count (``ignored_gt == 0``).
        cuts: ``float64 [K]``: the frame's distinct detection scores, ascending.
        counts: ``int64 [K + 1, 3]``: ``(tp, fp, fn)`` with the detections of score
            ``>= cuts[k]`` kept; row ``K``: none kept.
    """

    tp_scores: np.ndarray
    num_gt: int
    cuts: np.ndarray
    counts: np.ndarray

    def at(self, thresholds: np.ndarray) -> np.ndarray:
        """``int64 [len(thresholds), 3]``: ``(tp, fp, fn)`` keeping scores ``>= t``."""
        return self.counts[np.searchsorted(self.cuts, thresholds, side="left")]


def _overlap(a: np.ndarray, b: np.ndarray, over_a: bool = False) -> np.ndarray:
    """``[len(a), len(b)]``: IoU, or (``over_a``) intersection over the area of ``a``."""
    iw = np.minimum(a[:, None, 2], b[None, :, 2]) - np.maximum(a[:, None, 0], b[None, :, 0])
    ih = np.minimum(a[:, None, 3], b[None, :, 3]) - np.maximum(a[:, None, 1], b[None, :, 1])
    inter = np.clip(iw, 0, None) * np.clip(ih, 0, None)
    area_a = ((a[:, 2] - a[:, 0]) * (a[:, 3] - a[:, 1]))[:, None]
    area_b = ((b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1]))[None, :]
    denom = area_a if over_a else area_a + area_b - inter
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(denom > 0, inter / denom, 0.0)


def _ground_truth(objects: Sequence[KittiObject], cls: str,
                  level: KittiDifficulty) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(boxes [G, 4], ignored_gt [G] in {0, 1}, dontcare boxes [C, 4])``; objects marked -1
    by the devkit are left out here, which changes nothing (they are skipped)."""
    boxes, ignored, dontcare = [], [], []
    for o in objects:
        if o.type == "DontCare":
            dontcare.append(o.box)
            continue
        if o.type == cls:
            hard = (o.box[3] - o.box[1] <= level.min_height or o.occluded > level.max_occlusion
                    or o.truncated > level.max_truncation + 1e-6)
            boxes.append(o.box)
            ignored.append(1 if hard else 0)
        elif NEIGHBOURS.get(cls) == o.type:
            boxes.append(o.box)
            ignored.append(1)
    as_boxes = lambda b: np.asarray(b, dtype=np.float64).reshape(-1, 4)  # noqa: E731
    return as_boxes(boxes), np.asarray(ignored, dtype=np.int64), as_boxes(dontcare)


def _match(iou: np.ndarray, dc: np.ndarray, ignored_gt: np.ndarray, ignored_det: np.ndarray,
           scores: np.ndarray, kept: np.ndarray, min_overlap: float,
           compute_fp: bool) -> tuple[int, int, int, list[float]]:
    """The devkit's ``computeStatistics`` on one frame: ``(tp, fp, fn, tp scores)``.

    ``iou``: ``[D, G]``; ``dc``: ``[D, C]`` detection area inside each DontCare box;
    ``kept``: ``bool [D]``, detections at or above the threshold.
    """
    assigned = np.zeros(len(scores), dtype=bool)
    tp = fn = 0
    tp_scores: list[float] = []
    for g in range(iou.shape[1]):
        free = kept & ~assigned & (iou[:, g] > min_overlap)
        det = -1
        if not compute_fp:
            if free.any():
                det = int(np.flatnonzero(free)[np.argmax(scores[free])])
        else:
            good = free & (ignored_det == 0)
            if good.any():
                det = int(np.flatnonzero(good)[np.argmax(iou[good, g])])
            elif free.any():
                det = int(np.flatnonzero(free)[0])
        if det < 0:
            fn += int(ignored_gt[g] == 0)
        elif ignored_gt[g] == 1 or ignored_det[det] == 1:
            assigned[det] = True
        else:
            tp += 1
            tp_scores.append(float(scores[det]))
            assigned[det] = True
    fp = 0
    if compute_fp:
        free = kept & ~assigned & (ignored_det == 0)
        in_dontcare = (dc > min_overlap).any(1) if dc.shape[1] else np.zeros(len(scores), bool)
        fp = int((free & ~in_dontcare).sum())
    return tp, fp, fn, tp_scores


def frame_stats(objects: Sequence[KittiObject], boxes: Tensor | np.ndarray, scores: Tensor | np.ndarray,
                cls: str, level: str | KittiDifficulty = "moderate") -> FrameStats:
    """:class:`FrameStats` of one frame for class ``cls``.

    Args:
        objects: the frame's label lines, every type (DontCare and neighbours included).
        boxes: ``[D, 4]`` detections *of class* ``cls``; ``scores``: ``[D]``.
        level: ``"easy"``, ``"moderate"``, ``"hard"`` or a :class:`KittiDifficulty`.
    """
    lv = KITTI_DIFFICULTIES[level] if isinstance(level, str) else level
    det = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    sc = np.asarray(scores, dtype=np.float64).reshape(-1)
    gt, ignored_gt, dontcare = _ground_truth(objects, cls, lv)
    ignored_det = ((det[:, 3] - det[:, 1]) < lv.min_height).astype(np.int64)
    iou, dc = _overlap(det, gt), _overlap(det, dontcare, over_a=True)
    mo = MIN_OVERLAP[cls]
    _, _, _, tp_scores = _match(iou, dc, ignored_gt, ignored_det, sc, sc >= 0.0, mo, False)
    cuts = np.unique(sc)
    counts = [_match(iou, dc, ignored_gt, ignored_det, sc, sc >= t, mo, True)[:3] for t in cuts]
    counts.append(_match(iou, dc, ignored_gt, ignored_det, sc, np.zeros(len(sc), bool), mo, True)[:3])
    return FrameStats(np.asarray(tp_scores, dtype=np.float64), int((ignored_gt == 0).sum()), cuts,
                      np.asarray(counts, dtype=np.int64).reshape(-1, 3))


def get_thresholds(scores: np.ndarray, num_gt: int, num_sample_pts: int = N_SAMPLE_PTS) -> np.ndarray:
    """The devkit's ``getThresholds``: from the true positives' scores (descending), one
    score each time the recall passes the next of ``num_sample_pts - 1`` equal steps."""
    s = np.sort(np.asarray(scores, dtype=np.float64))[::-1]
    out, current = [], 0.0
    for i, score in enumerate(s):
        l_recall = (i + 1) / num_gt
        r_recall = (i + 2) / num_gt if i < len(s) - 1 else l_recall
        if (r_recall - current) < (current - l_recall) and i < len(s) - 1:
            continue
        out.append(score)
        current += 1.0 / (num_sample_pts - 1.0)
    return np.asarray(out, dtype=np.float64)


def average_precision(stats: Sequence[FrameStats]) -> float:
    """AP|R40 in [0, 1] of the frames ``stats`` (one class); ``nan`` with no object."""
    num_gt = sum(s.num_gt for s in stats)
    if num_gt == 0:
        return math.nan
    tp_scores = np.concatenate([s.tp_scores for s in stats]) if stats else np.zeros(0)
    thresholds = get_thresholds(tp_scores, num_gt)
    if len(thresholds) == 0:
        return 0.0
    totals = stats[0].at(thresholds)  # stats is not empty: there are thresholds
    for s in stats[1:]:
        totals = totals + s.at(thresholds)
    tp, fp = totals[:, 0].astype(np.float64), totals[:, 1].astype(np.float64)
    precision = np.zeros(N_SAMPLE_PTS)
    n = min(len(thresholds), N_SAMPLE_PTS)
    precision[:n] = tp[:n] / np.maximum(tp[:n] + fp[:n], 1e-12)
    precision = np.maximum.accumulate(precision[::-1])[::-1]
    return float(precision[1:].sum() / (N_SAMPLE_PTS - 1))


def evaluate(gts: Sequence[Sequence[KittiObject]], detections: Sequence[Mapping[str, Tensor]],
             classes: Sequence[str], level: str | KittiDifficulty = "moderate") -> dict[str, list[FrameStats]]:
    """Per class, the :class:`FrameStats` of every frame.

    Args:
        gts: per frame, its label lines (all types).
        detections: per frame, ``boxes [D, 4]``, ``scores [D]`` and ``labels [D]``
            (``int64``, index into ``classes``), in the pixels of the labels.
        classes: the class names the labels index; each must be in :data:`MIN_OVERLAP`.
    """
    if len(gts) != len(detections):
        raise ValueError(f"{len(gts)} label sets for {len(detections)} detection sets")
    unknown = [c for c in classes if c not in MIN_OVERLAP]
    if unknown:
        raise ValueError(f"no KITTI 2D overlap threshold for {unknown}; known: {list(MIN_OVERLAP)}")
    out: dict[str, list[FrameStats]] = {c: [] for c in classes}
    for objects, det in zip(gts, detections):
        labels = torch.as_tensor(det["labels"]).reshape(-1).cpu()
        boxes = torch.as_tensor(det["boxes"]).reshape(-1, 4).detach().cpu().double()
        scores = torch.as_tensor(det["scores"]).reshape(-1).detach().cpu().double()
        for i, c in enumerate(classes):
            m = labels == i
            out[c].append(frame_stats(objects, boxes[m].numpy(), scores[m].numpy(), c, level))
    return out


def kitti_ap(stats: Mapping[str, Sequence[FrameStats]], frames: Sequence[int] | None = None) -> dict[str, float]:
    """AP|R40 per class and their mean (``"mAP"``, over classes with objects), in [0, 1];
    ``frames``: indices of the frames to pool (repeats allowed; default all)."""
    out: dict[str, float] = {}
    for c, s in stats.items():
        out[c] = average_precision(s if frames is None else [s[i] for i in frames])
    defined = [v for v in out.values() if not math.isnan(v)]
    out["mAP"] = float(np.mean(defined)) if defined else math.nan
    return out


def bootstrap(stats: Mapping[str, Sequence[FrameStats]] | Sequence[Mapping[str, Sequence[FrameStats]]],
              samples: int = 1000, level: float = 0.95, seed: int = 0) -> dict[str, tuple[float, float]]:
    """Percentile intervals of :func:`kitti_ap` (each class and ``"mAP"``) over ``samples``
    draws of the frames with replacement: the objects of a frame share its scene, so frames,
    not objects, are the unit. ``nan`` draws (no object of a class drawn) are left out.
    ``stats`` may be a list of :func:`evaluate` results on the same frames (fits with other
    seeds): each draw then takes their mean AP."""
    runs = _runs(stats)
    (draws,) = _draws([runs], samples, seed)
    return {key: _span(np.asarray([d[key] for d in draws if not math.isnan(d[key])]), level)
            for key in [*runs[0], "mAP"]}


Arm = Mapping[str, Sequence[FrameStats]] | Sequence[Mapping[str, Sequence[FrameStats]]]
"""One arm for :func:`paired_bootstrap`: :func:`evaluate`'s result, or one per fit seed."""


def _runs(arm: Arm) -> list[Mapping[str, Sequence[FrameStats]]]:
    return [arm] if isinstance(arm, Mapping) else list(arm)


def _draws(arms: Sequence[Sequence[Mapping[str, Sequence[FrameStats]]]], samples: int,
           seed: int) -> list[list[dict[str, float]]]:
    """Per arm (its runs), :func:`_mean_ap` on each of ``samples`` draws of the frames with
    replacement, the same draws for every arm (seeded by ``seed``)."""
    n = len(next(iter(arms[0][0].values()), [])) if arms and arms[0] else 0
    if n == 0:
        raise ValueError("no frame to draw from")
    rng = np.random.default_rng(seed)
    out: list[list[dict[str, float]]] = [[] for _ in arms]
    for _ in range(samples):
        frames = rng.integers(0, n, n).tolist()
        for runs, got in zip(arms, out):
            got.append(_mean_ap(runs, frames))
    return out


def _span(values: np.ndarray, level: float) -> tuple[float, float]:
    """The percentile interval of ``values`` at ``level``; ``nan`` for none."""
    if len(values) == 0:
        return (math.nan, math.nan)
    low, high = np.quantile(values, [(1 - level) / 2, (1 + level) / 2])
    return float(low), float(high)


def _mean_ap(runs: Sequence[Mapping[str, Sequence[FrameStats]]], frames: Sequence[int] | None = None) -> dict[str, float]:
    """:func:`kitti_ap` averaged over ``runs`` (the same frames, other fits)."""
    aps = [kitti_ap(r, frames) for r in runs]
    return {k: float(np.mean([a[k] for a in aps])) for k in aps[0]}


@dataclass(frozen=True)
class PairedDifference:
    """Two detectors (arms A and B) on the same frames, one class (or ``"mAP"``); AP in [0, 1].

    Attributes:
        a, b: each arm's AP on all the frames.
        diff: ``b - a``.
        a_interval, b_interval: each arm's percentile interval over the draws.
        interval: the percentile interval of ``b - a`` over the same draws (frames drawn
            together for both arms).
        share_b_better: the share of draws where B beats A, ties counted half (0.5 for two
            identical arms); near 0 or 1 where one arm is better on nearly every draw.
        draws: draws where both arms had a defined AP (an object of the class drawn).
    """

    a: float
    b: float
    diff: float
    a_interval: tuple[float, float]
    b_interval: tuple[float, float]
    interval: tuple[float, float]
    share_b_better: float
    draws: int

    @property
    def verdict(self) -> str:
        """``"B better"`` / ``"A better"`` where the interval of ``b - a`` excludes 0, else
        ``"no difference shown"``."""
        if self.interval[0] > 0:
            return "B better"
        if self.interval[1] < 0:
            return "A better"
        return "no difference shown"


def paired_bootstrap(stats_a: Arm, stats_b: Arm, samples: int = 1000, level: float = 0.95,
                     seed: int = 0) -> dict[str, PairedDifference]:
    """The paired frame bootstrap of ``kitti_ap(stats_b) - kitti_ap(stats_a)``: each draw takes
    the frames with replacement and scores both arms on that same draw, so what the frames have
    in common (their objects, their difficulty) cancels out of the difference.

    Args:
        stats_a, stats_b: :func:`evaluate` of the two arms on the same frames, in the same
            order, with the same classes; or, for either, a list of them (fits with other
            seeds), whose APs are averaged on each draw: the arm's AP is then its mean over
            seeds, and the interval holds both the frames' and the seeds' spread as far as
            the seeds given show it.

    Returns:
        per class and ``"mAP"``, a :class:`PairedDifference` (``nan`` fields for a class
        without objects).

    Raises:
        ValueError: other classes, another number of frames, or objects that differ per frame
            (not the same frames), or no frame.
    """
    runs_a, runs_b = _runs(stats_a), _runs(stats_b)
    if not runs_a or not runs_b:
        raise ValueError("an arm without a run")
    first = runs_a[0]
    for other in runs_a[1:] + runs_b:
        if list(first) != list(other):
            raise ValueError(f"the arms score other classes: {list(first)} and {list(other)}")
        for c in first:
            if [s.num_gt for s in first[c]] != [s.num_gt for s in other[c]]:
                raise ValueError(f"{c}: the arms were not scored on the same frames (other frame counts or objects)")
    draws_a, draws_b = _draws([runs_a, runs_b], samples, seed)
    full_a, full_b = _mean_ap(runs_a), _mean_ap(runs_b)
    out: dict[str, PairedDifference] = {}
    for key in [*first, "mAP"]:
        pairs = np.asarray([(da[key], db[key]) for da, db in zip(draws_a, draws_b)
                            if not (math.isnan(da[key]) or math.isnan(db[key]))]).reshape(-1, 2)
        d = pairs[:, 1] - pairs[:, 0]
        share = float(((d > 0).sum() + 0.5 * (d == 0).sum()) / len(d)) if len(d) else math.nan
        out[key] = PairedDifference(full_a[key], full_b[key], full_b[key] - full_a[key], _span(pairs[:, 0], level),
                                    _span(pairs[:, 1], level), _span(d, level), share, int(len(d)))
    return out
