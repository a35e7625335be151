"""A second scoring pass over the best candidates (``ReebConfig.rescore``; not in the paper)."""

from __future__ import annotations

import torch
from torch import Tensor

from ..stages import refinement as _refinement
from ..stages import rescoring as _rescoring
from ..stages import windows as _windows
from .cache import GridCache
from .maps import ScoreMaps

__all__ = ["Rescoring"]


class Rescoring(GridCache):
    """Each image's best candidates ranked again on V times a cue (:mod:`reeb_torch.stages.rescoring`)."""

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
        all_boxes = self.device_tensor(grid.boxes, scores.device)
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
