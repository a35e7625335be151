"""``reeb_torch.config_text``: REEB's settings from text, as scripts read them. References:
the fields of the ReebConfig made, against the preset's and the values given."""

from __future__ import annotations

import json

import pytest

from reeb_torch import get_preset
from reeb_torch.config_text import SettingError, config_from, parse_sets, read_config_file


def test_each_later_source_overrides_the_earlier(tmp_path):
    f = tmp_path / "c.json"
    f.write_text(json.dumps({"nms_iou": 0.6, "top_k": 500, "use_regions": False}))
    cfg = config_from("training-free", f, ["nms_iou=0.65"], 300)
    assert (cfg.nms_iou, cfg.top_k, cfg.use_regions) == (0.65, 300, False)
    assert cfg.edge_threshold == get_preset("training-free").edge_threshold  # the rest: the preset's


def test_pairs_are_read_by_their_fields_type():
    got = parse_sets(["use_regions=off", "shadow_score=none", "ranker=1", "nms_iou=0.6",
                      'class_quota={"Pedestrian": 0.2}', "ground_band=null"])
    assert got == {"use_regions": False, "shadow_score": "none", "ranker": "1", "nms_iou": 0.6,
                   "class_quota": {"Pedestrian": 0.2}, "ground_band": None}


def test_a_field_may_be_named_with_its_part():
    assert parse_sets(["nms.top_k=500", "scores.shadow_score=none", "windows.min_window=12"]) == \
        {"top_k": 500, "shadow_score": "none", "min_window": 12}
    assert config_from("default", None, ["nms.top_k=7"]).top_k == 7
    with pytest.raises(SettingError, match="'nmx' is not a part of the settings; the parts are front_end"):
        parse_sets(["nmx.top_k=1"])
    with pytest.raises(SettingError, match=r"the part nms has no field 'min_window' \(it is in windows\)"):
        parse_sets(["nms.min_window=3"])


def test_a_saved_record_reads_as_its_config_and_its_ranker_from_beside_it(tmp_path):
    f = tmp_path / "cam.json"
    f.write_text(json.dumps({"config": {"horizon": 0.45, "ranker": "mine.safetensors"}, "fit": {}}))
    assert read_config_file(f) == {"horizon": 0.45, "ranker": str(tmp_path / "mine.safetensors")}


@pytest.mark.parametrize("args, option, reason", [
    ((None, ["nms_iou"]), "--set", "expected FIELD=VALUE"),
    ((None, ["use_regions=maybe"]), "--set", "is a yes/no setting"),
    ((None, ["class_quota=[0.2"]), "--set", "not valid JSON"),
    ((None, ["bogus=1"]), "--config/--set/--top-k", "unknown ReebConfig field(s): bogus"),
    (("missing.json", []), "--config", "missing.json: cannot read"),
])
def test_refusals_name_what_was_wrong_and_where_it_came_from(args, option, reason):
    with pytest.raises(SettingError) as e:
        config_from("default", *args)
    assert e.value.option == option and reason in str(e.value), str(e.value)
