"""REEB's window scoring and selection: the windows scored, cut per region and suppressed,
for the generator's Table 1.

The stages in :mod:`reeb_torch.stages` are plain functions; this package is the glue that
hands them their settings (each part its own: :attr:`ReebConfig.windows <reeb_torch.ReebConfig.windows>`,
``scores``, ``camera``, ``regions``, ``nms``), picks the compiled (numba, CPU) or the
tensor (any device, the reference) path of each, and keeps what is worth keeping:

* :class:`ScoreMaps` (:mod:`.maps`): what the scores of one batch read (edge map, groups,
  road mask, grey image, green-pixel counts) and the tables built from them — integral
  images and the enclosed-sum prefix tables — each built on first use and kept for the
  batch, so the grid scorer and the learned ranking's features read one set;
* :class:`WindowSelection`: the window grid, scores, selection and suppression, composed of
  three parts, one a module — :class:`WindowScoring` (:mod:`.score`: the grid, V),
  :class:`RegionCut` (:mod:`.cut`: eq. 9), :class:`Suppression` (:mod:`.suppress`: eq. 13) —
  sharing what depends only on the image size (the score plan, the location and normaliser
  tables, the windows' boxes in input pixels), cached per window grid (:mod:`.grid_cache`).

The learned ranking of the candidates is :mod:`reeb_torch.ranker`.

Where the paths split (both give the same numbers, tested bit for bit):

===========  ==============================================  =====================================
step         compiled (CPU)                                  tensor ops (CUDA, and the rest)
===========  ==============================================  =====================================
scores       ``stages.scoring.score_grid_cpu``, when no       ``WindowScoring.score_torch``, one
             term needs per-window maps                      batch of ops per window size
             (``WindowScoring.compiled_scoring_applies``)
eq. 9's cut  ``stages.scoring.select_per_region_cpu``        ``RegionCut.select_torch``
NMS          ``stages.nms.nms_windows_cpu``                  ``stages.nms.nms_top_k_many``
===========  ==============================================  =====================================
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Callable

from torch import Tensor

from ..stages import windows as _windows
from .cut import RegionCut
from .grid_cache import PLAN_GRIDS, GridCache
from .maps import ScoreMaps
from .score import WindowScoring
from .suppress import Suppression

if TYPE_CHECKING:
    from ..config import CameraSettings, ReebConfig, RegionSettings

__all__ = ["ScoreMaps", "WindowSelection", "WindowScoring", "RegionCut", "Suppression", "GridCache", "PLAN_GRIDS"]


class WindowSelection:
    """The windows, scored, cut per region and suppressed: three parts, each built from its own
    settings, sharing one :class:`GridCache`.

    :class:`~reeb_torch.ProposalGenerator` calls, in Table 1's order, :meth:`regions`,
    :meth:`window_grid`, :meth:`score`, :meth:`select` and :meth:`suppress`. Another part tries
    another selection: ``benchmarks/selection_variants.py`` hands in a :class:`RegionCut`
    whose :meth:`~RegionCut.region_cut` differs.

    Args:
        scoring: the window grid and V (:class:`WindowScoring`).
        cut: the regions and eq. 9's cut (:class:`RegionCut`).
        suppression: eq. 13's NMS and the output (:class:`Suppression`).
    """

    def __init__(self, scoring: WindowScoring, cut: RegionCut, suppression: Suppression) -> None:
        self.scoring, self.cut, self.suppression = scoring, cut, suppression

    @classmethod
    def from_config(cls, config: ReebConfig,
                    cut: Callable[[RegionSettings, CameraSettings, GridCache], RegionCut] = RegionCut,
                    ) -> "WindowSelection":
        """The parts of ``config``, each given its own settings (``cut``: makes the region cut
        from its settings and the shared cache, :class:`RegionCut` or a variant of it)."""
        cache = GridCache()
        return cls(WindowScoring(config.windows, config.scores, config.camera, cache),
                   cut(config.regions, config.camera, cache), Suppression(config.nms, cache))

    def regions(self, gray: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """The region strips, each image's region entropy and share (:meth:`RegionCut.regions`)."""
        return self.cut.regions(gray)

    def window_grid(self, maps: ScoreMaps, bounds: Tensor) -> _windows.WindowGrid:
        """The windows of the batch's image size (:meth:`WindowScoring.window_grid`)."""
        return self.scoring.window_grid(maps, bounds)

    def score(self, maps: ScoreMaps, grid: _windows.WindowGrid) -> Tensor:
        """V of every window, ``float32 [B, N]`` (:meth:`WindowScoring.score`)."""
        return self.scoring.score(maps, grid)

    def select(self, scores: Tensor, grid: _windows.WindowGrid, share: Tensor) -> Tensor:
        """The candidates, ``bool [B, N]`` (:meth:`RegionCut.select`)."""
        return self.cut.select(scores, grid, share)

    def suppress(self, maps: ScoreMaps, grid: _windows.WindowGrid, chosen: Tensor, scores: Tensor,
                 windows_out: list[Tensor] | None = None, class_of: Tensor | None = None,
                 class_shares: tuple[float, ...] | None = None) -> list[dict[str, Tensor]]:
        """The proposals of each image (:meth:`Suppression.suppress`)."""
        return self.suppression.suppress(maps, grid, chosen, scores, windows_out, class_of, class_shares)
