"""Tests of reeb_torch.eval.baselines: output contract on a KITTI frame, and the +1 box offsets
checked against what OpenCV's sources say, on synthetic images whose answer is known."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from tests.conftest import DATA
from reeb_torch.eval.baselines import (
    BASELINES,
    BingBaseline,
    EdgeBoxesBaseline,
    SelectiveSearchBaseline,
    bing_to_xyxy,
    edge_boxes_to_xyxy,
    edge_orientation,
    xywh_to_xyxy,
)
from reeb_torch.io import read_image

SAMPLE = Path(__file__).resolve().parents[2] / "examples" / "data" / "kitti_000001.png"
BING_MODEL = DATA / "bing_model"
"""BING's nine model files, in the dev data (``$REEB_DATA``, conftest)."""
HAVE_BING = BING_MODEL.is_dir()
needs_bing = pytest.mark.skipif(not HAVE_BING, reason=f"BING model folder absent: {BING_MODEL}")


def _tensor(rgb: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(rgb)).permute(2, 0, 1).contiguous()


@pytest.fixture(scope="module")
def kitti_image() -> torch.Tensor:
    return read_image(SAMPLE)


def _check_contract(out: dict, image: torch.Tensor, top_k: int) -> None:
    boxes, scores = out["boxes"], out["scores"]
    _, h, w = image.shape
    assert boxes.dtype == torch.float32 and boxes.ndim == 2 and boxes.shape[1] == 4
    assert scores.ndim == 1 and scores.shape[0] == boxes.shape[0]
    assert 0 < boxes.shape[0] <= top_k
    assert (boxes[:, 0] >= 0).all() and (boxes[:, 1] >= 0).all()
    assert (boxes[:, 2] <= w).all() and (boxes[:, 3] <= h).all()
    assert (boxes[:, 0] < boxes[:, 2]).all() and (boxes[:, 1] < boxes[:, 3]).all()
    assert (scores[1:] <= scores[:-1]).all(), "scores must be non-increasing (best first)"


def test_registry_names_classes():
    assert set(BASELINES) == {"edgeboxes", "bing", "selective-search"}
    assert BASELINES["edgeboxes"] is EdgeBoxesBaseline


@pytest.mark.parametrize("top_k", [2000, 50])
def test_edge_boxes_contract(kitti_image, top_k):
    eb = EdgeBoxesBaseline(top_k=top_k)
    _check_contract(eb(kitti_image), kitti_image, top_k)


@needs_bing
@pytest.mark.parametrize("top_k", [2000, 50])
def test_bing_contract(kitti_image, top_k):
    _check_contract(BingBaseline(BING_MODEL, top_k=top_k)(kitti_image), kitti_image, top_k)


def test_selective_search_contract(kitti_image):
    ss = SelectiveSearchBaseline(top_k=300, scale=0.5)
    _check_contract(ss(kitti_image), kitti_image, 300)


@needs_bing
def test_bing_rankings_agree_on_the_first_maxbgr_boxes(kitti_image):
    """Both orders start with the best MAXBGR boxes (rank keys 300 + i < HSV's first, 900)."""
    a = BingBaseline(BING_MODEL, ranking="opencv")(kitti_image)
    b = BingBaseline(BING_MODEL, ranking="interleaved")(kitti_image)
    _check_contract(b, kitti_image, 2000)
    assert torch.equal(a["boxes"][:500], b["boxes"][:500])
    assert not torch.equal(a["boxes"], b["boxes"])
    with pytest.raises(ValueError, match="ranking"):
        BingBaseline(BING_MODEL, ranking="descending")


def test_bing_missing_model_dir_raises(tmp_path):
    with pytest.raises(FileNotFoundError, match="BING model folder"):
        BingBaseline(model_dir=tmp_path / "nope")
    with pytest.raises(FileNotFoundError, match="lacks"):
        BingBaseline(model_dir=tmp_path)


def test_rejects_bad_input():
    eb = EdgeBoxesBaseline()
    with pytest.raises(ValueError, match="uint8"):
        eb(torch.zeros(3, 20, 20))
    with pytest.raises(ValueError, match=r"\(3, H, W\)"):
        eb(torch.zeros(20, 20, 3, dtype=torch.uint8))


# -- the +1 offsets ----------------------------------------------------------------------


