"""REEB's window scoring and selection: the windows scored, cut per region and suppressed,
for the generator's Table 1.

The stages in :mod:`reeb_torch.stages` are plain functions; this package is the glue that
maps a :class:`~reeb_torch.ReebConfig` onto them, picks the compiled (numba, CPU) or the
tensor (any device, the reference) path of each, and keeps what is worth keeping:

* :class:`ScoreMaps` (:mod:`.maps`): what the scores of one batch read (edge map, groups,
  road mask, grey image, green-pixel counts) and the tables built from them — integral
  images and the enclosed-sum prefix tables — each built on first use and kept for the
  batch, so the grid scorer and the learned ranking's features read one set;
* :class:`WindowSelection`: one config's window grid, scores, selection and suppression,
  one part a module — :mod:`.score` (the grid, V), :mod:`.cut` (eq. 9), :mod:`.suppress`
  (eq. 13) — with what depends only on the image size (the score plan, the location and normaliser tables, the windows' boxes
  in input pixels) cached per window grid (:mod:`.cache`).

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

from .grid_cache import PLAN_GRIDS, GridCache
from .cut import RegionCut
from .maps import ScoreMaps
from .score import WindowScoring
from .suppress import Suppression

__all__ = ["ScoreMaps", "WindowSelection", "GridCache", "PLAN_GRIDS"]


class WindowSelection(WindowScoring, RegionCut, Suppression):
    """One config's windows, scored, cut per region and suppressed.

    :class:`~reeb_torch.ProposalGenerator` calls, in Table 1's order, :meth:`window_grid`,
    :meth:`score`, :meth:`select` and :meth:`suppress`. A subclass may change a step to try another selection (the generator's
    ``selection`` attribute takes it; ``benchmarks/selection_variants.py`` changes
    :meth:`region_cut`).

    Args:
        config: the settings (:class:`~reeb_torch.ReebConfig`).
    """
