"""The REEB proposal generator: images in, ranked boxes out (the paper's Table 1).

``ProposalGenerator.forward`` reads top to bottom as the paper's pseudo-code: edge map,
road mask, regions, entropy and budget per region, dense windows, scores, ranking, NMS.
A batch of equal-sized images is computed as one batch; a list of images of different
sizes is split into equal-size batches.
"""

from __future__ import annotations

import math
import time
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Iterator

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ._checks import ImageBatch, check_images
from .config import ReebConfig
from .stages import edges as _edges
from .stages import entropy as _entropy
from .stages import groups as _groups
from .stages import refinement as _refinement
from .stages import regions as _regions
from .stages import road as _road
from .stages import scoring as _scoring
from .stages import windows as _windows
from .stages.edges import working_size
from .stages.nms import nms_top_k_many, nms_windows_cpu

__all__ = ["ProposalGenerator", "propose", "Inspection"]


@dataclass
class Inspection:
    """Everything :meth:`ProposalGenerator.inspect` computed for one image, at input
    resolution (``H × W``).

    Attributes:
        boxes: ``float32 [N, 4]`` proposals (x1, y1, x2, y2), ranked best first.
        scores: ``float32 [N]`` their combined scores V (eq. 12), descending.
        edges: ``float32 [H, W]`` edge magnitudes in [0, 1] after thresholding (Sec. 3.4).
        road_mask: ``bool [H, W]`` road pixels (eqs. 3–4).
        regions: ``float32 [R, 4]`` the region strips (x1, y1, x2, y2).
        entropy: ``float32 [R]`` Shannon entropy of each region in bits (eq. 2).
        share: ``float32 [R]`` fraction of the region's candidate budget it gets (eq. 9).
        num_groups: number of edge groups (Sec. 3.7).
        num_windows: number of sliding windows scored.
    """

    boxes: Tensor
    scores: Tensor
    edges: Tensor
    road_mask: Tensor
    regions: Tensor
    entropy: Tensor
    share: Tensor
    num_groups: int
    num_windows: int


