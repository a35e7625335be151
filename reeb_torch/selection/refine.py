"""Edge Boxes' refinement of the candidates (``ReebConfig.refine``; not in the paper), and V
of arbitrary boxes that it maximises."""

from __future__ import annotations

from typing import Callable

import torch
from torch import Tensor

from ..stages import refinement as _refinement
from ..stages import scoring as _scoring
from ..stages import windows as _windows
from .maps import ScoreMaps
from .score import WindowScoring

__all__ = ["Refinement", "BoxScoreFn"]

#: ``score_fn(boxes, b)`` of :meth:`Refinement.box_scorer`: V of int64 ``[K, 4]`` boxes of images ``b``.
BoxScoreFn = Callable[[Tensor, Tensor], Tensor]


def _centred(x0: Tensor, y0: Tensor, w: Tensor, h: Tensor, fraction: float) -> tuple[Tensor, ...]:
    """The centred ``fraction`` of each box, as :func:`~reeb_torch.stages.scoring.centre_box` places it."""
    cw = (w * fraction).round().long().clamp_(min=1)
    ch = (h * fraction).round().long().clamp_(min=1)
    cx0 = x0 + torch.div(w - cw, 2, rounding_mode="floor")
    cy0 = y0 + torch.div(h - ch, 2, rounding_mode="floor")
    return cx0, cy0, cx0 + cw, cy0 + ch


class Refinement(WindowScoring):
    """Each candidate moved to the box near it that scores best (compiled on the CPU where it
    applies, else tensor ops with :meth:`box_scorer`: the same boxes and scores)."""

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
        boxes = self.device_tensor(grid.boxes, maps.edges.device)[ni].round().long()
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

        return self.grid_cached(("box_tables", fx, fy, h_in, w_in), grid, build)

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
