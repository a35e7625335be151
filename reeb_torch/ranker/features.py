"""Per-box features for the learned ranking (not in the paper; ``ReebConfig.ranker``).

REEB's windows cover the objects, but its hand-weighted score V (eq. 12) cannot order
them: a small model over cheap per-box features can (:mod:`reeb_torch.ranker`). This
module computes those features, one row per candidate box, from the tables the batch
already builds — the integral images of the edge map, the grey image (and its square),
the green-pixel counts, and the groups' enclosed-sum tables — so each feature is a
handful of O(1) box sums. REEB's own terms are features of their own: the edge score S
(eq. 1), the location fit of each object class, the shadow and vegetation shares, the
region's entropy and share of the budget (eqs. 2, 9), and V itself.

Coordinates are working pixels; a box is ``int64 (x0, y0, x1, y1)`` with exclusive ends,
inside the image and at least one pixel wide and tall. :func:`feature_names` lists the
columns in order; :data:`FEATURES_VERSION` changes whenever a definition does (a weights
file names the version it was fitted on).

Two paths give the same features (to float32 rounding of the logarithms; tested):
:func:`box_features`, tensor ops on any device (the reference), and
:func:`box_features_cpu`, one compiled pass over the boxes (numba), split between the two
cores: ~70 box sums a box are ~70 gathers of ``K`` elements each as tensor ops, and a few
loads of cached memory in the compiled loop.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple, Sequence

import numba
import numpy as np
import torch
from torch import Tensor

from ..stages._threads import on_two_cores
from ..stages.enclosed import EnclosedTables, box_sum_at, enclosed_at
from ..stages.scoring import class_height_fits, class_width_fits, edge_norm

__all__ = ["FEATURES_VERSION", "FEATURE_GROUPS", "dropped_columns", "BoxMaps", "feature_names", "window_names",
           "cheap_count", "window_features", "box_features", "box_features_cpu"]

FEATURES_VERSION = 1
"""Version of the feature definitions; a weights file fitted on another is refused."""

_GEOMETRY = ("log_height", "log_width", "log_aspect", "top", "bottom", "centre_x", "off_centre", "depth",
             "log_ground_ratio", "at_border")
_DYNAMIC = ("log_v", "region_share", "region_entropy")
_TERMS = ("log_edge_score", "shadow", "vegetation")
_EDGES = ("edge_inside", "edge_centre", "edge_ring", "edge_contrast", "enclosed_share", "edge_left_right",
          "edge_top_bottom", "edge_border")
_GREY = ("grey_mean", "grey_std", "grey_ring", "grey_contrast", "green_share")
_LAYOUT = tuple(f"edge_cell_{i}{j}" for i in range(3) for j in range(3)) + (
    "ring_left", "ring_right", "ring_top", "ring_bottom")

_LOG_COLUMNS = ("log_v", "log_edge_score") + _LAYOUT
"""The columns that are logarithms (in this order in the compiled kernel's ``logs``)."""

RING = 0.25
"""The ring around a box: the box grown by this fraction of its width (height) on each side,
less the box (Alexe et al.'s surround), clipped to the image."""
CENTRE = 0.25
"""The centre of a box for ``edge_centre``: the box shrunk by this fraction of its side on each side."""
BORDER = 0.15
"""The inner border band: the box less the box shrunk by this fraction of its side on each side
(also the part of the box whose green share is ``vegetation``)."""
SHADOW_STRIP, SHADOW_MARGIN = 0.2, 0.15
"""The shadow strips (``ReebConfig.shadow_strip`` / ``shadow_margin``'s defaults, fixed here)."""


def window_names(classes: int) -> tuple[str, ...]:
    """The first columns, which depend on the window alone (its geometry, its location fit L
    and each of the ``classes`` classes' fits): :func:`window_features`, computed once per
    window grid."""
    return _GEOMETRY + ("location",) + tuple(f"class_fit_{c}" for c in range(classes))


def cheap_count(classes: int) -> int:
    """How many first columns need no box sum: :func:`window_names`, then V and its region's
    share and entropy. The ranker's prefilter reads only these, for every candidate; the
    other columns are computed for the candidates it keeps."""
    return len(window_names(classes)) + len(_DYNAMIC)


def feature_names(classes: int) -> tuple[str, ...]:
    """The names of the feature columns for a location score of ``classes`` classes."""
    return window_names(classes) + _DYNAMIC + _TERMS + _EDGES + _GREY + _LAYOUT


FEATURE_GROUPS: dict[str, tuple[str, ...]] = {
    "place": ("top", "bottom", "centre_x", "off_centre", "at_border"),
}
"""Named groups of feature columns for ``reeb fit --drop-features``
(:attr:`~reeb_torch.ranker.fit.FitOptions.drop_features`). ``place``: where the box lies in the
frame (its top and bottom rows, its centre's column, how far off the image's centre, whether
it touches the border), which a model of a few drives can learn as where those drives had
their objects."""


def dropped_columns(names: Sequence[str], drop: Sequence[str]) -> list[int]:
    """The indices in ``names`` of the columns ``drop`` names (feature names or
    :data:`FEATURE_GROUPS`), sorted. ValueError for a name that is neither."""
    cols: set[int] = set()
    for item in drop:
        members = FEATURE_GROUPS.get(item, (item,))
        unknown = [m for m in members if m not in names]
        if unknown:
            raise ValueError(f"drop_features: {', '.join(map(repr, unknown))} is no feature column or group "
                             f"(groups: {', '.join(FEATURE_GROUPS)}; columns: {', '.join(names)})")
        cols.update(names.index(m) for m in members)
    return sorted(cols)


@dataclass
class BoxMaps:
    """What the features of one batch of equal-sized images read (working resolution).

    Attributes:
        size: ``(h, w)`` of the working images.
        ii_edges: ``float64 (B, h + 1, w + 1)`` integral image of the edge magnitudes.
        ii_grey: ``float64 (B, h + 1, w + 1)`` integral image of the grey image in [0, 1].
        ii_grey2: ``float64 (B, h + 1, w + 1)`` integral image of its square.
        green: ``int32 (B, h + 1, w + 1)`` green-pixel counts, or None (those features are 0).
            (The tables may be None for :func:`window_features`, which reads none.)
        tables: the groups' enclosed-sum tables (:class:`~reeb_torch.stages.enclosed.EnclosedTables`).
        horizon: the horizon row as a fraction of the height.
        camera_height_m: the camera's height above the road.
        class_ratios: per class, its typical height over the camera height.
        class_weights: per class, its weight in the location fit.
        class_widths: per class, its ``(lo, hi)`` box width in metres (the shape fit), or None.
        log_sigma: the location fits' tolerance in log units.
        fx, fy: working pixels per input pixel.
        centre_fraction, score_norm, kappa, gamma: eq. 1's centre region and normaliser.
    """

    size: tuple[int, int]
    ii_edges: Tensor | None
    ii_grey: Tensor | None
    ii_grey2: Tensor | None
    green: Tensor | None
    tables: EnclosedTables | None
    horizon: float
    camera_height_m: float
    class_ratios: tuple[float, ...]
    class_weights: tuple[float, ...]
    class_widths: tuple[tuple[float, float], ...] | None
    log_sigma: float
    fx: float
    fy: float
    centre_fraction: float = 0.5
    score_norm: str = "perimeter"
    kappa: float = 1.6
    gamma: float = 0.75

    @property
    def aspect(self) -> float:
        """A working pixel's width over its height, in input pixels (``fx / fy``)."""
        return self.fx / self.fy


# -- the tensor path ------------------------------------------------------------------------------

Box = tuple[Tensor, Tensor, Tensor, Tensor]
"""Boxes as four ``int64 [K]`` columns ``(x0, y0, x1, y1)``, working pixels, ends exclusive."""


class _Sums(NamedTuple):
    """The tables the columns past the cheap ones read (:attr:`BoxMaps.ii_edges`, ...)."""

    edges: Tensor
    grey: Tensor
    grey2: Tensor
    tables: EnclosedTables


def _sums(maps: BoxMaps) -> _Sums:
    """``maps``' integral images and enclosed-sum tables; ValueError where it was made
    without them (they are None for :func:`window_features` and the cheap columns)."""
    if maps.ii_edges is None or maps.ii_grey is None or maps.ii_grey2 is None or maps.tables is None:
        raise ValueError("the box features past the cheap columns read the integral images and the groups' "
                         "enclosed-sum tables, which these BoxMaps lack (made with geometry_only=True)")
    return _Sums(maps.ii_edges, maps.ii_grey, maps.ii_grey2, maps.tables)


def _grown(x0: Tensor, y0: Tensor, x1: Tensor, y1: Tensor, f: float, h: int, w: int) -> Box:
    """The boxes grown (``f > 0``) or shrunk (``f < 0``) by ``round(f · side)`` on each side,
    clipped to the image; at least one pixel stays."""
    dx = ((x1 - x0).double() * f).round().long()
    dy = ((y1 - y0).double() * f).round().long()
    gx0, gy0 = (x0 - dx).clamp(0, w), (y0 - dy).clamp(0, h)
    gx1, gy1 = torch.maximum((x1 + dx).clamp(0, w), gx0 + 1), torch.maximum((y1 + dy).clamp(0, h), gy0 + 1)
    return gx0, gy0, gx1, gy1


def _area(b: Box) -> Tensor:
    return ((b[2] - b[0]) * (b[3] - b[1])).double()


def window_features(maps: BoxMaps, boxes: Tensor) -> Tensor:
    """The columns :func:`window_names` of ``int64 [K, 4]`` working-pixel boxes, ``float64
    [K, 11 + C]``: they read only the box and the camera, so the generator computes them once
    per window grid."""
    x0, y0, x1, y1 = boxes.unbind(1)
    fits = _class_fits(maps, y1, (x1 - x0).double(), (y1 - y0).double())
    cols = _geometry(maps, x0, y0, x1, y1) + [torch.stack(fits).amax(0)] + fits
    return torch.nan_to_num(torch.stack(cols, 1), nan=0.0, posinf=0.0, neginf=0.0)


def box_features(maps: BoxMaps, boxes: Tensor, bi: Tensor, scores: Tensor, region_share: Tensor,
                 region_entropy: Tensor, window: Tensor | None = None, cheap: bool = False) -> Tensor:
    """The features of ``K`` boxes, ``float32 [K, F]`` (columns :func:`feature_names`), as tensor
    ops; with ``cheap``, only the first :func:`cheap_count` columns.

    Args:
        maps: the batch's tables (:class:`BoxMaps`).
        boxes: ``int64 [K, 4]`` working-pixel boxes ``(x0, y0, x1, y1)``, ends exclusive.
        bi: ``int64 [K]`` the image of each box in the batch.
        scores: ``float [K]`` REEB's combined score V (eq. 12) of each box.
        region_share, region_entropy: ``float [K]`` its region's share of the budget (eq. 9)
            and entropy in bits (eq. 2).
        window: the boxes' :func:`window_features`, if already at hand.

    Every column is finite: logarithms are of clamped values, means of empty areas are 0.
    """
    x0, y0, x1, y1 = boxes.unbind(1)
    box: Box = (x0, y0, x1, y1)
    cols = list((window_features(maps, boxes) if window is None else window.double()).unbind(1))
    cols += [torch.log(scores.double().clamp(min=1e-6)), region_share.double(), region_entropy.double()]
    if not cheap:
        sums = _sums(maps)
        cols += _terms(maps, sums, box, bi) + _edge_stats(maps, sums, box, bi) + _grey_stats(maps, sums, box, bi)
        cols += _edge_layout(maps, sums, box, bi)
    out = torch.stack([c.to(torch.float64) for c in cols], 1)
    return torch.nan_to_num(out, nan=0.0, posinf=0.0, neginf=0.0).float()


def _geometry(maps: BoxMaps, x0: Tensor, y0: Tensor, x1: Tensor, y1: Tensor) -> list[Tensor]:
    """Size, aspect, position, depth below the horizon, height over that depth, at the border."""
    h, w = maps.size
    bw, bh = (x1 - x0).double(), (y1 - y0).double()
    depth = y1.double() - maps.horizon * h
    return [torch.log(bh / h), torch.log(bw / w), torch.log(bw / bh / maps.aspect), y0.double() / h, y1.double() / h,
            (x0 + x1).double() / (2 * w), ((x0 + x1).double() / w - 1).abs(), depth / h,
            torch.log(bh / depth.clamp(min=0.5)).clamp(-3, 3), ((x0 == 0) | (x1 == w)).double()]


def _class_fits(maps: BoxMaps, y1: Tensor, bw: Tensor, bh: Tensor) -> list[Tensor]:
    """Each class's location fit (eq. 11's ``classes`` variant): height, and width with the shape fit."""
    h = float(maps.size[0])
    fits = class_height_fits(y1.double(), bh, h, maps.horizon, maps.class_ratios, maps.log_sigma, maps.class_weights)
    if maps.class_widths is None:
        return fits
    widths = class_width_fits(y1.double(), bw / maps.aspect, h, maps.horizon, maps.class_widths, maps.log_sigma,
                              maps.camera_height_m)
    return [a * b for a, b in zip(fits, widths)]


def _terms(maps: BoxMaps, sums: _Sums, box: Box, bi: Tensor) -> list[Tensor]:
    """REEB's own terms that read the image: S (eq. 1), the shadow and vegetation shares."""
    h, w = maps.size
    x0, y0, x1, y1 = box
    at = box_sum_at
    bw, bh = (x1 - x0).double(), (y1 - y0).double()
    cw = (bw * maps.centre_fraction).round().long().clamp(min=1)
    ch = (bh * maps.centre_fraction).round().long().clamp(min=1)
    cx0 = x0 + torch.div(x1 - x0 - cw, 2, rounding_mode="floor")
    cy0 = y0 + torch.div(y1 - y0 - ch, 2, rounding_mode="floor")
    unit = 2.0 / (maps.fx + maps.fy)
    centre = at(sums.edges, bi, cx0, cy0, cx0 + cw, cy0 + ch)
    enclosed = enclosed_at(sums.tables, bi, x0, y0, x1, y1)
    s = (enclosed * unit - centre * unit) / edge_norm(bw / maps.fx, bh / maps.fy, maps.score_norm, maps.kappa,
                                                      maps.gamma)
    sh = (bh * SHADOW_STRIP).round().long().clamp(min=1)
    mx = torch.minimum((bw * SHADOW_MARGIN).floor().long(), torch.div(x1 - x0 - 1, 2, rounding_mode="floor"))
    cols = (x1 - x0 - 2 * mx).double()
    g_in = at(sums.grey, bi, x0 + mx, y1 - sh, x1 - mx, y1) / (sh.double() * cols)
    rows = torch.minimum((h - y1).clamp(min=0), sh)  # the strip below, cut at the image's bottom
    g_below = at(sums.grey, bi, x0 + mx, y1, x1 - mx, y1 + rows) / (rows.double() * cols).clamp(min=1)
    shadow = torch.where(rows > 0, ((g_below - g_in) / g_below.clamp(min=1e-3)).clamp(0, 1), torch.zeros_like(g_in))
    c = _grown(x0, y0, x1, y1, -BORDER, h, w)
    green = (at(maps.green, bi, *c).double() / _area(c) if maps.green is not None else torch.zeros_like(bw))
    return [torch.log(s.clamp(min=1e-4)), shadow, green]


def _edge_stats(maps: BoxMaps, sums: _Sums, box: Box, bi: Tensor) -> list[Tensor]:
    """Mean edge magnitude inside, in the centre and in the ring; the enclosed groups' share;
    left/right and top/bottom balance; the inner border band."""
    h, w = maps.size
    x0, y0, x1, y1 = box
    at = box_sum_at
    area = _area(box)
    e_in = at(sums.edges, bi, *box)
    c = _grown(*box, -CENTRE, h, w)
    r = _grown(*box, RING, h, w)
    r_area = _area(r) - area
    e_ring = torch.where(r_area > 0, (at(sums.edges, bi, *r) - e_in) / r_area.clamp(min=1), torch.zeros_like(e_in))
    mean_in = e_in / area
    enclosed = enclosed_at(sums.tables, bi, *box)  # exact for boxes larger than every group
    e_left = at(sums.edges, bi, x0, y0, torch.div(x0 + x1, 2, rounding_mode="floor"), y1)
    e_top = at(sums.edges, bi, x0, y0, x1, torch.div(y0 + y1, 2, rounding_mode="floor"))
    denom = e_in.clamp(min=1e-9)
    i = _grown(*box, -BORDER, h, w)
    band = (e_in - at(sums.edges, bi, *i)) / (area - _area(i)).clamp(min=1)
    return [mean_in, at(sums.edges, bi, *c) / _area(c), e_ring, mean_in - e_ring, (enclosed / denom).clamp(0, 1),
            ((2 * e_left - e_in) / denom).abs(), (2 * e_top - e_in) / denom, band]


def _grey_stats(maps: BoxMaps, sums: _Sums, box: Box, bi: Tensor) -> list[Tensor]:
    """Mean and spread of the grey image inside, its mean in the ring, their contrast, the green share."""
    h, w = maps.size
    at = box_sum_at
    area = _area(box)
    r = _grown(*box, RING, h, w)
    r_area = _area(r) - area
    g_sum = at(sums.grey, bi, *box)
    g_mean = g_sum / area
    g_var = (at(sums.grey2, bi, *box) / area - g_mean * g_mean).clamp(min=0)
    g_ring = torch.where(r_area > 0, (at(sums.grey, bi, *r) - g_sum) / r_area.clamp(min=1), g_mean)
    green = at(maps.green, bi, *box).double() / area if maps.green is not None else torch.zeros_like(area)
    return [g_mean, g_var.sqrt(), g_ring, (g_mean - g_ring).abs(), green]


def _edge_layout(maps: BoxMaps, sums: _Sums, box: Box, bi: Tensor) -> list[Tensor]:
    """Where the edges lie: the mean edge magnitude of each cell of a 3 × 3 grid over the box
    and of the ring's four strips beside its sides, each as ``log((m + ε) / (mean inside + ε))``."""
    h, w = maps.size
    x0, y0, x1, y1 = box
    at = box_sum_at
    eps = 1e-4
    ref = (at(sums.edges, bi, *box) / _area(box)).clamp(min=1e-6) + eps
    xs = [x0 + torch.div((x1 - x0) * k, 3, rounding_mode="floor") for k in range(4)]
    ys = [y0 + torch.div((y1 - y0) * k, 3, rounding_mode="floor") for k in range(4)]
    out = []
    for i in range(3):
        for j in range(3):
            cell = (xs[j], ys[i], torch.maximum(xs[j + 1], xs[j] + 1), torch.maximum(ys[i + 1], ys[i] + 1))
            out.append(torch.log((at(sums.edges, bi, *cell) / _area(cell) + eps) / ref))
    rx0, ry0, rx1, ry1 = _grown(*box, RING, h, w)
    for a, b, c, d in ((rx0, y0, x0, y1), (x1, y0, rx1, y1), (x0, ry0, x1, y0), (x0, y1, x1, ry1)):
        n = ((c - a) * (d - b)).double()
        m = torch.where(n > 0, at(sums.edges, bi, a, b, c, d) / n.clamp(min=1), torch.zeros_like(n))
        out.append(torch.log((m + eps) / ref))
    return out


# -- the compiled path ----------------------------------------------------------------------------

@numba.njit(cache=True, nogil=True, inline="always")
def _s(t: np.ndarray, b: int, x0: int, y0: int, x1: int, y1: int) -> float:  # pragma: no cover - compiled
    return float(t[b, y1, x1]) - float(t[b, y0, x1]) - float(t[b, y1, x0]) + float(t[b, y0, x0])


@numba.njit(cache=True, nogil=True, inline="always")
def _grow(a: int, b: int, f: float, lo: int, hi: int) -> tuple[int, int]:  # pragma: no cover - compiled
    """One axis of :func:`_grown`: ``[a, b)`` grown by ``round(f · (b − a))`` each side, clipped to ``[lo, hi]``."""
    d = int(np.rint((b - a) * f))
    ga = min(max(a - d, lo), hi)
    gb = max(min(max(b + d, lo), hi), ga + 1)
    return ga, gb


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _features_kernel(grid_boxes: np.ndarray, window: np.ndarray, scores: np.ndarray, share: np.ndarray,
                     entropy: np.ndarray, region_of: np.ndarray, bi: np.ndarray, ni: np.ndarray, ii: np.ndarray,
                     grey: np.ndarray, grey2: np.ndarray, green: np.ndarray, anchor: np.ndarray,
                     cut_col: np.ndarray, cut_row: np.ndarray, corner: np.ndarray, consts: np.ndarray,
                     out: np.ndarray, logs: np.ndarray, full: bool, lo: int,
                     hi: int) -> None:  # pragma: no cover - compiled
    """Rows ``lo:hi`` of :func:`box_features_cpu` (the same arithmetic as the tensor path, in
    float64, stored as float32), the window columns copied from ``window``; without ``full``,
    only the cheap columns. The arguments of the logarithms go to ``logs`` (float64, the
    columns :data:`_LOG_COLUMNS`), whose logarithms the caller takes, vectorised, and stores.
    ``consts``: h, w, fx, fy, centre fraction, norm (0 perimeter, 1 area), kappa, gamma, has
    green (1/0)."""
    h, w = int(consts[0]), int(consts[1])
    fx, fy, cf, norm_area, kappa, gamma = consts[2], consts[3], consts[4], consts[5] == 1.0, consts[6], consts[7]
    has_green = consts[8] == 1.0
    nw = window.shape[1]
    for k in range(lo, hi):
        b, n = bi[k], ni[k]
        x0, y0 = int(np.rint(grid_boxes[n, 0])), int(np.rint(grid_boxes[n, 1]))
        x1, y1 = int(np.rint(grid_boxes[n, 2])), int(np.rint(grid_boxes[n, 3]))
        o = out[k]
        for c in range(nw):
            o[c] = window[n, c]
        r = region_of[n]
        logs[k, 0] = max(float(scores[b, n]), 1e-6)
        o[nw + 1], o[nw + 2] = share[b, r], entropy[b, r]
        if full:
            _rest(o, logs[k], nw + 3, b, x0, y0, x1, y1, h, w, fx, fy, cf, norm_area, kappa, gamma, has_green, ii,
                  grey, grey2, green, anchor, cut_col, cut_row, corner)


@numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _rest(o: np.ndarray, lg: np.ndarray, j: int, b: int, x0: int, y0: int, x1: int, y1: int, h: int, w: int,
          fx: float, fy: float, cf: float, norm_area: bool, kappa: float, gamma: float, has_green: bool,
          ii: np.ndarray, grey: np.ndarray, grey2: np.ndarray, green: np.ndarray, anchor: np.ndarray,
          cut_col: np.ndarray, cut_row: np.ndarray, corner: np.ndarray) -> None:  # pragma: no cover - compiled
    """The columns after the cheap ones of one box, from column ``j`` of ``o``; the arguments
    of their logarithms in ``lg[1:]``."""
    bw, bh = float(x1 - x0), float(y1 - y0)
    area = bw * bh
    # REEB's terms: S (eq. 1), the shadow and vegetation shares
    cw, ch = max(int(np.rint(bw * cf)), 1), max(int(np.rint(bh * cf)), 1)
    cx0, cy0 = x0 + (x1 - x0 - cw) // 2, y0 + (y1 - y0 - ch) // 2
    unit = 2.0 / (fx + fy)
    enc = (_s(anchor, b, x0, y0, x1, y1) - (cut_col[b, y1, x1] - cut_col[b, y0, x1])
           - (cut_row[b, y1, x1] - cut_row[b, y1, x0]) + corner[b, y1, x1])
    centre = _s(ii, b, cx0, cy0, cx0 + cw, cy0 + ch)
    bwi, bhi = bw / fx, bh / fy
    nrm = 2.0 * (bwi * bhi) ** gamma if norm_area else (2.0 * (bwi + bhi)) ** kappa
    s = (enc * unit - centre * unit) / nrm
    sh = max(int(np.rint(bh * SHADOW_STRIP)), 1)
    mx = min(int(np.floor(bw * SHADOW_MARGIN)), (x1 - x0 - 1) // 2)
    ncol = float(x1 - x0 - 2 * mx)
    g_in = _s(grey, b, x0 + mx, y1 - sh, x1 - mx, y1) / (sh * ncol)
    rows = min(max(h - y1, 0), sh)
    g_below = _s(grey, b, x0 + mx, y1, x1 - mx, y1 + rows) / max(rows * ncol, 1.0)
    shadow = min(max((g_below - g_in) / max(g_below, 1e-3), 0.0), 1.0) if rows > 0 else 0.0
    vx0, vx1 = _grow(x0, x1, -BORDER, 0, w)
    vy0, vy1 = _grow(y0, y1, -BORDER, 0, h)
    veg = _s(green, b, vx0, vy0, vx1, vy1) / ((vx1 - vx0) * (vy1 - vy0)) if has_green else 0.0
    lg[1] = max(s, 1e-4)
    o[j + 1], o[j + 2] = shadow, veg
    j += 3
    # edge statistics
    e_in = _s(ii, b, x0, y0, x1, y1)
    qx0, qx1 = _grow(x0, x1, -CENTRE, 0, w)
    qy0, qy1 = _grow(y0, y1, -CENTRE, 0, h)
    rx0, rx1 = _grow(x0, x1, RING, 0, w)
    ry0, ry1 = _grow(y0, y1, RING, 0, h)
    r_area = float((rx1 - rx0) * (ry1 - ry0)) - area
    e_ring = (_s(ii, b, rx0, ry0, rx1, ry1) - e_in) / max(r_area, 1.0) if r_area > 0 else 0.0
    mean_in = e_in / area
    denom = max(e_in, 1e-9)
    e_left = _s(ii, b, x0, y0, (x0 + x1) // 2, y1)
    e_top = _s(ii, b, x0, y0, x1, (y0 + y1) // 2)
    ix0, ix1 = _grow(x0, x1, -BORDER, 0, w)
    iy0, iy1 = _grow(y0, y1, -BORDER, 0, h)
    band = (e_in - _s(ii, b, ix0, iy0, ix1, iy1)) / max(area - (ix1 - ix0) * (iy1 - iy0), 1.0)
    o[j], o[j + 1] = mean_in, _s(ii, b, qx0, qy0, qx1, qy1) / ((qx1 - qx0) * (qy1 - qy0))
    o[j + 2], o[j + 3], o[j + 4] = e_ring, mean_in - e_ring, min(max(enc / denom, 0.0), 1.0)
    o[j + 5], o[j + 6], o[j + 7] = abs((2 * e_left - e_in) / denom), (2 * e_top - e_in) / denom, band
    j += 8
    # grey statistics
    g_sum = _s(grey, b, x0, y0, x1, y1)
    g_mean = g_sum / area
    g_var = max(_s(grey2, b, x0, y0, x1, y1) / area - g_mean * g_mean, 0.0)
    g_ring = (_s(grey, b, rx0, ry0, rx1, ry1) - g_sum) / max(r_area, 1.0) if r_area > 0 else g_mean
    o[j], o[j + 1], o[j + 2], o[j + 3] = g_mean, np.sqrt(g_var), g_ring, abs(g_mean - g_ring)
    o[j + 4] = _s(green, b, x0, y0, x1, y1) / area if has_green else 0.0
    # where the edges lie
    ref = max(mean_in, 1e-6) + 1e-4
    for ci in range(3):
        ya, yb = y0 + (y1 - y0) * ci // 3, y0 + (y1 - y0) * (ci + 1) // 3
        yb = max(yb, ya + 1)
        for cj in range(3):
            xa, xb = x0 + (x1 - x0) * cj // 3, x0 + (x1 - x0) * (cj + 1) // 3
            xb = max(xb, xa + 1)
            lg[2 + 3 * ci + cj] = (_s(ii, b, xa, ya, xb, yb) / ((xb - xa) * (yb - ya)) + 1e-4) / ref
    for side in range(4):
        if side == 0:
            a, c, d, e = rx0, y0, x0, y1
        elif side == 1:
            a, c, d, e = x1, y0, rx1, y1
        elif side == 2:
            a, c, d, e = x0, ry0, x1, y0
        else:
            a, c, d, e = x0, y1, x1, ry1
        n = (d - a) * (e - c)
        lg[11 + side] = ((_s(ii, b, a, c, d, e) / n if n > 0 else 0.0) + 1e-4) / ref


def box_features_cpu(maps: BoxMaps, grid_boxes: Tensor, window: Tensor, scores: Tensor, share: Tensor,
                     entropy: Tensor, region_of: Tensor, bi: Tensor, ni: Tensor, cheap: bool = False,
                     extra: int = 0) -> Tensor:
    """:func:`box_features` of the candidates ``(bi, ni)`` (image, window) in one compiled pass, the
    boxes split between the two cores; the same numbers. It reads the windows where they lie:
    ``grid_boxes float32 [N, 4]`` (rounded to whole working pixels), their ``window`` columns
    ``float32 [N, 11 + C]``, V ``float32 [B, N]``, the regions' ``share`` and ``entropy``
    ``[B, R]`` and each window's region ``int64 [N]``. ``extra``: that many more columns after
    these, left for the caller to fill (uninitialised; no copy to append them)."""
    h, w = maps.size
    consts = np.array([h, w, maps.fx, maps.fy, maps.centre_fraction, 1.0 if maps.score_norm == "area" else 0.0,
                       maps.kappa, maps.gamma, 1.0 if maps.green is not None else 0.0])
    n_cls = len(maps.class_ratios)
    f = cheap_count(n_cls) if cheap else len(feature_names(n_cls))
    out = np.empty((len(bi), f + extra), np.float32)
    none = np.zeros((1, 1, 1))
    if cheap:
        tables = (none, none, none, np.zeros((1, 1, 1), np.int32), none, none, none, none)
    else:
        sums = _sums(maps)
        t = sums.tables
        tables = (sums.edges.numpy(), sums.grey.numpy(), sums.grey2.numpy(),
                  maps.green.numpy() if maps.green is not None else np.zeros((1, 1, 1), np.int32),
                  t.anchor.numpy(), t.cut_col.numpy(), t.cut_row.numpy(), t.corner.numpy())
    logs = np.empty((len(bi), 1 if cheap else len(_LOG_COLUMNS)))
    args = (grid_boxes.numpy(), window.numpy(), scores.numpy(), share.double().numpy(), entropy.double().numpy(),
            region_of.numpy(), bi.numpy(), ni.numpy(), *tables, consts, out, logs, not cheap)
    on_two_cores(lambda lo, hi: _features_kernel(*args, lo, hi), len(bi))
    # the logarithms, vectorised (a scalar log in the loop cost a third of its time), then
    # the non-finite values to 0, as the tensor path's torch.nan_to_num
    np.log(logs, out=logs)
    nw = window.shape[1]
    out[:, nw] = logs[:, 0]  # log_v
    if not cheap:  # log_edge_score, then the layout columns, the last ones
        out[:, nw + 3] = logs[:, 1]
        out[:, f - len(_LAYOUT): f] = logs[:, 2:]
    return torch.nan_to_num_(torch.from_numpy(out), nan=0.0, posinf=0.0, neginf=0.0)
