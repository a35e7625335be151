"""reeb_torch.io.read_image against OpenCV's own decoding, and its error messages."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from reeb_torch.io import ImageReadError, read_image

SAMPLE = Path(__file__).resolve().parent.parent / "examples" / "data" / "kitti_000001.png"


@pytest.fixture(scope="module")
def bgr() -> np.ndarray:
    rng = np.random.default_rng(0)
    return rng.integers(0, 256, size=(37, 53, 3), dtype=np.uint8)


def test_rgb_png_matches_opencv(tmp_path, bgr):
    p = tmp_path / "a.png"
    cv2.imwrite(str(p), bgr)
    t = read_image(p)
    assert t.dtype == torch.uint8 and t.shape == (3, 37, 53)
    assert np.array_equal(t.permute(1, 2, 0).numpy(), bgr[:, :, ::-1])  # BGR file -> RGB tensor


def test_sample_frame():
    t = read_image(SAMPLE)
    assert t.shape == (3, 375, 1242) and t.dtype == torch.uint8


def test_grey_is_replicated(tmp_path, bgr):
    grey = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)
    p = tmp_path / "g.png"
    cv2.imwrite(str(p), grey)
    t = read_image(p)
    assert t.shape == (3, 37, 53)
    for c in range(3):
        assert np.array_equal(t[c].numpy(), grey)


def test_rgba_drops_alpha(tmp_path, bgr):
    bgra = cv2.cvtColor(bgr, cv2.COLOR_BGR2BGRA)
    bgra[:, :, 3] = 7  # alpha must not matter
    p = tmp_path / "a.png"
    cv2.imwrite(str(p), bgra)
    assert np.array_equal(read_image(p).permute(1, 2, 0).numpy(), bgr[:, :, ::-1])


def test_16bit_scaled_to_8bit(tmp_path, bgr):
    deep = bgr.astype(np.uint16) * 257  # 255 -> 65535, 1 -> 257: exact inverse of /257
    p = tmp_path / "d.png"
    cv2.imwrite(str(p), deep)
    assert cv2.imread(str(p), cv2.IMREAD_UNCHANGED).dtype == np.uint16
    assert np.array_equal(read_image(p).permute(1, 2, 0).numpy(), bgr[:, :, ::-1])


def test_16bit_grey_rounds(tmp_path):
    grey = np.array([[0, 128, 65535, 65407]], dtype=np.uint16)  # 65407/257 = 254.5 -> 255
    p = tmp_path / "d.png"
    cv2.imwrite(str(p), grey)
    t = read_image(p)
    assert t[0, 0].tolist() == [0, 0, 255, 255]


def test_jpeg(tmp_path, bgr):
    p = tmp_path / "a.jpg"
    cv2.imwrite(str(p), bgr)
    ref = cv2.imread(str(p))[:, :, ::-1]
    assert np.array_equal(read_image(p).permute(1, 2, 0).numpy(), ref)


@pytest.mark.parametrize(
    "make, expected",
    [
        (lambda d, png: None, "no such file"),
        (lambda d, png: (d / "x.png").mkdir(), "is a folder"),
        (lambda d, png: (d / "x.png").write_bytes(b""), "empty file"),
        (lambda d, png: (d / "x.png").write_bytes(png[: len(png) // 2]), "corrupt or truncated PNG"),
        (lambda d, png: (d / "x.png").write_bytes(png[:64] + bytes(range(256)) * 4), "corrupt or truncated PNG"),
        (lambda d, png: (d / "x.png").write_text("just text"), "not an image file"),
    ],
    ids=["missing", "folder", "empty", "truncated", "corrupt", "text"],
)
def test_errors_name_the_file(tmp_path, bgr, make, expected):
    png = cv2.imencode(".png", bgr)[1].tobytes()
    make(tmp_path, png)
    p = tmp_path / "x.png"
    with pytest.raises(ImageReadError) as info:
        read_image(p)
    msg = str(info.value)
    assert str(p) in msg and expected in msg
    assert "\n" not in msg
    assert isinstance(info.value, ValueError)  # callers may catch ValueError


def test_truncated_jpeg_is_rejected(tmp_path, bgr):
    data = cv2.imencode(".jpg", bgr)[1].tobytes()
    p = tmp_path / "t.jpg"
    p.write_bytes(data[: len(data) // 2])
    with pytest.raises(ImageReadError, match="t.jpg"):
        read_image(p)


def test_exif_orientation_is_applied_as_viewers_do(tmp_path, bgr):
    # a JPEG stored 53 wide, 37 high, with EXIF orientation 6 ("rotate 90° clockwise to view")
    Image = pytest.importorskip("PIL.Image")
    ImageOps = pytest.importorskip("PIL.ImageOps")
    exif = Image.Exif()
    exif[0x0112] = 6
    p = tmp_path / "o6.jpg"
    Image.fromarray(bgr[:, :, ::-1]).save(p, quality=95, exif=exif.tobytes())
    t = read_image(p)
    assert t.shape == (3, 53, 37)  # the viewer's width and height
    with Image.open(p) as im:  # the reference: PIL's own decoder and transpose
        ref = np.asarray(ImageOps.exif_transpose(im).convert("RGB"))
    assert ref.shape == (53, 37, 3)
    diff = np.abs(t.permute(1, 2, 0).numpy().astype(int) - ref.astype(int))
    assert diff.mean() < 2.0  # two JPEG decoders; a wrong rotation differs by ~80
