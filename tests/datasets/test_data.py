"""Tests of reeb_torch.datasets.kitti: KITTI readers and dataset, on synthetic folders and real files."""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import numpy as np
import pytest
import torch

from tests.conftest import DATA
from reeb_torch.camera import camera_intrinsics, read_kitti_calib
from reeb_torch.datasets.kitti import (
    DEFAULT_CLASSES,
    KittiDataset,
    collate_keep_sizes,
    read_kitti_labels,
)

REPO = Path(__file__).resolve().parents[2]
EXAMPLES = REPO / "examples" / "data"
KITTI = DATA / "kitti"

LABELS_A = """\
Car 0.00 0 -1.58 587.01 173.33 614.12 200.12 1.65 1.67 3.64 -0.65 1.71 46.70 -1.59
Pedestrian 0.00 1 0.21 423.17 173.67 433.17 224.03 1.60 0.38 0.30 -5.99 1.85 32.25 0.03
DontCare -1 -1 -10 500.00 170.00 520.00 190.00 -1 -1 -1 -1000 -1000 -1000 -10
Van 0.00 0 1.84 300.00 150.00 400.00 200.00 2.00 1.80 4.50 -3.00 1.60 20.00 1.70
Cyclist 0.50 2 -0.20 10.00 20.00 30.50 60.25 1.70 0.60 1.80 5.00 1.70 15.00 0.10
"""
LABELS_B = """\
Truck 0.00 0 0.00 1.00 2.00 3.00 4.00 3.00 2.50 8.00 0.00 1.70 30.00 0.00

Misc 0.00 0 0.00 5.00 6.00 7.00 8.00 1.00 1.00 1.00 0.00 1.70 30.00 0.00
"""
CALIB = """\
P0: 1 0 2 0 0 3 4 0 0 0 1 0
P2: 721.5377 0 609.5593 44.85728 0 721.5377 172.854 0.2163791 0 0 1 0.002745884
R0_rect: 1 0 0 0 1 0 0 0 1
Tr_velo_to_cam: 0 -1 0 0 0 0 -1 0 1 0 0 0
"""


def _write_image(path: Path, h: int, w: int) -> None:
    import cv2

    rng = np.random.default_rng(h * 1000 + w)
    assert cv2.imwrite(str(path), rng.integers(0, 256, (h, w, 3), dtype=np.uint8))


def _make_folder(root: Path, layout: str, labels: bool = True, calib: bool = True) -> Path:
    img, lab = ("images", "labels") if layout == "project" else ("image_2", "label_2")
    (root / img).mkdir(parents=True)
    _write_image(root / img / "000001.png", 20, 30)
    _write_image(root / img / "000000.png", 240, 640)  # the labels (LABELS_A) lie inside it
    _write_image(root / img / "000002.png", 16, 16)
    (root / img / "notes.txt").write_text("not an image")
    if labels:
        (root / lab).mkdir()
        (root / lab / "000000.txt").write_text(LABELS_A)
        (root / lab / "000001.txt").write_text(LABELS_B)
        (root / lab / "000002.txt").write_text("")
    if calib:
        (root / "calib").mkdir()
        for i in range(3):
            (root / "calib" / f"00000{i}.txt").write_text(CALIB)
    return root


# -- labels ----------------------------------------------------------------------------


def test_read_labels_fields(tmp_path):
    p = tmp_path / "l.txt"
    p.write_text(LABELS_A)
    objs = read_kitti_labels(p)
    assert [o.type for o in objs] == ["Car", "Pedestrian", "DontCare", "Van", "Cyclist"]
    cyc = objs[4]
    assert cyc.truncated == 0.5 and cyc.occluded == 2 and cyc.alpha == -0.2
    assert cyc.box == (10.0, 20.0, 30.5, 60.25)
    assert cyc.dimensions == (1.7, 0.6, 1.8)
    assert cyc.location == (5.0, 1.7, 15.0)
    assert cyc.rotation_y == 0.1 and cyc.score is None
    assert [o.type for o in read_kitti_labels(p, classes=["Car", "Cyclist"])] == ["Car", "Cyclist"]


