"""REEB's window scores: the window grid (Sec. 3.6) and V (eqs. 1, 10–12) of every window,
compiled on the CPU where it applies, else tensor ops."""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from ..config import CameraSettings, ScoreSettings, WindowSettings
from ..stages import _scratch
from ..stages import enclosed as _enclosed
from ..stages import scoring as _scoring
from ..stages import windows as _windows
from ..stages.groups import EdgeGroups
from .grid_cache import GridCache
from .maps import ScoreMaps

__all__ = ["WindowScoring"]


def _tables_exact(groups: EdgeGroups, grid: _windows.WindowGrid) -> bool:
    """Whether the prefix tables give eq. 1's enclosed sums exactly for every window of
    ``grid``: every window is wider and taller than every edge group."""
    return groups.max_extent < grid.min_side


class WindowScoring:
    """The window grid of a batch's image size and V of its windows; the location score L
    (eq. 11 and its variants).

    Args:
        windows: the windows' sizes, strides and rows.
        scores: V's terms and weights.
        camera: the camera's height and horizon row (the windows' rows, L).
        cache: the per-grid tables, shared with the other parts (a new one if None).
    """

    def __init__(self, windows: WindowSettings, scores: ScoreSettings, camera: CameraSettings,
                 cache: GridCache | None = None) -> None:
        self.windows, self.scores, self.camera = windows, scores, camera
        self.cache = cache if cache is not None else GridCache()

    # -- windows (Sec. 3.6) -----------------------------------------------------------------
    def window_grid(self, maps: ScoreMaps, bounds: Tensor) -> _windows.WindowGrid:
        """The windows of the batch's image size, counted against the regions ``bounds``."""
        w, cam = self.windows, self.camera
        hk, wk = maps.edges.shape[-2:]
        fx, fy = maps.fx, maps.fy
        ground = None if w.ground_band is None else (cam.horizon, *w.ground_band)
        camera = None
        if w.window_geometry == "camera":
            # template extents (metres) over the camera height: the ratios box side / (y_b − y_h)
            h = cam.camera_height_m
            ratios = tuple((hl / h, hh / h, wl / h * fx / fy, wh / h * fx / fy)
                           for hl, hh, wl, wh in w.object_templates)
            camera = (cam.horizon, ratios)
        return _windows.window_grid(hk, wk, bounds, self.min_window_working(fx, fy), w.size_ratio,
                                    w.window_step, w.aspect_range, w.region_assign, ground, camera)

    def min_window_working(self, fx: float, fy: float) -> int:
        """The smallest window side in working pixels (at least 3)."""
        return max(3, int(round(self.windows.min_window * min(fx, fy))))

    # -- scores (eqs. 1, 10-12) ---------------------------------------------------------------
    def score(self, maps: ScoreMaps, grid: _windows.WindowGrid) -> Tensor:
        """V (eq. 12) of every window, ``float32 [B, N]``; ``-inf`` where S < min_edge_score.

        On the CPU, when no term needs per-window maps (no road fraction) and every window is
        wider and taller than every edge group, one compiled pass
        (:func:`reeb_torch.stages.scoring.score_grid_cpu`) scores all windows; otherwise one
        batch of tensor ops per window size (:meth:`score_torch`). Both give
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
        return maps.edges.device.type == "cpu" and self.scores.road_score == "none"

    def score_compiled(self, maps: ScoreMaps, grid: _windows.WindowGrid) -> Tensor:
        """:meth:`score` in one compiled pass (:func:`reeb_torch.stages.scoring.score_grid_cpu`)."""
        fx, fy = maps.fx, maps.fy
        plan, denom, loc, order = self._score_plan(grid, fx, fy, *maps.input_size)
        b = maps.edges.shape[0]
        out_np = _scratch.empty("score.out", (b, grid.count), np.float32)
        out_np.fill(-np.inf)  # (numpy's fill: one thread, where torch's would wake its pool)
        out = torch.from_numpy(out_np)
        ii_grey = shadow = sqrt_floor = None
        if self.scores.shadow_score != "none":
            ii_grey = maps.integral("grey")
            if self.scores.shadow_power == 0.5:  # the factor in the kernel: sqrt rounds alike everywhere
                sqrt_floor = self.scores.shadow_floor
            else:
                shadow = torch.zeros((b, grid.count), dtype=torch.float64)
        _scoring.score_grid_cpu(maps.integral("edges"), maps.tables(), plan, denom, loc, _scoring.unit_scale(fx, fy),
                                self.scores.alpha, 0.0, self.scores.min_edge_score, out, ii_grey, shadow, sqrt_floor,
                                maps.green, self.scores.vegetation_power, order)
        if shadow is not None:
            out = _scoring.apply_shadow(out, shadow, self.scores.shadow_floor, self.scores.shadow_power)
        return out

    def score_torch(self, maps: ScoreMaps, grid: _windows.WindowGrid) -> Tensor:
        """:meth:`score` as tensor ops, one batch of them per window size (any device, any config)."""
        edges, fx, fy = maps.edges, maps.fx, maps.fy
        b = edges.shape[0]
        ii_edges = maps.integral("edges")
        enclosed = self.enclosed(maps, grid)
        ii_road = maps.integral("road") if maps.road is not None else None  # None: no road term
        loc_cache: dict = {}  # L of a size's rows, shared between sizes with the same _loc_key
        unit = _scoring.unit_scale(fx, fy)
        out = torch.full((b, grid.count), -math.inf, dtype=torch.float32, device=edges.device)
        shadow = ii_grey_below = None
        if self.scores.shadow_score != "none":  # rows past the bottom add nothing to the strip below
            ii_grey_below = maps.integral_below("grey")
            shadow = torch.zeros((b, grid.count), dtype=torch.float64, device=edges.device)
        for s, enc, off in zip(grid.sizes, enclosed, grid.offsets):
            dx, dy, cw, ch = _scoring.centre_box(s.w, s.h, self.scores.center_fraction)
            centre = _scoring.box_sums(ii_edges, dx, dy, cw, ch, s)
            bw, bh = s.w / fx, s.h / fy
            sc = _scoring.edge_score(enc * unit, centre * unit, bw, bh, self.scores.score_norm, self.scores.kappa,
                                     self.scores.gamma).float()
            r = (_scoring.box_sums(ii_road, 0, 0, s.w, s.h, s) / (s.w * s.h)).float() if ii_road is not None \
                else torch.zeros_like(sc)
            key = self._loc_key(s)
            loc = loc_cache.get(key) if key is not None else None
            if loc is None:
                loc = self._location_rows(s, bw, bh, fy, *maps.input_size, edges.device)
                if key is not None:
                    loc_cache[key] = loc
            v = _scoring.combined_score(sc, loc, r, self.scores.alpha, self.scores.beta, self.scores.road_score)
            if maps.green is not None:  # trees and verges: the green-dominant share of the window
                gdx, gdy, gw, gh = _scoring.centre_box(s.w, s.h, self.scores.vegetation_box)
                f = _scoring.vegetation_factor(_scoring.box_sums(maps.green, gdx, gdy, gw, gh, s), float(gw * gh),
                                               self.scores.vegetation_power)
                v = v * f.float()
            v = torch.where(sc >= self.scores.min_edge_score, v, -math.inf)
            out[:, off: off + s.count] = v.reshape(b, -1)
            if shadow is not None:  # the darker bottom strip of a vehicle over the road below it
                assert ii_grey_below is not None and maps.grey is not None  # made with the shadow term
                sh, mx = _scoring.shadow_strips(s.w, s.h, self.scores.shadow_strip, self.scores.shadow_margin)
                inside = _scoring.box_sums(ii_grey_below, mx, s.h - sh, s.w - 2 * mx, sh, s)
                below = _scoring.box_sums(ii_grey_below, mx, s.h, s.w - 2 * mx, sh, s)
                y1 = torch.arange(s.ny, device=edges.device) * s.sy + s.oy + s.h
                rows = (maps.grey.shape[1] - y1).clamp(0, sh).view(1, -1, 1)
                u = _scoring.shadow_fraction(inside, below, sh * (s.w - 2 * mx), rows * (s.w - 2 * mx))
                shadow[:, off: off + s.count] = u.reshape(b, -1)
        if shadow is not None:  # one call on the whole score tensor, as the compiled path
            out = _scoring.apply_shadow(out, shadow, self.scores.shadow_floor, self.scores.shadow_power)
        return out

    def enclosed(self, maps: ScoreMaps, grid: _windows.WindowGrid) -> list[Tensor]:
        """Eq. 1's enclosed sums of every window, per size. Groups bounded to tiles smaller
        than every window: the batch's four prefix tables (:meth:`ScoreMaps.tables`), then
        strided slices per size (:func:`reeb_torch.stages.enclosed.enclosed_grid`); otherwise
        one scatter per size (:func:`reeb_torch.stages.scoring.enclosed_sums`). Both are exact
        float64 sums: the same numbers."""
        if not grid.sizes:
            return []
        if _tables_exact(maps.groups, grid):
            tables = maps.tables()
            return [_enclosed.enclosed_grid(tables, s) for s in grid.sizes]
        return _scoring.enclosed_sums(maps.groups, maps.edges.shape[0], grid.sizes)

    def _ground_ratios(self) -> tuple[float, ...]:
        """Box height / (bottom row − horizon) of the objects the location score expects, one
        per class (``classes``: typical height / camera height)."""
        return tuple(h / self.camera.camera_height_m for h in self.scores.class_heights_m)

    def _class_weights(self) -> tuple[float, ...] | None:
        return tuple(self.scores.class_weights) if self.scores.location_score == "classes" else None

    def _template_widths(self) -> tuple[tuple[float, float], ...] | None:
        """Each class's width range in metres when the location score fits the box's shape
        (``location_score='classes'``), else None."""
        if self.scores.location_score == "classes":
            return tuple((t[2], t[3]) for t in self.windows.object_templates)
        return None

    def _loc_key(self, s: _windows.WindowSize) -> tuple | None:
        """What L of a window size's rows depends on, to share it between sizes: the height
        and rows, and the width with the class shape fit; None for the printed L (it reads
        the width and is not shared)."""
        if self.scores.location_score == "paper":
            return None
        return (s.h, s.oy, s.sy, s.ny, s.w if self._template_widths() is not None else 0)

    def _location(self, bottom: Tensor, bw: float | Tensor, bh: float | Tensor, h_in: int, w_in: int) -> Tensor:
        """L (eq. 11 or its variants) of boxes ``bw × bh`` (input pixels) whose bottom is row ``bottom``."""
        return _scoring.location_score(bottom, bw, bh, float(w_in), float(h_in), self.scores.location_score,
                                       self.camera.horizon, self._ground_ratios(), self.scores.ground_log_sigma,
                                       self._class_weights(), self._template_widths(), self.camera.camera_height_m)

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
        return self.cache.grid_cached(("plan", fx, fy, h_in, w_in), grid,
                                 lambda: self._build_score_plan(grid, fx, fy, h_in, w_in))

    def _build_score_plan(self, grid: _windows.WindowGrid, fx: float, fy: float, h_in: int,
                          w_in: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        rows, denoms, locs = [], [], []
        loc_cache: dict = {}
        loc_offset = 0
        for s, off in zip(grid.sizes, grid.offsets):
            dx, dy, cw, ch = _scoring.centre_box(s.w, s.h, self.scores.center_fraction)
            bw, bh = s.w / fx, s.h / fy
            denom = _scoring.edge_norm(bw, bh, self.scores.score_norm, self.scores.kappa, self.scores.gamma)
            lkey = self._loc_key(s)
            start = loc_cache.get(lkey) if lkey is not None else None
            if start is None:
                start = loc_offset
                locs.append(self._location_rows(s, bw, bh, fy, h_in, w_in, torch.device("cpu")).reshape(-1))
                loc_offset += s.ny
                if lkey is not None:
                    loc_cache[lkey] = start
            sh, mx = _scoring.shadow_strips(s.w, s.h, self.scores.shadow_strip, self.scores.shadow_margin)
            gdx, gdy, gw, gh = _scoring.centre_box(s.w, s.h, self.scores.vegetation_box)
            rows.append((s.w, s.h, s.sx, s.sy, s.nx, s.ny, s.oy, off, dx, dy, cw, ch, start, sh, mx, gdx, gdy, gw, gh))
            denoms.append(denom)
        plan = np.asarray(rows, dtype=np.int64).reshape(-1, len(_scoring.PLAN_COLUMNS))
        return (plan, np.asarray(denoms, dtype=np.float64), torch.cat(locs).numpy() if locs else np.zeros(0, np.float32),
                _scoring.row_order(plan))
