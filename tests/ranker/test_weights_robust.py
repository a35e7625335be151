"""Weights files that are damaged, hand-edited or hostile: refused at load in one line naming
the file and what is wrong, before anything is allocated; weights that are not finite are
never written, and never give a row with a score that is not a number."""

from __future__ import annotations

import errno
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from reeb_torch.ranker import BoxRanker, RankerWeightsError, load_ranker, save_ranker, shipped_path

REPO = Path(__file__).resolve().parents[2]
SAMPLE = REPO / "examples" / "data" / "kitti_000001.png"


def _shipped() -> tuple[dict[str, torch.Tensor], dict]:
    from safetensors import safe_open
    from safetensors.torch import load_file

    path = str(shipped_path("kitti"))
    with safe_open(path, framework="pt") as f:
        meta = json.loads(f.metadata()["reeb-ranker"])
    return load_file(path), meta


def _edited(path: Path, edit) -> Path:
    """The shipped weights, edited by ``edit(tensors, meta)`` (which may return the metadata
    text to write instead), written to ``path``."""
    from safetensors.torch import save_file

    tensors, meta = _shipped()
    raw = edit(tensors, meta)
    save_file(tensors, str(path), metadata={"reeb-ranker": raw if isinstance(raw, str) else json.dumps(meta)})
    return path


def _set(tensor: str, index, value: float):
    def edit(t, m):
        t[tensor][index] = value
    return edit


def _meta(key: str, value):
    def edit(t, m):
        m[key] = value
    return edit


_COLUMNS = len(load_ranker("kitti").feature_names)  # the shipped model's feature columns


def _shape(t, m):
    t["members.0.0.weight"] = t["members.0.0.weight"][:, :-1].contiguous()


def _extra(t, m):
    t["members.1.0.weight"] = torch.zeros(2, 2)


def _missing(t, m):
    del t["classifier.2.bias"]


def _ints(t, m):
    t["mean"] = torch.zeros(len(t["mean"]), dtype=torch.int32)


CASES = [
    # 1: NaN or inf weights, everywhere or in one element, mean included
    (_set("members.0.0.weight", slice(None), float("nan")),
     rf"tensor 'members\.0\.0\.weight' holds {64 * _COLUMNS} values that are not finite \(element 0 is nan\), "
     r"expected finite numbers"),
    (_set("members.0.2.bias", 3, float("inf")), r"tensor 'members\.0\.2\.bias' holds 1 value that is not finite "
     r"\(element 3 is inf\)"),
    (_set("mean", 0, float("nan")), r"tensor 'mean' holds 1 value that is not finite"),
    (_set("scale", 5, float("-inf")), r"tensor 'scale' holds 1 value that is not finite"),
    # 3: metadata that would allocate without bound
    (_meta("members", 1_000_000_000), r"metadata field 'members' is 1000000000, expected an integer from 1 to 256"),
    (_meta("hidden", [10 ** 9, 64]), r"metadata field 'hidden' is 1000000000, expected an integer from 1 to 65536"),
    (_meta("hidden", [64] * 100), r"metadata field 'hidden' is \[64, .*expected a list of 1 to 16 layer widths"),
    (_meta("members", True), r"metadata field 'members' is true, expected an integer"),
    # 7: a scale of zeros (features are divided by it)
    (_set("scale", slice(None), 0.0), r"tensor 'scale' is 0\.0 for feature 'log_height', expected positive values"),
    # 8: metadata that is JSON but no object; feature names that are not strings
    (lambda t, m: "[1, 2]", r"its 'reeb-ranker' metadata is a JSON array, expected a JSON object"),
    (lambda t, m: "{not json", r"its 'reeb-ranker' metadata is not valid JSON"),
    (_meta("feature_names", list(range(47))), r"metadata field 'feature_names' is \[0, 1, .*expected a list of "
     r"1 to 4096 names \(non-empty strings\)"),
    (_meta("config", "camera.json"), r"its 'config' metadata is not a JSON object \(a JSON string\)"),
    # 12: messages that name the field or tensor and what was expected
    (_shape, rf"tensor 'members\.0\.0\.weight' has shape \[64, {_COLUMNS - 1}\], expected \[64, {_COLUMNS}\] from the "
     r"metadata"),
    (_meta("hidden", "abc"), r"metadata field 'hidden' is \"abc\", expected a list of 1 to 16 layer widths "
     r"\(integers from 1 to 65536\)"),
    (_meta("classes", 5), r"metadata field 'classes' is 5, expected a list of 2 to 1024 names"),
    (_extra, r"tensor 'members\.1\.0\.weight' is not one of the model's \(1 unexpected\)"),
    (_missing, r"tensor 'classifier\.2\.bias' is missing"),
    (_ints, r"tensor 'mean' is I32, expected floating point"),
    (_meta("prefilter", [0]), r"metadata field 'prefilter' is 0, expected an integer from 1 to 65536"),
    # duplicate classes
    (_meta("classes", ["Car", "Car", "Cyclist", "Truck"]), r"metadata field 'classes' names 'Car' more than once, "
     r"expected distinct names"),
]


