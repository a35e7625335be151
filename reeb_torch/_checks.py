"""Input checks at the door: one call, a message that names what was expected."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import TYPE_CHECKING

import numba
import numpy as np
import torch
from torch import Tensor

from .stages._threads import on_two_cores
from .stages.edges import working_size

if TYPE_CHECKING:
    from .config import FrontEndSettings

__all__ = ["check_images", "check_fits", "check_range", "ImageBatch"]

ImageBatch = Tensor | Sequence[Tensor]


def _check_storage(t: Tensor, where: str) -> None:
    """TypeError for tensors that hold no readable values: meta device, sparse layouts."""
    if t.device.type == "meta":
        raise TypeError(f"{where}: a meta-device tensor holds no values; expected a tensor on a real device "
                        "(CPU or CUDA)")
    if t.layout != torch.strided:
        raise TypeError(f"{where}: expected a dense (strided) tensor, got layout {t.layout}; call .to_dense() first")


@numba.njit(cache=True, nogil=True)
def _count_in_unit_range(x: np.ndarray) -> int:  # pragma: no cover - compiled
    """How many of the flat float32 ``x`` lie in [0, 1] (NaN does not): one pass, vectorised."""
    n = 0
    zero, one = np.float32(0.0), np.float32(1.0)
    for i in range(x.shape[0]):
        v = x[i]
        n += (v >= zero) & (v <= one)
    return n


def _in_unit_range(img: Tensor) -> bool:
    """Whether every value of the float image is in [0, 1] (no NaN, no infinity): on the CPU
    one compiled pass over float32, its two halves on the two cores (``torch.isfinite(img).all()``,
    ``min``, ``max`` were three passes, and torch's threaded reductions slow down several
    times when other work holds the cores); elsewhere one ``aminmax``."""
    if img.device.type == "cpu" and img.dtype == torch.float32 and img.is_contiguous():
        flat = img.reshape(-1).numpy()
        inside: list[int] = []
        on_two_cores(lambda lo, hi: inside.append(_count_in_unit_range(flat[lo:hi])), flat.shape[0])
        return sum(inside) == flat.shape[0]
    lo, hi = torch.aminmax(img)
    return bool((lo >= 0) & (hi <= 1))


def check_range(img: Tensor, where: str) -> None:
    """Raise ValueError, naming ``where``, unless every value of the float image ``img`` is
    finite and in [0, 1]."""
    if img.numel() and not _in_unit_range(img):
        lo_t, hi_t = torch.aminmax(img)  # min and max propagate NaN; an infinity is one of them
        lo, hi = float(lo_t), float(hi_t)
        if not (math.isfinite(lo) and math.isfinite(hi)):
            raise ValueError(f"{where}: contains NaN or infinite values")
        if lo < 0.0 or hi > 1.0:
            raise ValueError(
                f"{where}: float images must hold values in [0, 1], got range [{lo:.4g}, {hi:.4g}]"
                " (divide uint8 data by 255, or pass the uint8 tensor)"
            )


def _check_one(img: Tensor, where: str, keep_uint8: bool = False, defer_range: bool = False) -> Tensor:
    if not isinstance(img, Tensor):
        raise TypeError(f"{where}: expected a torch.Tensor, got {type(img).__name__}")
    _check_storage(img, where)
    if img.ndim != 3:
        raise ValueError(f"{where}: expected shape (3, H, W), got {tuple(img.shape)}")
    if img.shape[0] != 3:
        raise ValueError(f"{where}: expected 3 (RGB) channels in dim 0, got shape {tuple(img.shape)}")
    if img.dtype == torch.uint8:
        return img if keep_uint8 else img.float().div_(255.0)
    if not img.is_floating_point():
        raise TypeError(f"{where}: expected dtype float or uint8, got {img.dtype}")
    if not defer_range:
        check_range(img, where)
    return img.float()


def check_fits(height: int, width: int, front_end: FrontEndSettings, where: str = "image") -> None:
    """Raise ValueError when the front end cannot run on a ``height × width`` image: at the
    working resolution (``scale``) the Gaussian blur (``blur_sigma``; kernel side
    ``2*ceil(2σ)+1``, reflected borders) needs more than ``ceil(2σ)`` pixels per side.
    The message names the image size and both settings."""
    s, sigma = front_end.scale, front_end.blur_sigma
    hk, wk = working_size(height, width, s)
    reach = math.ceil(2 * sigma)
    if reach >= min(hk, wk):
        raise ValueError(
            f"{where}: size {width}x{height} (WxH) is {wk}x{hk} pixels at ReebConfig.scale={s!r}, too small "
            f"for ReebConfig.blur_sigma={sigma!r}, whose kernel reaches {reach} px on each side (the working "
            f"image needs more than {reach} px per side): lower blur_sigma, raise scale, or pass a larger image"
        )


def check_images(images: ImageBatch, min_side: int, front_end: FrontEndSettings | None = None,
                 keep_uint8: bool = False, unchecked: list[int] | None = None) -> list[Tensor]:
    """Validate a batch and return a list of float32 ``(3, H, W)`` images in [0, 1]
    (with ``keep_uint8``, uint8 images are returned as they are, for a caller that
    converts them itself: ``x.float().div_(255.0)``).

    Accepts a ``(B, 3, H, W)`` float/uint8 tensor or a sequence of ``(3, H, W)`` tensors,
    dense, on a real device (a meta tensor is a TypeError). ``min_side`` is the smallest
    height/width an image may have (the smallest window); with ``front_end``, each image must
    also fit its working resolution (:func:`check_fits`). Wrong types raise TypeError,
    wrong shapes, values or sizes ValueError. Given a list ``unchecked``, the values of
    float32 CPU images are not checked here: their indices go into the list, for a caller
    that checks them as it reads them (:func:`check_range` where it cannot).
    """
    if isinstance(images, Tensor):
        if images.ndim == 3:
            raise ValueError(
                f"expected a batch (B, 3, H, W) or a list of (3, H, W) images, got one image of shape "
                f"{tuple(images.shape)}; wrap it as images[None] or [image]"
            )
        _check_storage(images, "images")
        if images.ndim != 4:
            raise ValueError(f"expected images of shape (B, 3, H, W), got {tuple(images.shape)}")
        seq: Sequence[Tensor] = list(images.unbind(0))
    elif isinstance(images, Sequence) and not isinstance(images, (str, bytes)):
        seq = images
    else:
        raise TypeError(f"expected a Tensor or a list of Tensors, got {type(images).__name__}")
    if len(seq) == 0:
        raise ValueError("empty batch: expected at least one image")
    out = []
    for i, img in enumerate(seq):
        defer = (unchecked is not None and isinstance(img, Tensor) and img.dtype == torch.float32
                 and img.device.type == "cpu")
        x = _check_one(img, f"image {i}", keep_uint8, defer)
        if defer and unchecked is not None:
            unchecked.append(i)
        h, w = x.shape[-2:]
        if h < min_side or w < min_side:
            raise ValueError(
                f"image {i}: size {w}x{h} (WxH) is smaller than the smallest window ({min_side} px)"
            )
        if front_end is not None:
            check_fits(h, w, front_end, f"image {i}")
        out.append(x)
    return out
