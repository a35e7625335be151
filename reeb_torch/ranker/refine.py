"""Box refinement: a small regression head that moves each side of an output box towards the
object's border (not in the paper; its future work: "a lightweight regression head to refine
the localization accuracy"; ``ReebConfig.refine_top``).

The windows of REEB's grid land close to an object but step by 15 % of their size, so many
are close but not tight. Per box, :func:`refine_features` reads the edge strength in thin
strips parallel to each side at offsets −0.3…+0.3 of the box's size, a coarse brightness
profile across the box and its surround, and the box's geometry — all box sums of the
integral images the batch already has (:meth:`ScoreMaps.integral <reeb_torch.selection.maps.ScoreMaps.integral>`),
one compiled pass over the boxes on the CPU, tensor ops over all of them elsewhere — and :class:`BoxRefiner` (an MLP) predicts the four side
offsets ``(dx1 / w, dy1 / h, dx2 / w, dy2 / h)``; :func:`apply_offsets` moves the boxes,
:func:`merge_refined` puts the refined boxes beside their originals in the output.

The refiner lives in the ranking model's weights file (``refiner.*`` tensors, optional, as the
class head: :mod:`reeb_torch.ranker.weights`); ``reeb fit`` fits it on the training frames'
candidates that overlap an object (:func:`reeb_torch.ranker.fit.fit_refiner`). Off by default
(``refine_top=0``): on the dev frames, cross-validated by whole drives, no arrangement of the
refined boxes beside the originals found more objects at 2000 proposals / IoU 0.7
(``docs/results/ranker/refine_whole_drives``).
"""

from __future__ import annotations

from typing import Sequence

import numba
import numpy as np
import torch
from torch import Tensor, nn

from ..stages.enclosed import box_sum_at

__all__ = ["OFFSETS", "STRIP", "TARGET_SCALE", "refine_feature_names", "refine_features", "refine_features_tensor",
           "BoxRefiner",
           "apply_offsets", "merge_refined", "offset_targets"]

OFFSETS: tuple[float, ...] = (-0.3, -0.2, -0.1, 0.0, 0.1, 0.2, 0.3)
"""Where the edge strips lie, per side: the side moved by these fractions of the box's width
(left, right) or height (top, bottom); negative is left / up."""
STRIP = 0.05
"""The edge strips' thickness, a fraction of the box's width (left, right) or height (top, bottom); 1 pixel at least."""
BANDS = 5
"""The brightness profile: this many bands across the box grown by 0.3 of its size on each side, each way."""
GROW = 0.3
"""How far the brightness profile reaches past the box, a fraction of its size on each side."""
TARGET_SCALE = 0.1
"""The model's outputs are the side offsets divided by this (targets of order 1)."""
_EPS = 1e-3
_SIDES = ("left", "top", "right", "bottom")


def refine_feature_names() -> tuple[str, ...]:
    """The columns of :func:`refine_features`, in order (49)."""
    strips = tuple(f"edge_{side}_{round(100 * o):+d}" for side in _SIDES for o in OFFSETS)
    bands = tuple(f"grey_row_{i}" for i in range(BANDS)) + tuple(f"grey_col_{i}" for i in range(BANDS))
    geometry = ("log_width", "log_height", "centre_x", "centre_y", "bottom", "at_left", "at_top", "at_right",
                "at_bottom")
    return strips + ("log_edge_box",) + bands + ("grey_box",) + geometry


def _box_means(ii: Tensor, bi: Tensor, rects: Tensor) -> Tensor:
    """Mean value of ``ii``'s image (``float [B, h + 1, w + 1]`` integral images) over each
    rectangle ``rects`` (``float [K, R, 4]`` working pixels ``(x0, y0, x1, y1)``, of image
    ``bi[k]``), rounded to whole pixels and clipped to the image: ``float32 [K, R]``; 0 for a
    rectangle wholly outside."""
    h, w = ii.shape[-2] - 1, ii.shape[-1] - 1
    r = rects.round().long()
    x0, x1 = r[..., 0].clamp(0, w), r[..., 2].clamp(0, w)
    y0, y1 = r[..., 1].clamp(0, h), r[..., 3].clamp(0, h)
    x1, y1 = torch.maximum(x0, x1), torch.maximum(y0, y1)
    s = box_sum_at(ii, bi[:, None].expand_as(x0), x0, y0, x1, y1)
    area = ((x1 - x0) * (y1 - y0)).clamp(min=1)
    return (s / area).float()