@pytest.mark.parametrize("edit,message", CASES, ids=[f"case{i}" for i in range(len(CASES))])
def test_a_damaged_weights_file_is_one_line_naming_the_file_and_the_fault(tmp_path, edit, message):
    path = _edited(tmp_path / "edited.safetensors", edit)
    with pytest.raises(RankerWeightsError, match=message) as e:
        load_ranker(str(path))
    assert "\n" not in str(e.value) and str(path) in str(e.value)


def test_a_folder_given_as_the_ranker_is_called_a_folder(tmp_path):
    with pytest.raises(RankerWeightsError, match="a folder, not a weights file") as e:
        load_ranker(str(tmp_path))
    assert "no such file" not in str(e.value)


def test_the_generator_refuses_non_finite_weights(tmp_path):
    from reeb_torch import ProposalGenerator, ReebConfig

    path = _edited(tmp_path / "nan.safetensors", _set("mean", 0, float("nan")))
    with pytest.raises(RankerWeightsError, match="tensor 'mean' holds 1 value that is not finite"):
        ProposalGenerator(ReebConfig(ranker=str(path)))


def test_propose_with_nan_weights_exits_2_in_one_line_and_writes_nothing(tmp_path):
    _edited(tmp_path / "nan.safetensors", _set("members.0.0.weight", slice(None), float("nan")))
    r = subprocess.run([sys.executable, "-m", "reeb_torch.runs.cli", "propose", str(SAMPLE), "--set",
                        "ranker=nan.safetensors", "-o", "o.jsonl", "--device", "cpu"], cwd=tmp_path,
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in r.stderr, r.stderr
    assert "nan.safetensors" in lines[0] and "'members.0.0.weight'" in lines[0] and "not finite" in lines[0]
    assert not (tmp_path / "o.jsonl").exists()


def _invoke(args, cwd: Path, monkeypatch):
    from click.testing import CliRunner

    from reeb_torch.runs.cli import main

    monkeypatch.chdir(cwd)
    res = CliRunner().invoke(main, [str(a) for a in args])
    assert res.exception is None or isinstance(res.exception, SystemExit), repr(res.exception)
    return res


def test_a_config_naming_bad_weights_is_one_line(tmp_path, monkeypatch):
    conc = tmp_path / "conc"
    conc.mkdir()
    _edited(conc / "abc.safetensors", _meta("hidden", "abc"))
    (conc / "c.json").write_text(json.dumps({"ranker": "abc.safetensors"}))
    res = _invoke(["propose", SAMPLE, "--config", "conc/c.json", "-o", "o.jsonl", "--device", "cpu"], tmp_path,
                  monkeypatch)
    assert res.exit_code == 2, res.output
    line = res.output.strip().splitlines()[-1]
    assert "abc.safetensors" in line and "metadata field 'hidden' is \"abc\"" in line


def test_bad_json_in_a_setting_is_called_bad_json_naming_the_setting(tmp_path, monkeypatch):
    res = _invoke(["propose", SAMPLE, "--set", 'class_quota=[["Car", 0.5]', "-o", "o.jsonl", "--device", "cpu"],
                  tmp_path, monkeypatch)
    assert res.exit_code == 2, res.output
    assert "class_quota=" in res.output and "not valid JSON" in res.output and "type" not in res.output.lower()


def _model() -> BoxRanker:
    return BoxRanker(load_ranker("kitti").feature_names, (8,), prefilter=(4,))


def test_non_finite_weights_are_never_written(tmp_path):
    out = tmp_path / "w.safetensors"
    out.write_bytes(b"old")
    model = _model()
    with torch.no_grad():
        model.members[0][0].weight[0, 0] = float("nan")
    with pytest.raises(RankerWeightsError, match="not written: tensor 'members.0.0.weight' holds 1 value"):
        save_ranker(model, out)
    assert out.read_bytes() == b"old" and os.listdir(tmp_path) == ["w.safetensors"]


def test_a_failed_write_leaves_the_old_weights(tmp_path, monkeypatch):
    from reeb_torch.ranker import weights as W

    out = save_ranker(_model(), tmp_path / "w.safetensors")
    old = out.read_bytes()

    def full(fd):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(W.os, "fsync", full)
    with pytest.raises(OSError, match="No space left"):
        save_ranker(BoxRanker(load_ranker("kitti").feature_names, (4,)), out)
    assert out.read_bytes() == old and os.listdir(tmp_path) == ["w.safetensors"]


def test_a_row_never_holds_a_score_that_is_not_a_number():
    from reeb_torch.runs.rows import result_row

    row = result_row("x.png", 10, 10, torch.tensor([[0.0, 0, 5, 5], [1, 1, 4, 4]]),
                     torch.tensor([1.0, float("nan")]), "cfg")
    assert row["status"].startswith("error: ") and "not finite" in row["status"] and row["scores"] == []

    def refuse(token):
        raise AssertionError(f"{token} in a row")

    json.loads(json.dumps(row), parse_constant=refuse)


def test_export_of_a_damaged_results_file_says_it_exports_nothing(tmp_path):
    from reeb_torch.runs.export import ExportError, read_rows

    p = tmp_path / "r.jsonl"
    p.write_text('{"image": "a.png", "status": "ok", "boxes": [], "scores": []}\nnot json\n')
    with pytest.raises(ExportError) as e:
        read_rows(p)
    assert "skipped" not in str(e.value) and "nothing exported" in str(e.value) and f"{p}:2" in str(e.value)
