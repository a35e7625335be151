"""Ranking the windows: scores (eqs. 1, 10–12), each region's budget (eq. 9), Edge Boxes'
refinement and the final NMS (eq. 13), for the generator's Table 1.

The stages in :mod:`reeb_torch.stages` are plain functions; this module is the glue that
maps a :class:`~reeb_torch.ReebConfig` onto them, picks the compiled (numba, CPU) or the
tensor (any device, the reference) path of each, and keeps what is worth keeping:

* :class:`ScoreMaps`: what the scores of one batch read (edge map, groups, road mask,
  grey image, green-pixel counts) and the tables built from them — integral images and
  the enclosed-sum prefix tables — each built on first use and kept for the batch, so the
  grid scorer, the box scorer and the refinement read one set;
* :class:`Ranking`: one config's window grid, scoring passes, selection, refinement and
  suppression, with what depends only on the image size (the score plan, the location
  and normaliser tables, the windows' boxes in input pixels) cached per window grid.

Where the paths split (both give the same numbers, tested bit for bit):

=================  ===========================================  ==================================
step               compiled (CPU)                               tensor ops (CUDA, and the rest)
=================  ===========================================  ==================================
scores             :func:`~reeb_torch.stages.scoring.score_grid_cpu`,  :meth:`Ranking.score_torch`, one
                   when no term needs per-window maps           batch of ops per window size
                   (:meth:`Ranking.compiled_scoring_applies`)
eq. 9's cut        :func:`~reeb_torch.stages.scoring.select_per_region_cpu`  :meth:`Ranking.select_torch`
refinement         :func:`~reeb_torch.stages.refinement.refine_boxes_cpu`  :func:`~reeb_torch.stages.refinement.refine_boxes`
                   (:meth:`Ranking.compiled_refine_applies`)    with :meth:`Ranking.box_scorer`
NMS                :func:`~reeb_torch.stages.nms.nms_windows_cpu`  :func:`~reeb_torch.stages.nms.nms_top_k_many`
=================  ===========================================  ==================================
"""

from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass, field
from contextlib import nullcontext
from typing import Callable, ContextManager, Literal

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from .config import ReebConfig
from .stages import _scratch
from .stages import refinement as _refinement
from .stages import rescoring as _rescoring
from .stages import scoring as _scoring
from .stages import windows as _windows
from .ranker import features as _features
from .ranker.prefilter import prefilter_cpu
from .stages.groups import EdgeGroups
from .stages._radix import kth_largest
from .ranker.model import softmax_rows
from .stages.nms import boxes_valid, nms_top_k_many, nms_windows_cpu

__all__ = ["ScoreMaps", "Ranking"]

#: ``score_fn(boxes, b)`` of :meth:`Ranking.box_scorer`: V of int64 ``[K, 4]`` boxes of images ``b``.
BoxScoreFn = Callable[[Tensor, Tensor], Tensor]


@dataclass(eq=False)
class ScoreMaps:
    """What the scores of one batch of equal-sized images read, at the working resolution,
    and the tables built from it (built on first use, then kept for the batch).

    Attributes:
        edges: ``float32 (B, h, w)`` edge magnitudes (Sec. 3.4).
        groups: the batch's :class:`~reeb_torch.stages.groups.EdgeGroups` (Sec. 3.7).
        input_size: ``(H, W)`` of the input images (boxes are returned in those pixels).
        road: ``(B, h, w)`` road mask (eqs. 3–4), or None where no road term reads it.
        grey: ``float32 (B, h, w)`` grey image (the shadow term, the learned ranking's features), or None.
        green: ``int32 (B, h + 1, w + 1)`` green-pixel counts (an integral image already)
            for the vegetation term, or None without it.
        crossing: the straddling term's ``(columns, rows)`` maps of edges crossing a side,
            or None without it.
    """

    edges: Tensor
    groups: EdgeGroups
    input_size: tuple[int, int]
    road: Tensor | None = None
    grey: Tensor | None = None
    green: Tensor | None = None
    crossing: tuple[Tensor, Tensor] | None = None
    _kept: dict = field(default_factory=dict, repr=False)
    _pending: Callable[[], _refinement.EnclosedTables] | None = field(default=None, repr=False)

    @property
    def fx(self) -> float:
        """Working pixels per input pixel, horizontally."""
        return self.edges.shape[-1] / self.input_size[1]

    @property
    def fy(self) -> float:
        """Working pixels per input pixel, vertically."""
        return self.edges.shape[-2] / self.input_size[0]

    def _keep(self, key: object, build: Callable[[], object]):
        if key not in self._kept:
            self._kept[key] = build()
        return self._kept[key]

    def tables(self) -> _refinement.EnclosedTables:
        """The groups' enclosed-sum prefix tables (:func:`~reeb_torch.stages.refinement.enclosed_tables`);
        where :meth:`start_tables` started them, waits for them."""
        self.settle()
        b, hk, wk = self.edges.shape
        return self._keep("tables", lambda: _refinement.enclosed_tables(self.groups, b, hk, wk))

    def start_tables(self) -> None:
        """Start :meth:`tables` on the helper thread (CPU only): this thread goes on meanwhile
        and :meth:`tables` collects them. Whoever calls this calls :meth:`settle` before
        the batch ends, whatever happens (the tables are memory the next batch reuses)."""
        if "tables" not in self._kept and self._pending is None and self.edges.device.type == "cpu":
            b, hk, wk = self.edges.shape
            self._pending = _refinement.enclosed_tables_started(self.groups, b, hk, wk)

    def settle(self) -> None:
        """Wait for the tables :meth:`start_tables` started, if any, and keep them."""
        pending, self._pending = self._pending, None
        if pending is not None:
            self._kept["tables"] = pending()

    def integral(self, name: Literal["edges", "grey", "road"]) -> Tensor:
        """The integral image (:func:`~reeb_torch.stages.scoring.integral_image`) of the
        edge map, the grey image or the road mask."""
        return self._keep(name, lambda: _scoring.integral_image(getattr(self, name), key=f"integral.{name}"))

    def integral_below(self, name: Literal["grey", "road"]) -> Tensor:
        """:meth:`integral` extended past the bottom row (strips below a box read zeros
        there: :func:`~reeb_torch.stages.scoring.extend_below`)."""
        return self._keep((name, "below"), lambda: _scoring.extend_below(self.integral(name)))

    def crossing_integrals(self, band: int) -> tuple[Tensor, Tensor]:
        """Integral images of the straddling term's two maps, padded by ``band`` so that
        sides at the image border read zeros."""
        def build() -> tuple[Tensor, Tensor]:
            assert self.crossing is not None, "the straddling term's maps were not made"
            cols, rows = self.crossing
            return (_scoring.integral_image(F.pad(cols, (band, band, band, band))),
                    _scoring.integral_image(F.pad(rows, (band, band, band, band))))

        return self._keep(("crossing", band), build)


PLAN_GRIDS = 16
"""Window grids (image sizes) whose per-size tables :class:`Ranking` keeps, the latest used."""

_NOT_SEEN_BY_RANKER = ("top_k", "ranker", "ranker_keep", "ranker_v_share", "nms_iou", "region_quota",
                       "class_quota")
"""Fields a ranking model does not depend on (they act after it)."""


def _warn_if_fitted_elsewhere(config: ReebConfig, fitted: dict | None) -> None:
    """Warn (once per setting) when ``config`` differs from the one the ranking model was fitted
    with in a field its features or candidates depend on: it still runs, likely worse."""
    if not fitted:
        return
    import json
    import warnings

    now = json.loads(json.dumps(config.to_dict(), default=list))
    differ = [k for k, v in now.items() if k in fitted and k not in _NOT_SEEN_BY_RANKER and fitted[k] != v]
    if differ:
        shown = ", ".join(f"{k}={now[k]!r} (fitted with {fitted[k]!r})" for k in differ[:3])
        more = f" and {len(differ) - 3} more" if len(differ) > 3 else ""
        warnings.warn(f"reeb: the ranker {config.ranker!r} was fitted with other settings: {shown}{more}; it "
                      "ranks these candidates, likely worse than on its own (reeb fit fits one for them)",
                      UserWarning, stacklevel=4)