def refine_features(ii_edges: Tensor, ii_grey: Tensor, boxes: Tensor, bi: Tensor, horizon: float) -> Tensor:
    """:func:`refine_features_tensor`: on the CPU one compiled pass over the boxes
    (:func:`_features_kernel`), elsewhere the tensor ops; the same
    numbers (to float32 rounding of the logarithms). ``float32 [K, 49]``."""
    if ii_edges.device.type != "cpu" or not len(boxes):
        return refine_features_tensor(ii_edges, ii_grey, boxes, bi, horizon)
    out = np.empty((len(boxes), len(refine_feature_names())), np.float32)
    _features_kernel(ii_edges.double().numpy(), ii_grey.double().numpy(),
                     boxes.detach().double().contiguous().numpy(), bi.long().contiguous().numpy(), float(horizon),
                     np.asarray(OFFSETS, np.float64), _band_edges().numpy(), out)
    return torch.from_numpy(out)


def _band_edges(device: torch.device | None = None) -> Tensor:
    """The brightness bands' edges as fractions of the box's side, ``float64 [BANDS + 1]``."""
    return torch.linspace(-GROW, 1.0 + GROW, BANDS + 1, device=device, dtype=torch.float64)


@numba.njit(cache=True, nogil=True, inline="always")
def _mean(ii: np.ndarray, b: int, x0f: float, y0f: float, x1f: float, y1f: float) -> np.float32:
    """:func:`_box_means` of one rectangle."""
    h, w = ii.shape[1] - 1, ii.shape[2] - 1
    x0, x1 = min(max(int(np.rint(x0f)), 0), w), min(max(int(np.rint(x1f)), 0), w)
    y0, y1 = min(max(int(np.rint(y0f)), 0), h), min(max(int(np.rint(y1f)), 0), h)
    x1, y1 = max(x0, x1), max(y0, y1)
    s = ii[b, y1, x1] - ii[b, y0, x1] - ii[b, y1, x0] + ii[b, y0, x0]
    return np.float32(s / max((x1 - x0) * (y1 - y0), 1))


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _features_kernel(ii_e: np.ndarray, ii_g: np.ndarray, boxes: np.ndarray, bi: np.ndarray, horizon: float,
                     offsets: np.ndarray, band: np.ndarray, out: np.ndarray) -> None:  # pragma: no cover - compiled
    """:func:`refine_features_tensor`, box by box, into ``out`` ``float32 [K, 49]``."""
    h, w = ii_e.shape[1] - 1, ii_e.shape[2] - 1
    n, nb = len(offsets), len(band) - 1
    eps = np.float32(1e-3)
    for k in range(len(boxes)):
        b = bi[k]
        x1, y1, x2, y2 = boxes[k, 0], boxes[k, 1], boxes[k, 2], boxes[k, 3]
        bw, bh = max(x2 - x1, 1.0), max(y2 - y1, 1.0)
        tw, th = max(STRIP * bw, 1.0) / 2, max(STRIP * bh, 1.0) / 2
        box_e = np.log(_mean(ii_e, b, x1, y1, x2, y2) + eps)
        for j in range(n):
            o = offsets[j]
            cl, cr, ct, cb = x1 + o * bw, x2 + o * bw, y1 + o * bh, y2 + o * bh
            out[k, j] = np.log(_mean(ii_e, b, cl - tw, y1, cl + tw, y2) + eps) - box_e
            out[k, n + j] = np.log(_mean(ii_e, b, x1, ct - th, x2, ct + th) + eps) - box_e
            out[k, 2 * n + j] = np.log(_mean(ii_e, b, cr - tw, y1, cr + tw, y2) + eps) - box_e
            out[k, 3 * n + j] = np.log(_mean(ii_e, b, x1, cb - th, x2, cb + th) + eps) - box_e
        c = 4 * n
        out[k, c] = box_e
        box_g = _mean(ii_g, b, x1, y1, x2, y2)
        gx0, gx1, gy0, gy1 = x1 - GROW * bw, x2 + GROW * bw, y1 - GROW * bh, y2 + GROW * bh
        for j in range(nb):
            out[k, c + 1 + j] = _mean(ii_g, b, gx0, y1 + band[j] * bh, gx1, y1 + band[j + 1] * bh) - box_g
            out[k, c + 1 + nb + j] = _mean(ii_g, b, x1 + band[j] * bw, gy0, x1 + band[j + 1] * bw, gy1) - box_g
        c += 1 + 2 * nb
        out[k, c] = box_g
        out[k, c + 1] = np.log(bw / w)
        out[k, c + 2] = np.log(bh / h)
        out[k, c + 3] = (x1 + x2) / (2 * w)
        out[k, c + 4] = (y1 + y2) / (2 * h) - horizon
        out[k, c + 5] = y2 / h - horizon
        out[k, c + 6] = 1.0 if x1 <= 0.5 else 0.0
        out[k, c + 7] = 1.0 if y1 <= 0.5 else 0.0
        out[k, c + 8] = 1.0 if x2 >= w - 0.5 else 0.0
        out[k, c + 9] = 1.0 if y2 >= h - 0.5 else 0.0


