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
