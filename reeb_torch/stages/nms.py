"""Sec. 3.8, eq. 13 — non-maximum suppression, stopped once enough boxes are kept.

Greedy NMS decides each box from the better-ranked boxes it kept only. :func:`nms_top_k`
returns exactly ``torchvision.ops.nms(boxes, scores, iou)[:k]`` (equal scores keep input
order, as torchvision's CPU kernel does), by one of two paths:

* **CPU, ``iou >= 0.5``: a grid-bucketed greedy NMS compiled with numba.** If the IoU of
  two boxes exceeds t >= 0.5, their intersection spans more than t times the wider
  one's width (and the taller one's height), so their centres lie less than (1 − t) times
  either box's width (height) apart. Every kept box is registered in the grid cells within
  that reach of its centre (with a small margin against rounding), and a candidate is tested
  only against the kept boxes registered in its centre's cell and in the adjacent
  log-width/log-height bins (IoU > t also needs width and height ratios > t), with torchvision's IoU
  arithmetic in the boxes' dtype; the loop stops once ``k`` boxes are kept. The first call
  in a fresh environment compiles the kernel (about a second); ``cache=True`` stores the
  machine code beside the package so later processes load it.
* :func:`nms_windows_cpu` does the generator's whole per-image step compiled (gather the
  chosen windows, order the best ``3k`` of them by a stable radix sort, the grid kernel;
  all of them only if those keep fewer than ``k``), two images at once.
* **Otherwise** (CUDA tensors, ``iou < 0.5``, dtypes other than float32/float64, boxes
  with NaN/inf or negative width or height): torchvision's ``nms`` on a growing prefix of
  the ranking (a box's fate depends only on the boxes ranked above it).
"""

from __future__ import annotations

import numba
import numpy as np
import torch
from torch import Tensor

from ._radix import descending_order, kth_largest
from ._threads import on_two_cores

__all__ = ["NO_THIN", "nms_top_k", "nms_top_k_many", "nms_windows_cpu"]

NO_CLASSES = np.zeros(0, np.int64)
"""The empty ``labels`` and ``wanted`` of :func:`_grid_nms_sorted`: stop at ``k`` kept boxes."""

_GRID_CELLS = 16
"""Cells along the longer side of the boxes' extent in the grid-bucketed kernel."""
_SIZE_BINS = 32
"""Most log-width (and log-height) bins per cell: IoU > t needs width and height ratios > t.
In practice the bins' width (at least −log t) caps them first: fine size bins make the
kernel faster on KITTI's candidates and coarse cells keep the table small (timed with
``benchmarks/kernel_ab.py``; docs/results.md, "What makes the CPU path fast"); the result is
the same whatever these two constants are."""


