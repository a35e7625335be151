"""reeb export --format detectron2 (reeb_torch.runs.export): the precomputed-proposals pickle.

detectron2 is not needed: the pickle is loaded with ``pickle`` and checked against what
detectron2's ``load_proposals_into_dataset`` reads (keys, per-image ``N×4`` XYXY_ABS boxes
and ``N`` logits, ``str(id)`` matching).
"""

from __future__ import annotations

import json
import pickle
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from reeb_torch.runs.cli import main
from reeb_torch.runs.export import ExportError, detectron2_proposals, image_ids, read_id_map
from reeb_torch.runs.output_files import open_writer
from reeb_torch.runs.rows import error_row, hint_names, result_row, round_like_python, significant_like_python


def _rows():
    g = torch.Generator().manual_seed(0)
    rows = []
    for name, n in [("data/000007.png", 5), ("other/000123.png", 3), ("data/000200.png", 0)]:
        xy = torch.rand(n, 2, generator=g) * 300
        wh = torch.rand(n, 2, generator=g) * 100 + 1
        boxes = torch.cat([xy, xy + wh], 1)
        scores = torch.sort(torch.rand(n, generator=g), descending=True).values
        rows.append(result_row(name, 640, 480, boxes, scores, "cfg"))
    rows.append(error_row("data/broken.png", "data/broken.png: corrupt", "cfg"))
    return rows


@pytest.fixture(params=["jsonl", "parquet"])
def results_file(request, tmp_path):
    if request.param == "parquet":
        pytest.importorskip("pyarrow")
    path = tmp_path / f"p.{request.param}"
    w = open_writer(path)
    w.write(_rows())
    w.commit()
    return path


def test_detectron2_pickle_round_trip(results_file, tmp_path):
    out = tmp_path / "proposals.pkl"
    res = CliRunner().invoke(main, ["export", str(results_file), "-o", str(out),
                                    "--format", "detectron2"])
    assert res.exit_code == 0, res.output
    assert "data/broken.png" in res.output and "1 failed images left out" in res.output
    d = pickle.loads(out.read_bytes())
    assert set(d) == {"ids", "boxes", "objectness_logits", "bbox_mode"}
    assert d["bbox_mode"] == 0                      # BoxMode.XYXY_ABS
    assert d["ids"] == ["000007", "000123", "000200"]
    rows = {Path(r["image"]).stem: r for r in _rows()}
    for i, boxes, logits in zip(d["ids"], d["boxes"], d["objectness_logits"]):
        ref = rows[i]
        assert boxes.dtype == np.float32 and boxes.shape == (len(ref["boxes"]), 4)
        assert logits.dtype == np.float32 and logits.shape == (len(ref["boxes"]),)
        # x1, y1, x2, y2 in pixels, in the rows' order (best first)
        np.testing.assert_allclose(boxes, np.asarray(ref["boxes"]).reshape(-1, 4), rtol=1e-6)
        np.testing.assert_allclose(logits, ref["scores"], rtol=1e-6)
        assert (boxes[:, 2] > boxes[:, 0]).all() and (boxes[:, 3] > boxes[:, 1]).all()
        assert (np.diff(logits) <= 0).all()
    # what detectron2 does with it: str(id) -> index
    assert {str(x): k for k, x in enumerate(d["ids"])}["000123"] == 1


def test_ids_from_a_mapping_file(results_file, tmp_path):
    mapping = tmp_path / "ids.json"
    mapping.write_text(json.dumps({"data/000007.png": 7, "000123.png": 123, "000200": 200}))
    out = tmp_path / "p.pkl"
    res = CliRunner().invoke(main, ["export", str(results_file), "-o", str(out),
                                    "--ids", str(mapping)])
    assert res.exit_code == 0, res.output
    assert pickle.loads(out.read_bytes())["ids"] == [7, 123, 200]
    csv = tmp_path / "ids.csv"
    csv.write_text("image,id\ndata/000007.png,a\nother/000123.png,b\n")
    res = CliRunner().invoke(main, ["export", str(results_file), "-o", str(out), "--ids", str(csv), "--overwrite"])
    assert res.exit_code == 2 and "000200.png: not in the id mapping" in res.output


def test_id_rules():
    assert image_ids(["a/000012.png"], id_type="int") == [12]
    with pytest.raises(ExportError, match="both get id"):
        image_ids(["a/x.png", "b/x.png"])
    with pytest.raises(ExportError, match="not an integer"):
        image_ids(["a/x.png"], id_type="int")
    # a resumed run: the ok row wins over an earlier error row of the same image
    rows = [error_row("a/1.png", "a/1.png: gone", "c"),
            result_row("a/1.png", 10, 10, torch.tensor([[0., 0., 5., 5.]]), torch.tensor([.5]), "c")]
    d, failed = detectron2_proposals(rows)
    assert d["ids"] == ["1"] and failed == [] and d["boxes"][0].shape == (1, 4)


