"""ReebConfig: defaults, presets, validation, round trips."""

from __future__ import annotations

import pytest

from reeb_torch import PRESETS, ReebConfig, get_preset


def test_paper_constants_are_the_defaults():
    c = ReebConfig()
    assert (c.alpha, c.beta, c.nms_iou, c.top_k) == (0.6, 0.4, 0.7, 2000)
    assert (c.camera_height_m, c.vertical_fov_deg, c.horizontal_fov_deg, c.max_object_width_m) == (1.65, 35.0, 90.0, 2.55)
    assert c.entropy_sigma == 4.0 and c.region_overlap == 0.5


def test_paper_preset_follows_the_printed_text():
    p = ReebConfig.paper()
    assert p.scale == 1.0 and p.grouping == "connected" and p.group_cell is None
    assert p.score_norm == "area" and p.road_score == "reward" and p.location_score == "paper"
    assert p.road_combine == "and" and not p.thin_edges and not p.local_max
    assert p.min_edge_score == 0.01 and p.ground_band is None and p.region_assign == "contained"


def test_presets_and_lookup():
    assert set(PRESETS) == {"default", "default-no-regions", "paper", "paper-no-regions"}
    assert not get_preset("paper-no-regions").use_regions
    with pytest.raises(ValueError, match="unknown preset"):
        get_preset("nope")


@pytest.mark.parametrize(
    "field, value",
    [("scale", 0), ("scale", float("nan")), ("edge_threshold", 1.5), ("grouping", "blob"), ("group_cell", 1),
     ("road_band", (0.5, 0.5, 0.4, 1.0)), ("road_combine", "xor"), ("entropy_bins", 1), ("top_k", 0),
     ("nms_iou", 0), ("min_window", 2), ("size_ratio", 1.0), ("aspect_range", (2.0, 1.0)),
     ("location_score", "sky"), ("road_score", "maybe"), ("region_overlap", 0.0)],
)
def test_bad_values_name_the_field(field, value):
    with pytest.raises(ValueError, match=f"ReebConfig.{field}"):
        ReebConfig(**{field: value})


def test_dict_round_trip_and_fingerprint():
    c = ReebConfig(top_k=100)
    assert ReebConfig.from_dict(c.to_dict()) == c
    assert c.fingerprint() == ReebConfig(top_k=100).fingerprint() != ReebConfig().fingerprint()
    with pytest.raises(ValueError, match="unknown ReebConfig field"):
        ReebConfig.from_dict({"speed": 3})