def refine_features_tensor(ii_edges: Tensor, ii_grey: Tensor, boxes: Tensor, bi: Tensor, horizon: float) -> Tensor:
    """The refiner's features of ``boxes`` (``float [K, 4]`` ``(x1, y1, x2, y2)`` in working
    pixels, of images ``bi`` ``int64 [K]``) from the batch's integral images of the edge map
    and the grey image (``float [B, h + 1, w + 1]`` each): ``float32 [K, 49]``
    (:func:`refine_feature_names`):

    * 28 edge strips: per side (left, top, right, bottom) and offset (:data:`OFFSETS`), the
      log of the mean edge strength in a strip :data:`STRIP` thick parallel to the side,
      moved by the offset, spanning the box along that side, over the box's own mean edge;
      then the log of that mean;
    * the brightness profile: the grey mean of :data:`BANDS` rows and as many columns across
      the box grown by :data:`GROW` on each side, less the box's grey mean; then that mean;
    * the geometry: log width and height over the image's, the centre over the image's size
      (its row less ``horizon``), the bottom row less ``horizon``, and whether each side
      touches the image border."""
    h, w = ii_edges.shape[-2] - 1, ii_edges.shape[-1] - 1
    b = boxes.double()
    x1, y1, x2, y2 = b.unbind(1)
    bw, bh = (x2 - x1).clamp(min=1.0), (y2 - y1).clamp(min=1.0)
    off = torch.tensor(OFFSETS, device=b.device, dtype=b.dtype)
    tw, th = (STRIP * bw).clamp(min=1.0)[:, None] / 2, (STRIP * bh).clamp(min=1.0)[:, None] / 2
    k, n = len(b), len(OFFSETS)
    cx = [x1[:, None] + off * bw[:, None], x2[:, None] + off * bw[:, None]]  # left, right: [K, n]
    cy = [y1[:, None] + off * bh[:, None], y2[:, None] + off * bh[:, None]]  # top, bottom
    ya, yb = y1[:, None].expand(k, n), y2[:, None].expand(k, n)
    xa, xb = x1[:, None].expand(k, n), x2[:, None].expand(k, n)
    strips = [torch.stack([cx[0] - tw, ya, cx[0] + tw, yb], -1), torch.stack([xa, cy[0] - th, xb, cy[0] + th], -1),
              torch.stack([cx[1] - tw, ya, cx[1] + tw, yb], -1), torch.stack([xa, cy[1] - th, xb, cy[1] + th], -1)]
    box = b[:, None, :]
    rects = torch.cat(strips + [box], 1)  # [K, 4n + 1, 4]
    edge = _box_means(ii_edges, bi, rects)
    log_edge = torch.log(edge + torch.tensor(_EPS, dtype=torch.float32))
    strip_cols = log_edge[:, :-1] - log_edge[:, -1:]
    # the brightness profile: BANDS rows and columns across the box grown by GROW on each side
    edges_f = _band_edges(b.device)
    ry = y1[:, None] + edges_f * bh[:, None]
    rx = x1[:, None] + edges_f * bw[:, None]
    gx0, gx1 = (x1 - GROW * bw)[:, None].expand(k, BANDS), (x2 + GROW * bw)[:, None].expand(k, BANDS)
    gy0, gy1 = (y1 - GROW * bh)[:, None].expand(k, BANDS), (y2 + GROW * bh)[:, None].expand(k, BANDS)
    rows = torch.stack([gx0, ry[:, :-1], gx1, ry[:, 1:]], -1)
    cols = torch.stack([rx[:, :-1], gy0, rx[:, 1:], gy1], -1)
    grey = _box_means(ii_grey, bi, torch.cat([rows, cols, box], 1))
    grey_cols = grey[:, :-1] - grey[:, -1:]
    geometry = torch.stack([torch.log(bw / w), torch.log(bh / h), (x1 + x2) / (2 * w), (y1 + y2) / (2 * h) - horizon,
                            y2 / h - horizon, (x1 <= 0.5).to(b.dtype), (y1 <= 0.5).to(b.dtype),
                            (x2 >= w - 0.5).to(b.dtype), (y2 >= h - 0.5).to(b.dtype)], 1)
    return torch.cat([strip_cols, log_edge[:, -1:], grey_cols, grey[:, -1:], geometry.float()], 1).float()


