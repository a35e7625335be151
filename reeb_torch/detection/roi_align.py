"""RoIAlign over the detector's pyramid, compiled for the CPU: torchvision's numbers, faster.

torchvision's :func:`~torchvision.ops.roi_align` on the CPU walks each RoI's channels one
plane at a time on one core. Here the maps are laid out channels-last, so every sampling
point reads (and, going back, writes) one contiguous vector of channels:
:func:`_pool_range` is a compiled loop over RoIs that computes, for each output bin,
torchvision's sampling points and bilinear weights (the same float32 arithmetic, in the same
order) and adds the four corners' channel vectors; :func:`_grad_range` spreads the output's
gradient back over the same corners, in torchvision's order, for a range of channels (the
two halves of the channels run at once, touching different memory).
:class:`PyramidRoIAlign` is :class:`~torchvision.ops.MultiScaleRoIAlign` (the FPN level of
each box, ``aligned=False``) that takes this path for one image's float32 maps on the CPU,
training included, and torchvision's elsewhere. Both directions give torchvision's numbers
bit for bit (``tests/detection/test_detection_speed.py``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numba
import numpy as np
import torch
from torch import Tensor
from torchvision.ops import MultiScaleRoIAlign
from torchvision.ops.boxes import box_area

from ..stages._threads import on_two_cores

__all__ = ["PyramidRoIAlign", "roi_align_levels"]


@numba.njit(cache=True, nogil=True, inline="always")
def _corner(v: Any, size: int) -> tuple[int, int, Any]:
    """torchvision's bilinear corner for one coordinate: low index, high index, and the
    fraction toward the high one (``v`` already known to lie in ``[-1, size]``)."""
    if v <= 0:
        v = np.float32(0.0)
    low = int(v)
    if low >= size - 1:
        return size - 1, size - 1, np.float32(0.0)
    return low, low + 1, np.float32(v - np.float32(low))


@numba.njit(cache=True, nogil=True, inline="always")
def _box_bins(boxes: Any, n: int, s: Any, pooled: Any) -> tuple[Any, Any, Any, Any]:
    """Box ``n``'s corner on the level (``x0``, ``y0``) and its bins' width and height, as
    torchvision computes them (a box at least 1 level pixel wide and high)."""
    x0, y0 = boxes[n, 0] * s, boxes[n, 1] * s
    roi_w = max(boxes[n, 2] * s - x0, np.float32(1.0))
    roi_h = max(boxes[n, 3] * s - y0, np.float32(1.0))
    return x0, y0, roi_w / pooled, roi_h / pooled


@numba.njit(cache=True, nogil=True, inline="always")
def _sample(y: Any, x: Any, height: int, width: int) -> tuple[bool, int, int, int, int, Any, Any, Any, Any]:
    """The bilinear sample at ``(y, x)``: whether it counts (inside ``[-1, size]``), its
    corners ``yl, yh, xl, xh`` and their weights ``w1..w4`` (top-left, top-right,
    bottom-left, bottom-right)."""
    zero = np.float32(0.0)
    if y < -1.0 or y > height or x < -1.0 or x > width:
        return False, 0, 0, 0, 0, zero, zero, zero, zero
    yl, yh, ly = _corner(y, height)
    xl, xh, lx = _corner(x, width)
    hy, hx = np.float32(1.0) - ly, np.float32(1.0) - lx
    return True, yl, yh, xl, xh, hy * hx, hy * lx, ly * hx, ly * lx


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _pool_range(data, boxes, scale, out_size, sampling, out, lo, hi):  # pragma: no cover - compiled
    """``out[n]`` (``[out_size, out_size, C]``) for the boxes ``lo..hi-1`` of one level:
    ``data`` ``float32 [H, W, C]``, ``boxes`` ``float32 [N, 4]`` input pixels, ``scale`` the
    level's (1 / stride), ``sampling`` points per bin side (> 0)."""
    height, width, channels = data.shape
    s = np.float32(scale)
    grid = np.float32(sampling)
    count = np.float32(max(sampling * sampling, 1))
    pooled = np.float32(out_size)
    acc = np.zeros(channels, np.float32)
    for n in range(lo, hi):
        x0, y0, bin_w, bin_h = _box_bins(boxes, n, s, pooled)
        for ph in range(out_size):
            for pw in range(out_size):
                acc[:] = 0
                for iy in range(sampling):
                    y = y0 + np.float32(ph) * bin_h + np.float32(iy + 0.5) * bin_h / grid
                    for ix in range(sampling):
                        x = x0 + np.float32(pw) * bin_w + np.float32(ix + 0.5) * bin_w / grid
                        inside, yl, yh, xl, xh, w1, w2, w3, w4 = _sample(y, x, height, width)
                        if not inside:
                            continue
                        for c in range(channels):
                            acc[c] += (w1 * data[yl, xl, c] + w2 * data[yl, xh, c]
                                       + w3 * data[yh, xl, c] + w4 * data[yh, xh, c])
                for c in range(channels):
                    out[n, ph, pw, c] = acc[c] / count


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _grad_range(grad, boxes, scale, out_size, sampling, out, c_lo, c_hi):  # pragma: no cover - compiled
    """Add the gradient of :func:`_pool_range`'s output (``grad`` ``[N, out_size, out_size,
    C]``) for channels ``c_lo..c_hi-1`` into ``out`` (``float32 [H, W, C]``), box after box,
    bin after bin, sampling point after sampling point, corner after corner: torchvision's
    order of additions for every value."""
    height, width = out.shape[0], out.shape[1]
    s = np.float32(scale)
    grid = np.float32(sampling)
    count = np.float32(sampling * sampling)
    pooled = np.float32(out_size)
    for n in range(boxes.shape[0]):
        x0, y0, bin_w, bin_h = _box_bins(boxes, n, s, pooled)
        for ph in range(out_size):
            for pw in range(out_size):
                for iy in range(sampling):
                    y = y0 + np.float32(ph) * bin_h + np.float32(iy + 0.5) * bin_h / grid
                    for ix in range(sampling):
                        x = x0 + np.float32(pw) * bin_w + np.float32(ix + 0.5) * bin_w / grid
                        inside, yl, yh, xl, xh, w1, w2, w3, w4 = _sample(y, x, height, width)
                        if not inside:
                            continue
                        for c in range(c_lo, c_hi):
                            g = grad[n, ph, pw, c]
                            out[yl, xl, c] += g * w1 / count
                            out[yl, xh, c] += g * w2 / count
                            out[yh, xl, c] += g * w3 / count
                            out[yh, xh, c] += g * w4 / count