def test_read_labels_result_file_with_score(tmp_path):
    p = tmp_path / "r.txt"
    p.write_text("Car -1 -1 0.1 1 2 3 4 1.5 1.6 3.9 0 1 10 0.2 0.87\n")
    assert read_kitti_labels(p)[0].score == pytest.approx(0.87)


def test_read_labels_real_example():
    objs = read_kitti_labels(EXAMPLES / "kitti_000001.txt")
    assert objs and all(len(o.box) == 4 for o in objs)


@pytest.mark.parametrize(
    "bad",
    [
        "Car 0.00 0 -1.58 587.01 173.33 614.12 200.12 1.65 1.67 3.64 -0.65 1.71 46.70",
        "Car 0.00 0 -1.58 587.01 oops 614.12 200.12 1.65 1.67 3.64 -0.65 1.71 46.70 -1.59",
    ],
)
def test_read_labels_malformed_names_file_and_line(tmp_path, bad):
    p = tmp_path / "broken.txt"
    p.write_text(LABELS_A.splitlines()[0] + "\n\n" + bad + "\n")
    with pytest.raises(ValueError, match=r"broken\.txt:3:"):
        read_kitti_labels(p)


def test_read_labels_missing_file(tmp_path):
    with pytest.raises(FileNotFoundError):
        read_kitti_labels(tmp_path / "nope.txt")


# -- calib -----------------------------------------------------------------------------


def test_read_calib_real_example():
    calib = read_kitti_calib(EXAMPLES / "kitti_000001_calib.txt")
    assert set(calib) == {"P0", "P1", "P2", "P3", "R0_rect", "Tr_velo_to_cam", "Tr_imu_to_velo"}
    P2 = calib["P2"]
    assert P2.shape == (3, 4) and P2.dtype == torch.float64
    assert P2[0, 0].item() == 721.5377
    assert P2[2, 3].item() == pytest.approx(2.745884e-03)
    assert calib["R0_rect"].shape == (3, 3)
    assert calib["Tr_velo_to_cam"].shape == (3, 4)
    # the same numbers another way: plain text parsing with numpy
    line = next(
        ln for ln in (EXAMPLES / "kitti_000001_calib.txt").read_text().splitlines()
        if ln.startswith("P2:")
    )
    ref = np.array(line.split()[1:], dtype=np.float64).reshape(3, 4)
    np.testing.assert_array_equal(P2.numpy(), ref)
    fx, fy, cx, cy = camera_intrinsics(P2)
    assert (fx, fy, cx, cy) == (721.5377, 721.5377, 609.5593, 172.854)


def test_read_calib_missing_keys_and_no_colon(tmp_path):
    p = tmp_path / "c.txt"
    p.write_text("P2: 1 0 2 0 0 3 4 0 0 0 1 0\nR_rect 1 0 0 0 1 0 0 0 1\nextra: 1 2\n\n")
    calib = read_kitti_calib(p)
    assert set(calib) == {"P2", "R_rect", "extra"}
    assert calib["R_rect"].shape == (3, 3) and calib["extra"].shape == (2,)
    assert camera_intrinsics(calib["P2"]) == (1.0, 3.0, 2.0, 4.0)


@pytest.mark.parametrize("bad", ["P2: 1 2 3", "R0_rect: 1 0 0 0 x 0 0 0 1", "Tr_velo_to_cam:"])
def test_read_calib_malformed_names_file_and_line(tmp_path, bad):
    p = tmp_path / "calib_bad.txt"
    p.write_text("P0: 1 0 2 0 0 3 4 0 0 0 1 0\n" + bad + "\n")
    with pytest.raises(ValueError, match=r"calib_bad\.txt:2:"):
        read_kitti_calib(p)


def test_camera_intrinsics_rejects_bad_shape():
    with pytest.raises(ValueError, match="3x4"):
        camera_intrinsics(torch.zeros(4, 4))