@numba.njit(cache=True, nogil=True, inline="always")
def _size_bin(edge: np.ndarray, size: float) -> int:  # pragma: no cover - compiled
    """The size bin of ``size``: the last ``q < 32`` with ``edge[q] <= size`` (``edge``: the
    bins' ascending lower edges, ``edge[0]`` unread, ``inf`` from the last bin on, 64 long),
    as five selects without branches."""
    q = 0
    q = q + 16 if edge[q + 16] <= size else q
    q = q + 8 if edge[q + 8] <= size else q
    q = q + 4 if edge[q + 4] <= size else q
    q = q + 2 if edge[q + 2] <= size else q
    return q + 1 if edge[q + 1] <= size else q


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _box_columns(boxes: np.ndarray):  # pragma: no cover - compiled
    """The columns of ``boxes`` ``[N, 4]`` (x1, y1, x2, y2) and their areas, in the boxes'
    dtype (as torchvision), and the extent ``(x0, y0, xe, ye)`` of all of them and their
    largest side ``wmax`` (at least 1e-6). Plain loops, no array expressions: each of those
    is a function of its own to compile."""
    n = boxes.shape[0]
    x1 = np.empty(n, boxes.dtype)
    y1 = np.empty(n, boxes.dtype)
    x2 = np.empty(n, boxes.dtype)
    y2 = np.empty(n, boxes.dtype)
    areas = np.empty(n, boxes.dtype)
    x0, y0, xe, ye, wmax = np.inf, np.inf, -np.inf, -np.inf, 1e-6
    for i in range(n):
        a, b, c, d = boxes[i, 0], boxes[i, 1], boxes[i, 2], boxes[i, 3]
        x1[i], y1[i], x2[i], y2[i] = a, b, c, d
        areas[i] = (c - a) * (d - b)  # as torchvision: in the boxes' dtype
        x0, y0 = min(x0, float(a)), min(y0, float(b))
        xe, ye = max(xe, float(c)), max(ye, float(d))
        # size bins: IoU > t implies min/max width > t and min/max height > t, so with bins of
        # log-size at least -log(t) wide (a margin against rounding), partners sit in adjacent bins
        wmax = max(wmax, float(c - a), float(d - b))
    return x1, y1, x2, y2, areas, x0, y0, xe, ye, wmax


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _size_edges(wmax: float, iou: float):  # pragma: no cover - compiled
    """The size bins of boxes up to ``wmax`` at threshold ``iou``: ``(edge, nb)``, bin ``q``
    holding sizes from ``floor · e^(q · bw)``, found by a binary search of these lower edges
    (:func:`_size_bin`; no logarithm per box); consecutive edges are more than 1/t apart."""
    floor_ = wmax * 1e-4
    span = np.log(wmax / floor_)
    bw = max(-np.log(min(iou, 0.999)) * 1.01 + 1e-9, span / (_SIZE_BINS - 0.5))
    nb = min(int(span / bw) + 1, _SIZE_BINS)
    edge = np.full(2 * _SIZE_BINS, np.inf)
    for q in range(1, nb):
        edge[q] = floor_ * np.exp(q * bw)
    return edge, nb


@numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _suppressed(head: np.ndarray, base: int, nb: int, bx: int, by: int, ent: np.ndarray, e_next: np.ndarray,
                ix1, iy1, ix2, iy2, ia, iou: float, zero) -> bool:  # pragma: no cover - compiled
    """Whether a kept box registered in the cell at ``base`` in the 3 × 3 size bins around
    ``(by, bx)`` (its own first: the likeliest to hold it) overlaps the box ``ix1, iy1, ix2, iy2`` (area
    ``ia``) at IoU over ``iou``, with torchvision's arithmetic in the boxes' dtype."""
    for q in range(9):
        bb, ba = by + (q // 3 + 1) % 3 - 1, bx + (q % 3 + 1) % 3 - 1
        if bb < 0 or bb >= nb or ba < 0 or ba >= nb:
            continue
        e = head[base + bb * nb + ba]
        while e >= 0:
            o = np.uint64(8 * e)
            w = max(min(ent[o + 2], ix2) - max(ent[o], ix1), zero)
            h = max(min(ent[o + 3], iy2) - max(ent[o + 1], iy1), zero)
            inter = w * h
            ovr = inter / (ent[o + 4] + ia - inter)
            if ovr > iou:
                return True
            e = e_next[e]
    return False


@numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _register(head: np.ndarray, ent: np.ndarray, e_next: np.ndarray, used: int, cell0: int, nb: int, gw: int,
              gh: int, x0: float, y0: float, cs: float, iou: float, ix1, iy1, ix2, iy2,
              ia):  # pragma: no cover - compiled
    """Register a kept box in the cells a box it suppresses can have its centre in (its size
    bin's offset in each cell: ``cell0``), with a margin for rounding: IoU > t >= 0.5 needs
    the widths to overlap by more than t·max(w), so the centres lie less than (1 − t)·w_i
    apart (the heights likewise). Returns ``(ent, e_next, used)``, the entries grown where
    they were full."""
    wi, hi = float(ix2) - float(ix1), float(iy2) - float(iy1)
    mx = 0.01 * wi + 1e-6 * (abs(float(ix1)) + abs(float(ix2)) + cs)
    my = 0.01 * hi + 1e-6 * (abs(float(iy1)) + abs(float(iy2)) + cs)
    ccx, ccy = 0.5 * (float(ix1) + float(ix2)), 0.5 * (float(iy1) + float(iy2))
    reach = 1.0 - iou
    ca = min(max(int((ccx - reach * wi - mx - x0) / cs), 0), gw - 1)
    cb = min(max(int((ccx + reach * wi + mx - x0) / cs), 0), gw - 1)
    ra = min(max(int((ccy - reach * hi - my - y0) / cs), 0), gh - 1)
    rb = min(max(int((ccy + reach * hi + my - y0) / cs), 0), gh - 1)
    need = used + (cb - ca + 1) * (rb - ra + 1)
    cap = e_next.shape[0]
    if need > cap:
        cap = max(2 * cap, need)
        n_ent, n_next = np.empty(cap * 8, ent.dtype), np.empty(cap, np.int32)
        for e in range(8 * used):  # a loop, not a slice assignment: that one costs seconds to compile
            n_ent[e] = ent[e]
        for e in range(used):
            n_next[e] = e_next[e]
        ent, e_next = n_ent, n_next
    for r in range(ra, rb + 1):
        for c in range(ca, cb + 1):
            cell = (r * gw + c) * nb * nb + cell0
            o = np.uint64(8 * used)
            ent[o], ent[o + 1], ent[o + 2], ent[o + 3], ent[o + 4] = ix1, iy1, ix2, iy2, ia
            e_next[used] = head[cell]
            head[cell] = used
            used += 1
    return ent, e_next, used


@numba.njit(cache=True, nogil=True, error_model="numpy")  # 0/0 -> NaN, as in C++
def _grid_nms_sorted(boxes: np.ndarray, iou: float, k: int, labels: np.ndarray,
                     wanted: np.ndarray, thin_iou: float, thin_aspect: float) -> np.ndarray:  # pragma: no cover
    """Rows of ``boxes`` (``[N, 4]`` x1, y1, x2, y2, best first, finite, x1 <= x2, y1 <= y2)
    that greedy NMS keeps at threshold ``iou >= 0.5``, the first ``k`` of them, in order; a
    box narrower than ``thin_aspect`` times its height is suppressed only above
    ``thin_iou`` where that is higher (:func:`nms_top_k`'s ``thin``).
    With ``wanted`` (``int64 [C]``, else empty) and ``labels`` (``int64 [N]`` in ``0..C-1``, else
    empty): the first ones until ``k`` are kept *and* each class ``c`` has ``wanted[c]`` of its
    boxes among them (or all): what an output quota per class draws from (:data:`NO_CLASSES`)."""
    n = boxes.shape[0]
    nc = wanted.shape[0]
    keep = np.empty(n if nc else min(n, k), np.int64)
    if n == 0 or k <= 0:
        return keep[:0]
    count = np.zeros(max(nc, 1), np.int64)
    short = 0  # classes whose need is not met yet
    for j in range(nc):
        if wanted[j] > 0:
            short += 1
    x1, y1, x2, y2, areas, x0, y0, xe, ye, wmax = _box_columns(boxes)
    zero = areas[0] - areas[0]  # 0 in the boxes' dtype (max(float32, 0) would widen)
    cs = max(xe - x0, ye - y0, 1e-6) / _GRID_CELLS
    gw = min(int((xe - x0) / cs) + 1, _GRID_CELLS + 1)
    gh = min(int((ye - y0) / cs) + 1, _GRID_CELLS + 1)
    edge, nb = _size_edges(wmax, iou)
    head = np.full(gw * gh * nb * nb, -1, np.int32)  # per cell and size bin: a linked list
    # of the kept boxes registered there, each entry holding its box (no second lookup):
    # x1, y1, x2, y2 and area side by side in a row of 8 (one cache line per test, where
    # five arrays take five), the links apart; one flat array read at unsigned offsets (no
    # test for negative indices, and quicker to compile than a 2-D array)
    cap = 4 * n + 64
    ent, e_next = np.empty(cap * 8, boxes.dtype), np.empty(cap, np.int32)
    used = 0
    nk = 0
    for i in range(n):
        cx = int((0.5 * (float(x1[i]) + float(x2[i])) - x0) / cs)
        cy = int((0.5 * (float(y1[i]) + float(y2[i])) - y0) / cs)
        cx = min(max(cx, 0), gw - 1)
        cy = min(max(cy, 0), gh - 1)
        ix1, iy1, ix2, iy2, ia = x1[i], y1[i], x2[i], y2[i], areas[i]
        bx = _size_bin(edge, float(ix2) - float(ix1))
        by = _size_bin(edge, float(iy2) - float(iy1))
        t = iou  # (a higher threshold suppresses fewer: the grid built for iou holds every pair over it)
        if thin_iou > iou and float(ix2) - float(ix1) < thin_aspect * (float(iy2) - float(iy1)):
            t = thin_iou
        if _suppressed(head, (cy * gw + cx) * nb * nb, nb, bx, by, ent, e_next, ix1, iy1, ix2, iy2, ia, t, zero):
            continue
        keep[nk] = i
        nk += 1
        if nc:
            lab = labels[i]
            count[lab] += 1
            if count[lab] == wanted[lab]:
                short -= 1
        if nk >= k and short == 0:
            break
        ent, e_next, used = _register(head, ent, e_next, used, by * nb + bx, nb, gw, gh, x0, y0, cs, iou,
                                      ix1, iy1, ix2, iy2, ia)
    return keep[:nk]


def _grid_ok(boxes: Tensor, iou: float) -> bool:
    """Whether the compiled grid kernel applies (else torchvision's ``nms``)."""
    if boxes.device.type != "cpu" or boxes.dtype not in (torch.float32, torch.float64) or not iou >= 0.5:
        return False
    if not bool(torch.isfinite(boxes).all()):
        return False
    return bool((boxes[:, 2] >= boxes[:, 0]).all() and (boxes[:, 3] >= boxes[:, 1]).all())


NO_THIN = (0.0, 0.0)
"""``thin`` of :func:`nms_top_k`: one threshold for every box."""


def nms_top_k(boxes: Tensor, scores: Tensor, iou: float, k: int, first: int | None = None,
              thin: tuple[float, float] = NO_THIN) -> Tensor:
    """Indices (into ``boxes``) of the first ``k`` boxes greedy NMS keeps, best first.

    Equal to ``torchvision.ops.nms(boxes, scores, iou)[:k]``, ties included (with ``thin``,
    a greedy NMS of the same order whose threshold is ``thin_iou`` for the thin boxes).

    Args:
        boxes: ``float [N, 4]`` (x1, y1, x2, y2), CPU or CUDA.
        scores: ``float [N]``; higher is better; ties keep input order.
        iou: suppress a box whose IoU with a kept, better box exceeds this (eq. 13).
        k: number of boxes wanted.
        first: initial prefix length on the torchvision path (default ``2k``); the
            compiled CPU path stops at ``k`` kept by itself and ignores it.
        thin: ``(thin_iou, thin_aspect)``: a box narrower than ``thin_aspect`` times its
            height is suppressed only by a kept box it overlaps at IoU over ``thin_iou``
            (where that is above ``iou``): thin boxes (a person) whose loose and tight boxes
            overlap more than wide ones' do. :data:`NO_THIN`: ``iou`` for every box.

    Returns:
        ``int64 [min(k, kept)]`` on ``boxes``' device.
    """
    return nms_top_k_many([(boxes, scores)], iou, k, first, thin)[0]


def _torchvision_sorted(order: Tensor, sboxes: Tensor, iou: float, k: int, first: int | None = None,
                        thin: tuple[float, float] = NO_THIN) -> Tensor:
    """The torchvision path of :func:`nms_top_k` on boxes already sorted by ``order``:
    ``nms`` on a growing prefix of the ranking (a box's fate depends only on the boxes
    ranked above it); with ``thin``, a greedy loop in tensor ops (:func:`_greedy_thin`)."""
    if thin[0] > iou:
        return order[_greedy_thin(sboxes, iou, thin, k)]
    from torchvision.ops import nms  # here: its import is slow (torch._dynamo); the compiled path needs none

    n = sboxes.shape[0]
    rank_score = torch.arange(n, 0, -1, device=sboxes.device, dtype=torch.float32)  # strict order
    p = min(n, first or 2 * k)
    while True:
        keep = nms(sboxes[:p], rank_score[:p], iou)
        if keep.numel() >= k or p == n:
            return order[keep[:k]]
        p = n


def _greedy_thin(sboxes: Tensor, iou: float, thin: tuple[float, float], k: int) -> Tensor:
    """Greedy NMS of boxes sorted best first with :func:`nms_top_k`'s ``thin`` thresholds, in
    tensor ops on the boxes' device (a box at a time: the path of devices other than the
    CPU); the first ``k`` kept, ``int64``. The IoU in the boxes' dtype, as torchvision's."""
    from torchvision.ops import box_iou

    w, h = sboxes[:, 2] - sboxes[:, 0], sboxes[:, 3] - sboxes[:, 1]
    limit = torch.where(w < thin[1] * h, max(thin[0], iou), iou).tolist()
    kept: list[int] = []
    kept_boxes = sboxes[:0]
    for i in range(len(sboxes)):
        if len(kept) >= k:
            break
        if len(kept) and bool((box_iou(sboxes[i: i + 1], kept_boxes)[0] > limit[i]).any()):
            continue
        kept.append(i)
        kept_boxes = sboxes[kept]
    return torch.tensor(kept, dtype=torch.long, device=sboxes.device)


def nms_top_k_many(pairs: list[tuple[Tensor, Tensor]], iou: float, k: int,
                   first: int | None = None, thin: tuple[float, float] = NO_THIN) -> list[Tensor]:
    """:func:`nms_top_k` of each ``(boxes, scores)`` pair (the images of a batch): the
    compiled CPU kernels of the images run two at a time (they release the GIL) after the
    sorting, which stays in torch."""
    out: list[Tensor | None] = [None] * len(pairs)
    todo: list[tuple[int, Tensor, np.ndarray]] = []
    for i, (boxes, scores) in enumerate(pairs):
        if scores.numel() == 0:
            out[i] = torch.zeros(0, dtype=torch.long, device=boxes.device)
            continue
        order = torch.sort(scores, descending=True, stable=True).indices
        sboxes = boxes[order]
        if _grid_ok(sboxes, iou):
            todo.append((i, order, sboxes.contiguous().numpy()))
        else:
            out[i] = _torchvision_sorted(order, sboxes, iou, k, first, thin)
    kept: list[np.ndarray | None] = [None] * len(todo)

    def run(lo: int, hi: int) -> None:
        for j in range(lo, hi):
            kept[j] = _grid_nms_sorted(todo[j][2], float(iou), int(k), NO_CLASSES, NO_CLASSES, *map(float, thin))

    on_two_cores(run, len(todo))
    for (i, order, _), keep in zip(todo, kept):
        out[i] = order[torch.from_numpy(keep)]
    return out  # type: ignore[return-value]


def nms_windows_cpu(chosen: Tensor, boxes: Tensor, scores: Tensor, iou: float, k: int,
                    boxes_ok: bool | None = None, classes: Tensor | None = None,
                    need: Tensor | None = None, thin: tuple[float, float] = NO_THIN) -> list[Tensor] | None:
    """For each image ``b``, the windows (indices into ``boxes``) that
    ``nms_top_k(boxes[c], scores[b, c], iou, k)`` keeps, best first, with ``c`` the
    chosen windows ``chosen[b].nonzero()``: the same indices (tested), but the whole
    per-image work (gathering the candidates, the stable sort, the NMS) runs compiled, the
    two halves of the batch on two cores.

    Args:
        chosen: ``bool [B, N]``, the candidates of each image.
        boxes: ``float32 [N, 4]`` (x1, y1, x2, y2), the windows, shared by the images.
        scores: ``float32 [B, N]``.
        boxes_ok: :func:`boxes_valid` of ``boxes`` where the caller knows it (a grid's
            windows are the same batch after batch); ``None``: checked here.
        classes, need: an output quota per group (``ReebConfig.class_quota``'s classes):
            ``classes`` ``int [B, N]`` each window's group
            (``0..C-1``), ``need`` ``int [C]`` (or ``[B, C]``, per image) how many kept boxes
            of each group the quota draws; the NMS goes on past ``k`` kept boxes until each
            group has its ``need`` among them (or the candidates run out), so that the quota's
            output is the same as from all of them (the first boxes of each group and the best
            of the rest all lie in that prefix).
        thin: :func:`nms_top_k`'s.

    Returns ``None`` where this path does not apply (not CPU float32, ``iou < 0.5``); an
    image whose candidates hold NaN scores or boxes that are not finite with
    ``x1 <= x2, y1 <= y2`` is done by :func:`nms_top_k` (as the grid kernel needs; with
    ``classes``, all of its candidates)."""
    if (boxes.device.type != "cpu" or boxes.dtype != torch.float32 or scores.dtype != torch.float32
            or not iou >= 0.5):
        return None
    ch = chosen.contiguous().numpy()
    bx = boxes.contiguous().numpy()
    sc = scores.contiguous().numpy()
    cl = nd = None
    if classes is not None:
        assert need is not None, "a class quota needs each class's count (need)"
        cl = classes.to(torch.int64).contiguous().numpy()
        nd = need.to(torch.int64).expand(ch.shape[0], -1).contiguous().numpy()
    out: list[np.ndarray | None] = [np.empty(0, np.int64)] * ch.shape[0]
    if boxes_ok is None:
        boxes_ok = boxes_valid(boxes)

    def run(lo: int, hi: int) -> None:
        for i in range(lo, hi):
            out[i] = _nms_window_image(ch[i], bx, sc[i], float(iou), int(k), boxes_ok,
                                       cl[i] if cl is not None else None, nd[i] if nd is not None else NO_CLASSES,
                                       thin)

    on_two_cores(run, ch.shape[0])
    result = []
    for i, keep in enumerate(out):
        if keep is None:  # NaN or bad boxes: the checked path
            cand = torch.nonzero(chosen[i]).squeeze(1)
            result.append(cand[nms_top_k(boxes[cand], scores[i, cand], iou, k if cl is None else len(cand),
                                         thin=thin)])
        else:
            result.append(torch.from_numpy(keep))
    return result


def boxes_valid(boxes: Tensor) -> bool:
    """Whether every row of ``float32 [N, 4]`` CPU ``boxes`` is finite with ``x1 <= x2``
    and ``y1 <= y2`` (what the window NMS's prefix path needs of all of them)."""
    bx = boxes.contiguous().numpy()
    return bool(np.isfinite(bx).all() and (bx[:, 2] >= bx[:, 0]).all() and (bx[:, 3] >= bx[:, 1]).all())


_PREFIX = 3
"""The window NMS first sorts only the best ``_PREFIX · k`` candidates (greedy NMS decides a
box from the boxes ranked above it, so a prefix of the ranking gives the same first boxes);
on KITTI the 2000th kept box is about the 4800th candidate of 17 000–34 000. Only if the
prefix keeps fewer than ``k`` does it sort and suppress all of them."""


def _nms_window_image(chosen: np.ndarray, boxes: np.ndarray, scores: np.ndarray, iou: float, k: int,
                      boxes_ok: bool, classes: np.ndarray | None = None,
                      need: np.ndarray = NO_CLASSES, thin: tuple[float, float] = NO_THIN) -> np.ndarray | None:
    """:func:`nms_windows_cpu` for one image, in compiled steps (each its own kernel, so each
    compiles on its own and quickly); ``None`` where the checked path must run.
    ``boxes_ok``: every row of ``boxes`` is finite with ``x1 <= x2, y1 <= y2`` (checked
    once per batch), so only the best ``_PREFIX · k`` candidates need sorting first.
    ``classes`` (``int64 [N]``, the windows') and ``need``: as :func:`nms_windows_cpu`'s; all
    the candidates are sorted then (the rare classes' needs mostly reach past the prefix, and
    a prefix that falls short is work thrown away), the NMS stopping where the needs are met."""
    cand, vals, has_nan = _candidate_scores(chosen, scores)
    if has_nan:
        return None
    m = _PREFIX * k
    if boxes_ok and 0 < m < len(cand) and classes is None:  # (a quota's needs often outrun the prefix)
        sel = np.flatnonzero(vals >= kth_largest(vals, m))  # the best m and their ties, in window order
        order, sb, _ = _sorted_boxes(sel, cand, vals, boxes)  # valid: boxes_ok
        keep = _grid_nms_sorted(sb, iou, k, NO_CLASSES, NO_CLASSES, *map(float, thin))
        if len(keep) == k:
            return cand[sel[order[keep]]]
    sel = np.arange(len(cand))
    order, sb, ok = _sorted_boxes(sel, cand, vals, boxes)
    if not ok:
        return None
    labels = classes[cand[order]] if classes is not None else NO_CLASSES
    return cand[order[_grid_nms_sorted(sb, iou, k, labels, need, *map(float, thin))]]


@numba.njit(cache=True, nogil=True)
def _candidate_scores(chosen: np.ndarray, scores: np.ndarray):  # pragma: no cover - compiled
    """The chosen windows (ascending), their float32 scores, and whether one is NaN: a
    counting pass, then one pass that writes every window at the next free place and moves
    on only past a chosen one (no branch per window, where ``np.nonzero`` and a gather
    would take one)."""
    n = chosen.shape[0]
    m = 0
    for i in range(n):
        m += chosen[i]
    cand = np.empty(m + 1, np.int64)  # one spare place for the writes past the last chosen
    vals = np.empty(m + 1, np.float32)
    j = 0
    nan = False
    for i in range(n):
        v = scores[i]
        c = chosen[i]
        cand[j] = i
        vals[j] = v
        nan |= c & np.isnan(v)
        j += c
    return cand[:m], vals[:m], nan


@numba.njit(cache=True, nogil=True)
def _sorted_boxes(sel: np.ndarray, cand: np.ndarray, vals: np.ndarray, boxes: np.ndarray):  # pragma: no cover
    """The stable descending order of ``vals[sel]`` (radix sort), the boxes of
    ``cand[sel]`` in that order, and whether all are finite with ``x1 <= x2, y1 <= y2``."""
    n = sel.shape[0]
    sv = np.empty(n, np.float32)
    for j in range(n):
        sv[j] = vals[sel[j]]
    order = descending_order(sv)
    sb = np.empty((n, 4), np.float32)
    for j in range(n):
        src = cand[sel[order[j]]]
        a, b, c, d = boxes[src, 0], boxes[src, 1], boxes[src, 2], boxes[src, 3]
        if not (np.isfinite(a) and np.isfinite(b) and np.isfinite(c) and np.isfinite(d) and c >= a and d >= b):
            return order, sb, False
        sb[j, 0], sb[j, 1], sb[j, 2], sb[j, 3] = a, b, c, d
    return order, sb, True