def _level_of(boxes: Tensor, k_min: int, k_max: int) -> Tensor:
    """FPN's level of each box (torchvision's ``LevelMapper``: canonical 224 px at level 4),
    as an index from ``k_min``."""
    s = torch.sqrt(box_area(boxes))
    k = torch.floor(4 + torch.log2(s / 224) + torch.tensor(1e-6, dtype=s.dtype))
    return (k.clamp(min=k_min, max=k_max).to(torch.int64) - k_min)


def _scale(feature: Tensor, image_size: tuple[int, int]) -> float:
    return 2.0 ** round(math.log2(feature.shape[-2] / image_size[0]))


def _levels_and_scales(levels: Sequence[Tensor], boxes: Tensor,
                       image_size: tuple[int, int]) -> tuple[list[float], Tensor]:
    scales = [_scale(f, image_size) for f in levels]
    k_min, k_max = int(-math.log2(scales[0])), int(-math.log2(scales[-1]))
    return scales, _level_of(boxes.float(), k_min, k_max)


class _PyramidRoIAlignFn(torch.autograd.Function):
    """:func:`roi_align_levels` with its gradient for the maps (the boxes get none)."""

    @staticmethod
    def forward(ctx: Any, boxes: Tensor, image_size: tuple[int, int], output_size: int, sampling: int,
                *levels: Tensor) -> Tensor:
        n, c = len(boxes), levels[0].shape[1]
        out = np.zeros((n, output_size, output_size, c), np.float32)
        scales, which = _levels_and_scales(levels, boxes, image_size)
        rows = boxes.detach().float().cpu().contiguous().numpy()
        parts = []
        for level, (feature, scale) in enumerate(zip(levels, scales)):
            idx = torch.nonzero(which == level).flatten().numpy()
            parts.append(idx)
            if not len(idx):
                continue
            data = feature[0].detach().float().permute(1, 2, 0).contiguous().numpy()  # no copy when channels-last
            part = np.ascontiguousarray(rows[idx])
            res = np.zeros((len(idx), output_size, output_size, c), np.float32)
            on_two_cores(lambda lo, hi: _pool_range(data, part, scale, output_size, sampling, res, lo, hi), len(idx))
            out[idx] = res
        ctx.save_for_backward(boxes)
        ctx.parts, ctx.scales, ctx.shapes = parts, scales, [tuple(f.shape) for f in levels]
        ctx.output_size, ctx.sampling = output_size, sampling
        return torch.from_numpy(out).permute(0, 3, 1, 2).contiguous()

    @staticmethod
    def backward(ctx: Any, grad: Tensor) -> tuple[Any, ...]:
        (boxes,) = ctx.saved_tensors
        rows = boxes.detach().float().cpu().contiguous().numpy()
        g = grad.detach().float().permute(0, 2, 3, 1).contiguous().numpy()
        grads: list[Tensor | None] = []
        for idx, scale, shape, needed in zip(ctx.parts, ctx.scales, ctx.shapes, ctx.needs_input_grad[4:]):
            if not needed:
                grads.append(None)
                continue
            out = np.zeros((shape[2], shape[3], shape[1]), np.float32)
            if len(idx):
                part, gp = np.ascontiguousarray(rows[idx]), np.ascontiguousarray(g[idx])
                on_two_cores(lambda lo, hi: _grad_range(gp, part, scale, ctx.output_size, ctx.sampling, out, lo, hi),
                             shape[1])
            grads.append(torch.from_numpy(out).permute(2, 0, 1)[None])
        return (None, None, None, None, *grads)


