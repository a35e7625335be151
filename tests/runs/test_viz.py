"""reeb_torch.runs.viz.crop_sheet: one tile per object, its box and the nearest proposal drawn."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from reeb_torch.runs.viz import GT_COLOR, NEAREST_COLOR, crop_sheet


def _has(tile: np.ndarray, color: tuple[int, int, int]) -> bool:
    return bool((np.abs(tile.astype(int) - np.array(color)).sum(-1) < 60).any())


def test_sheet_has_one_tile_per_crop_in_rows_of_columns(sample_image):
    boxes = [(600, 150, 700, 250), (0, 0, 30, 40), (1200, 340, 1242, 375), (10, 100, 600, 370), (300, 160, 312, 200)]
    crops = [(sample_image, b, None if i % 2 else (b[0] + 5, b[1], b[2] + 5, b[3]), f"object {i}")
             for i, b in enumerate(boxes)]
    sheet = crop_sheet(crops, columns=2, tile=(120, 90))
    assert sheet.dtype == np.uint8 and sheet.shape == (3 * (90 + 16), 2 * 120, 3)
    tiles = [sheet[r * 106:(r + 1) * 106, c * 120:(c + 1) * 120] for r in range(3) for c in range(2)]
    for i in range(5):
        assert _has(tiles[i][:90], GT_COLOR)  # every object's box, border crops included
        assert _has(tiles[i][:90], NEAREST_COLOR) == (i % 2 == 0)  # the nearest proposal where given
        assert tiles[i][90:].max() > 200  # the caption
    assert tiles[5].max() == 0  # the empty place of the last row


def test_sheet_takes_arrays_and_rejects_bad_layouts(sample_image):
    hwc = sample_image.permute(1, 2, 0).numpy()
    assert crop_sheet([(hwc, (50, 60, 90, 120), None, "x")], columns=4).shape == (150 + 16, 4 * 200, 3)
    assert crop_sheet([]).shape == (0, 0, 3)
    with pytest.raises(ValueError, match="columns"):
        crop_sheet([(hwc, (0, 0, 5, 5), None, "x")], columns=0)
    with pytest.raises(ValueError, match="shape"):
        crop_sheet([(torch.zeros(4, 8, 8), (0, 0, 5, 5), None, "x")])


def test_the_best_boxes_carry_their_class_hint():
    from reeb_torch.runs.viz import draw_proposals

    img = torch.zeros(3, 120, 200, dtype=torch.uint8)
    boxes = torch.tensor([[20.0, 60.0, 60.0, 110.0], [120.0, 60.0, 180.0, 110.0]])
    plain = draw_proposals(img, boxes, top=2)
    hinted = draw_proposals(img, boxes, top=2, hints=["Pedestrian", "Car"])
    assert plain.shape == hinted.shape == (120, 200, 3)
    # the tag above each box is wider with its hint (the number alone ends within a few pixels)
    tag = lambda pic, x1: int((pic[40:56, x1 + 12: x1 + 40].max(axis=2) > 0).sum())  # noqa: E731
    assert tag(plain, 20) == 0 and tag(hinted, 20) > 0 and tag(hinted, 120) > 0


def test_near_duplicate_boxes_share_one_label_and_labels_do_not_overlap():
    """The best boxes of a ranking are often one object (the bundled frame's top five are one
    truck): one label lists their ranks, the picture says so, and no two labels overlap."""
    from reeb_torch.runs.viz import _free_spot, draw_proposals, rank_labels

    truck = [[600, 155, 632, 195], [592, 155, 640, 195], [608, 155, 640, 195], [600, 159, 640, 191]]
    boxes = np.array(truck + [[392, 179, 424, 199], [604, 157, 630, 196]], np.float32)
    labels = rank_labels(boxes, 6, ["Truck"] * 4 + ["Car", "Car"])
    assert labels == [([0, 1, 2, 3, 5], "1,2,3,4,6 Truck/Car"), ([4], "5 Car")]
    placed: list = []
    spots = [_free_spot(600, 140, 80, 12, placed, 1242, 375) for _ in range(3)]  # three labels wanted in one place
    assert len(set(spots)) == 3 and all(abs(a[1] - b[1]) >= 12 for a, b in zip(spots, spots[1:]))
    img = torch.zeros(3, 375, 1242, dtype=torch.uint8)
    with_note = draw_proposals(img, torch.from_numpy(boxes), top=6, title="x")
    without = draw_proposals(img, torch.from_numpy(boxes[[0, 4]]), top=2, title="x")
    band = lambda pic: int((pic[: pic.shape[0] - 375].max(axis=2) > 100).sum())  # noqa: E731
    assert band(with_note) > 3 * band(without)  # the band explains the shared label


def test_text_that_opencv_cannot_draw_is_made_ascii():
    from reeb_torch.runs.viz import cv_text, draw_detections, draw_proposals

    assert cv_text("x\udcff.png") == "x\\xff.png" and cv_text("caf\u00e9") == "caf?"
    img = torch.zeros(3, 60, 120, dtype=torch.uint8)
    boxes = torch.tensor([[10.0, 20.0, 50.0, 50.0]])
    assert draw_proposals(img, boxes, title="x\udcff.png", gt=[("P\udcff", (5, 5, 30, 30))]).shape[1] == 120
    assert draw_detections(img, boxes, ["Car\udcff"], torch.tensor([0.9]), title="x\udcff").shape[1] == 120


def test_detection_labels_in_a_crowd_do_not_cover_each_other(monkeypatch):
    """Six detections on one spot: six labels, none over another (as propose --viz spreads its)."""
    from reeb_torch.runs import viz

    spots = []
    real = viz._free_spot

    def spy(x, y, tw, th, placed, width, height):
        out = real(x, y, tw, th, placed, width, height)
        spots.append((*out, out[0] + tw, out[1] + th))
        return out

    monkeypatch.setattr(viz, "_free_spot", spy)
    img = torch.zeros(3, 200, 300, dtype=torch.uint8)
    boxes = torch.tensor([[100.0 + i, 80.0, 140.0 + i, 150.0] for i in range(6)])
    viz.draw_detections(img, boxes, ["Pedestrian"] * 6, torch.linspace(0.9, 0.4, 6))
    assert len(spots) == 6
    for i, a in enumerate(spots):
        for b in spots[i + 1:]:
            assert not (a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]), (a, b)