def _chosen(chosen: Tensor) -> tuple[Tensor, Tensor]:
    """``torch.nonzero(chosen, as_tuple=True)`` of a ``bool [B, N]`` mask: ``(bi, ni)``
    ``int64``, image-major, windows ascending. On the CPU numpy's ``flatnonzero``, an image
    at a time (torch's 2-D nonzero took 3 ms for 4 KITTI images' 170 000 windows; this 0.4)."""
    if chosen.device.type != "cpu":
        images, windows = torch.nonzero(chosen, as_tuple=True)
        return images, windows
    mask = chosen.numpy()
    parts = [np.flatnonzero(row) for row in mask]
    ni = np.concatenate(parts) if parts else np.zeros(0, np.int64)
    bi = np.repeat(np.arange(len(parts)), [len(p) for p in parts])
    return torch.from_numpy(bi.astype(np.int64, copy=False)), torch.from_numpy(ni.astype(np.int64, copy=False))


def _gather(values: Tensor, bi: Tensor, ni: Tensor, counts: Tensor) -> Tensor:
    """``values[bi, ni]`` for :func:`_chosen`'s ``(bi, ni)`` (image-major, ``counts`` an
    image): on the CPU numpy's take, an image row at a time (torch's 2-D gather took 0.25 ms
    for a KITTI image's 77 000 candidates; this 0.07)."""
    if values.device.type != "cpu":
        return values[bi, ni]
    rows, idx = values.numpy(), ni.numpy()
    parts, start = [], 0
    for b, n in enumerate(counts.tolist()):
        parts.append(np.take(rows[b], idx[start: start + n]))
        start += n
    return torch.from_numpy(np.concatenate(parts) if parts else rows.reshape(-1)[:0].copy())


def _best_per_image(values: Tensor, counts: Tensor, keep: int) -> Tensor:
    """Indices of the best ``keep`` of each image's ``values`` (the images' values lie in
    consecutive runs of ``counts``), ties to the earlier; ascending. On the CPU a compiled
    radix selection (:func:`~reeb_torch.stages._radix.kth_largest`), elsewhere a stable sort."""
    out, start = [], 0
    for n in counts.tolist():
        part = values[start: start + n]
        if n <= keep:
            sel = torch.arange(n, device=values.device)
        elif values.device.type == "cpu":
            v = part.detach().float().contiguous().numpy()
            thr = kth_largest(v, keep)
            mask = v > thr
            mask[np.flatnonzero(v == thr)[: keep - int(mask.sum())]] = True  # ascending, without a sort
            sel = torch.from_numpy(np.flatnonzero(mask))
        else:
            sel = torch.sort(part, descending=True, stable=True).indices[:keep].sort().values
        out.append(sel + start)
        start += n
    return torch.cat(out) if out else values.new_zeros(0, dtype=torch.long)


def _tables_exact(groups: EdgeGroups, grid: _windows.WindowGrid) -> bool:
    """Whether the prefix tables give eq. 1's enclosed sums exactly for every window of
    ``grid``: every window is wider and taller than every edge group."""
    return groups.max_extent < grid.min_side


def _centred(x0: Tensor, y0: Tensor, w: Tensor, h: Tensor, fraction: float) -> tuple[Tensor, ...]:
    """The centred ``fraction`` of each box, as :func:`~reeb_torch.stages.scoring.centre_box` places it."""
    cw = (w * fraction).round().long().clamp_(min=1)
    ch = (h * fraction).round().long().clamp_(min=1)
    cx0 = x0 + torch.div(w - cw, 2, rounding_mode="floor")
    cy0 = y0 + torch.div(h - ch, 2, rounding_mode="floor")
    return cx0, cy0, cx0 + cw, cy0 + ch