def offset_targets(boxes: Tensor, objects: Tensor) -> Tensor:
    """The side offsets that move ``boxes`` onto ``objects`` (``float [K, 4]`` each, the same
    pixels): ``float32 [K, 4]`` ``((ox1 − x1) / w, (oy1 − y1) / h, (ox2 − x2) / w, (oy2 − y2) / h)``."""
    b, o = boxes.float(), objects.float()
    wh = (b[:, 2:] - b[:, :2]).clamp(min=1e-6).repeat(1, 2)
    return (o - b) / wh


def apply_offsets(boxes: Tensor, offsets: Tensor, size: tuple[int, int]) -> Tensor:
    """``boxes`` (``float [K, 4]``) moved by ``offsets`` (``[K, 4]``, :func:`offset_targets`'
    terms), clipped to the image of ``size`` ``(H, W)``: ``float32 [K, 4]``. A box the offsets
    would turn inside out or shrink below 1 pixel keeps its sides."""
    b = boxes.float()
    wh = (b[:, 2:] - b[:, :2]).repeat(1, 2)
    out = b + offsets.float() * wh
    h, w = size
    out[:, 0::2] = out[:, 0::2].clamp(0.0, float(w))
    out[:, 1::2] = out[:, 1::2].clamp(0.0, float(h))
    bad = (out[:, 2] - out[:, 0] < 1.0) | (out[:, 3] - out[:, 1] < 1.0)
    out[bad] = b[bad]
    return out


def _nms_in_order(boxes: Tensor, iou: float) -> Tensor:
    """Indices (ascending) of ``boxes`` (``float [N, 4]``, in rank order) kept by greedy NMS at ``iou``."""
    from torchvision.ops import nms

    if not len(boxes):
        return torch.zeros(0, dtype=torch.long, device=boxes.device)
    rank = -torch.arange(len(boxes), device=boxes.device, dtype=torch.float32)
    return nms(boxes.float(), rank, iou).sort().values


