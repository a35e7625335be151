"""Sec. 3.8, eq. 13 — non-maximum suppression, stopped once enough boxes are kept.

Greedy NMS decides each box from the boxes ranked above it only, so running it on the
best ``p`` candidates gives exactly the decisions of a run on all of them for those
``p``. :func:`nms_top_k` therefore runs torchvision's NMS on a prefix of the ranking and,
if that keeps fewer than ``k`` boxes, on all candidates: the same
result as ``torchvision.ops.nms(boxes, scores, iou)[:k]`` (ties broken by input order),
at a fraction of the cost when there are many more candidates than ``k``.
"""

from __future__ import annotations

import torch
from torch import Tensor
from torchvision.ops import nms

__all__ = ["nms_top_k"]


def nms_top_k(boxes: Tensor, scores: Tensor, iou: float, k: int, first: int | None = None) -> Tensor:
    """Indices (into ``boxes``) of the first ``k`` boxes greedy NMS keeps, best first.

    Args:
        boxes: ``float [N, 4]`` (x1, y1, x2, y2).
        scores: ``float [N]``; higher is better; ties keep input order.
        iou: suppress a box whose IoU with a kept, better box exceeds this (eq. 13).
        k: number of boxes wanted.
        first: initial prefix length (default ``2k``).
    """
    n = scores.numel()
    if n == 0:
        return torch.zeros(0, dtype=torch.long, device=boxes.device)
    order = torch.sort(scores, descending=True, stable=True).indices
    sboxes = boxes[order]
    rank_score = torch.arange(n, 0, -1, device=boxes.device, dtype=torch.float32)  # strict order
    p = min(n, first or 2 * k)
    while True:
        keep = nms(sboxes[:p], rank_score[:p], iou)
        if keep.numel() >= k or p == n:
            return order[keep[:k]]
        p = n