class ProposalGenerator(nn.Module):
    """Region Enhanced Edge-Based (REEB) object proposals; no parameters, no training.

    Args:
        config: a :class:`ReebConfig` (default: ``ReebConfig()``, the best measured variant).
        **overrides: fields of the config to change, e.g. ``top_k=500``.

    ``forward(images)`` accepts a float ``(B, 3, H, W)`` tensor of RGB values in [0, 1], a
    ``uint8`` tensor of the same shape, or a list of ``(3, H, W)`` tensors of any sizes,
    on any device; it returns one dict per image with

    * ``boxes``: ``float32 [N, 4]`` (x1, y1, x2, y2) in that image's pixels, ranked;
    * ``scores``: ``float32 [N]``, descending; ``N <= config.top_k``.
    """

    def __init__(self, config: ReebConfig | None = None, **overrides: object) -> None:
        super().__init__()
        cfg = config if config is not None else ReebConfig()
        if not isinstance(cfg, ReebConfig):
            raise TypeError(f"config must be a ReebConfig, got {type(cfg).__name__}")
        self.config = cfg.replace(**overrides) if overrides else cfg
        self._device_cache: dict = {}
        self._plan_cache: dict = {}
        self.stage_times: dict[str, float] | None = None
        """Set to ``{}`` to accumulate wall seconds per stage (edges, groups, road,
        regions, scoring, nms) over calls; ``None`` (default) records nothing."""

    @contextmanager
    def _stage(self, name: str, device: torch.device) -> Iterator[None]:
        if self.stage_times is None:
            yield
            return
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        t0 = time.perf_counter()
        yield
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        self.stage_times[name] = self.stage_times.get(name, 0.0) + time.perf_counter() - t0

    def extra_repr(self) -> str:
        c = self.config
        return f"top_k={c.top_k}, scale={c.scale}, use_regions={c.use_regions}, grouping={c.grouping!r}"

    @property
    def min_side(self) -> int:
        """Smallest image height/width accepted, in input pixels (the smallest window)."""
        return self.config.min_window

    # ------------------------------------------------------------------------------------
    @torch.no_grad()
    def forward(self, images: ImageBatch) -> list[dict[str, Tensor]]:
        imgs = check_images(images, self.min_side, self.config, keep_uint8=True)
        results: list[dict[str, Tensor] | None] = [None] * len(imgs)
        by_size: dict[tuple, list[int]] = {}
        for i, im in enumerate(imgs):
            by_size.setdefault((tuple(im.shape), im.device), []).append(i)
        for idx in by_size.values():
            out, _ = self._propose_batch([imgs[i] for i in idx])
            for i, r in zip(idx, out):
                results[i] = r
        return results  # type: ignore[return-value]

    @torch.no_grad()
    def inspect(self, image: Tensor) -> Inspection:
        """Run on one ``(3, H, W)`` image and keep the intermediate maps (for pictures)."""
        (x,) = check_images([image], self.min_side, self.config)
        out, extra = self._propose_batch([x], keep=True)
        h, w = x.shape[-2:]
        up = lambda t, mode: F.interpolate(t[None].float(), size=(h, w), mode=mode)[0, 0]  # noqa: E731
        return Inspection(
            boxes=out[0]["boxes"], scores=out[0]["scores"],
            edges=up(extra["edges"], "bilinear"),
            road_mask=up(extra["road"], "nearest") > 0.5,
            regions=extra["regions"], entropy=extra["entropy"][0], share=extra["share"][0],
            num_groups=extra["num_groups"], num_windows=extra["num_windows"],
        )

    # ------------------------------------------------------------------------------------
    def _propose_batch(self, images: list[Tensor], keep: bool = False) -> tuple[list[dict[str, Tensor]], dict]:
        """The algorithm on a batch of equal-sized ``(3, H, W)`` images, float32 in [0, 1]
        or uint8."""
        cfg = self.config
        b = len(images)
        _, h_in, w_in = images[0].shape
        dev = images[0].device
        needs_road = keep or cfg.road_score not in ("none", "flat")
        # Sec. 3.4: Edge_Map = Sobel(Gaussian_Blur(I)), at the working resolution
        with self._stage("edges", dev):
            xk = None  # the colour image at the working resolution, only where a stage reads it
            gray = green = None
            want_green = cfg.vegetation_score != "none"
            if cfg.edge_channels == "gray" and not needs_road:
                front = _edges.working_gray(images, cfg.scale, with_green=want_green)
                if front is not None:
                    gray, green = front
            if gray is None:
                xk = self._working_batch(images)
                gray = _edges.to_gray(xk)
                green = _scoring.count_integral(_edges.green_mask(xk)) if want_green else None
            src = gray if cfg.edge_channels == "gray" else xk
            crossing = None
            if cfg.straddle_weight > 0:  # edge orientations for the straddling term
                edges, gx, gy = _edges.edge_map(src, cfg.blur_sigma, cfg.edge_threshold, cfg.remove_isolated,
                                                cfg.thin_edges, return_gradients=True)
                crossing = _edges.crossing_maps(edges, gx, gy)
            else:
                edges = _edges.edge_map(src, cfg.blur_sigma, cfg.edge_threshold, cfg.remove_isolated,
                                        cfg.thin_edges)
        hk, wk = gray.shape[-2:]
        fx, fy = wk / w_in, hk / h_in
        # Sec. 3.7: adjacent edge pixels form edge groups
        with self._stage("groups", dev):
            groups = _groups.edge_groups(edges, cfg.grouping, cfg.group_cell)
        # Sec. 3.5: Road_Mask = Generate_Road_Segmentation(I, HSV); skipped when no score reads it
        road = None
        if needs_road:
            with self._stage("road", dev):
                road = _road.road_mask(xk, cfg.road_samples, cfg.road_band, cfg.road_tolerance,
                                       cfg.road_combine, cfg.seed)
        # Sec. 3.6: Regions = Divide_Image_Into_Regions(I, Camera_Params); eqs. 2 and 9
        with self._stage("regions", dev):
            bounds = self._region_bounds(wk)
            if cfg.use_regions:
                entropy = _entropy.region_entropy(gray, bounds, cfg.entropy_bins)
                share = _entropy.proposal_share(entropy, cfg.entropy_sigma, cfg.entropy_form)
            else:  # one region, the whole image: entropy is not applicable (Sec. 4.2)
                entropy = torch.zeros(b, 1, device=dev)
                share = torch.ones(b, 1, device=dev)
        # Sec. 3.6-3.7: dense sliding windows, scored by eqs. 1, 10-12, ranked per region
        with self._stage("scoring", dev):
            grid = self._window_grid(hk, wk, bounds, fx, fy)
            grey = gray[:, 0] if cfg.shadow_score != "none" else None
            tabs: dict = {}  # integral images and prefix tables of this batch, built once for scoring and refinement
            scores = self._score_windows(edges, road, groups, grid, fx, fy, h_in, w_in, crossing, grey, green,
                                         tabs=tabs)
            chosen = self._select(scores, grid, share)
        # Edge Boxes' refinement of the candidates (not in the paper; ``ReebConfig.refine``)
        cand_boxes = cand_scores = None
        if cfg.refine:
            with self._stage("refine", dev):
                cand_boxes, cand_scores = self._refine(chosen, scores, grid, edges, road, groups, crossing,
                                                       fx, fy, h_in, w_in, grey, green, tabs=tabs)
        # Sec. 3.8: Final_Proposals = NMS(Sorted_Proposals) (eq. 13)
        with self._stage("nms", dev):
            to_input = torch.tensor([fx, fy, fx, fy], device=dev)
            boxes_in = self._grid_cached(("boxes_in", fx, fy, str(dev)), grid,
                                         lambda: self._device_tensor(grid.boxes, dev) / to_input)
            region_of = self._device_tensor(grid.region_of, dev)
            quota = cfg.region_quota and len(bounds) > 1
            kept = None
            if cand_boxes is None:  # the windows themselves: gathered, sorted and suppressed compiled
                kept = nms_windows_cpu(chosen, boxes_in, scores, cfg.nms_iou, grid.count if quota else cfg.top_k)
            if kept is not None:
                pairs = [(boxes_in, scores[i]) for i in range(b)]
                windows = kept
            else:
                cands = [torch.nonzero(chosen[i]).squeeze(1) for i in range(b)]
                if cand_boxes is not None:
                    pairs = [(cand_boxes[i] / to_input, cand_scores[i]) for i in range(b)]
                else:
                    pairs = [(boxes_in[c], scores[i, c]) for i, c in enumerate(cands)]
                kept = nms_top_k_many(pairs, cfg.nms_iou, max(len(p[1]) for p in pairs) if quota else cfg.top_k)
                windows = [c[k] for c, k in zip(cands, kept)]
            results = []
            for i, ((bx, sc), keep_idx, win) in enumerate(zip(pairs, kept, windows)):
                if quota:
                    keep_idx = self._quota(keep_idx, region_of[win], share[i])[: cfg.top_k]
                results.append({"boxes": bx[keep_idx].contiguous(), "scores": sc[keep_idx].contiguous()})
        extra: dict = {}
        if keep:
            extra = dict(edges=edges, road=road, entropy=entropy, share=share,
                         regions=torch.stack([bounds[:, 0] / fx, torch.zeros(len(bounds)),
                                              bounds[:, 1] / fx, torch.full((len(bounds),), float(h_in))], 1).float(),
                         num_groups=len(groups), num_windows=grid.count)
        return results, extra

    # -- stages ---------------------------------------------------------------------------
    def _working_batch(self, images: list[Tensor]) -> Tensor:
        """``(B, 3, h, w)`` float32: the images at the working resolution, each resized on its
        own and then stacked (stacking the full-resolution images first would copy 4× the
        data); uint8 images are converted to [0, 1] first."""
        images = [x.float().div_(255.0) if x.dtype == torch.uint8 else x for x in images]
        s = self.config.scale
        if s == 1.0:
            return torch.stack(images) if len(images) > 1 else images[0][None]
        size = working_size(*images[0].shape[-2:], s)
        small = [F.interpolate(x[None], size=size, mode="bilinear", align_corners=False, antialias=s < 1)
                 for x in images]
        return torch.cat(small) if len(small) > 1 else small[0]

    def _min_window_working(self, fx: float, fy: float) -> int:
        return max(3, int(round(self.config.min_window * min(fx, fy))))

    def _window_grid(self, hk: int, wk: int, bounds: Tensor, fx: float, fy: float) -> _windows.WindowGrid:
        cfg = self.config
        ground = None if cfg.ground_band is None else (cfg.horizon, *cfg.ground_band)
        camera = None
        if cfg.window_geometry == "camera":
            # template extents (metres) over the camera height: the ratios box side / (y_b − y_h)
            ratios = tuple((hl / cfg.camera_height_m, hh / cfg.camera_height_m,
                            wl / cfg.camera_height_m * fx / fy, wh / cfg.camera_height_m * fx / fy)
                           for hl, hh, wl, wh in cfg.object_templates)
            camera = (cfg.horizon, ratios, cfg.border_windows, cfg.horizon_slack)
        return _windows.window_grid(hk, wk, bounds, self._min_window_working(fx, fy), cfg.size_ratio,
                                    cfg.window_step, cfg.aspect_range, cfg.region_assign, ground, camera)

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

    def _region_bounds(self, width: int) -> Tensor:
        cfg = self.config
        if not cfg.use_regions:
            return torch.tensor([[0, width]])
        frac = _regions.region_width_fraction(cfg.camera_height_m, cfg.vertical_fov_deg, cfg.horizontal_fov_deg,
                                              cfg.max_object_width_m, cfg.region_width_round)
        return _regions.region_bounds(width, frac, cfg.region_overlap)

    def _score_windows(self, edges: Tensor, road: Tensor | None, groups: _groups.EdgeGroups,
                       grid: _windows.WindowGrid, fx: float, fy: float, h_in: int, w_in: int,
                       crossing: tuple[Tensor, Tensor] | None = None, grey: Tensor | None = None,
                       green: Tensor | None = None, *, tabs: dict | None = None) -> Tensor:
        """V (eq. 12) of every window, ``float32 [B, N]``; ``-inf`` where S < min_edge_score
        (or, with ``local_max``, where a neighbouring position of the same size scores higher).
        ``green``: the pixel counts of the green mask, ``(B, h + 1, w + 1)``, for the
        vegetation term. ``tabs`` keeps the batch's prefix tables (:meth:`_tables`) for the
        refinement.

        On the CPU, when no term needs per-window maps (no road fraction, straddling or
        local maxima) and every window is wider and taller than every edge group, one
        compiled pass (:func:`reeb_torch.stages.scoring.score_grid_cpu`) scores all windows;
        otherwise one batch of tensor ops per window size. Both give the same numbers."""
        if self._compiled_scoring_applies(edges, groups, grid, crossing):
            return self._score_windows_compiled(edges, groups, grid, fx, fy, h_in, w_in, grey, green, tabs=tabs)
        return self._score_windows_torch(edges, road, groups, grid, fx, fy, h_in, w_in, crossing, grey, green,
                                         tabs=tabs)

    def _compiled_scoring_applies(self, edges: Tensor, groups: _groups.EdgeGroups, grid: _windows.WindowGrid,
                                  crossing: tuple[Tensor, Tensor] | None) -> bool:
        cfg = self.config
        if (edges.device.type != "cpu" or crossing is not None or cfg.local_max
                or cfg.road_score not in ("none", "flat") or not grid.sizes):
            return False
        return _tables_exact(groups, grid)

    def _score_plan(self, grid: _windows.WindowGrid, fx: float, fy: float, h_in: int,
                    w_in: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per-size constants of the compiled scoring pass (cached per grid and input size):
        the ``int64 [S, 19]`` size table, eq. 1's normalisers ``float64 [S]`` and L of every
        size's rows ``float32 [Σ ny]`` (computed by the same tensor code as the torch path)."""
        return self._grid_cached(("plan", fx, fy, h_in, w_in, self.config), grid,
                                 lambda: self._build_score_plan(grid, fx, fy, h_in, w_in))

    def _build_score_plan(self, grid: _windows.WindowGrid, fx: float, fy: float, h_in: int,
                          w_in: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        cfg = self.config
        rows, denoms, locs = [], [], []
        loc_cache: dict = {}
        loc_offset = 0
        for s, off in zip(grid.sizes, grid.offsets):
            dx, dy, cw, ch = _scoring.centre_box(s.w, s.h, cfg.center_fraction)
            bw, bh = s.w / fx, s.h / fy
            denom = _scoring.edge_norm(bw, bh, cfg.score_norm, cfg.kappa, cfg.gamma)
            lkey = (s.h, s.oy, s.sy, s.ny) if cfg.location_score != "paper" else None
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
        return (np.asarray(rows, dtype=np.int64).reshape(-1, len(_scoring.PLAN_COLUMNS)),
                np.asarray(denoms, dtype=np.float64),
                torch.cat(locs).numpy() if locs else np.zeros(0, np.float32))

    def _grid_cached(self, key: tuple, grid: _windows.WindowGrid, build):
        """``build()``, cached per ``key`` and window grid (grids are cached themselves, so
        one is recognised by identity; the entry keeps it alive so its id is not reused)."""
        key = (id(grid), *key)
        hit = self._plan_cache.get(key)
        if hit is not None and hit[0] is grid:
            return hit[1]
        value = build()
        if len(self._plan_cache) >= 32:  # grids of many image sizes: start afresh
            self._plan_cache.clear()
        self._plan_cache[key] = (grid, value)
        return value

    def _location_rows(self, s: _windows.WindowSize, bw: float, bh: float, fy: float, h_in: int, w_in: int,
                       device: torch.device) -> Tensor:
        """L (eq. 11 or its variants) of the rows of window size ``s``: ``float32 (1, ny, 1)``."""
        cfg = self.config
        bottom = ((torch.arange(s.ny, device=device, dtype=torch.float32) * s.sy + s.oy + s.h) / fy).view(1, -1, 1)
        return _scoring.location_score(bottom, bw, bh, float(w_in), float(h_in), cfg.location_score,
                                       cfg.horizon, self._ground_ratios(), cfg.ground_log_sigma,
                                       self._class_weights())

    def _score_windows_compiled(self, edges: Tensor, groups: _groups.EdgeGroups, grid: _windows.WindowGrid,
                                fx: float, fy: float, h_in: int, w_in: int, grey: Tensor | None = None,
                                green: Tensor | None = None, *, tabs: dict | None = None) -> Tensor:
        cfg = self.config
        plan, denom, loc = self._score_plan(grid, fx, fy, h_in, w_in)
        b = edges.shape[0]
        tables = self._tables(tabs, edges, groups)
        ii_edges = self._kept_integral(tabs, "edges", edges)
        out = torch.full((b, grid.count), -math.inf, dtype=torch.float32)
        road = 1.0 if cfg.road_score == "flat" else 0.0
        ii_grey = shadow = sqrt_floor = None
        if cfg.shadow_score != "none":
            ii_grey = self._kept_integral(tabs, "grey", grey)
            if cfg.shadow_power == 0.5:  # the factor in the kernel: sqrt rounds alike everywhere
                sqrt_floor = cfg.shadow_floor
            else:
                shadow = torch.zeros((b, grid.count), dtype=torch.float64)
        _scoring.score_grid_cpu(ii_edges, tables, plan, denom, loc, _scoring.unit_scale(fx, fy), cfg.alpha,
                                cfg.beta * road, cfg.min_edge_score, out, ii_grey, shadow, sqrt_floor,
                                green, cfg.vegetation_power)
        if shadow is not None:
            out = _scoring.apply_shadow(out, shadow, cfg.shadow_floor, cfg.shadow_power)
        return out

    def _score_windows_torch(self, edges: Tensor, road: Tensor | None, groups: _groups.EdgeGroups,
                             grid: _windows.WindowGrid, fx: float, fy: float, h_in: int, w_in: int,
                             crossing: tuple[Tensor, Tensor] | None = None, grey: Tensor | None = None,
                             green: Tensor | None = None, *, tabs: dict | None = None) -> Tensor:
        """:meth:`_score_windows` as tensor ops, one batch of them per window size (any device, any config).

        ``tabs`` keeps the batch's integral images and prefix tables for the refinement."""
        cfg = self.config
        b = edges.shape[0]
        ii_edges = self._kept_integral(tabs, "edges", edges)
        enclosed = self._enclosed(edges, groups, grid, tabs)
        ii_road = self._kept_integral(tabs, "road", road) if road is not None else None  # None: no road term
        ii_road_below = _scoring.extend_below(ii_road) if cfg.road_score == "stand" else None  # none past the bottom
        loc_cache: dict = {}  # L depends on the window height and rows only (not on ``paper``'s b_w)
        band = cfg.straddle_band
        if crossing is not None:  # padded by the band so sides at the image border read zeros
            ii_cols = _scoring.integral_image(F.pad(crossing[0], (band, band, band, band)))
            ii_rows = _scoring.integral_image(F.pad(crossing[1], (band, band, band, band)))
        unit = _scoring.unit_scale(fx, fy)
        out = torch.full((b, grid.count), -math.inf, dtype=torch.float32, device=edges.device)
        shadow = ii_grey_below = None
        if cfg.shadow_score != "none":  # rows past the bottom add nothing to the strip below
            ii_grey_below = _scoring.extend_below(self._kept_integral(tabs, "grey", grey))
            shadow = torch.zeros((b, grid.count), dtype=torch.float64, device=edges.device)
        for s, enc, off in zip(grid.sizes, enclosed, grid.offsets):
            dx, dy, cw, ch = _scoring.centre_box(s.w, s.h, cfg.center_fraction)
            centre = _scoring.box_sums(ii_edges, dx, dy, cw, ch, s)
            if crossing is not None:  # contours cut by the box's sides (straddling edges)
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
                below = _scoring.box_sums(ii_road_below, 0, s.h, s.w, sh, s) / (s.w * sh)
                r = (below.float() * (1.0 - r)).clamp_(0, 1)
            key = (s.h, s.oy, s.sy, s.ny) if cfg.location_score != "paper" else None  # L ignores b_w
            loc = loc_cache.get(key) if key is not None else None
            if loc is None:
                loc = self._location_rows(s, bw, bh, fy, h_in, w_in, edges.device)
                if key is not None:
                    loc_cache[key] = loc
            v = _scoring.combined_score(sc, loc, r, cfg.alpha, cfg.beta, cfg.road_score)
            if green is not None:  # trees and verges: the green-dominant share of the window
                gdx, gdy, gw, gh = _scoring.centre_box(s.w, s.h, cfg.vegetation_box)
                f = _scoring.vegetation_factor(_scoring.box_sums(green, gdx, gdy, gw, gh, s), float(gw * gh),
                                               cfg.vegetation_power)
                v = v * f.float()
            v = torch.where(sc >= cfg.min_edge_score, v, -math.inf)
            out[:, off: off + s.count] = v.reshape(b, -1)
            if shadow is not None:  # the darker bottom strip of a vehicle over the road below it
                sh, mx = _scoring.shadow_strips(s.w, s.h, cfg.shadow_strip, cfg.shadow_margin)
                inside = _scoring.box_sums(ii_grey_below, mx, s.h - sh, s.w - 2 * mx, sh, s)
                below = _scoring.box_sums(ii_grey_below, mx, s.h, s.w - 2 * mx, sh, s)
                y1 = torch.arange(s.ny, device=edges.device) * s.sy + s.oy + s.h
                rows = (grey.shape[1] - y1).clamp(0, sh).view(1, -1, 1)
                u = _scoring.shadow_fraction(inside, below, sh * (s.w - 2 * mx), rows * (s.w - 2 * mx))
                shadow[:, off: off + s.count] = u.reshape(b, -1)
        if shadow is not None:  # one call on the whole score tensor, as the compiled path
            out = _scoring.apply_shadow(out, shadow, cfg.shadow_floor, cfg.shadow_power)
        if cfg.local_max:
            for s, off in zip(grid.sizes, grid.offsets):
                v = out[:, off: off + s.count].view(b, s.ny, s.nx)
                peak = F.max_pool2d(v[:, None], 3, stride=1, padding=1)[:, 0]
                out[:, off: off + s.count] = torch.where(v >= peak, v, -math.inf).reshape(b, -1)
        return out

    def _enclosed(self, edges: Tensor, groups: _groups.EdgeGroups, grid: _windows.WindowGrid,
                  tabs: dict | None = None) -> list[Tensor]:
        """Eq. 1's enclosed sums of every window, per size. Groups bounded to tiles smaller
        than every window: four prefix tables built once (:meth:`_tables`, kept in ``tabs``),
        then strided slices per size (:func:`reeb_torch.stages.refinement.enclosed_grid`); otherwise
        one scatter per size (:func:`reeb_torch.stages.scoring.enclosed_sums`). Both are exact float64
        sums: the same numbers."""
        if not grid.sizes:
            return []
        if _tables_exact(groups, grid):
            tables = self._tables(tabs, edges, groups)
            return [_refinement.enclosed_grid(tables, s) for s in grid.sizes]
        return _scoring.enclosed_sums(groups, edges.shape[0], grid.sizes)

    def _box_scorer(self, edges: Tensor, road: Tensor | None, groups: _groups.EdgeGroups,
                    crossing: tuple[Tensor, Tensor] | None, fx: float, fy: float, h_in: int, w_in: int,
                    grey: Tensor | None = None, green: Tensor | None = None, *, tabs: dict | None = None):
        """V (eq. 12) of arbitrary boxes: returns ``(score_fn, min_side)`` where
        ``score_fn(boxes, b)`` takes int64 ``[K, 4]`` working-pixel boxes (x1, y1 exclusive)
        and their image indices ``[K]`` and gives ``float64 [K]``, the same numbers
        :meth:`_score_windows` gives a window of the grid; exact for boxes at least
        ``min_side`` wide and tall. ``road`` is None where the road term does not read the
        mask (``none``, ``flat``). ``tabs``: the prefix tables the scoring kept (else built here)."""
        cfg = self.config
        hk = edges.shape[1]
        tables = self._tables(tabs, edges, groups)
        ii_edges = self._kept_integral(tabs, "edges", edges)
        if road is not None:  # else a road term that does not read the mask (none, flat)
            ii_road = self._kept_integral(tabs, "road", road)
            ii_road_below = _scoring.extend_below(ii_road)
        band = cfg.straddle_band
        if crossing is not None:
            ii_cols = _scoring.integral_image(F.pad(crossing[0], (band, band, band, band)))
            ii_rows = _scoring.integral_image(F.pad(crossing[1], (band, band, band, band)))
        unit = _scoring.unit_scale(fx, fy)
        at = _refinement.box_sum_at
        if cfg.shadow_score != "none":
            ii_grey_below = _scoring.extend_below(self._kept_integral(tabs, "grey", grey))

        def centred(x0: Tensor, y0: Tensor, w: Tensor, h: Tensor, fraction: float) -> tuple[Tensor, ...]:
            """The centred ``fraction`` of each box, as :func:`scoring.centre_box` places it."""
            cw = (w * fraction).round().long().clamp_(min=1)
            ch = (h * fraction).round().long().clamp_(min=1)
            cx0 = x0 + torch.div(w - cw, 2, rounding_mode="floor")
            cy0 = y0 + torch.div(h - ch, 2, rounding_mode="floor")
            return cx0, cy0, cx0 + cw, cy0 + ch

        def score_fn(boxes: Tensor, bi: Tensor) -> Tensor:
            x0, y0, x1, y1 = boxes.unbind(1)
            w, h = x1 - x0, y1 - y0
            centre = at(ii_edges, bi, *centred(x0, y0, w, h, cfg.center_fraction))
            if crossing is not None:
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
            loc = _scoring.location_score(y1.double() / fy, bw, bh, float(w_in), float(h_in), cfg.location_score,
                                          cfg.horizon, self._ground_ratios(), cfg.ground_log_sigma,
                                          self._class_weights())
            v = _scoring.combined_score(sc, loc, r, cfg.alpha, cfg.beta, cfg.road_score)
            if green is not None:
                gx0, gy0, gx1, gy1 = centred(x0, y0, w, h, cfg.vegetation_box)
                v = v * _scoring.vegetation_factor(at(green, bi, gx0, gy0, gx1, gy1),
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

    @staticmethod
    def _tables(tabs: dict | None, edges: Tensor, groups: _groups.EdgeGroups) -> _refinement.EnclosedTables:
        """The groups' :class:`~reeb_torch.stages.refinement.EnclosedTables` of a batch (``edges``:
        its ``(B, H, W)`` edge map), built on first use and kept in ``tabs`` (when given) for
        the next."""
        if tabs is None or "tables" not in tabs:
            b, hk, wk = edges.shape
            built = _refinement.enclosed_tables(groups, b, hk, wk)
            if tabs is None:
                return built
            tabs["tables"] = built
        return tabs["tables"]

    @staticmethod
    def _kept_integral(tabs: dict | None, name: str, x: Tensor) -> Tensor:
        """The integral image of the batch's ``x`` (``"edges"``: the edge map; ``"grey"``: the
        shadow term's grey image; ``"road"``: the road mask), kept in ``tabs`` under ``name``
        like :meth:`_tables`."""
        if tabs is None:
            return _scoring.integral_image(x)
        if name not in tabs:
            tabs[name] = _scoring.integral_image(x)
        return tabs[name]

    def _compiled_refine_applies(self, edges: Tensor, crossing: tuple[Tensor, Tensor] | None) -> bool:
        """Whether :func:`reeb_torch.stages.refinement.refine_boxes_cpu` computes this config's box
        score: on the CPU, without the straddling and road terms, with a location score
        tabulated by box height and bottom row, and a square-root shadow factor (or none)."""
        cfg = self.config
        return (edges.device.type == "cpu" and crossing is None and cfg.road_score in ("none", "flat")
                and cfg.location_score in ("ground", "classes", "none")
                and (cfg.shadow_score == "none" or cfg.shadow_power == 0.5))

    def _box_tables(self, grid: _windows.WindowGrid, hk: int, wk: int, fx: float, fy: float, h_in: int,
                    w_in: int) -> tuple[Tensor, Tensor]:
        """``loc[y1, h]`` (the location score of a box ``h`` working pixels tall whose bottom is
        working row ``y1``) and ``norm[w, h]`` (eq. 1's normaliser of a ``w × h`` box), from the
        tensor functions the box scorer calls, cached with the window grid of the image size."""
        cfg = self.config

        def build() -> tuple[Tensor, Tensor]:
            rows = torch.arange(hk + 1, dtype=torch.float64)
            bottom, bh = rows[:, None] / fy, rows[None, :] / fy
            loc = _scoring.location_score(bottom, bh, bh, float(w_in), float(h_in), cfg.location_score, cfg.horizon,
                                          self._ground_ratios(), cfg.ground_log_sigma, self._class_weights())
            bw = torch.arange(wk + 1, dtype=torch.float64)[:, None] / fx
            norm = _scoring.edge_norm(bw, bh, cfg.score_norm, cfg.kappa, cfg.gamma)
            return loc.expand(hk + 1, hk + 1).contiguous(), norm.contiguous()

        return self._grid_cached(("box_tables", fx, fy, h_in, w_in), grid, build)

    def _refine(self, chosen: Tensor, scores: Tensor, grid: _windows.WindowGrid, edges: Tensor, road: Tensor | None,
                groups: _groups.EdgeGroups, crossing: tuple[Tensor, Tensor] | None, fx: float, fy: float,
                h_in: int, w_in: int, grey: Tensor | None = None, green: Tensor | None = None, *,
                tabs: dict | None = None) -> tuple[list[Tensor], list[Tensor]]:
        """Edge Boxes' refinement of every chosen window (:func:`reeb_torch.stages.refinement.refine_boxes_cpu`,
        compiled, where :meth:`_compiled_refine_applies`; else :func:`reeb_torch.stages.refinement.refine_boxes`
        with :meth:`_box_scorer`: the same boxes and scores); per image, ``float32 [K, 4]`` working-pixel
        boxes and ``float32 [K]`` scores, in the order of ``nonzero(chosen[i])``. Boxes narrower or
        shorter than the exact-sum limit, or narrower than ``refine_min_aspect`` times their height,
        stay as they are. ``tabs``: the prefix tables the compiled scoring built (else built here)."""
        cfg = self.config
        b, hk, wk = edges.shape
        bi, ni = torch.nonzero(chosen, as_tuple=True)
        boxes = self._device_tensor(grid.boxes, edges.device)[ni].round().long()
        vals = scores[bi, ni]
        compiled = self._compiled_refine_applies(edges, crossing)
        if compiled:
            tables = self._tables(tabs, edges, groups)
            ii_edges = self._kept_integral(tabs, "edges", edges)
            exact_side = tables.max_extent + 1
        else:
            score_fn, exact_side = self._box_scorer(edges, road, groups, crossing, fx, fy, h_in, w_in, grey, green,
                                                    tabs=tabs)
        min_side = max(exact_side, self._min_window_working(fx, fy))
        wh = boxes[:, 2:] - boxes[:, :2]
        movable = torch.nonzero((wh >= min_side).all(1) & (wh[:, 0] >= cfg.refine_min_aspect * wh[:, 1])).squeeze(1)
        if movable.numel():
            if compiled:
                grey_below = (_scoring.extend_below(self._kept_integral(tabs, "grey", grey))
                              if cfg.shadow_score != "none" else None)
                rb, rs = _refinement.refine_boxes_cpu(
                    boxes[movable], bi[movable], tables, ii_edges, *self._box_tables(grid, hk, wk, fx, fy, h_in, w_in),
                    green, grey_below,
                    dict(unit=_scoring.unit_scale(fx, fy), alpha=cfg.alpha,
                         beta_road=cfg.beta if cfg.road_score == "flat" else 0.0,
                         center_fraction=cfg.center_fraction, vegetation_box=cfg.vegetation_box,
                         vegetation_power=cfg.vegetation_power, shadow_strip=cfg.shadow_strip,
                         shadow_margin=cfg.shadow_margin, shadow_floor=cfg.shadow_floor),
                    wk, hk, min_side, cfg.window_step)
            else:
                rb, rs = _refinement.refine_boxes(boxes[movable], bi[movable], score_fn, wk, hk, min_side,
                                                  cfg.window_step)
            boxes[movable] = rb
            vals = vals.clone()
            vals[movable] = torch.maximum(vals[movable], rs.float())
        counts = torch.bincount(bi, minlength=b).tolist()
        return list(boxes.float().split(counts)), list(vals.split(counts))

    def _select(self, scores: Tensor, grid: _windows.WindowGrid, share: Tensor) -> Tensor:
        """Each region passes on its best ``share · candidates_per_region`` windows (eq. 9).
        Returns ``bool [B, N]``; ties at the cut go to the lower window index. On the CPU one
        compiled pass (:func:`reeb_torch.stages.scoring.select_per_region_cpu`), elsewhere a stable sort."""
        budget = self._region_budget(share)
        if scores.device.type == "cpu":
            members, starts = self._region_members(grid)
            return _scoring.select_per_region_cpu(scores, members, starts, budget)
        return self._select_torch(scores, grid, budget)

    def _region_budget(self, share: Tensor) -> Tensor:
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

    def _select_torch(self, scores: Tensor, grid: _windows.WindowGrid, budget: Tensor) -> Tensor:
        """:meth:`_select` as one stable sort per region (any device). Ties at the cut go to
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

    def _quota(self, keep: Tensor, region: Tensor, share: Tensor) -> Tensor:
        """Eq. 9 on the output: of the ``top_k`` proposals, region r gets up to
        ``top_k · share_r / Σ share`` (its best after NMS); places a region leaves empty go
        to the best of the rest. ``keep`` is in descending score order and stays so."""
        k = self.config.top_k
        if keep.numel() <= k:
            return keep
        total = float(share.sum())
        if total <= 0:
            return keep
        quota = torch.floor(share * (k / total)).long()  # (R,)
        onehot = torch.nn.functional.one_hot(region, share.numel())
        rank = (onehot.cumsum(0) * onehot).sum(1)  # 1-based rank within its region
        first = rank <= quota[region]
        n_first = int(first.sum())
        rest = torch.nonzero(~first).squeeze(1)[: max(0, k - n_first)]
        sel = torch.cat([torch.nonzero(first).squeeze(1), rest]).sort().values
        return keep[sel]

    def _device_tensor(self, t: Tensor, device: torch.device) -> Tensor:
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


def _tables_exact(groups: _groups.EdgeGroups, grid: _windows.WindowGrid) -> bool:
    """Whether the prefix tables give eq. 1's enclosed sums exactly for every window of
    ``grid``: every window is wider and taller than every edge group."""
    return groups.max_extent < min(min(s.w, s.h) for s in grid.sizes)


def propose(images: ImageBatch, config: ReebConfig | None = None, **overrides: object) -> list[dict[str, Tensor]]:
    """Functional form of :class:`ProposalGenerator`: ``propose(images, config)``."""
    return ProposalGenerator(config, **overrides)(images)