# -- dataset ---------------------------------------------------------------------------


@pytest.mark.parametrize("layout", ["project", "kitti"])
def test_dataset_both_layouts(tmp_path, layout):
    ds = KittiDataset(_make_folder(tmp_path / "d", layout))
    assert len(ds) == 3 and ds.ids == ["000000", "000001", "000002"]
    item = ds[0]
    assert item["image"].dtype == torch.uint8 and item["image"].shape == (3, 240, 640)
    assert item["image_id"] == "000000" and item["path"].endswith("000000.png")
    # DontCare and Van dropped; classes are the paper's four
    assert item["class_names"] == ["Car", "Pedestrian", "Cyclist"]
    assert item["labels"].tolist() == [0, 1, 2] and item["labels"].dtype == torch.int64
    assert item["boxes"].dtype == torch.float32 and item["boxes"].shape == (3, 4)
    torch.testing.assert_close(item["boxes"][2], torch.tensor([10.0, 20.0, 30.5, 60.25]))
    assert item["occluded"].tolist() == [0, 1, 2]
    assert item["calib"]["P2"][0, 0].item() == 721.5377
    # Misc dropped, Truck kept (index 3); empty label file: empty, well-shaped targets
    assert ds[1]["labels"].tolist() == [3]
    empty = ds[2]
    assert empty["boxes"].shape == (0, 4) and empty["labels"].shape == (0,)
    assert ds[-1]["image_id"] == "000002"


def test_dataset_kitti_training_subfolder(tmp_path):
    _make_folder(tmp_path / "k" / "training", "kitti")
    assert len(KittiDataset(tmp_path / "k")) == 3


def test_dataset_class_filter_and_subset(tmp_path):
    root = _make_folder(tmp_path / "d", "project")
    ds = KittiDataset(root, classes=("Van", "Car"), ids=["000001", "000000"])
    assert ds.ids == ["000000", "000001"]
    assert ds[0]["class_names"] == ["Car", "Van"] and ds[0]["labels"].tolist() == [1, 0]
    assert len(ds[1]["boxes"]) == 0
    # DontCare is never a target, even when asked for
    ds = KittiDataset(root, classes=("DontCare", "Car"))
    assert ds[0]["class_names"] == ["Car"]
    assert KittiDataset(root, limit=2).ids == ["000000", "000001"]
    with pytest.raises(ValueError, match="000009"):
        KittiDataset(root, ids=["000009"])


def test_dataset_images_only(tmp_path):
    ds = KittiDataset(_make_folder(tmp_path / "d", "kitti", labels=False, calib=False))
    item = ds[1]
    assert item["calib"] is None and item["boxes"].shape == (0, 4) and item["class_names"] == []


def test_dataset_transform(tmp_path):
    def flip(sample):
        w = sample["image"].shape[-1]
        sample["image"] = sample["image"].flip(-1)
        b = sample["boxes"].clone()
        sample["boxes"] = torch.stack([w - b[:, 2], b[:, 1], w - b[:, 0], b[:, 3]], dim=1)
        return sample

    root = _make_folder(tmp_path / "d", "project")
    plain, flipped = KittiDataset(root)[0], KittiDataset(root, transform=flip)[0]
    assert torch.equal(flipped["image"], plain["image"].flip(-1))
    assert flipped["boxes"][0, 0].item() == pytest.approx(640 - 614.12, abs=1e-3)


