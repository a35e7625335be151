"""The regions (Sec. 3.6, eqs. 2 and 5–9) and eq. 9's cut: each region passes on its best
windows, by its share of the budget."""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from ..config import CameraSettings, RegionSettings
from ..stages import entropy as _entropy
from ..stages import regions as _regions
from ..stages import scoring as _scoring
from ..stages import windows as _windows
from .grid_cache import GridCache

__all__ = ["RegionCut"]


class RegionCut:
    """The regions, their entropy and share of the budget, and eq. 9's cut of the scored
    windows (compiled on the CPU, a stable sort elsewhere).

    Args:
        regions: the strips, their entropy and the budget.
        camera: the camera's height and opening angles (the strips' width, eqs. 5-7).
        cache: the per-grid tables, shared with the other parts (a new one if None).
    """

    def __init__(self, regions: RegionSettings, camera: CameraSettings, cache: GridCache | None = None) -> None:
        self.settings, self.camera = regions, camera
        self.cache = cache if cache is not None else GridCache()

    def regions(self, gray: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Sec. 3.6, eqs. 2 and 9: the region strips ``int64 (R, 2)`` (working columns), each
        image's region entropy ``(B, R)`` and its share of the window budget ``(B, R)``."""
        b = gray.shape[0]
        bounds = self.region_bounds(gray.shape[-1])
        if self.settings.use_regions:
            entropy = _entropy.region_entropy(gray, bounds, self.settings.entropy_bins)
            share = _entropy.proposal_share(entropy, self.settings.entropy_sigma)
        else:  # one region, the whole image: entropy is not applicable (Sec. 4.2)
            entropy = torch.zeros(b, 1, device=gray.device)
            share = torch.ones(b, 1, device=gray.device)
        return bounds, entropy, share

    def region_bounds(self, width: int) -> Tensor:
        """Sec. 3.6, eqs. 5–8: the region strips of an image ``width`` working pixels wide,
        ``int64 (R, 2)`` (first and end column), or one strip without ``use_regions``."""
        if not self.settings.use_regions:
            return torch.tensor([[0, width]])
        cam = self.camera
        frac = _regions.region_width_fraction(cam.camera_height_m, cam.vertical_fov_deg, cam.horizontal_fov_deg,
                                              self.settings.max_object_width_m, self.settings.region_width_round)
        return _regions.region_bounds(width, frac, self.settings.region_overlap)

    def select(self, scores: Tensor, grid: _windows.WindowGrid, share: Tensor) -> Tensor:
        """The candidates, ``bool [B, N]``, of the windows scored ``scores`` (``float32 [B, N]``)
        with the regions' shares ``share`` (``[B, R]``): :meth:`region_cut` (a subclass may
        change it)."""
        return self.region_cut(scores, grid, share)

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
        r = self.settings
        per_region = r.candidates_per_region if r.use_regions else r.candidates_without_regions
        return (share * per_region).round().long()

    def _region_members(self, grid: _windows.WindowGrid) -> tuple[np.ndarray, np.ndarray]:
        """The windows of every region, concatenated (``int64``), and where each region starts."""
        def build() -> tuple[np.ndarray, np.ndarray]:
            lists = [t.numpy().astype(np.int64) for t in grid.region_windows]
            starts = np.cumsum([0] + [len(x) for x in lists]).astype(np.int64)
            return (np.concatenate(lists) if lists else np.zeros(0, np.int64), starts)

        return self.cache.grid_cached(("members",), grid, build)

    def select_torch(self, scores: Tensor, grid: _windows.WindowGrid, budget: Tensor) -> Tensor:
        """:meth:`region_cut` as one stable sort per region (any device). Ties at the cut go to
        the lower window index, as in the CPU pass (``topk`` leaves their order unspecified,
        and windows without edges all score 0, so ties are common)."""
        chosen = torch.zeros_like(scores, dtype=torch.uint8)
        for r, idx_cpu in enumerate(grid.region_windows):
            k = min(int(idx_cpu.numel()), int(budget[:, r].max()))
            if k == 0:
                continue
            idx = self.cache.device_tensor(idx_cpu, scores.device)
            vals, pos = scores[:, idx].sort(dim=1, descending=True, stable=True)  # ties: lower index first
            vals, pos = vals[:, :k], pos[:, :k]
            ok = torch.isfinite(vals) & (torch.arange(k, device=scores.device)[None] < budget[:, r: r + 1])
            chosen.scatter_add_(1, idx[pos], ok.to(torch.uint8))
        return chosen > 0