class Ranking:
    """One config's windows, scored, cut per region, refined and suppressed.

    :class:`~reeb_torch.ProposalGenerator` calls, in Table 1's order, :meth:`window_grid`,
    :meth:`score`, :meth:`select`, :meth:`rescore`, :meth:`refine` (with ``refine``) and
    :meth:`suppress`.
    A subclass may change a step to try another ranking (the generator's ``ranking``
    attribute takes it; ``benchmarks/selection_variants.py`` changes :meth:`region_cut`),
    and :attr:`on_select` sees every region cut (``benchmarks/_common.py``).
    """

    def __init__(self, config: ReebConfig) -> None:
        self.config = config
        self.on_select: Callable[[Tensor, _windows.WindowGrid, Tensor, Tensor], None] | None = None
        """Called as ``on_select(scores, grid, chosen, share)`` after each region cut
        (diagnostics); ``None`` (default) calls nothing. Inside ``forward`` the ``scores``
        and ``chosen`` it is handed live in memory the next call reuses: copy what you keep."""
        self.on_rank: Callable[[Tensor, Tensor], None] | None = None
        """Called as ``on_rank(scores, chosen)`` with what :meth:`rank_learned` returns
        (diagnostics; live memory as for :attr:`on_select`); ``None`` (default) calls nothing."""
        self._device_cache: dict = {}
        self._plan_cache: OrderedDict[int, tuple[_windows.WindowGrid, dict]] = OrderedDict()
        self.model = None
        """The learned ranking's :class:`~reeb_torch.ranker.BoxRanker` (``config.ranker``), or None."""
        self.class_share: tuple[float, ...] | None = None
        """``config.class_quota`` as one share a class of the model's class head
        (:meth:`~reeb_torch.config.ReebConfig.class_shares`), or None: no class quota."""
        if config.ranker != "none":
            from .ranker import load_ranker

            self.model = load_ranker(config.ranker, self.feature_names())
            _warn_if_fitted_elsewhere(config, self.model.meta.get("config"))
            self.class_share = config.class_shares(self.model.classes)
            if config.class_quota and self.class_share is None:
                import warnings

                warnings.warn(f"ReebConfig.class_quota is ignored: the ranker {config.ranker!r} has no class head "
                              "(fit one with reeb fit, whose models have one by default)", UserWarning, stacklevel=3)

    # -- windows (Sec. 3.6) -----------------------------------------------------------------
    def window_grid(self, maps: ScoreMaps, bounds: Tensor) -> _windows.WindowGrid:
        """The windows of the batch's image size, counted against the regions ``bounds``."""
        cfg = self.config
        hk, wk = maps.edges.shape[-2:]
        fx, fy = maps.fx, maps.fy
        ground = None if cfg.ground_band is None else (cfg.horizon, *cfg.ground_band)
        camera = None
        if cfg.window_geometry == "camera":
            # template extents (metres) over the camera height: the ratios box side / (y_b − y_h)
            ratios = tuple((hl / cfg.camera_height_m, hh / cfg.camera_height_m,
                            wl / cfg.camera_height_m * fx / fy, wh / cfg.camera_height_m * fx / fy)
                           for hl, hh, wl, wh in cfg.object_templates)
            camera = (cfg.horizon, ratios, cfg.border_windows, cfg.horizon_slack)
        return _windows.window_grid(hk, wk, bounds, self.min_window_working(fx, fy), cfg.size_ratio,
                                    cfg.window_step, cfg.aspect_range, cfg.region_assign, ground, camera)

    def min_window_working(self, fx: float, fy: float) -> int:
        """The smallest window side in working pixels (at least 3)."""
        return max(3, int(round(self.config.min_window * min(fx, fy))))

    # -- scores (eqs. 1, 10-12) ---------------------------------------------------------------
    def score(self, maps: ScoreMaps, grid: _windows.WindowGrid) -> Tensor:
        """V (eq. 12) of every window, ``float32 [B, N]``; ``-inf`` where S < min_edge_score
        (or, with ``local_max``, where a neighbouring position of the same size scores higher).

        On the CPU, when no term needs per-window maps (no road fraction, straddling or
        local maxima) and every window is wider and taller than every edge group, one
        compiled pass (:func:`reeb_torch.stages.scoring.score_grid_cpu`) scores all windows;
        otherwise one batch of tensor ops per window size (:meth:`score_torch`). Both give
        the same numbers."""
        if self.compiled_scoring_applies(maps, grid):
            return self.score_compiled(maps, grid)
        return self.score_torch(maps, grid)

    def compiled_scoring_applies(self, maps: ScoreMaps, grid: _windows.WindowGrid) -> bool:
        """Whether :meth:`score_compiled` computes this config's scores on this batch."""
        return self.compiled_scoring_may_apply(maps) and bool(grid.sizes) and _tables_exact(maps.groups, grid)

    def compiled_scoring_may_apply(self, maps: ScoreMaps) -> bool:
        """:meth:`compiled_scoring_applies` but for the window grid's part: whether the
        scores may read ``maps.tables()`` (the generator starts them early then)."""
        cfg = self.config
        return (maps.edges.device.type == "cpu" and maps.crossing is None and not cfg.local_max
                and cfg.road_score in ("none", "flat"))

    def score_compiled(self, maps: ScoreMaps, grid: _windows.WindowGrid) -> Tensor:
        """:meth:`score` in one compiled pass (:func:`reeb_torch.stages.scoring.score_grid_cpu`)."""
        cfg = self.config
        fx, fy = maps.fx, maps.fy
        plan, denom, loc, order = self._score_plan(grid, fx, fy, *maps.input_size)
        b = maps.edges.shape[0]
        out_np = _scratch.empty("score.out", (b, grid.count), np.float32)
        out_np.fill(-np.inf)  # (numpy's fill: one thread, where torch's would wake its pool)
        out = torch.from_numpy(out_np)
        road = 1.0 if cfg.road_score == "flat" else 0.0
        ii_grey = shadow = sqrt_floor = None
        if cfg.shadow_score != "none":
            ii_grey = maps.integral("grey")
            if cfg.shadow_power == 0.5:  # the factor in the kernel: sqrt rounds alike everywhere
                sqrt_floor = cfg.shadow_floor
            else:
                shadow = torch.zeros((b, grid.count), dtype=torch.float64)
        _scoring.score_grid_cpu(maps.integral("edges"), maps.tables(), plan, denom, loc, _scoring.unit_scale(fx, fy),
                                cfg.alpha, cfg.beta * road, cfg.min_edge_score, out, ii_grey, shadow, sqrt_floor,
                                maps.green, cfg.vegetation_power, order)
        if shadow is not None:
            out = _scoring.apply_shadow(out, shadow, cfg.shadow_floor, cfg.shadow_power)
        return out

    def score_torch(self, maps: ScoreMaps, grid: _windows.WindowGrid) -> Tensor:
        """:meth:`score` as tensor ops, one batch of them per window size (any device, any config)."""
        cfg = self.config
        edges, fx, fy = maps.edges, maps.fx, maps.fy
        b = edges.shape[0]
        ii_edges = maps.integral("edges")
        enclosed = self.enclosed(maps, grid)
        ii_road = maps.integral("road") if maps.road is not None else None  # None: no road term
        ii_road_below = maps.integral_below("road") if cfg.road_score == "stand" else None  # none past the bottom
        loc_cache: dict = {}  # L of a size's rows, shared between sizes with the same _loc_key
        band = cfg.straddle_band
        if maps.crossing is not None:  # padded by the band so sides at the image border read zeros
            ii_cols, ii_rows = maps.crossing_integrals(band)
        unit = _scoring.unit_scale(fx, fy)
        out = torch.full((b, grid.count), -math.inf, dtype=torch.float32, device=edges.device)
        shadow = ii_grey_below = None
        if cfg.shadow_score != "none":  # rows past the bottom add nothing to the strip below
            ii_grey_below = maps.integral_below("grey")
            shadow = torch.zeros((b, grid.count), dtype=torch.float64, device=edges.device)
        for s, enc, off in zip(grid.sizes, enclosed, grid.offsets):
            dx, dy, cw, ch = _scoring.centre_box(s.w, s.h, cfg.center_fraction)
            centre = _scoring.box_sums(ii_edges, dx, dy, cw, ch, s)
            if maps.crossing is not None:  # contours cut by the box's sides (straddling edges)
                r2 = 2 * band
                cut = (_scoring.box_sums(ii_cols, 0, band, r2, s.h, s) + _scoring.box_sums(ii_cols, s.w, band, r2, s.h, s)
                       + _scoring.box_sums(ii_rows, band, 0, s.w, r2, s) + _scoring.box_sums(ii_rows, band, s.h, s.w, r2, s))
                centre = centre + cfg.straddle_weight * cut
            bw, bh = s.w / fx, s.h / fy
            sc = _scoring.edge_score(enc * unit, centre * unit, bw, bh, cfg.score_norm, cfg.kappa, cfg.gamma).float()
            r = (_scoring.box_sums(ii_road, 0, 0, s.w, s.h, s) / (s.w * s.h)).float() if ii_road is not None \
                else torch.zeros_like(sc)
            if cfg.road_score == "stand":  # road just below the box, little road inside it
                sh = max(1, int(round(cfg.road_strip * s.h)))
                assert ii_road_below is not None  # made above for road_score='stand'
                below = _scoring.box_sums(ii_road_below, 0, s.h, s.w, sh, s) / (s.w * sh)
                r = (below.float() * (1.0 - r)).clamp_(0, 1)
            key = self._loc_key(s)
            loc = loc_cache.get(key) if key is not None else None
            if loc is None:
                loc = self._location_rows(s, bw, bh, fy, *maps.input_size, edges.device)
                if key is not None:
                    loc_cache[key] = loc
            v = _scoring.combined_score(sc, loc, r, cfg.alpha, cfg.beta, cfg.road_score)
            if maps.green is not None:  # trees and verges: the green-dominant share of the window
                gdx, gdy, gw, gh = _scoring.centre_box(s.w, s.h, cfg.vegetation_box)
                f = _scoring.vegetation_factor(_scoring.box_sums(maps.green, gdx, gdy, gw, gh, s), float(gw * gh),
                                               cfg.vegetation_power)
                v = v * f.float()
            v = torch.where(sc >= cfg.min_edge_score, v, -math.inf)
            out[:, off: off + s.count] = v.reshape(b, -1)
            if shadow is not None:  # the darker bottom strip of a vehicle over the road below it
                assert ii_grey_below is not None and maps.grey is not None  # made with the shadow term
                sh, mx = _scoring.shadow_strips(s.w, s.h, cfg.shadow_strip, cfg.shadow_margin)
                inside = _scoring.box_sums(ii_grey_below, mx, s.h - sh, s.w - 2 * mx, sh, s)
                below = _scoring.box_sums(ii_grey_below, mx, s.h, s.w - 2 * mx, sh, s)
                y1 = torch.arange(s.ny, device=edges.device) * s.sy + s.oy + s.h
                rows = (maps.grey.shape[1] - y1).clamp(0, sh).view(1, -1, 1)
                u = _scoring.shadow_fraction(inside, below, sh * (s.w - 2 * mx), rows * (s.w - 2 * mx))
                shadow[:, off: off + s.count] = u.reshape(b, -1)
        if shadow is not None:  # one call on the whole score tensor, as the compiled path
            out = _scoring.apply_shadow(out, shadow, cfg.shadow_floor, cfg.shadow_power)
        if cfg.local_max:
            self._keep_local_maxima(out, grid)
        return out

    @staticmethod
    def _keep_local_maxima(out: Tensor, grid: _windows.WindowGrid) -> None:
        """``local_max``: ``-inf`` (in place) where a neighbouring position of the same size scores higher."""
        b = out.shape[0]
        for s, off in zip(grid.sizes, grid.offsets):
            v = out[:, off: off + s.count].view(b, s.ny, s.nx)
            peak = F.max_pool2d(v[:, None], 3, stride=1, padding=1)[:, 0]
            out[:, off: off + s.count] = torch.where(v >= peak, v, -math.inf).reshape(b, -1)

    def enclosed(self, maps: ScoreMaps, grid: _windows.WindowGrid) -> list[Tensor]:
        """Eq. 1's enclosed sums of every window, per size. Groups bounded to tiles smaller
        than every window: the batch's four prefix tables (:meth:`ScoreMaps.tables`), then
        strided slices per size (:func:`reeb_torch.stages.refinement.enclosed_grid`); otherwise
        one scatter per size (:func:`reeb_torch.stages.scoring.enclosed_sums`). Both are exact
        float64 sums: the same numbers."""
        if not grid.sizes:
            return []
        if _tables_exact(maps.groups, grid):
            tables = maps.tables()
            return [_refinement.enclosed_grid(tables, s) for s in grid.sizes]
        return _scoring.enclosed_sums(maps.groups, maps.edges.shape[0], grid.sizes)

    def _ground_ratios(self) -> float | tuple[float, ...]:
        """Box height / (bottom row − horizon) of the objects the location score expects:
        one ratio (``ground``) or one per class (``classes``: typical height / camera height)."""
        cfg = self.config
        if cfg.location_score == "classes":
            return tuple(h / cfg.camera_height_m for h in cfg.class_heights_m)
        return cfg.ground_ratio

    def _class_weights(self) -> tuple[float, ...] | None:
        cfg = self.config
        return tuple(cfg.class_weights) if cfg.location_score == "classes" else None

    def _template_widths(self) -> tuple[tuple[float, float], ...] | None:
        """Each class's width range in metres when the location score fits the box's shape
        (``location_fit='shape'`` with ``location_score='classes'``), else None."""
        cfg = self.config
        if cfg.location_score == "classes" and cfg.location_fit == "shape":
            return tuple((t[2], t[3]) for t in cfg.object_templates)
        return None

    def _loc_key(self, s: _windows.WindowSize) -> tuple | None:
        """What L of a window size's rows depends on, to share it between sizes: the height
        and rows, and the width with the class shape fit; None for the printed L (it reads
        the width and is not shared)."""
        if self.config.location_score == "paper":
            return None
        return (s.h, s.oy, s.sy, s.ny, s.w if self._template_widths() is not None else 0)

    def _location(self, bottom: Tensor, bw: float | Tensor, bh: float | Tensor, h_in: int, w_in: int) -> Tensor:
        """L (eq. 11 or its variants) of boxes ``bw × bh`` (input pixels) whose bottom is row ``bottom``."""
        cfg = self.config
        return _scoring.location_score(bottom, bw, bh, float(w_in), float(h_in), cfg.location_score,
                                       cfg.horizon, self._ground_ratios(), cfg.ground_log_sigma,
                                       self._class_weights(), self._template_widths(), cfg.camera_height_m)

    def _location_rows(self, s: _windows.WindowSize, bw: float, bh: float, fy: float, h_in: int, w_in: int,
                       device: torch.device) -> Tensor:
        """L of the rows of window size ``s``: ``float32 (1, ny, 1)``."""
        bottom = ((torch.arange(s.ny, device=device, dtype=torch.float32) * s.sy + s.oy + s.h) / fy).view(1, -1, 1)
        return self._location(bottom, bw, bh, h_in, w_in)

    def _score_plan(self, grid: _windows.WindowGrid, fx: float, fy: float, h_in: int,
                    w_in: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Per-size constants of the compiled scoring pass (cached per grid and input size):
        the ``int64 [S, 19]`` size table, eq. 1's normalisers ``float64 [S]``, L of every
        size's rows ``float32 [Σ ny]`` (computed by the same tensor code as the torch path)
        and the order of the rows (:func:`~reeb_torch.stages.scoring.row_order`)."""
        return self._grid_cached(("plan", fx, fy, h_in, w_in, self.config), grid,
                                 lambda: self._build_score_plan(grid, fx, fy, h_in, w_in))

    def _build_score_plan(self, grid: _windows.WindowGrid, fx: float, fy: float, h_in: int,
                          w_in: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        cfg = self.config
        rows, denoms, locs = [], [], []
        loc_cache: dict = {}
        loc_offset = 0
        for s, off in zip(grid.sizes, grid.offsets):
            dx, dy, cw, ch = _scoring.centre_box(s.w, s.h, cfg.center_fraction)
            bw, bh = s.w / fx, s.h / fy
            denom = _scoring.edge_norm(bw, bh, cfg.score_norm, cfg.kappa, cfg.gamma)
            lkey = self._loc_key(s)
            start = loc_cache.get(lkey) if lkey is not None else None
            if start is None:
                start = loc_offset
                locs.append(self._location_rows(s, bw, bh, fy, h_in, w_in, torch.device("cpu")).reshape(-1))
                loc_offset += s.ny
                if lkey is not None:
                    loc_cache[lkey] = start
            sh, mx = _scoring.shadow_strips(s.w, s.h, cfg.shadow_strip, cfg.shadow_margin)
            gdx, gdy, gw, gh = _scoring.centre_box(s.w, s.h, cfg.vegetation_box)
            rows.append((s.w, s.h, s.sx, s.sy, s.nx, s.ny, s.oy, off, dx, dy, cw, ch, start, sh, mx, gdx, gdy, gw, gh))
            denoms.append(denom)
        plan = np.asarray(rows, dtype=np.int64).reshape(-1, len(_scoring.PLAN_COLUMNS))
        return (plan, np.asarray(denoms, dtype=np.float64), torch.cat(locs).numpy() if locs else np.zeros(0, np.float32),
                _scoring.row_order(plan))

    # -- eq. 9: each region's budget --------------------------------------------------------
    def select(self, scores: Tensor, grid: _windows.WindowGrid, share: Tensor) -> Tensor:
        """The candidates, ``bool [B, N]``: :meth:`region_cut` (a subclass may change it),
        then :attr:`on_select` is called, if set."""
        chosen = self.region_cut(scores, grid, share)
        if self.on_select is not None:
            self.on_select(scores, grid, chosen, share)
        return chosen

    def region_cut(self, scores: Tensor, grid: _windows.WindowGrid, share: Tensor) -> Tensor:
        """Each region passes on its best ``share · candidates_per_region`` windows (eq. 9).
        Returns ``bool [B, N]``; ties at the cut go to the lower window index. On the CPU one
        compiled pass (:func:`reeb_torch.stages.scoring.select_per_region_cpu`), elsewhere a
        stable sort (:meth:`select_torch`)."""
        budget = self.region_budget(share)
        if scores.device.type == "cpu":
            members, starts = self._region_members(grid)
            return _scoring.select_per_region_cpu(scores, members, starts, budget)
        return self.select_torch(scores, grid, budget)

    def region_budget(self, share: Tensor) -> Tensor:
        """Eq. 9: the windows each region may pass on, ``int64 (B, R)`` from its ``share``."""
        cfg = self.config
        per_region = cfg.candidates_per_region if cfg.use_regions else cfg.candidates_without_regions
        return (share * per_region).round().long()

    def _region_members(self, grid: _windows.WindowGrid) -> tuple[np.ndarray, np.ndarray]:
        """The windows of every region, concatenated (``int64``), and where each region starts."""
        def build() -> tuple[np.ndarray, np.ndarray]:
            lists = [t.numpy().astype(np.int64) for t in grid.region_windows]
            starts = np.cumsum([0] + [len(x) for x in lists]).astype(np.int64)
            return (np.concatenate(lists) if lists else np.zeros(0, np.int64), starts)

        return self._grid_cached(("members",), grid, build)

    def select_torch(self, scores: Tensor, grid: _windows.WindowGrid, budget: Tensor) -> Tensor:
        """:meth:`region_cut` as one stable sort per region (any device). Ties at the cut go to
        the lower window index, as in the CPU pass (``topk`` leaves their order unspecified,
        and windows without edges all score 0, so ties are common)."""
        chosen = torch.zeros_like(scores, dtype=torch.uint8)
        for r, idx_cpu in enumerate(grid.region_windows):
            k = min(int(idx_cpu.numel()), int(budget[:, r].max()))
            if k == 0:
                continue
            idx = self._device_tensor(idx_cpu, scores.device)
            vals, pos = scores[:, idx].sort(dim=1, descending=True, stable=True)  # ties: lower index first
            vals, pos = vals[:, :k], pos[:, :k]
            ok = torch.isfinite(vals) & (torch.arange(k, device=scores.device)[None] < budget[:, r: r + 1])
            chosen.scatter_add_(1, idx[pos], ok.to(torch.uint8))
        return chosen > 0

    # -- a second scoring pass (ReebConfig.rescore) -----------------------------------------
    def rescore(self, maps: ScoreMaps, grid: _windows.WindowGrid, scores: Tensor,
                chosen: Tensor) -> tuple[Tensor, Tensor]:
        """``rescore``: each image's best ``rescore_top`` chosen windows (by V), ranked on
        V·f^p (:mod:`reeb_torch.stages.rescoring`); the other candidates are dropped. Returns
        new ``(scores float32 [B, N], chosen bool [B, N])``; ``rescore='none'`` returns the
        arguments themselves."""
        cfg = self.config
        if cfg.rescore == "none":
            return scores, chosen
        idx = _rescoring.top_candidates(scores, chosen, cfg.rescore_top)
        kept = torch.zeros_like(chosen)
        for i, ix in enumerate(idx):
            kept[i, ix] = True
        counts = [int(ix.numel()) for ix in idx]
        if not sum(counts):
            return scores, kept
        all_boxes = self._device_tensor(grid.boxes, scores.device)
        bi = torch.cat([torch.full_like(ix, i) for i, ix in enumerate(idx)])
        boxes = all_boxes[torch.cat(idx)].round().long()
        if cfg.rescore == "affinity":
            x0, y0, x1, y1 = boxes.unbind(1)
            enclosed = _refinement.enclosed_at(maps.tables(), bi, x0, y0, x1, y1)
            cue = _rescoring.affinity_cue(maps.edges, enclosed, boxes, bi, cfg.group_cell)
        elif cfg.rescore == "orientation":
            cue = _rescoring.orientation_cue(maps.edges, boxes, bi, cfg.group_cell)
        elif cfg.rescore == "density":
            cue = _rescoring.density_cue(maps.integral("edges"), boxes, bi)
        else:
            cue = _rescoring.contrast_cue(maps.integral("edges"), boxes, bi)
        scope = self._rescore_scope(boxes, maps.edges.shape[-2])
        out = _rescoring.apply_cue(scores, idx, list(cue.split(counts)), list(scope.split(counts)), cfg.rescore_power)
        return out, kept

    def _rescore_scope(self, boxes: Tensor, hk: int) -> Tensor:
        """Which of the int64 ``[K, 4]`` working-pixel boxes get the cue (``rescore_scope``):
        all, or the person-shaped ones (narrower than ``rescore_thin`` times their height and,
        with ``rescore_max_height_m``, no taller than that on the ground plane)."""
        cfg = self.config
        if cfg.rescore_scope == "all":
            return torch.ones(len(boxes), dtype=torch.bool, device=boxes.device)
        wh = boxes[:, 2:] - boxes[:, :2]
        scope = wh[:, 0] < cfg.rescore_thin * wh[:, 1]
        if cfg.rescore_max_height_m is not None:
            depth = boxes[:, 3].double() - cfg.horizon * hk  # bottom row below the horizon row
            real = wh[:, 1].double() / depth.clamp(min=1e-9) * cfg.camera_height_m
            scope &= (depth > 0) & (real <= cfg.rescore_max_height_m)
        return scope

    # -- the learned ranking (ReebConfig.ranker) -------------------------------------------
    def feature_names(self) -> tuple[str, ...]:
        """The columns of :meth:`features` for this config (one location fit per class)."""
        return _features.feature_names(len(self.config.class_heights_m))

    def box_maps(self, maps: ScoreMaps, geometry_only: bool = False) -> _features.BoxMaps:
        """The tables the per-box features read (:class:`~reeb_torch.ranker.features.BoxMaps`);
        with ``geometry_only``, only their sizes (for the window columns: no table is built)."""
        cfg = self.config
        grey = maps.grey
        widths = (tuple((t[2], t[3]) for t in cfg.object_templates)
                  if cfg.location_fit == "shape" and len(cfg.object_templates) == len(cfg.class_heights_m) else None)
        ii_edges = ii_grey = ii_grey2 = green = None
        tables = None
        if not geometry_only:
            assert grey is not None, "the per-box features read the grey image (ScoreMaps.grey)"
            ii_edges, ii_grey = maps.integral("edges"), maps.integral("grey")
            ii_grey2 = maps._keep("grey2", lambda: _scoring.integral_image(grey * grey))
            green, tables = maps.green, maps.tables()
        return _features.BoxMaps(
            (maps.edges.shape[-2], maps.edges.shape[-1]), ii_edges, ii_grey, ii_grey2, green, tables, cfg.horizon,
            cfg.camera_height_m,
            tuple(h / cfg.camera_height_m for h in cfg.class_heights_m), tuple(cfg.class_weights), widths,
            cfg.ground_log_sigma, maps.fx, maps.fy, cfg.center_fraction, cfg.score_norm, cfg.kappa, cfg.gamma)

    def features(self, maps: ScoreMaps, grid: _windows.WindowGrid, scores: Tensor, chosen: Tensor,
                 share: Tensor, entropy: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """The features of every candidate: ``(bi int64 [K], ni int64 [K], float32 [K, F])``,
        the image and window index of each candidate (``nonzero(chosen)`` order) and its
        features (:func:`~reeb_torch.ranker.features.box_features`; compiled on the CPU)."""
        bi, ni = _chosen(chosen)
        return bi, ni, self._features_of(maps, grid, scores, share, entropy, bi, ni)

    def _window_table(self, maps: ScoreMaps, grid: _windows.WindowGrid) -> Tensor:
        """The window columns of every window of ``grid`` (:func:`~reeb_torch.ranker.features.window_features`),
        ``float32 [N, 11 + C]`` (as the features hold them), computed once per grid."""
        dev = maps.edges.device
        def build() -> Tensor:
            boxes = self._device_tensor(grid.boxes, dev).round().long()
            return _features.window_features(self.box_maps(maps, geometry_only=True), boxes).float()

        return self._grid_cached(("window_features", maps.fx, maps.fy, str(dev)), grid, build)

    def _features_of(self, maps: ScoreMaps, grid: _windows.WindowGrid, scores: Tensor, share: Tensor,
                     entropy: Tensor, bi: Tensor, ni: Tensor, cheap: bool = False) -> Tensor:
        dev = scores.device
        region_of = self._device_tensor(grid.region_of, dev)
        if dev.type == "cpu":
            return _features.box_features_cpu(self.box_maps(maps, geometry_only=cheap), grid.boxes,
                                              self._window_table(maps, grid), scores, share, entropy, region_of,
                                              bi, ni, cheap)
        boxes = self._device_tensor(grid.boxes, dev)[ni].round().long()
        region = region_of[ni]
        return _features.box_features(self.box_maps(maps, geometry_only=cheap), boxes, bi, scores[bi, ni],
                                      share[bi, region], entropy[bi, region], self._window_table(maps, grid)[ni],
                                      cheap)

    def rank_learned(self, maps: ScoreMaps, grid: _windows.WindowGrid, scores: Tensor, chosen: Tensor,
                     share: Tensor, entropy: Tensor,
                     features_out: list[tuple[Tensor, Tensor, Tensor]] | None = None,
                     timer: Callable[[str, torch.device], ContextManager] | None = None) -> tuple[Tensor, Tensor]:
        """``ranker``: the candidates ranked by the model, for :meth:`suppress`: ``(scores
        float32 [B, N], chosen bool [B, N])``, the model's logit of each candidate it ranks
        (``-inf`` elsewhere) and which those are: where the model has a prefilter, each
        image's best ``ranker_keep`` candidates: ``ranker_v_share`` of them its best by V, the
        rest its best by the prefilter; all of them otherwise.
        ``features_out``, if given, gets ``(bi, ni, features)`` of the candidates it ranked
        (in ``nonzero(chosen)`` order), so that :meth:`class_hints` need not compute them again.
        ``timer(name, device)``, if given, times its parts (``ranker.prefilter``: the pairs, the
        prefilter and its cut; ``ranker.features``; ``ranker.model``: the MLP and the scatter)."""
        model = self._model_on(scores.device)
        dev = scores.device
        timed = timer if timer is not None else (lambda name, device: nullcontext())
        with timed("ranker.prefilter", dev):
            bi, ni = _chosen(chosen)
            keep = self.config.ranker_keep
            counts = torch.bincount(bi, minlength=scores.shape[0])
            by_v = round(self.config.ranker_v_share * keep)
            if model.prefilter is not None and len(bi) and int(counts.max()) > keep:
                if by_v >= keep:  # V alone
                    sel = _best_per_image(_gather(scores, bi, ni, counts), counts, keep)
                else:
                    pre = self._prefilter(model, maps, grid, scores, share, entropy, bi, ni)
                    if by_v:  # each image's best by V first, whatever the prefilter says
                        pre[_best_per_image(_gather(scores, bi, ni, counts), counts, by_v)] = math.inf
                    sel = _best_per_image(pre, counts, keep)
                bi, ni = bi[sel], ni[sel]
        out = torch.full_like(scores, -math.inf)
        kept = torch.zeros_like(chosen)
        if len(bi):
            with timed("ranker.features", dev):
                feats = self._features_of(maps, grid, scores, share, entropy, bi, ni)
            with timed("ranker.model", dev):
                out[bi, ni] = model.rank(feats)
                kept[bi, ni] = True
            if features_out is not None:
                features_out.append((bi, ni, feats))
        if self.on_rank is not None:
            self.on_rank(out, kept)
        return out, kept

    def class_map(self, ranked: tuple[Tensor, Tensor, Tensor], shape: tuple[int, int]) -> tuple[Tensor, Tensor]:
        """``int8 [B, N]``: the class the model's head hints for each candidate :meth:`rank_learned`
        ranked (``ranked``: its ``(bi, ni, features)``; the index into the model's classes),
        ``-1`` elsewhere: what ``class_quota`` shares the output by (:meth:`suppress`); and the
        head's logits of those candidates, ``float32 [K, C]`` in their order (so that
        :meth:`class_hints` need not run the head again over the output)."""
        bi, ni, feats = ranked
        out = torch.full(shape, -1, dtype=torch.int8, device=feats.device)
        model = self._model_on(feats.device)
        logits = feats.new_zeros(0, len(model.classes))
        if len(bi):
            logits = model.class_logits(feats)
            out[bi, ni] = logits.argmax(1).to(torch.int8)
        return out, logits

    def _prefilter(self, model, maps: ScoreMaps, grid: _windows.WindowGrid, scores: Tensor, share: Tensor,
                   entropy: Tensor, bi: Tensor, ni: Tensor) -> Tensor:
        """The prefilter's logit of each candidate ``(bi, ni)``, ``float32 [K]``: on the CPU,
        for a one-hidden-layer prefilter, the hidden layer's share of the window columns is
        tabulated once per grid and the rest compiled (:func:`~reeb_torch.ranker.prefilter.prefilter_cpu`);
        elsewhere the model on the cheap columns (the same to float32 rounding)."""
        pre = model.prefilter
        if scores.device.type != "cpu" or len(pre) != 3:
            return model.prefilter_scores(self._features_of(maps, grid, scores, share, entropy, bi, ni, cheap=True))
        first, last = pre[0], pre[2]
        nw = self._window_table(maps, grid).shape[1]

        def build() -> Tensor:
            win = (self._window_table(maps, grid).float() - model.mean[:nw]) / model.scale[:nw]
            return torch.addmm(first.bias, win, first.weight[:, :nw].T).contiguous()

        table = self._grid_cached(("prefilter", id(model)), grid, build)
        return prefilter_cpu(table, scores, share, entropy, grid.region_of, bi, ni, model.mean[nw: nw + 3],
                                       model.scale[nw: nw + 3], first.weight[:, nw:], last.weight[0],
                                       float(last.bias[0]))

    def class_hints(self, maps: ScoreMaps, grid: _windows.WindowGrid, scores: Tensor, share: Tensor,
                    entropy: Tensor, windows: list[Tensor],
                    ranked: tuple[Tensor, Tensor, Tensor] | None = None,
                    ranked_logits: Tensor | None = None) -> list[Tensor]:
        """The class head's probabilities (:meth:`~reeb_torch.ranker.BoxRanker.class_probs`) of
        the windows ``windows[i]`` (``int64 [N_i]``) of each image, ``float32 [N_i, C]``, from
        their features under REEB's scores V (``scores [B, N]``, before the learned ranking).
        ``ranked``: :meth:`rank_learned`'s ``(bi, ni, features)`` under the same V; the rows of
        the windows among them are taken from there (the same numbers), the others computed.
        ``ranked_logits``: :meth:`class_map`'s logits of those rows, if it ran; the windows
        among them take their logits from there (the same numbers: the head runs row by row)."""
        model = self._model_on(scores.device)
        counts = [len(w) for w in windows]
        dev = scores.device
        bi = torch.repeat_interleave(torch.arange(len(windows), device=dev), torch.tensor(counts, device=dev))
        ni = torch.cat(windows).to(dev) if windows else bi
        if not len(ni):
            return [scores.new_zeros(0, len(model.classes)) for _ in windows]
        if ranked is not None and len(ranked[0]):
            rb, rn, rf = ranked
            n = scores.shape[1]
            known = rb * n + rn  # ascending: nonzero order
            key = bi * n + ni
            at = torch.searchsorted(known, key).clamp_(max=len(known) - 1)
            miss = known.index_select(0, at) != key
            if ranked_logits is not None:  # the head's logits of the ranked rows: only the misses run it
                logits = ranked_logits.index_select(0, at)
                if bool(miss.any()):
                    logits[miss] = model.class_logits(
                        self._features_of(maps, grid, scores, share, entropy, bi[miss], ni[miss]))
                return list(softmax_rows(logits).split(counts))
            feats = rf.index_select(0, at)
            if bool(miss.any()):
                feats[miss] = self._features_of(maps, grid, scores, share, entropy, bi[miss], ni[miss])
        else:
            feats = self._features_of(maps, grid, scores, share, entropy, bi, ni)
        probs = model.class_probs(feats)
        return list(probs.split(counts))

    def _model_on(self, device: torch.device):
        """:attr:`model` on ``device`` (the shared CPU model, or a copy per device)."""
        assert self.model is not None, "no ranking model (ranker='none')"
        if device.type == "cpu":
            return self.model
        key = ("model", str(device))
        if key not in self._device_cache:
            import copy

            self._device_cache[key] = (None, copy.deepcopy(self.model).to(device))
        return self._device_cache[key][1]

    # -- Edge Boxes' refinement (ReebConfig.refine) -----------------------------------------
    def refine(self, maps: ScoreMaps, grid: _windows.WindowGrid, chosen: Tensor,
               scores: Tensor) -> tuple[list[Tensor], list[Tensor]]:
        """Edge Boxes' refinement of every chosen window (:func:`reeb_torch.stages.refinement.refine_boxes_cpu`,
        compiled, where :meth:`compiled_refine_applies`; else :func:`reeb_torch.stages.refinement.refine_boxes`
        with :meth:`box_scorer`: the same boxes and scores); per image, ``float32 [K, 4]`` working-pixel
        boxes and ``float32 [K]`` scores, in the order of ``nonzero(chosen[i])``. Boxes narrower or
        shorter than the exact-sum limit, or narrower than ``refine_min_aspect`` times their height,
        stay as they are."""
        cfg = self.config
        b = maps.edges.shape[0]
        bi, ni = torch.nonzero(chosen, as_tuple=True)
        boxes = self._device_tensor(grid.boxes, maps.edges.device)[ni].round().long()
        vals = scores[bi, ni]
        compiled = self.compiled_refine_applies(maps)
        if compiled:
            exact_side = maps.tables().max_extent + 1
        else:
            score_fn, exact_side = self.box_scorer(maps)
        min_side = max(exact_side, self.min_window_working(maps.fx, maps.fy))
        wh = boxes[:, 2:] - boxes[:, :2]
        movable = torch.nonzero((wh >= min_side).all(1) & (wh[:, 0] >= cfg.refine_min_aspect * wh[:, 1])).squeeze(1)
        if movable.numel():
            if compiled:
                rb, rs = self._refine_compiled(maps, grid, boxes[movable], bi[movable], min_side)
            else:
                hk, wk = maps.edges.shape[-2:]
                rb, rs = _refinement.refine_boxes(boxes[movable], bi[movable], score_fn, wk, hk, min_side,
                                                  cfg.window_step)
            boxes[movable] = rb
            vals = vals.clone()
            vals[movable] = torch.maximum(vals[movable], rs.float())
        counts = torch.bincount(bi, minlength=b).tolist()
        return list(boxes.float().split(counts)), list(vals.split(counts))

    def compiled_refine_applies(self, maps: ScoreMaps) -> bool:
        """Whether :func:`reeb_torch.stages.refinement.refine_boxes_cpu` computes this config's box
        score: on the CPU, without the straddling and road terms, with a location score
        tabulated by box height and bottom row, and a square-root shadow factor (or none)."""
        cfg = self.config
        return (maps.edges.device.type == "cpu" and maps.crossing is None and cfg.road_score in ("none", "flat")
                and cfg.location_score in ("ground", "classes", "none")
                and (cfg.shadow_score == "none" or cfg.shadow_power == 0.5))

    def _refine_compiled(self, maps: ScoreMaps, grid: _windows.WindowGrid, boxes: Tensor, bi: Tensor,
                         min_side: int) -> tuple[Tensor, Tensor]:
        cfg = self.config
        hk, wk = maps.edges.shape[-2:]
        grey_below = maps.integral_below("grey") if cfg.shadow_score != "none" else None
        return _refinement.refine_boxes_cpu(
            boxes, bi, maps.tables(), maps.integral("edges"), *self._box_tables(grid, maps), maps.green, grey_below,
            dict(unit=_scoring.unit_scale(maps.fx, maps.fy), alpha=cfg.alpha,
                 beta_road=cfg.beta if cfg.road_score == "flat" else 0.0,
                 center_fraction=cfg.center_fraction, vegetation_box=cfg.vegetation_box,
                 vegetation_power=cfg.vegetation_power, shadow_strip=cfg.shadow_strip,
                 shadow_margin=cfg.shadow_margin, shadow_floor=cfg.shadow_floor),
            wk, hk, min_side, cfg.window_step)

    def _box_tables(self, grid: _windows.WindowGrid, maps: ScoreMaps) -> tuple[Tensor, Tensor, Tensor]:
        """The location score and eq. 1's normaliser of any box, tabulated by the tensor
        functions the box scorer calls (cached with the window grid of the image size):
        ``loc_h[c, y1, h] · loc_w[c, y1, w]``, at its best over the classes ``c``, is L of a
        box ``w × h`` working pixels whose bottom is working row ``y1`` (one "class" of the
        whole L and ``loc_w = 1`` where L does not read the width), and ``norm[w, h]``
        eq. 1's normaliser."""
        cfg = self.config
        hk, wk = maps.edges.shape[-2:]
        fx, fy = maps.fx, maps.fy
        h_in, w_in = maps.input_size

        def build() -> tuple[Tensor, Tensor, Tensor]:
            rows = torch.arange(hk + 1, dtype=torch.float64)
            bottom, bh = rows[:, None] / fy, rows[None, :] / fy
            bw = torch.arange(wk + 1, dtype=torch.float64)[None, :] / fx
            widths = self._template_widths()
            if widths is None:
                loc_h = self._location(bottom, bh, bh, h_in, w_in).expand(hk + 1, hk + 1)[None]
                loc_w = torch.ones((1, hk + 1, wk + 1), dtype=torch.float64)
            else:
                ratios = self._ground_ratios()
                assert isinstance(ratios, tuple)  # one a class: widths are fitted only with location_score='classes'
                loc_h = torch.stack(_scoring.class_height_fits(bottom, bh, float(h_in), cfg.horizon, ratios,
                                                               cfg.ground_log_sigma, self._class_weights()))
                loc_w = torch.stack(_scoring.class_width_fits(bottom, bw, float(h_in), cfg.horizon, widths,
                                                              cfg.ground_log_sigma, cfg.camera_height_m))
            norm = _scoring.edge_norm(bw.T, bh, cfg.score_norm, cfg.kappa, cfg.gamma)
            return loc_h.contiguous(), loc_w.contiguous(), norm.contiguous()

        return self._grid_cached(("box_tables", fx, fy, h_in, w_in), grid, build)

    def box_scorer(self, maps: ScoreMaps) -> tuple[BoxScoreFn, int]:
        """V (eq. 12) of arbitrary boxes: returns ``(score_fn, min_side)`` where
        ``score_fn(boxes, b)`` takes int64 ``[K, 4]`` working-pixel boxes (x1, y1 exclusive)
        and their image indices ``[K]`` and gives ``float64 [K]``, the same numbers
        :meth:`score` gives a window of the grid; exact for boxes at least ``min_side`` wide
        and tall. It reads the batch's tables from ``maps``."""
        cfg = self.config
        hk = maps.edges.shape[1]
        h_in, w_in = maps.input_size
        fx, fy = maps.fx, maps.fy
        tables = maps.tables()
        ii_edges = maps.integral("edges")
        road = maps.road  # None where the road term does not read the mask (none, flat)
        if road is not None:
            ii_road, ii_road_below = maps.integral("road"), maps.integral_below("road")
        band = cfg.straddle_band
        if maps.crossing is not None:
            ii_cols, ii_rows = maps.crossing_integrals(band)
        unit = _scoring.unit_scale(fx, fy)
        at = _refinement.box_sum_at
        if cfg.shadow_score != "none":
            ii_grey_below = maps.integral_below("grey")

        def score_fn(boxes: Tensor, bi: Tensor) -> Tensor:
            x0, y0, x1, y1 = boxes.unbind(1)
            w, h = x1 - x0, y1 - y0
            centre = at(ii_edges, bi, *_centred(x0, y0, w, h, cfg.center_fraction))
            if maps.crossing is not None:
                r2 = 2 * band
                cut = (at(ii_cols, bi, x0, y0 + band, x0 + r2, y1 + band)
                       + at(ii_cols, bi, x1, y0 + band, x1 + r2, y1 + band)
                       + at(ii_rows, bi, x0 + band, y0, x1 + band, y0 + r2)
                       + at(ii_rows, bi, x0 + band, y1, x1 + band, y1 + r2))
                centre = centre + cfg.straddle_weight * cut
            enc = _refinement.enclosed_at(tables, bi, x0, y0, x1, y1)
            bw, bh = w.double() / fx, h.double() / fy
            sc = _scoring.edge_score(enc * unit, centre * unit, bw, bh, cfg.score_norm, cfg.kappa, cfg.gamma)
            area = (w * h).double()
            if road is None:
                r = torch.zeros_like(area)
            else:
                r = at(ii_road, bi, x0, y0, x1, y1) / area
            if cfg.road_score == "stand":
                sh = (h * cfg.road_strip).round().long().clamp_(min=1)
                below = at(ii_road_below, bi, x0, y1, x1, y1 + sh) / (w * sh).double()
                r = (below * (1.0 - r)).clamp_(0, 1)
            v = _scoring.combined_score(sc, self._location(y1.double() / fy, bw, bh, h_in, w_in), r,
                                        cfg.alpha, cfg.beta, cfg.road_score)
            if maps.green is not None:
                gx0, gy0, gx1, gy1 = _centred(x0, y0, w, h, cfg.vegetation_box)
                v = v * _scoring.vegetation_factor(at(maps.green, bi, gx0, gy0, gx1, gy1),
                                                   ((gx1 - gx0) * (gy1 - gy0)).double(), cfg.vegetation_power)
            if cfg.shadow_score != "none":
                sh = (h.double() * cfg.shadow_strip).round().long().clamp_(min=1)
                mx = torch.minimum((w.double() * cfg.shadow_margin).floor().long(), torch.div(w - 1, 2, rounding_mode="floor"))
                inside = at(ii_grey_below, bi, x0 + mx, y1 - sh, x1 - mx, y1)
                below = at(ii_grey_below, bi, x0 + mx, y1, x1 - mx, y1 + sh)
                rows = torch.minimum((hk - y1).clamp(min=0), sh)
                u = _scoring.shadow_fraction(inside, below, (sh * (w - 2 * mx)).double(), rows * (w - 2 * mx))
                v = _scoring.apply_shadow(v, u, cfg.shadow_floor, cfg.shadow_power)
            return v

        return score_fn, tables.max_extent + 1

    # -- eq. 13: the final proposals ----------------------------------------------------------
    def suppress(self, maps: ScoreMaps, grid: _windows.WindowGrid, chosen: Tensor, scores: Tensor, share: Tensor,
                 refined: tuple[list[Tensor], list[Tensor]] | None = None,
                 windows_out: list[Tensor] | None = None,
                 class_of: Tensor | None = None) -> list[dict[str, Tensor]]:
        """Greedy NMS (eq. 13) of each image's candidates, best first, stopping at ``top_k``
        (with ``region_quota``, each region's share of the output first: :meth:`quota`; with
        ``class_of``, :meth:`class_map`'s hints, each class's ``class_quota`` share first):
        one dict per image, ``boxes`` ``float32 [N, 4]`` in input pixels and ``scores``
        ``float32 [N]``. ``refined``: :meth:`refine`'s boxes and scores of the candidates
        (else the windows themselves, gathered, sorted and suppressed in one compiled pass
        on the CPU: :func:`reeb_torch.stages.nms.nms_windows_cpu`). ``windows_out``, if
        given, gets each image's ``int64 [N]`` window index of each output row."""
        cfg = self.config
        b, dev = scores.shape[0], scores.device
        fx, fy = maps.fx, maps.fy
        to_input = torch.tensor([fx, fy, fx, fy], device=dev)
        boxes_in = self._grid_cached(("boxes_in", fx, fy, str(dev)), grid,
                                     lambda: self._device_tensor(grid.boxes, dev) / to_input)
        region_of = self._device_tensor(grid.region_of, dev)
        class_share = (torch.tensor(self.class_share, device=dev)
                       if class_of is not None and self.class_share is not None else None)
        quota = (cfg.region_quota and share.shape[1] > 1) or class_share is not None
        kept = None
        if refined is None:  # the windows themselves: gathered, sorted and suppressed compiled
            ok = (self._grid_cached(("boxes_ok", fx, fy), grid, lambda: boxes_valid(boxes_in))
                  if dev.type == "cpu" and boxes_in.dtype == torch.float32 else None)
            groups = need = None  # with a quota: past top_k only until each group has its share of the kept boxes
            if class_share is not None:
                assert class_of is not None  # class_share is made only with it
                groups, need = class_of.long().clamp(min=0), self.quota_counts(class_share)
            elif quota:  # each image's regions, by its own shares (none where they sum to 0: quota keeps the best)
                groups = region_of.expand(b, -1)
                need = torch.stack([self.quota_counts(s, float(s.sum())) if float(s.sum()) > 0
                                    else torch.zeros(len(s), dtype=torch.long, device=dev) for s in share])
            kept = nms_windows_cpu(chosen, boxes_in, scores, cfg.nms_iou, cfg.top_k, ok, groups, need)
        cands = None
        if kept is not None:
            pairs = [(boxes_in, scores[i]) for i in range(b)]
            windows = kept
        else:
            cands = [torch.nonzero(chosen[i]).squeeze(1) for i in range(b)]
            if refined is not None:
                pairs = [(rb / to_input, rs) for rb, rs in zip(*refined)]
            else:
                pairs = [(boxes_in[c], scores[i, c]) for i, c in enumerate(cands)]
            kept = nms_top_k_many(pairs, cfg.nms_iou, max(len(p[1]) for p in pairs) if quota else cfg.top_k)
            windows = [c[k] for c, k in zip(cands, kept)]
        results = []
        h_in, w_in = maps.input_size
        for i, ((bx, sc), keep_idx, win) in enumerate(zip(pairs, kept, windows)):
            if class_share is not None:
                assert class_of is not None  # class_share is made only with it
                keep_idx = self.quota(keep_idx, class_of[i, win].long().clamp(min=0), class_share,
                                      whole=True)[: cfg.top_k]
            elif quota:
                keep_idx = self.quota(keep_idx, region_of[win], share[i])[: cfg.top_k]
            if windows_out is not None:
                windows_out.append(keep_idx if cands is None else cands[i][keep_idx])
            # the contract 0 <= x1 < x2 <= W, 0 <= y1 < y2 <= H in input pixels: a window on
            # the last working column maps back to W plus a rounding error (odd sides at
            # scale 0.5: 99.0000076 for W = 99); after NMS, so the ranking is unchanged
            if bx.device.type == "cpu":  # numpy's take and clip: the same copies, without torch's pool
                idx = keep_idx.numpy()
                b_np = np.take(bx.numpy(), idx, axis=0)
                np.clip(b_np[:, 0::2], 0.0, float(w_in), out=b_np[:, 0::2])
                np.clip(b_np[:, 1::2], 0.0, float(h_in), out=b_np[:, 1::2])
                results.append({"boxes": torch.from_numpy(b_np), "scores": torch.from_numpy(np.take(sc.numpy(), idx))})
                continue
            boxes = bx[keep_idx].contiguous()  # a copy (indexed): clamped in place below
            boxes[:, 0::2] = boxes[:, 0::2].clamp(0.0, float(w_in))
            boxes[:, 1::2] = boxes[:, 1::2].clamp(0.0, float(h_in))
            results.append({"boxes": boxes, "scores": sc[keep_idx].contiguous()})
        return results

    def quota(self, keep: Tensor, region: Tensor, share: Tensor, whole: bool = False) -> Tensor:
        """Eq. 9 on the output: of the ``top_k`` proposals, region r gets up to
        ``top_k · share_r / Σ share`` (its best after NMS); places a region leaves empty go
        to the best of the rest. ``keep`` is in descending score order and stays so. With
        ``whole``, the shares are fractions of ``top_k`` as they are (not normalised): the
        class quota (``region`` then each box's class)."""
        k = self.config.top_k
        if keep.numel() <= k:
            return keep
        total = 1.0 if whole else float(share.sum())
        if total <= 0:
            return keep
        quota = self.quota_counts(share, total)  # (R,)
        onehot = torch.nn.functional.one_hot(region, share.numel())
        rank = (onehot.cumsum(0) * onehot).sum(1)  # 1-based rank within its region
        first = rank <= quota[region]
        n_first = int(first.sum())
        rest = torch.nonzero(~first).squeeze(1)[: max(0, k - n_first)]
        sel = torch.cat([torch.nonzero(first).squeeze(1), rest]).sort().values
        return keep[sel]

    def quota_counts(self, share: Tensor, total: float = 1.0) -> Tensor:
        """``int64 [R]``: how many of the ``top_k`` proposals each share draws in :meth:`quota`
        (``floor(top_k · share / total)``)."""
        return torch.floor(share * (self.config.top_k / total)).long()

    # -- what depends on the image size only, kept per window grid ------------------------------
    def _grid_cached(self, key: tuple, grid: _windows.WindowGrid, build):
        """``build()``, cached per ``key`` and window grid (grids are cached themselves, so
        one is recognised by identity; the entry keeps it alive so its id is not reused).
        The values of the :data:`PLAN_GRIDS` grids used last are kept, whatever their number
        of keys: a cap on entries cleared every value at each batch once the image sizes
        times the keys per grid (8 for the default) passed it (KITTI's 4 sizes are 32)."""
        slot = self._plan_cache.get(id(grid))
        if slot is None or slot[0] is not grid:
            slot = (grid, {})
            self._plan_cache[id(grid)] = slot
            while len(self._plan_cache) > PLAN_GRIDS:
                self._plan_cache.popitem(last=False)
        else:
            self._plan_cache.move_to_end(id(grid))
        values = slot[1]
        if key not in values:
            values[key] = build()
        return values[key]

    def _device_tensor(self, t: Tensor, device: torch.device) -> Tensor:
        """``t`` on ``device``, copied once per tensor and device."""
        if t.device == device:
            return t
        key = (id(t), str(device))
        hit = self._device_cache.get(key)
        if hit is None or hit[0] is not t:
            if len(self._device_cache) >= 256:  # grids of many image sizes: start afresh
                self._device_cache.clear()
            hit = (t, t.to(device))
            self._device_cache[key] = hit
        return hit[1]