def roi_align_levels(levels: list[Tensor], boxes: Tensor, image_size: tuple[int, int], output_size: int = 7,
                     sampling_ratio: int = 2) -> Tensor:
    """RoIAlign of one image's boxes over its pyramid, each box on its FPN level, with the
    gradient for the maps where they need one.

    Args:
        levels: the maps ``[1, C, h_i, w_i]`` float32, finest first, strides doubling.
        boxes: ``[N, 4]`` ``(x1, y1, x2, y2)`` in the pixels of ``image_size``.
        image_size: ``(h, w)`` the levels' strides refer to (the largest image of the batch).
        output_size: bins per side; sampling_ratio: sampling points per bin side (> 0).

    Returns:
        ``float32 [N, C, output_size, output_size]``: what
        ``MultiScaleRoIAlign(names, output_size, sampling_ratio)`` gives (``aligned=False``).
    """
    return _PyramidRoIAlignFn.apply(boxes, tuple(image_size), output_size, sampling_ratio, *levels)


class PyramidRoIAlign(MultiScaleRoIAlign):
    """:class:`~torchvision.ops.MultiScaleRoIAlign` that runs :func:`roi_align_levels` for one
    image's float32 maps on the CPU (``sampling_ratio > 0``, square output), in inference and
    in training, and torchvision's otherwise. The same arguments, the same outputs and
    gradients."""

    def forward(self, x: dict[str, Tensor], boxes: list[Tensor], image_shapes: list[tuple[int, int]]) -> Tensor:
        levels = [x[name] for name in self.featmap_names]
        fast = (len(boxes) == 1 and self.sampling_ratio > 0
                and all(f.device.type == "cpu" and f.dtype == torch.float32 for f in levels)
                and self.output_size[0] == self.output_size[1])
        if not fast:
            return super().forward(x, boxes, image_shapes)
        size = (max(s[0] for s in image_shapes), max(s[1] for s in image_shapes))
        return roi_align_levels(levels, boxes[0], size, self.output_size[0], self.sampling_ratio)