def test_conversions_by_hand():
    # Edge Boxes Rect(X, Y, w, h) is 1-based and covers w + 1 columns.
    assert edge_boxes_to_xyxy(np.array([[11, 21, 9, 4]]), 100, 100).tolist() == [[10, 20, 20, 25]]
    # BING (minX, minY, maxX, maxY) is 1-based and inclusive.
    assert bing_to_xyxy(np.array([[11, 21, 26, 36]]), 100, 100).tolist() == [[10, 20, 26, 36]]
    # cv::Rect (x, y, w, h) is 0-based, w columns; everything is clipped to the image.
    assert xywh_to_xyxy(np.array([[10, 20, 5, 90]]), 100, 100).tolist() == [[10, 20, 15, 100]]


def test_edge_orientation_axis_aligned():
    e = np.zeros((40, 40), np.float32)
    e[:, 20] = 1.0  # vertical edge: normal along x
    assert abs(float(edge_orientation(e)[20, 20])) < 1e-3 or abs(float(edge_orientation(e)[20, 20]) - np.pi) < 1e-3
    assert abs(float(edge_orientation(e.T.copy())[20, 20]) - np.pi / 2) < 1e-3


def test_edge_boxes_fits_a_rectangle_symmetrically():
    """The best Edge Boxes box of a filled rectangle encloses it with equal margins.

    Edge Boxes puts box sides just outside the edges (sides that cut an edge group lose
    it), and the thinned Sobel edge of a step is 2 px wide, so margins are >= 2 px; its
    refinement stops at steps <= 2 px, so they are a few px. If the +1 conversion were
    wrong, the mean left-minus-right (top-minus-bottom) margin would be about -1 px
    instead of 0: that is what this checks, over random rectangles.
    """
    rng = np.random.default_rng(0)
    eb = EdgeBoxesBaseline(top_k=20)
    margins = []
    for _ in range(40):
        hh, ww = 240, 320
        w, h = int(rng.integers(40, 150)), int(rng.integers(30, 120))
        x, y = int(rng.integers(20, ww - w - 20)), int(rng.integers(20, hh - h - 20))
        img = np.zeros((hh, ww, 3), np.uint8)
        img[y : y + h, x : x + w] = int(rng.integers(120, 256))
        b = eb(_tensor(img))["boxes"][0].tolist()
        margins.append((x - b[0], y - b[1], b[2] - (x + w), b[3] - (y + h)))
    m = np.array(margins)
    assert (m >= 1).all(), "the best box must enclose the rectangle"
    assert np.median(m) <= 5 and m.max() <= 12
    assert abs(np.mean(m[:, 0] - m[:, 2])) < 0.5
    assert abs(np.mean(m[:, 1] - m[:, 3])) < 0.5


def test_edge_boxes_white_rectangle_is_best():
    img = np.zeros((200, 300, 3), np.uint8)
    img[50:120, 80:200] = 255  # (x1, y1, x2, y2) = (80, 50, 200, 120)
    b = EdgeBoxesBaseline()(_tensor(img))["boxes"][0].tolist()
    assert 75 <= b[0] <= 79 and 46 <= b[1] <= 49 and 201 <= b[2] <= 205 and 121 <= b[3] <= 124


@needs_bing
def test_bing_box_sizes_are_powers_of_two(kitti_image):
    """BING windows are 2^i x 2^j pixels; with the right +1 handling every box not clipped
    by the image border is exactly that size (off by one otherwise)."""
    for image in (kitti_image, _tensor(np.pad(np.full((70, 120, 3), 255, np.uint8), ((50, 80), (80, 100), (0, 0))))):
        b = BingBaseline(BING_MODEL)(image)["boxes"]
        _, h, w = image.shape
        inner = (b[:, 2] < w) & (b[:, 3] < h)
        assert inner.sum() > 100
        sizes = torch.cat([b[inner, 2] - b[inner, 0], b[inner, 3] - b[inner, 1]]).to(torch.int64)
        assert ((sizes & (sizes - 1)) == 0).all()


def test_selective_search_finds_exact_rectangles():
    """A flat rectangle on a flat background is one segment: its box must come out exact."""
    img = np.full((200, 300, 3), 40, np.uint8)
    img[50:120, 80:200] = (200, 60, 60)
    img[130:180, 20:60] = (60, 200, 60)
    boxes = SelectiveSearchBaseline()(_tensor(img))["boxes"].tolist()
    assert [80.0, 50.0, 200.0, 120.0] in boxes
    assert [20.0, 130.0, 60.0, 180.0] in boxes