def merge_refined(result: dict[str, Tensor], refined: Tensor, order: str, top_k: int,
                  nms_iou: float = 1.0, which: Tensor | None = None) -> dict[str, Tensor]:
    """One image's output dict (``boxes [N, 4]``, ``scores [N]``, optional ``labels``,
    ``class_probs``) with ``refined`` (``float32 [M, 4]``: the boxes ``which``, ``int64 [M]``
    ascending, refined; default the first ``M``) put beside the originals, at most ``top_k``
    rows: ``order`` ``"interleave"`` (each refined box right after its original),
    ``"refined_first"`` (the refined boxes, then the originals) or ``"replace"`` (each
    refined box in its original's place); with ``nms_iou`` < 1, a
    greedy NMS over that order at ``nms_iou`` first. A refined box takes its original's
    score and class hints."""
    m, n = len(refined), len(result["boxes"])
    dev = result["boxes"].device
    which = torch.arange(m, device=dev) if which is None else which.to(dev)
    orig = torch.arange(n, device=dev)
    if order == "replace":
        boxes_all = result["boxes"].clone()
        boxes_all[which] = refined.to(boxes_all.dtype)
        keep = _nms_in_order(boxes_all, nms_iou) if nms_iou < 1.0 else orig
        keep = keep[:top_k]
        return {k: (boxes_all if k == "boxes" else v)[keep].contiguous() for k, v in result.items()}
    if order == "interleave":
        key = torch.cat([2 * orig, 2 * which + 1])
    elif order == "refined_first":
        key = torch.cat([orig, torch.arange(m, device=dev) - m])
    else:
        raise ValueError(f"refine order {order!r}: expected 'interleave', 'refined_first' or 'replace'")
    at = torch.sort(key).indices  # rows of the pool (originals, then refined) in output order
    of = torch.cat([orig, which])[at]  # each row's original
    boxes_all = torch.cat([result["boxes"], refined.to(result["boxes"].dtype)])[at]
    keep = _nms_in_order(boxes_all, nms_iou) if nms_iou < 1.0 else torch.arange(len(at), device=dev)
    keep = keep[:top_k]
    out = {"boxes": boxes_all[keep].contiguous()}
    for key_name, value in result.items():
        if key_name != "boxes":
            out[key_name] = value[of[keep]].contiguous()
    return out


class BoxRefiner(nn.Module):
    """``forward(features float [K, F]) -> float32 [K, 4]``: each box's side offsets
    (:func:`offset_targets`' terms) from its :func:`refine_features`.

    Args:
        feature_names: the ``F`` columns it reads (:func:`refine_feature_names`).
        hidden: the widths of the MLP's hidden layers.

    Attributes:
        mean, scale: ``float32 [F]`` buffers; a feature enters as ``(x − mean) / scale``.
    """

    mean: Tensor
    scale: Tensor

    def __init__(self, feature_names: Sequence[str], hidden: Sequence[int] = (64, 64)) -> None:
        super().__init__()
        if not hidden or min(hidden) < 1:
            raise ValueError(f"BoxRefiner needs hidden widths >= 1, got {tuple(hidden)}")
        self.feature_names = tuple(feature_names)
        self.hidden = tuple(int(h) for h in hidden)
        f = len(self.feature_names)
        self.register_buffer("mean", torch.zeros(f))
        self.register_buffer("scale", torch.ones(f))
        layers: list[nn.Module] = []
        inputs = f
        for width in self.hidden:
            layers += [nn.Linear(inputs, width), nn.ReLU()]
            inputs = width
        layers.append(nn.Linear(inputs, 4))
        self.mlp = nn.Sequential(*layers)

    def extra_repr(self) -> str:
        return f"features={len(self.feature_names)}, hidden={self.hidden}"

    def raw(self, features: Tensor) -> Tensor:
        """The MLP's outputs (offsets / :data:`TARGET_SCALE`), ``float32 [K, 4]``, with gradients: what the fit fits."""
        if features.ndim != 2 or features.shape[1] != len(self.feature_names):
            raise ValueError(f"BoxRefiner expects features of shape [K, {len(self.feature_names)}], "
                             f"got {tuple(features.shape)}")
        return self.mlp((features.float() - self.mean) / self.scale)

    def forward(self, features: Tensor) -> Tensor:
        return self.raw(features) * TARGET_SCALE

    @torch.no_grad()
    def refine(self, ii_edges: Tensor, ii_grey: Tensor, boxes: Tensor, bi: Tensor, horizon: float,
               size: tuple[int, int], steps: int = 1) -> Tensor:
        """``boxes`` (``float [K, 4]`` working pixels, of images ``bi``) refined ``steps`` times
        (features read again at each step), clipped to the working image of ``size`` ``(h, w)``:
        ``float32 [K, 4]``."""
        out = boxes.float()
        for _ in range(steps):
            if not len(out):
                break
            out = apply_offsets(out, self(refine_features(ii_edges, ii_grey, out, bi, horizon)), size)
        return out
