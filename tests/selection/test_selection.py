"""The window selection is composed of three parts, each built from its own settings."""

from __future__ import annotations

import warnings

import torch

from reeb_torch import ProposalGenerator, ReebConfig
from reeb_torch.config import CameraSettings, RegionSettings
from reeb_torch.selection import GridCache, RegionCut, Suppression, WindowScoring, WindowSelection


def test_each_part_holds_its_own_settings_and_the_parts_share_one_cache():
    cfg = ReebConfig(top_k=300, min_window=20, use_regions=False)
    sel = WindowSelection.from_config(cfg)
    assert isinstance(sel.scoring, WindowScoring) and isinstance(sel.cut, RegionCut)
    assert isinstance(sel.suppression, Suppression)
    assert sel.scoring.windows == cfg.windows and sel.scoring.scores == cfg.scores
    assert sel.cut.settings == cfg.regions and sel.cut.camera == cfg.camera
    assert sel.suppression.nms.top_k == 300
    assert sel.scoring.cache is sel.cut.cache is sel.suppression.cache
    assert not any(hasattr(part, "config") for part in (sel.scoring, sel.cut, sel.suppression))


def test_a_part_runs_on_its_settings_alone():
    """A part needs no ReebConfig: the region strips from region and camera settings."""
    cfg = ReebConfig()
    cut = RegionCut(RegionSettings(**cfg.regions.to_dict()), CameraSettings(**cfg.camera.to_dict()))
    bounds = cut.region_bounds(621)
    assert torch.equal(bounds, WindowSelection.from_config(cfg).cut.region_bounds(621))
    assert len(bounds) > 1 and int(bounds[0, 0]) == 0 and int(bounds[-1, 1]) == 621
    wider = RegionCut(cfg.regions.replace(max_object_width_m=5.0), cfg.camera).region_bounds(621)
    assert len(wider) < len(bounds)


def test_another_cut_goes_in_through_from_config(sample_image):
    """``from_config(cut=...)`` builds the region cut from its settings and the shared cache:
    a cut that passes nothing on leaves the generator with no proposals."""
    class Nothing(RegionCut):
        def region_cut(self, scores, grid, share):
            return torch.zeros_like(scores, dtype=torch.bool)

    cfg = ReebConfig(ranker="none")
    gen = ProposalGenerator(cfg)
    gen.selection = WindowSelection.from_config(cfg, cut=Nothing)
    assert isinstance(gen.selection.cut.cache, GridCache)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the generator warns once about an empty result
        out = gen([sample_image[:, :200, :400]])[0]
    assert out["boxes"].shape == (0, 4)