def test_dataset_errors(tmp_path):
    with pytest.raises(ValueError, match="no such folder"):
        KittiDataset(tmp_path / "missing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match=r"empty.*images/.*image_2/"):
        KittiDataset(tmp_path / "empty")
    (tmp_path / "noimg" / "image_2").mkdir(parents=True)
    with pytest.raises(ValueError, match=r"image_2: no images"):
        KittiDataset(tmp_path / "noimg")
    root = _make_folder(tmp_path / "d", "project")
    (root / "labels" / "000001.txt").unlink()
    with pytest.raises(ValueError, match=r"no label file for ids \['000001'\]"):
        KittiDataset(root)


def test_collate_keeps_sizes(tmp_path):
    ds = KittiDataset(_make_folder(tmp_path / "d", "project"))
    loader = torch.utils.data.DataLoader(ds, batch_size=3, collate_fn=collate_keep_sizes)
    batch = next(iter(loader))
    assert [tuple(im.shape) for im in batch["image"]] == [(3, 240, 640), (3, 20, 30), (3, 16, 16)]
    assert [len(b) for b in batch["boxes"]] == [3, 1, 0]
    assert batch["image_id"] == ["000000", "000001", "000002"]
    assert collate_keep_sizes([]) == {}
    with pytest.raises(ValueError, match="keys"):
        collate_keep_sizes([{"a": 1}, {"b": 2}])


# -- the real 60 frames ------------------------------------------------------------------


@pytest.mark.kitti
@pytest.mark.skipif(not KITTI.is_dir(), reason=f"{KITTI} not present")
def test_real_kitti_folder():
    ds = KittiDataset(KITTI)
    assert len(ds) == 60 and ds.ids[0] == "000000" and ds.ids[-1] == "000059"
    counts: Counter[str] = Counter()
    for i in range(len(ds)):
        target = ds.load_target(i)
        counts.update(target["class_names"])
        assert target["labels"].tolist() == [DEFAULT_CLASSES.index(n) for n in target["class_names"]]
        assert target["calib"]["P2"].shape == (3, 4)
    assert dict(counts) == {"Car": 175, "Pedestrian": 25, "Cyclist": 8, "Truck": 8}
    assert sum(len(t) for t in (ds[i]["boxes"] for i in range(3))) > 0
    item = ds[0]
    assert item["image"].shape[0] == 3 and 370 <= item["image"].shape[1] <= 376
    vans = KittiDataset(KITTI, classes=("Van",))
    assert sum(len(vans.load_target(i)["boxes"]) for i in range(len(vans))) == 18


# -- camera (reeb_torch.camera) ----------------------------------------------------------


def test_camera_module_is_the_one_home_of_the_readers():
    from reeb_torch import camera
    from reeb_torch.datasets import kitti as data

    assert "read_kitti_calib" in camera.__all__ and "camera_intrinsics" in camera.__all__
    assert "read_kitti_calib" not in data.__all__ and "camera_intrinsics" not in data.__all__
    assert not hasattr(data, "camera_intrinsics")


def test_camera_from_kitti_calib_and_fov(tmp_path):
    import math

    from reeb_torch.camera import Camera

    cam = Camera.from_kitti_calib(EXAMPLES / "kitti_000001_calib.txt")
    assert cam == Camera(721.5377, 721.5377, 609.5593, 172.854)
    assert Camera.from_matrix(read_kitti_calib(EXAMPLES / "kitti_000001_calib.txt")["P2"]) == cam
    # θ = 2·atan(W / 2f), checked against the README's ≈ 81° × 29° for 1242 × 375 px
    h, v = cam.fov_deg(1242, 375)
    assert h == pytest.approx(2 * math.degrees(math.atan(621 / 721.5377)))
    assert round(h) == 81 and round(v) == 29
    p = tmp_path / "no_p2.txt"
    p.write_text("P0: 1 0 2 0 0 3 4 0 0 0 1 0\n")
    with pytest.raises(ValueError, match=r"no_p2\.txt: no P2 matrix"):
        Camera.from_kitti_calib(p)
    assert Camera.from_kitti_calib(p, key="P0") == Camera(1.0, 3.0, 2.0, 4.0)


@pytest.mark.parametrize("fields", [dict(fx=0.0), dict(fy=-1.0), dict(cx=float("nan")), dict(cy="1")])
def test_camera_rejects_bad_values(fields):
    from reeb_torch.camera import Camera

    values = dict(fx=700.0, fy=700.0, cx=600.0, cy=170.0) | fields
    with pytest.raises(ValueError, match="Camera"):
        Camera(**values)