def test_read_id_map_tsv(tmp_path):
    p = tmp_path / "m.tsv"
    p.write_text("a.png\t3\nb.png\tcar_b\n")
    assert read_id_map(p) == {"a.png": 3, "b.png": "car_b"}


def test_engine_ray_without_ray_says_how_to_install(monkeypatch, tmp_path):
    monkeypatch.setitem(sys.modules, "ray", None)     # import ray -> ImportError
    res = CliRunner().invoke(main, ["propose", str(Path(__file__).parents[2] / "examples" / "data"), "--engine", "ray",
                                    "-o", str(tmp_path / "o.parquet")])
    assert res.exit_code == 2
    assert 'pip install "reeb-torch[ray]"' in res.output


def _adversarial(rng: np.random.Generator) -> np.ndarray:
    """Values at and around decimal ties, powers of ten, zeros, signs, scales."""
    ties = np.arange(-2000, 2000) / 200.0  # x.xx5 and x.xx0: ties of round(v, 2) in decimal
    near = np.concatenate([ties + d for d in (0.0, 1e-12, -1e-12, 1e-9, -1e-9, 5e-7, -5e-7)])
    powers = np.array([10.0 ** k for k in range(-12, 8)])
    edges = np.concatenate([powers * f for f in (1.0, 0.9999995, 0.99999949999, 1.0000005, 0.99999950001)])
    ulps = np.concatenate([np.nextafter(x, np.inf) for x in (ties, edges)] + [np.nextafter(x, -np.inf) for x in (ties, edges)])
    specials = np.array([0.0, -0.0, 1e-300, -1e-300, 1e15, 1e22, 1e300, 2.675, 1.005, 0.125, 0.375, 1234.565, 0.0012345650])
    rand = np.concatenate([rng.uniform(-1300, 1300, 20000), 10.0 ** rng.uniform(-12, 6, 20000),
                           rng.integers(0, 2500, 5000) / 8.0, rng.integers(0, 2500, 5000) / 3.0])
    return np.concatenate([near, edges, -edges, ulps, specials, rand]).astype(np.float64)


def test_vectorised_rounding_is_pythons_bit_for_bit():
    vals = _adversarial(np.random.default_rng(7))
    for d in (0, 1, 2, 3, 6):
        got = round_like_python(vals, d)
        want = np.array([round(float(v), d) for v in vals])
        assert np.array_equal(got.view(np.int64), want.view(np.int64)), d  # -0.0 and 0.0 told apart too
    for digits in (3, 6, 9):
        got = significant_like_python(vals, digits)
        want = np.array([float(f"{float(v):.{digits}g}") for v in vals])
        assert np.array_equal(got.view(np.int64), want.view(np.int64)), digits


def test_result_row_numbers_are_those_of_round_and_format(sample_image):
    from reeb_torch import ProposalGenerator

    out = ProposalGenerator(top_k=500)([sample_image])[0]
    row = result_row("x.png", 1242, 375, out["boxes"], out["scores"], "cfg")
    assert row["boxes"] == [[round(v, 2) for v in r] for r in out["boxes"].double().tolist()]
    assert row["scores"] == [float(f"{v:.6g}") for v in out["scores"].double().tolist()]
    assert all(type(v) is float for r in row["boxes"] for v in r) and all(type(v) is float for v in row["scores"])
    empty = result_row("x.png", 4, 4, torch.zeros(0, 4), torch.zeros(0), "cfg")
    assert empty["boxes"] == [] and empty["scores"] == []
    assert row["labels"] is None  # no hints given
    hinted = result_row("x.png", 1242, 375, out["boxes"], out["scores"], "cfg", labels=["Car"] * len(out["boxes"]))
    assert hinted["labels"] == ["Car"] * len(out["boxes"])
    with pytest.raises(ValueError, match="1 labels for"):
        result_row("x.png", 1242, 375, out["boxes"], out["scores"], "cfg", labels=["Car"])
    assert error_row("x.png", "x.png: broken", "cfg")["labels"] is None


def test_hint_names_are_the_classes_of_the_labels():
    assert hint_names(("Car", "Pedestrian"), torch.tensor([1, 0, 1])) == ["Pedestrian", "Car", "Pedestrian"]
    assert hint_names(None, torch.tensor([0])) is None
    assert hint_names(("Car", "Pedestrian"), None) is None
