"""ReebConfig: defaults, presets, validation, round trips."""

from __future__ import annotations

import dataclasses
import json
import math
import typing
from dataclasses import dataclass
from typing import Literal

import numpy as np
import pytest
import torch

from reeb_torch import PRESETS, ProposalGenerator, ReebConfig, get_preset
from reeb_torch import config as _config


def test_paper_constants_are_the_defaults():
    c = ReebConfig()
    assert (c.alpha, c.beta, c.top_k) == (0.6, 0.4, 2000)
    assert get_preset("paper").nms_iou == 0.7 and c.nms_iou == 0.75  # eq. 13 as printed / Edge Boxes' β
    assert (c.camera_height_m, c.vertical_fov_deg, c.horizontal_fov_deg, c.max_object_width_m) == (1.65, 35.0, 90.0, 2.55)
    assert c.entropy_sigma == 4.0 and c.region_overlap == 0.5


def test_paper_preset_follows_the_printed_text():
    p = ReebConfig.paper()
    assert p.scale == 1.0 and p.group_cell is None
    assert p.score_norm == "area" and p.road_score == "reward" and p.location_score == "paper"
    assert not p.thin_edges
    assert p.min_edge_score == 0.01 and p.ground_band is None and p.region_assign == "contained"


def test_presets_and_lookup():
    assert set(PRESETS) == {"default", "training-free", "paper"}
    # the class quota is a field a user sets: the default but for the output's shares per hinted class
    assert ReebConfig(class_quota={"Pedestrian": 0.3, "Cyclist": 0.1, "Truck": 0.05}) == ReebConfig().replace(
        class_quota=(("Pedestrian", 0.3), ("Cyclist", 0.1), ("Truck", 0.05)))
    # the default ranks with the shipped model; training-free is it without the learned part
    assert ReebConfig().ranker == "kitti" and get_preset("training-free") == ReebConfig().training_free()
    assert get_preset("training-free").ranker == "none"
    assert get_preset("paper").ranker == "none"  # the printed text
    # an unknown name (a removed preset or a former alias too) is one line naming the valid ones
    for name in ("nope", "refined", "class-quota", "default-no-regions", "persons", "paper-no-regions",
                 "training-free-no-regions"):
        with pytest.raises(ValueError) as info:
            get_preset(name)
        assert str(info.value) == f"unknown preset {name!r}; choose one of {', '.join(sorted(PRESETS))}"


def test_front_end_fields_come_from_the_field_declarations():
    """The fields that change the front end are marked where they are declared; the
    generator's cache key (``reeb tune``) reads the same names."""
    from reeb_torch import generator

    assert set(_config.FRONT_END_FIELDS) == set(generator.FRONT_END_FIELDS) == {
        "scale", "blur_sigma", "edge_threshold", "thin_edges", "remove_isolated",
        "group_cell", "vegetation_score", "road_score", "road_samples", "road_band",
        "road_tolerance", "seed", "shadow_score"}
    marked = [f.name for f in dataclasses.fields(ReebConfig) if f.metadata.get("stage") == "front"]
    assert list(_config.FRONT_END_FIELDS) == marked


def test_no_figures_in_the_configs_words():
    """Docstrings and messages say what a knob does, not how it scored (the record is in docs)."""
    import inspect
    import re

    text = inspect.getsource(_config)
    for pattern in (r"\bp [<=]? ?0\.\d", r"\+\d+ / [-−]\d+", r"\d+(\.\d+)? against \d", r"\.\./shared",
                    r"\b(dev|kept-apart) frames\b"):
        assert not re.search(pattern, text), pattern


