"""Image decoding: any common image file to an RGB ``uint8`` tensor, or a clear error; and
writing a file so that a failed write never destroys the previous one."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import cv2
import numpy as np
import torch

__all__ = ["ImageReadError", "read_image", "IMAGE_EXTENSIONS", "replace_file"]

#: The file extensions a folder scan picks up: exactly the formats :func:`read_image` decodes
#: (OpenCV's readers), so that a file named on the command line and one found in a folder
#: are treated alike.
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp", ".ppm", ".pgm",
                    ".pnm", ".gif")


class ImageReadError(ValueError):
    """An image file could not be read; the message names the file and the reason."""


def to_rgb8(array: np.ndarray, name: str = "image") -> np.ndarray:
    """Convert a decoded OpenCV array (BGR/BGRA/grey, 8 or 16 bit, or float) to RGB uint8.

    Grey is replicated to three channels, the alpha channel is dropped, 16-bit values are
    scaled by 1/257 (65535 → 255) and floats in [0, 1] by 255.
    """

    a = array
    if a.dtype == np.uint16:
        a = (a.astype(np.float32) / 257.0 + 0.5).astype(np.uint8)
    elif a.dtype in (np.float32, np.float64):
        a = (np.clip(a, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    elif a.dtype != np.uint8:
        raise ImageReadError(f"{name}: unsupported pixel type {a.dtype}")
    if a.ndim == 2:
        return np.ascontiguousarray(np.repeat(a[:, :, None], 3, axis=2))
    if a.ndim == 3 and a.shape[2] == 1:
        return np.ascontiguousarray(np.repeat(a, 3, axis=2))
    if a.ndim == 3 and a.shape[2] == 3:
        return cv2.cvtColor(a, cv2.COLOR_BGR2RGB)
    if a.ndim == 3 and a.shape[2] == 4:
        return cv2.cvtColor(a, cv2.COLOR_BGRA2RGB)
    raise ImageReadError(f"{name}: unsupported image shape {a.shape}")


_SIGNATURES = (
    (b"\x89PNG\r\n\x1a\n", "PNG"),
    (b"\xff\xd8\xff", "JPEG"),
    (b"BM", "BMP"),
    (b"II*\x00", "TIFF"),
    (b"MM\x00*", "TIFF"),
    (b"GIF8", "GIF"),
)


def _sniff(head: bytes) -> str | None:
    """The image format named by a file's first bytes, or ``None`` if none is recognised."""
    for magic, name in _SIGNATURES:
        if head.startswith(magic):
            return name
    if head[:4] == b"RIFF" and head[8:12] == b"WEBP":
        return "WebP"
    if len(head) >= 2 and head[:1] == b"P" and head[1:2] in b"123456":
        return "PNM"
    return None


def read_image(path: str | os.PathLike) -> torch.Tensor:
    """Read an image file as an RGB ``uint8`` tensor of shape ``(3, H, W)``.

    Grey, RGBA and 16-bit images are converted, not rejected. The EXIF orientation of a
    JPEG (or TIFF, WebP) is applied as image viewers do, so ``H, W`` are the size as the
    image is viewed (a phone picture with orientation 6 comes out upright). Raises
    :class:`ImageReadError` naming the file when it is missing, empty, truncated, corrupt
    or not an image.
    """

    p = Path(path)
    if not p.exists():
        raise ImageReadError(f"{p}: no such file")
    if p.is_dir():
        raise ImageReadError(f"{p}: is a folder, not an image")
    try:
        data = np.fromfile(str(p), dtype=np.uint8)
    except OSError as e:
        raise ImageReadError(f"{p}: cannot read ({e.strerror or e})") from e
    if data.size == 0:
        raise ImageReadError(f"{p}: empty file")
    # IMREAD_UNCHANGED would skip the EXIF orientation; ANYDEPTH|ANYCOLOR keeps 16-bit and
    # grey pixels as they are, drops alpha (as to_rgb8 does) and applies the orientation
    array = cv2.imdecode(data, cv2.IMREAD_ANYDEPTH | cv2.IMREAD_ANYCOLOR)
    if array is None or array.size == 0:
        kind = _sniff(data[:16].tobytes())
        if kind is None:
            raise ImageReadError(f"{p}: not an image file (unknown format)")
        raise ImageReadError(f"{p}: corrupt or truncated {kind} file (cannot decode it)")
    rgb = to_rgb8(array, str(p))
    return torch.from_numpy(rgb).permute(2, 0, 1).contiguous()


def replace_file(path: str | os.PathLike, data: bytes) -> Path:
    """Write ``data`` to ``path`` through a temporary file beside it (hidden, ``.<name>.*.tmp``),
    flushed to disk and renamed into place: ``path`` holds its old bytes or the new ones, never
    a part. The file gets the umask's permissions; missing folders are made. A symbolic link
    at ``path`` stays a link: the file it points to is written.

    Raises:
        OSError: it cannot be written (the temporary file is removed; ``path`` is as it was).
    """
    out = Path(path)
    if out.is_symlink():
        out = Path(os.path.realpath(out))
    out.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{out.name[:200]}.", suffix=".tmp", dir=out.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        mask = os.umask(0)
        os.umask(mask)
        os.chmod(tmp, 0o666 & ~mask)  # as Python's open would make it (mkstemp's is 0600)
        os.replace(tmp, out)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return out
