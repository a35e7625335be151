"""Proposal recall: the share of ground-truth objects covered by the top-k proposals.

Conventions, kept in every function:

- Boxes are ``Tensor[N, 4]``, ``(x1, y1, x2, y2)`` in pixels, float (any float dtype; the
  computation runs in ``float32`` on the proposals' device, results come back on the CPU).
- Proposals of one image are *ranked*: row 0 is the best. "The top k" are rows ``0..k-1``;
  an image with fewer than k proposals uses all it has, one with none covers nothing.
- A ground-truth box is *recalled* at IoU threshold t by the top k when its best IoU with
  them is ``>= t`` (Hosang et al., "What makes for effective detection proposals?",
  TPAMI 2016). IoU is :func:`torchvision.ops.box_iou`; degenerate boxes give IoU 0.
- Recall is counted over objects. *Micro* recall pools all objects of all images (the
  paper's Table 3 number). *Per-class* recall counts the objects of one class;
  the *class mean* averages the per-class recalls over the classes that have at least one
  object (a class with none has an undefined recall, ``nan``, and is left out).
- Images with no ground truth contribute nothing.

The work is one ``box_iou`` per image against the top ``max(ks)`` proposals and a
cumulative max along the ranking: ``run[g, j]`` is the best IoU of object g with
proposals ``0..j``, so the best IoU at any k is ``run[g, k - 1]``.

>>> result = recall_table(proposals, gt_boxes, gt_labels, ("Car", "Pedestrian"))
>>> print(result.format_table())
>>> result.to_dict()["micro"]["2000"]["0.7"]
>>> result.per_class_at(2000, 0.7)                     # {"Car": 0.8, "Pedestrian": 0.5}

KITTI's difficulty levels (the usual protocol of KITTI proposal papers reports the
*moderate* objects) select objects with :func:`kitti_difficulty_mask` and
:func:`select_objects` before the recall is computed.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Literal, Union

import torch
from torch import Tensor

__all__ = [
    "AR_IOUS", "RecallResult", "best_iou", "recall_table", "average_recall", "recall_vs_proposals",
    "recall_vs_iou", "KittiDifficulty", "KITTI_DIFFICULTIES", "kitti_difficulty_mask",
    "select_objects", "object_hits", "RecallInterval", "recall_interval", "bootstrap_recalls",
    "RecallComparison", "sign_test", "compare_recall"
]

AR_IOUS: tuple[float, ...] = tuple(round(0.5 + 0.05 * i, 2) for i in range(10))
"""IoU thresholds 0.5:0.05:0.95 of average recall (Hosang et al.; COCO)."""

Boxes = Union[Tensor, Mapping[str, Tensor]]
"""``Tensor[N, 4]``, or a mapping with a ``"boxes"`` entry (a proposal generator's output)."""


# ---------------------------------------------------------------------------------------
# checks and the core computation
# ---------------------------------------------------------------------------------------


def _as_boxes(b: Boxes, name: str) -> Tensor:
    if isinstance(b, Mapping):
        if "boxes" not in b:
            raise ValueError(f"{name}: a mapping must have a 'boxes' entry, has {sorted(b)}")
        b = b["boxes"]
    if not isinstance(b, Tensor):
        raise TypeError(f"{name}: expected Tensor[N, 4], got {type(b).__name__}")
    if b.ndim != 2 or b.shape[1] != 4:
        if b.numel() == 0:  # tolerate torch.empty(0) / Tensor[0] for "no boxes"
            return b.new_zeros((0, 4), dtype=torch.float32)
        raise ValueError(f"{name}: expected Tensor[N, 4] (x1, y1, x2, y2), got {tuple(b.shape)}")
    return b if b.is_floating_point() else b.float()


def _check_ks(ks: Sequence[int] | int) -> tuple[int, ...]:
    ks = (ks,) if isinstance(ks, int) else tuple(int(k) for k in ks)
    if not ks or min(ks) < 1:
        raise ValueError(f"ks must be positive numbers of proposals, got {ks}")
    return ks


def _check_ious(ious: Sequence[float] | float) -> tuple[float, ...]:
    ious = (float(ious),) if isinstance(ious, (int, float)) else tuple(float(t) for t in ious)
    if not ious or min(ious) < 0.0 or max(ious) > 1.0:
        raise ValueError(f"IoU thresholds must lie in [0, 1], got {ious}")
    return ious


def _running_best(proposals: Tensor, gt: Tensor, k_max: int) -> Tensor:
    """``Tensor[G, min(k_max, P)]``: best IoU of each GT box with proposals ``0..j``."""
    from torchvision.ops import box_iou  # here: its import takes ~2.7 s, which `reeb propose` need not pay

    p = proposals[:k_max].to(torch.float32)
    g = gt.to(device=p.device, dtype=torch.float32)
    iou = box_iou(g, p).nan_to_num_(0.0)  # 0/0 for two degenerate boxes
    return iou.cummax(dim=1).values


def _best_at(proposals: Tensor, gt: Tensor, ks: Sequence[int]) -> Tensor:
    """``Tensor[G, len(ks)]`` (CPU): best IoU of each GT box with the top k, for each k."""
    if gt.shape[0] == 0 or proposals.shape[0] == 0:
        return torch.zeros((gt.shape[0], len(ks)), dtype=torch.float32)
    run = _running_best(proposals, gt, max(ks))
    cols = torch.tensor([min(k, run.shape[1]) - 1 for k in ks], device=run.device)
    return run[:, cols].cpu()


def _gather(
    proposals: Sequence[Boxes],
    gts: Sequence[Boxes],
    gt_labels: Sequence[Tensor] | None,
    ks: Sequence[int],
) -> tuple[Tensor, Tensor | None, int]:
    """Best IoUs of all GT objects pooled over images: ``(Tensor[G, len(ks)], labels
    Tensor[G] or None, number of images with ground truth)``."""
    if len(proposals) != len(gts):
        raise ValueError(f"{len(proposals)} proposal sets for {len(gts)} ground-truth sets")
    if gt_labels is not None and len(gt_labels) != len(gts):
        raise ValueError(f"{len(gt_labels)} label sets for {len(gts)} ground-truth sets")
    best: list[Tensor] = []
    labels: list[Tensor] = []
    n_images = 0
    for i, (prop, gt) in enumerate(zip(proposals, gts)):
        gt = _as_boxes(gt, f"gts[{i}]")
        prop = _as_boxes(prop, f"proposals[{i}]")
        if gt_labels is not None:
            lab = torch.as_tensor(gt_labels[i]).reshape(-1).to("cpu", torch.int64)
            if lab.shape[0] != gt.shape[0]:
                raise ValueError(
                    f"gt_labels[{i}] has {lab.shape[0]} labels for {gt.shape[0]} boxes"
                )
            labels.append(lab)
        if gt.shape[0] == 0:
            continue
        n_images += 1
        best.append(_best_at(prop, gt, ks))
    all_best = torch.cat(best) if best else torch.zeros((0, len(ks)))
    all_labels = None
    if gt_labels is not None:
        all_labels = torch.cat(labels) if labels else torch.zeros(0, dtype=torch.int64)
    return all_best, all_labels, n_images


def best_iou(proposals: Boxes, gt: Boxes, top_k: int | None = None) -> Tensor:
    """Best IoU of each ground-truth box with the first ``top_k`` ranked proposals.

    Args:
        proposals: ranked ``Tensor[P, 4]`` (row 0 = best).
        gt: ``Tensor[G, 4]``.
        top_k: how many proposals to consider; ``None`` = all. Fewer than ``top_k``
            proposals: all are used.

    Returns:
        ``float32`` ``Tensor[G]`` in [0, 1] (CPU); 0 for every box when there are no
        proposals (or ``top_k == 0``).
    """
    proposals = _as_boxes(proposals, "proposals")
    gt = _as_boxes(gt, "gt")
    if top_k is not None:
        if top_k < 0:
            raise ValueError(f"top_k must be >= 0, got {top_k}")
        proposals = proposals[:top_k]
    if proposals.shape[0] == 0:
        return torch.zeros(gt.shape[0], dtype=torch.float32)
    return _best_at(proposals, gt, [proposals.shape[0]])[:, 0]


# ---------------------------------------------------------------------------------------
# recall table
# ---------------------------------------------------------------------------------------


@dataclass
class RecallResult:
    """Recall of ranked proposals at several numbers of proposals k and IoU thresholds.

    All recall tensors are ``float64`` on the CPU with values in [0, 1], indexed
    ``[k index, IoU index]`` (per class: ``[class, k index, IoU index]``).

    Attributes:
        ks: numbers of proposals.
        ious: IoU thresholds.
        class_names: names of the classes (empty without labels).
        micro: ``Tensor[len(ks), len(ious)]``, recall over all objects (``nan`` when
            there is no object at all).
        per_class: ``Tensor[C, len(ks), len(ious)]``; ``nan`` for a class with no object.
        class_mean: ``Tensor[len(ks), len(ious)]``, mean of ``per_class`` over the classes
            with at least one object (``nan`` if there is none, or no labels were given).
        num_objects: objects counted in ``micro``.
        num_per_class: ``Tensor[C]`` (``int64``), objects of each class.
        num_images: images with at least one object.
    """

    ks: tuple[int, ...]
    ious: tuple[float, ...]
    class_names: tuple[str, ...]
    micro: Tensor
    per_class: Tensor
    class_mean: Tensor
    num_objects: int
    num_per_class: Tensor
    num_images: int

    def at(self, k: int, iou: float, cls: str | None = None) -> float:
        """Recall at ``k`` proposals and IoU ``iou``: micro, or of class ``cls``
        (``"mean"`` for the class mean)."""
        i, j = self.ks.index(k), self._iou_index(iou)
        if cls is None:
            return float(self.micro[i, j])
        if cls == "mean":
            return float(self.class_mean[i, j])
        return float(self.per_class[self.class_names.index(cls), i, j])

    def per_class_at(self, k: int, iou: float) -> dict[str, float]:
        """Recall of each class at ``k`` proposals and IoU ``iou``, ``{name: recall}``
        in class order (``nan`` for a class with no object)."""
        i, j = self.ks.index(k), self._iou_index(iou)
        return {c: float(self.per_class[ci, i, j]) for ci, c in enumerate(self.class_names)}

    def _iou_index(self, iou: float) -> int:
        for j, t in enumerate(self.ious):
            if math.isclose(t, iou, abs_tol=1e-9):
                return j
        raise ValueError(f"IoU {iou} not in {self.ious}")

    def average_recall(self, average: Literal["micro", "class"] = "micro") -> Tensor:
        """``Tensor[len(ks)]``: recall averaged over this table's IoU thresholds — the
        average recall (AR) when they are :data:`AR_IOUS`. ``average`` chooses micro
        recall or the class mean."""
        table = self.micro if average == "micro" else self.class_mean
        return table.mean(dim=1)

    def to_dict(self) -> dict[str, Any]:
        """JSON-able nested dicts: ``d["micro"][str(k)][f"{iou:g}"]`` is a recall in [0, 1];
        likewise ``d["class_mean"]`` and ``d["per_class"][name]``. Undefined recalls
        (``nan``) become ``None``."""

        def grid(t: Tensor) -> dict[str, dict[str, float | None]]:
            return {
                str(k): {
                    f"{iou:g}": (None if math.isnan(v := float(t[i, j])) else v)
                    for j, iou in enumerate(self.ious)
                }
                for i, k in enumerate(self.ks)
            }

        return {
            "ks": list(self.ks),
            "ious": list(self.ious),
            "num_images": self.num_images,
            "num_objects": self.num_objects,
            "num_per_class": {
                c: int(n) for c, n in zip(self.class_names, self.num_per_class.tolist())
            },
            "micro": grid(self.micro),
            "class_mean": grid(self.class_mean),
            "per_class": {c: grid(self.per_class[ci]) for ci, c in enumerate(self.class_names)},
        }

    def format_table(self, percent: bool = True, digits: int = 1) -> str:
        """Plain-text table laid out as the paper's Table 3: one row per class (micro
        "all" first, then the class mean and each class with its object count), one column
        per (k, IoU). Values in percent unless ``percent=False``; ``-`` = undefined."""
        scale = 100.0 if percent else 1.0
        width = max(6, digits + 5)
        rows: list[tuple[str, Tensor]] = [(f"all ({self.num_objects})", self.micro)]
        if self.class_names:
            rows.append(("class mean", self.class_mean))
            for ci, c in enumerate(self.class_names):
                rows.append((f"{c} ({int(self.num_per_class[ci])})", self.per_class[ci]))
        name_w = max(len(r[0]) for r in rows)
        n_iou = len(self.ious)
        group_w = n_iou * (width + 1) - 1

        def cell(v: float) -> str:
            return f"{'-':>{width}}" if math.isnan(v) else f"{v * scale:>{width}.{digits}f}"

        unit = "%" if percent else "fraction"
        lines = [
            f"Recall ({unit}) of the top k proposals, {self.num_images} images, "
            f"{self.num_objects} objects",
            " " * name_w + " | " + " | ".join(f"{f'k={k}':^{group_w}}" for k in self.ks),
            " " * name_w
            + " | "
            + " | ".join(" ".join(f"{f'{t:g}':>{width}}" for t in self.ious) for _ in self.ks),
        ]
        lines.append("-" * len(lines[-1]))
        for name, table in rows:
            groups = [
                " ".join(cell(float(table[i, j])) for j in range(n_iou))
                for i in range(len(self.ks))
            ]
            lines.append(f"{name:<{name_w}} | " + " | ".join(groups))
        return "\n".join(line.rstrip() for line in lines)

    def __str__(self) -> str:
        return self.format_table()


def _recall(
    best: Tensor, labels: Tensor | None, num_classes: int, ious: Sequence[float]
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """``(micro, per_class, class_mean, objects per class)`` from pooled best IoUs
    ``Tensor[G, K]`` and their labels ``Tensor[G]``."""
    thr = torch.tensor(ious, dtype=best.dtype)
    hit = (best.unsqueeze(-1) >= thr).to(torch.float64)  # [G, K, T]
    n = best.shape[0]
    micro = hit.sum(0) / n if n else torch.full(hit.shape[1:], math.nan, dtype=torch.float64)
    if labels is None or num_classes == 0:
        per_class = torch.zeros((0, *hit.shape[1:]), dtype=torch.float64)
        counts = torch.zeros(0, dtype=torch.int64)
    else:
        if labels.numel() and (labels.min() < 0 or labels.max() >= num_classes):
            raise ValueError(
                f"gt_labels must be class indices in [0, {num_classes}), got "
                f"[{int(labels.min())}, {int(labels.max())}]"
            )
        sums = torch.zeros((num_classes, *hit.shape[1:]), dtype=torch.float64)
        sums.index_add_(0, labels, hit)
        counts = torch.bincount(labels, minlength=num_classes)
        per_class = sums / counts.to(torch.float64).reshape(-1, 1, 1)  # 0/0 = nan
    if per_class.shape[0] and bool((counts > 0).any()):
        class_mean = per_class[counts > 0].mean(0)
    else:
        class_mean = torch.full(hit.shape[1:], math.nan, dtype=torch.float64)
    return micro, per_class, class_mean, counts


def recall_table(
    proposals: Sequence[Boxes],
    gts: Sequence[Boxes],
    gt_labels: Sequence[Tensor] | None = None,
    class_names: Sequence[str] | None = None,
    ks: Sequence[int] = (500, 1000, 2000),
    ious: Sequence[float] = (0.3, 0.5, 0.7),
) -> RecallResult:
    """Recall of ranked proposals for each number of proposals k and IoU threshold.

    Args:
        proposals: per image, ranked ``Tensor[P_i, 4]`` (or a dict with ``"boxes"``).
        gts: per image, ground truth ``Tensor[G_i, 4]`` (or a dict with ``"boxes"``).
        gt_labels: per image, ``int64`` ``Tensor[G_i]`` of indices into ``class_names``;
            ``None``: micro recall only.
        class_names: names of the classes; ``None`` with labels: ``"0"``, ``"1"``, ...
        ks: numbers of proposals (the paper: 500, 1000, 2000).
        ious: IoU thresholds (the paper: 0.3, 0.5, 0.7).

    Returns:
        :class:`RecallResult`. Micro recall pools all objects; the class mean leaves out
        classes with no object (their per-class recall is ``nan``).
    """
    ks = _check_ks(ks)
    ious = _check_ious(ious)
    best, labels, n_images = _gather(proposals, gts, gt_labels, ks)
    if labels is not None and class_names is None:
        class_names = [str(i) for i in range(int(labels.max()) + 1 if labels.numel() else 0)]
    names = tuple(class_names) if (class_names is not None and labels is not None) else ()
    micro, per_class, class_mean, counts = _recall(best, labels, len(names), ious)
    return RecallResult(
        ks=ks,
        ious=ious,
        class_names=names,
        micro=micro,
        per_class=per_class,
        class_mean=class_mean,
        num_objects=int(best.shape[0]),
        num_per_class=counts,
        num_images=n_images,
    )


def average_recall(
    proposals: Sequence[Boxes],
    gts: Sequence[Boxes],
    ks: Sequence[int] = (500, 1000, 2000),
    gt_labels: Sequence[Tensor] | None = None,
    class_names: Sequence[str] | None = None,
    average: Literal["micro", "class"] = "micro",
) -> Tensor:
    """Average recall (AR, Hosang et al.): recall averaged over IoU 0.5:0.05:0.95.

    Args:
        proposals, gts, gt_labels, class_names: as :func:`recall_table`.
        ks: numbers of proposals.
        average: ``"micro"`` (all objects pooled) or ``"class"`` (mean of the per-class
            ARs over classes with objects; needs ``gt_labels``).

    Returns:
        ``float64`` ``Tensor[len(ks)]`` in [0, 1]: AR at each k.
    """
    if average == "class" and gt_labels is None:
        raise ValueError("average='class' needs gt_labels")
    if average not in ("micro", "class"):
        raise ValueError(f"average must be 'micro' or 'class', got {average!r}")
    result = recall_table(proposals, gts, gt_labels, class_names, ks=ks, ious=AR_IOUS)
    return result.average_recall(average)


# ---------------------------------------------------------------------------------------
# KITTI difficulty levels
# ---------------------------------------------------------------------------------------


@dataclass(frozen=True)
class KittiDifficulty:
    """One of KITTI's difficulty levels: an object counts when its 2D box is at least
    ``min_height`` pixels tall (``y2 - y1``), its ``occluded`` code is at most
    ``max_occlusion`` and its ``truncated`` fraction at most ``max_truncation`` (all
    bounds inclusive, as in KITTI's ``evaluate_object.cpp``)."""

    min_height: float
    max_occlusion: int
    max_truncation: float


KITTI_DIFFICULTIES: dict[str, KittiDifficulty] = {
    "easy": KittiDifficulty(40.0, 0, 0.15),
    "moderate": KittiDifficulty(25.0, 1, 0.30),
    "hard": KittiDifficulty(25.0, 2, 0.50),
}
"""KITTI's levels (object devkit; SubCNN's ``compute_recall_simple.m`` for proposals).
Each level includes the easier ones: every easy object is also moderate and hard."""

_TRUNCATION_TOL = 1e-6  # truncation is read as float32: 0.3 must pass "<= 0.3"


def kitti_difficulty_mask(
    boxes: Tensor,
    occluded: Tensor,
    truncated: Tensor,
    level: str | KittiDifficulty = "moderate",
) -> Tensor:
    """Which objects of one image count at a KITTI difficulty level.

    Args:
        boxes: ``Tensor[N, 4]`` ``(x1, y1, x2, y2)`` pixels; the height is ``y2 - y1``.
        occluded: ``Tensor[N]`` KITTI occlusion codes (0 visible, 1 partly, 2 largely,
            3 unknown; 3 never passes ``easy``/``moderate``/``hard``).
        truncated: ``Tensor[N]`` fractions in [0, 1].
        level: ``"easy"``, ``"moderate"``, ``"hard"`` (:data:`KITTI_DIFFICULTIES`) or a
            :class:`KittiDifficulty`.

    Returns:
        ``bool`` ``Tensor[N]`` on the CPU.
    """
    if isinstance(level, str):
        if level not in KITTI_DIFFICULTIES:
            raise ValueError(
                f"unknown KITTI difficulty {level!r}; choose one of {', '.join(KITTI_DIFFICULTIES)}"
            )
        level = KITTI_DIFFICULTIES[level]
    b = _as_boxes(boxes, "boxes").cpu()
    occ = torch.as_tensor(occluded).reshape(-1).cpu()
    trunc = torch.as_tensor(truncated).reshape(-1).cpu().to(torch.float64)
    if not (occ.shape[0] == trunc.shape[0] == b.shape[0]):
        raise ValueError(
            f"kitti_difficulty_mask: {b.shape[0]} boxes, {occ.shape[0]} occlusion codes and "
            f"{trunc.shape[0]} truncations; expected one of each per box"
        )
    height = (b[:, 3] - b[:, 1]).to(torch.float64)
    return (
        (height >= level.min_height)
        & (occ <= level.max_occlusion)
        & (trunc <= level.max_truncation + _TRUNCATION_TOL)
    )


def select_objects(
    gts: Sequence[Boxes],
    gt_labels: Sequence[Tensor] | None,
    masks: Sequence[Tensor],
) -> tuple[list[Tensor], list[Tensor] | None]:
    """Keep the objects of each image where ``masks[i]`` (``bool Tensor[G_i]``) is true.

    Returns ``(gts, gt_labels)`` filtered alike (``gt_labels`` stays ``None``), ready for
    :func:`recall_table`. Images left with no object contribute nothing to recall.
    """
    if len(masks) != len(gts):
        raise ValueError(f"{len(masks)} masks for {len(gts)} ground-truth sets")
    out_gts: list[Tensor] = []
    out_labels: list[Tensor] | None = None if gt_labels is None else []
    for i, (gt, m) in enumerate(zip(gts, masks)):
        g = _as_boxes(gt, f"gts[{i}]")
        m = torch.as_tensor(m, dtype=torch.bool).reshape(-1).to(g.device)
        if m.shape[0] != g.shape[0]:
            raise ValueError(f"masks[{i}] has {m.shape[0]} entries for {g.shape[0]} boxes")
        out_gts.append(g[m])
        if out_labels is not None and gt_labels is not None:
            out_labels.append(torch.as_tensor(gt_labels[i]).reshape(-1)[m.cpu()])
    return out_gts, out_labels


# ---------------------------------------------------------------------------------------
# curves
# ---------------------------------------------------------------------------------------


def _proposal_grid(max_k: int, points: int) -> list[int]:
    grid = torch.logspace(0.0, math.log10(max_k), points, dtype=torch.float64).round()
    return sorted({int(k) for k in grid.tolist()} | {1, max_k})


def recall_vs_proposals(
    proposals: Sequence[Boxes],
    gts: Sequence[Boxes],
    iou: float = 0.7,
    ks: Sequence[int] | None = None,
    max_k: int | None = None,
    points: int = 50,
) -> tuple[Tensor, Tensor]:
    """Micro recall at IoU ``iou`` as a function of the number of proposals k.

    Args:
        proposals, gts: as :func:`recall_table`.
        iou: IoU threshold.
        ks: numbers of proposals; ``None``: about ``points`` log-spaced values from 1 to
            ``max_k`` (both included). ``ks=range(1, K + 1)`` gives every k.
        max_k: largest k of the default grid; ``None``: the most proposals of any image.

    Returns:
        ``(ks, recall)``: ``int64`` ``Tensor[M]`` and ``float64`` ``Tensor[M]`` in [0, 1].
    """
    if ks is None:
        if max_k is None:
            sizes = [_as_boxes(p, f"proposals[{i}]").shape[0] for i, p in enumerate(proposals)]
            max_k = max(sizes, default=1)
        ks = _proposal_grid(max(int(max_k), 1), points)
    result = recall_table(proposals, gts, ks=ks, ious=(iou,))
    return torch.tensor(result.ks, dtype=torch.int64), result.micro[:, 0]


def recall_vs_iou(
    proposals: Sequence[Boxes],
    gts: Sequence[Boxes],
    k: int = 2000,
    ious: Sequence[float] | None = None,
) -> tuple[Tensor, Tensor]:
    """Micro recall of the top ``k`` proposals as a function of the IoU threshold.

    Args:
        proposals, gts: as :func:`recall_table`.
        k: number of proposals.
        ious: thresholds; ``None``: 0.5, 0.55, ..., 1.0 (Hosang et al.'s plots).
            ``torch.linspace(0, 1, 21)`` covers the whole range.

    Returns:
        ``(ious, recall)``: ``float64`` ``Tensor[M]`` each; recall in [0, 1]. The area
        under the curve on [0.5, 1] times 2 approximates the average recall.
    """
    if ious is None:
        ious = [round(0.5 + 0.05 * i, 2) for i in range(11)]
    elif isinstance(ious, Tensor):
        ious = ious.tolist()
    result = recall_table(proposals, gts, ks=(k,), ious=ious)
    return torch.tensor(result.ious, dtype=torch.float64), result.micro[0]


# ---------------------------------------------------------------------------------------
# how sure a recall figure is: frame bootstrap, paired comparison
# ---------------------------------------------------------------------------------------


def object_hits(proposals: Sequence[Boxes], gts: Sequence[Boxes], k: int = 2000, iou: float = 0.7) -> list[Tensor]:
    """Per image, which ground-truth objects the top ``k`` proposals recall at IoU ``iou``:
    ``bool Tensor[G_i]`` each (the hits :func:`recall_table` counts)."""
    if len(proposals) != len(gts):
        raise ValueError(f"got {len(proposals)} proposal lists for {len(gts)} ground-truth lists")
    k = _check_ks(k)[0]
    iou = _check_ious(iou)[0]
    return [best_iou(p, g, k) >= iou for p, g in zip(proposals, gts)]


@dataclass(frozen=True)
class RecallInterval:
    """Micro recall and a bootstrap interval for it (fractions in [0, 1]).

    Attributes:
        recall: micro recall of all objects.
        low, high: the percentile interval of the recall of frames drawn with replacement.
        level: the interval's coverage (e.g. 0.95).
        num_objects, num_images: what was counted (images with at least one object).
    """

    recall: float
    low: float
    high: float
    level: float
    num_objects: int
    num_images: int

    def __str__(self) -> str:
        return (f"{100 * self.recall:.1f} % ({100 * self.level:g} % interval {100 * self.low:.1f}-"
                f"{100 * self.high:.1f}, {self.num_objects} objects in {self.num_images} frames)")


def recall_interval(hits: Sequence[Tensor], level: float = 0.95, samples: int = 4000,
                    seed: int = 0) -> RecallInterval:
    """Micro recall of ``hits`` (per image, ``bool Tensor[G_i]``, as :func:`object_hits`
    gives) with a frame-bootstrap percentile interval.

    Frames, not objects, are drawn with replacement (``samples`` times): the objects of one
    frame share its lighting, clutter and crowding, so treating them as independent would
    make the interval too narrow. Images with no object are left out. With 60 KITTI frames
    and ~70 % recall the 95 % interval is about ±6 points (±10 on 20 frames): two settings
    whose recall differs by less than that are not told apart by it (compare them with
    :func:`compare_recall` instead, which pairs the objects).

    Raises:
        ValueError: ``level`` outside (0, 1), ``samples < 1``, or no object at all.
    """
    if not 0.0 < level < 1.0:
        raise ValueError(f"level must be in (0, 1), got {level}")
    if samples < 1:
        raise ValueError(f"samples must be >= 1, got {samples}")
    found = torch.tensor([int(h.sum()) for h in hits if h.numel()], dtype=torch.float64)
    counts = torch.tensor([h.numel() for h in hits if h.numel()], dtype=torch.float64)
    if counts.numel() == 0:
        raise ValueError("no ground-truth object: recall is undefined")
    boot = bootstrap_recalls(found[:, None], counts[:, None], samples, seed)
    q = torch.tensor([(1.0 - level) / 2, (1.0 + level) / 2], dtype=torch.float64)
    low, high = torch.quantile(boot, q).tolist()
    return RecallInterval(float(found.sum() / counts.sum()), low, high, level, int(counts.sum()), counts.numel())


def bootstrap_recalls(found: Tensor, counts: Tensor, samples: int = 4000, seed: int = 0,
                      balanced: bool = False) -> Tensor:
    """The frame bootstrap's recall on each of ``samples`` draws of the F frames with
    replacement: ``float64 Tensor[samples]``. ``found`` and ``counts`` (``Tensor[F, C]``)
    hold per frame and class the objects found and present (C = 1 for micro recall);
    ``balanced`` takes on each draw the mean recall of the classes it holds. The draws are
    ``torch.randint`` of a generator seeded with ``seed``, the same in every caller
    (:func:`recall_interval`, :func:`reeb_torch.tuning.bootstrap_interval`)."""
    draw = torch.randint(found.shape[0], (samples, found.shape[0]), generator=torch.Generator().manual_seed(seed))
    f, n = found[draw].sum(1), counts[draw].sum(1)  # (samples, C)
    return torch.where(n > 0, f / n.clamp(min=1), torch.nan).nanmean(1) if balanced else f.sum(1) / n.sum(1)


@dataclass(frozen=True)
class RecallComparison:
    """Two settings on the same objects: what the second finds that the first does not.

    Attributes:
        gained: objects recalled by ``b`` and not by ``a``.
        lost: objects recalled by ``a`` and not by ``b``.
        num_objects: objects compared.
        p_value: two-sided exact sign test (McNemar's exact test) of ``gained`` against
            ``lost``: the chance of a split at least this uneven if the two settings were
            equally good. 1.0 when nothing changed.
    """

    gained: int
    lost: int
    num_objects: int
    p_value: float

    @property
    def net(self) -> int:
        return self.gained - self.lost

    def __str__(self) -> str:
        return f"+{self.gained} / -{self.lost} of {self.num_objects} objects (p = {self.p_value:.2g})"


def sign_test(gained: int, lost: int) -> float:
    """Two-sided exact sign test: ``P(|X - n/2| >= |gained - n/2|)`` for ``X ~ Bin(n, 1/2)``,
    ``n = gained + lost`` (1.0 when ``n == 0``)."""
    if gained < 0 or lost < 0:
        raise ValueError(f"counts must be >= 0, got {gained} and {lost}")
    n = gained + lost
    if n == 0:
        return 1.0
    tail = sum(math.comb(n, i) for i in range(min(gained, lost) + 1)) / 2.0**n
    return min(1.0, 2.0 * tail)


def compare_recall(hits_a: Sequence[Tensor], hits_b: Sequence[Tensor]) -> RecallComparison:
    """Pair two settings' hits on the same objects (per image, ``bool Tensor[G_i]`` from
    :func:`object_hits`): counts of objects only one of them recalls, and the sign test.

    Raises:
        ValueError: the two do not cover the same images and objects.
    """
    if len(hits_a) != len(hits_b):
        raise ValueError(f"got hits for {len(hits_a)} and {len(hits_b)} images")
    gained = lost = total = 0
    for i, (a, b) in enumerate(zip(hits_a, hits_b)):
        if a.shape != b.shape:
            raise ValueError(f"image {i}: {tuple(a.shape)} objects against {tuple(b.shape)}")
        a, b = a.bool(), b.bool()
        gained += int((b & ~a).sum())
        lost += int((a & ~b).sum())
        total += a.numel()
    return RecallComparison(gained, lost, total, sign_test(gained, lost))