@pytest.mark.parametrize(
    "field, value",
    [("scale", 0), ("scale", float("nan")), ("edge_threshold", 1.5), ("window_geometry", "blob"), ("group_cell", 1),
     ("road_band", (0.5, 0.5, 0.4, 1.0)), ("region_assign", "xor"), ("entropy_bins", 1), ("top_k", 0),
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


# -- strict types and ranges ---------------------------------------------------------------

BOOL_FIELDS = [f.name for f in dataclasses.fields(ReebConfig) if isinstance(getattr(ReebConfig(), f.name), bool)]


@pytest.mark.parametrize("field", BOOL_FIELDS)
@pytest.mark.parametrize("value", [None, "off", "false", "no", "", 0, 1, [True], 1.0, np.bool_(True)])
def test_bool_fields_take_only_bools(field, value):
    with pytest.raises(TypeError, match=rf"^ReebConfig\.{field} must be True or False \(a bool\), got "):
        ReebConfig(**{field: value})
    assert getattr(ReebConfig(**{field: False}), field) is False


@pytest.mark.parametrize(
    "field, value, error, expected",
    [
        ("top_k", True, TypeError, "an int (not a bool)"),  # bool is not an int
        ("kappa", 200, ValueError, "in (0, 8]"),  # used to overflow in (2(w+h))**kappa
        ("seed", None, TypeError, "an int"),
        ("seed", "a", TypeError, "an int"),
        ("seed", 1.5, TypeError, "an int"),
        ("seed", 2**64, ValueError, "in [-2**63, 2**64)"),
        ("entropy_sigma", True, TypeError, "a finite number"),
        ("min_edge_score", "x", TypeError, "a finite number"),
        ("min_edge_score", float("nan"), ValueError, "a finite number"),
        ("scale", 10**400, ValueError, "a finite number"),
        ("group_cell", 8.0, TypeError, "None or an int (not a bool)"),
        ("road_score", 3, TypeError, "one of 'reward', 'none'"),
        ("road_band", (0.3, 0.8, 0.7), ValueError, "a tuple of 4 finite numbers"),
        ("road_band", "0.3,0.8,0.7,1", TypeError, "a tuple of 4 finite numbers"),
        ("aspect_range", (0.5, None), TypeError, "a tuple of 2 finite numbers"),
        ("object_templates", ((1.0, 2.0, 3.0),), ValueError, "a tuple of tuples of 4 finite numbers"),
        ("object_templates", ((2.0, 1.0, 0.3, 0.4),), ValueError, "a non-empty tuple of (height_lo"),
        ("class_heights_m", (), ValueError, "a non-empty tuple of heights > 0"),
        ("vertical_fov_deg", 180, ValueError, "in (0, 180)"),
        ("alpha", -1, ValueError, ">= 0"),
        ("beta", -1, ValueError, ">= 0"),
    ],
)
def test_wrong_types_and_ranges_say_what_was_expected(field, value, error, expected):
    with pytest.raises(error) as info:
        ReebConfig(**{field: value})
    msg = str(info.value)
    assert msg.startswith(f"ReebConfig.{field} must be {expected}"), msg
    assert type(info.value) is error


def test_every_field_is_type_checked_from_its_annotation():
    """No field escapes the checker: an object of no known type is a TypeError naming it."""
    for f in dataclasses.fields(ReebConfig):
        with pytest.raises(TypeError, match=rf"^ReebConfig\.{f.name} must be "):
            ReebConfig(**{f.name: object()})


def test_numeric_fields_have_a_range():
    """Each int/float field declares its range (or is free by design): a new numeric field
    must say its range where it is declared (``_knob(default, "(0, 1]")``)."""
    free = {"min_edge_score"}  # a threshold on S: any finite number (negative keeps all)
    hints = typing.get_type_hints(ReebConfig)
    numeric = {n for n, h in hints.items()
               if h in (int, float) or set(typing.get_args(h)) - {type(None)} in ({int}, {float})}
    missing = sorted(numeric - set(_config._RANGES) - free)
    assert not missing, f"declare a range for {missing} in reeb_torch.config (_knob)"
    assert set(_config._RANGES) <= set(hints), "range table names a field ReebConfig no longer has"


def test_joint_conditions_name_all_their_fields():
    with pytest.raises(ValueError, match=r"^ReebConfig\.class_heights_m and ReebConfig\.class_weights must be of the same length"):
        ReebConfig(class_weights=(1.0,))
    with pytest.raises(ValueError, match=r"^ReebConfig\.class_heights_m and ReebConfig\.object_templates must be of the same length"):
        ReebConfig(object_templates=((1.0, 2.0, 0.5, 4.0),))
    # eq. 7 with a tiny object: region strips far narrower than a pixel would be thousands
    with pytest.raises(ValueError, match=r"ReebConfig\.max_object_width_m, .* at most 1024 regions"):
        ReebConfig(max_object_width_m=1e-3, region_width_round=None)


def test_new_fields_are_checked_from_their_annotations():
    """A subclass (as the next release's new fields) gets type checks without new code."""

    @dataclass(frozen=True)
    class Extended(ReebConfig):
        flag: bool = False
        mode: Literal["a", "b"] = "a"
        size: tuple[float, float] = (1.0, 2.0)
        count: int | None = None
        many: tuple[tuple[float, float], ...] = ((1.0, 2.0),)

    assert Extended(size=[3, 4], many=[[1, 2]]).size == (3.0, 4.0)
    for field, value, error in [("flag", "no", TypeError), ("mode", "c", ValueError), ("mode", 1, TypeError),
                                ("size", (1.0,), ValueError), ("count", 1.0, TypeError),
                                ("many", ((1.0, "x"),), TypeError)]:
        with pytest.raises(error, match=rf"^ReebConfig\.{field} must be "):
            Extended(**{field: value})
    with pytest.raises(ValueError, match=r"^ReebConfig\.top_k must be >= 1"):
        Extended(top_k=0)  # the range table still applies


def test_values_are_normalised_so_equal_settings_are_equal():
    a = ReebConfig(scale=1, road_band=[0.3, 0.8, 0.7, 1], top_k=np.int64(5), kappa=np.float32(1.5))
    b = ReebConfig(scale=1.0, road_band=(0.3, 0.8, 0.7, 1.0), top_k=5, kappa=1.5)
    assert a == b and hash(a) == hash(b) and a.fingerprint() == b.fingerprint()
    assert type(a.scale) is float and type(a.top_k) is int and type(a.road_band) is tuple
    assert all(type(v) is float for v in a.road_band)


def test_shape_fit_needs_one_template_per_class():
    with pytest.raises(ValueError, match="one template per class"):
        ReebConfig(object_templates=((1.0, 2.0, 0.5, 4.0),))


def test_json_round_trip_with_nested_tuples():
    c = ReebConfig(object_templates=((1.0, 2.0, 0.5, 4.0), (0.9, 2.2, 0.3, 1.4)), ground_band=None,
                   class_heights_m=(1.5, 1.72), class_weights=(1.0, 1.0))
    back = ReebConfig.from_dict(json.loads(json.dumps(c.to_dict())))
    assert back == c and hash(back) == hash(c) and back.fingerprint() == c.fingerprint()
    assert back.object_templates == ((1.0, 2.0, 0.5, 4.0), (0.9, 2.2, 0.3, 1.4))


@pytest.mark.parametrize("overrides, size, words", [
    (dict(blur_sigma=1000.0), (100, 120), ["blur_sigma=1000.0", "120x100", "scale=0.5"]),
    (dict(scale=0.01), (100, 120), ["scale=0.01", "120x100", "1x1 pixels", "blur_sigma=1.0"]),
    (dict(scale=0.05, blur_sigma=1.0), (40, 300), ["scale=0.05", "300x40", "15x2 pixels"]),
])
def test_a_config_too_large_for_the_image_is_a_value_error_at_the_door(overrides, size, words):
    """The kernel that cannot fit is reported with the image size, not as a padding
    RuntimeError from inside the blur; ``inspect`` checks the same."""
    g = ProposalGenerator(**overrides)
    x = torch.rand(1, 3, *size)
    for call in (lambda: g(x), lambda: g([x[0]]), lambda: g.inspect(x[0])):
        with pytest.raises(ValueError) as info:
            call()
        assert all(w in str(info.value) for w in words), str(info.value)
    # the boundary: σ = 1 reaches ceil(2σ) = 2 px, so a side of 3 working px runs and 2 does not
    reach = math.ceil(2 * 1.0)
    g = ProposalGenerator(min_window=4)  # scale 0.5: 2 input px per working px
    assert len(g(torch.rand(1, 3, 2 * (reach + 1), 40))) == 1
    with pytest.raises(ValueError, match="blur_sigma"):
        g(torch.rand(1, 3, 2 * reach, 40))


# -- each part's settings ---------------------------------------------------------------------


def test_every_field_is_in_exactly_one_part():
    """The parts partition the flat fields: each ``ReebConfig`` field is in one part, with the
    same annotation, and ``PART_OF`` maps it there."""
    fields = [f.name for f in dataclasses.fields(ReebConfig)]
    in_parts = [name for names in _config.PART_FIELDS.values() for name in names]
    assert sorted(in_parts) == sorted(fields) and len(set(in_parts)) == len(in_parts)
    hints = typing.get_type_hints(ReebConfig)
    for part, cls in _config.PARTS.items():
        for name, hint in typing.get_type_hints(cls).items():
            assert hint == hints[name], (part, name)
            assert _config.PART_OF[name] == part


@pytest.mark.parametrize("preset", sorted(PRESETS))
def test_a_configs_parts_hold_its_fields(preset):
    cfg = get_preset(preset)
    for part in _config.PARTS:
        settings = getattr(cfg, part)
        assert type(settings) is _config.PARTS[part]
        assert settings.to_dict() == {n: getattr(cfg, n) for n in _config.PART_FIELDS[part]}
        assert getattr(cfg, part) is settings  # made once per config
        assert cfg.replace(**{part: settings}) == cfg


def test_a_part_replaced_whole_changes_only_its_fields():
    cfg = ReebConfig()
    nms = cfg.nms.replace(top_k=123, nms_iou=0.6)
    out = cfg.replace(nms=nms)
    assert out.top_k == 123 and out.nms_iou == 0.6 and out.nms == nms
    assert out.replace(top_k=5, nms=nms).top_k == 5  # a field named beside its part wins
    assert ReebConfig.from_parts(nms=nms) == out
    assert out.fingerprint() == ReebConfig(top_k=123, nms_iou=0.6).fingerprint()
    with pytest.raises(TypeError, match="takes a NmsSettings, got WindowSettings"):
        cfg.replace(nms=cfg.windows)


def test_a_part_checks_its_fields_as_the_config_does():
    cfg = ReebConfig()
    with pytest.raises(ValueError, match=r"NmsSettings.nms_iou must be in \(0, 1\], got 2.0"):
        cfg.nms.replace(nms_iou=2.0)
    with pytest.raises(TypeError, match="WindowSettings.min_window must be an int"):
        cfg.windows.replace(min_window=True)
    assert cfg.windows.replace(aspect_range=[0.5, 2]).aspect_range == (0.5, 2.0)
    named = cfg.ranking.replace(class_quota={"Pedestrian": 0.2})
    assert named.class_quota == (("Pedestrian", 0.2),)
    assert named.class_shares(("Car", "Pedestrian")) == (0.0, 0.2)
    # the joint checks need the whole config: they run when a part goes back into one
    with pytest.raises(ValueError, match="class_heights_m and ReebConfig.class_weights"):
        cfg.replace(scores=cfg.scores.replace(class_weights=(1.0,)))


def test_a_config_file_may_give_its_fields_by_part():
    d = {"nms": {"top_k": 1000}, "windows": {"min_window": 12}, "scale": 1.0}
    assert ReebConfig.from_dict(d) == ReebConfig(top_k=1000, min_window=12, scale=1.0)
    with pytest.raises(ValueError, match="unknown NmsSettings field.*min_window"):
        ReebConfig.from_dict({"nms": {"min_window": 12}})
