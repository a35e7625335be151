"""RoIAlign over the detector's pyramid, compiled for the CPU: torchvision's numbers, faster.

torchvision's :func:`~torchvision.ops.roi_align` on the CPU walks each RoI's channels one
plane at a time on one core. The detector's maps are channels-last, so here every sampling
point reads one contiguous vector of channels: :func:`_pool_range` is a compiled loop over
RoIs that computes, for each output bin, torchvision's sampling points and bilinear weights
(the same float32 arithmetic, in the same order) and adds the four corners' channel vectors.
:class:`PyramidRoIAlign` is :class:`~torchvision.ops.MultiScaleRoIAlign` (the FPN level of
each box, ``aligned=False``) that takes this path in inference on the CPU, and torchvision's
everywhere else (training, where gradients flow, and other devices). The two agree to float
rounding (``tests/test_detection_speed.py``).
"""

from __future__ import annotations

import math

import numba
import numpy as np
import torch
from torch import Tensor
from torchvision.ops import MultiScaleRoIAlign
from torchvision.ops.boxes import box_area

__all__ = ["PyramidRoIAlign", "roi_align_levels"]


@numba.njit(cache=True, nogil=True, inline="always")
def _corner(v: float, size: int) -> tuple[int, int, float]:
    """torchvision's bilinear corner for one coordinate: low index, high index, and the
    fraction toward the high one (``v`` already known to lie in ``[-1, size]``)."""
    if v <= 0:
        v = np.float32(0.0)
    low = int(v)
    if low >= size - 1:
        return size - 1, size - 1, np.float32(0.0)
    return low, low + 1, np.float32(v - np.float32(low))


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
        x0, y0 = boxes[n, 0] * s, boxes[n, 1] * s
        roi_w = max(boxes[n, 2] * s - x0, np.float32(1.0))
        roi_h = max(boxes[n, 3] * s - y0, np.float32(1.0))
        bin_w, bin_h = roi_w / pooled, roi_h / pooled
        for ph in range(out_size):
            for pw in range(out_size):
                acc[:] = 0
                for iy in range(sampling):
                    y = y0 + np.float32(ph) * bin_h + np.float32(iy + 0.5) * bin_h / grid
                    for ix in range(sampling):
                        x = x0 + np.float32(pw) * bin_w + np.float32(ix + 0.5) * bin_w / grid
                        if y < -1.0 or y > height or x < -1.0 or x > width:
                            continue
                        yl, yh, ly = _corner(y, height)
                        xl, xh, lx = _corner(x, width)
                        hy, hx = np.float32(1.0) - ly, np.float32(1.0) - lx
                        w1, w2, w3, w4 = hy * hx, hy * lx, ly * hx, ly * lx
                        for c in range(channels):
                            acc[c] += (w1 * data[yl, xl, c] + w2 * data[yl, xh, c]
                                       + w3 * data[yh, xl, c] + w4 * data[yh, xh, c])
                for c in range(channels):
                    out[n, ph, pw, c] = acc[c] / count


def _level_of(boxes: Tensor, k_min: int, k_max: int) -> Tensor:
    """FPN's level of each box (torchvision's ``LevelMapper``: canonical 224 px at level 4),
    as an index from ``k_min``."""
    s = torch.sqrt(box_area(boxes))
    k = torch.floor(4 + torch.log2(s / 224) + torch.tensor(1e-6, dtype=s.dtype))
    return (k.clamp(min=k_min, max=k_max).to(torch.int64) - k_min)


def _scale(feature: Tensor, image_size: tuple[int, int]) -> float:
    return 2.0 ** round(math.log2(feature.shape[-2] / image_size[0]))


def roi_align_levels(levels: list[Tensor], boxes: Tensor, image_size: tuple[int, int], output_size: int = 7,
                     sampling_ratio: int = 2) -> Tensor:
    """RoIAlign of one image's boxes over its pyramid, each box on its FPN level.

    Args:
        levels: the maps ``[1, C, h_i, w_i]`` float32, finest first, strides doubling.
        boxes: ``[N, 4]`` ``(x1, y1, x2, y2)`` in the pixels of ``image_size``.
        image_size: ``(h, w)`` the levels' strides refer to (the padded batch's size).
        output_size: bins per side; sampling_ratio: sampling points per bin side (> 0).

    Returns:
        ``float32 [N, C, output_size, output_size]``: what
        ``MultiScaleRoIAlign(names, output_size, sampling_ratio)`` gives (``aligned=False``).
    """
    from ..stages._threads import on_two_cores

    n, c = len(boxes), levels[0].shape[1]
    out = np.zeros((n, output_size, output_size, c), np.float32)
    if n:
        scales = [_scale(f, image_size) for f in levels]
        k_min, k_max = int(-math.log2(scales[0])), int(-math.log2(scales[-1]))
        which = _level_of(boxes.float(), k_min, k_max)
        rows = boxes.detach().float().cpu().contiguous().numpy()
        for level, (feature, scale) in enumerate(zip(levels, scales)):
            idx = torch.nonzero(which == level).flatten()
            if not len(idx):
                continue
            data = feature[0].detach().float().permute(1, 2, 0).contiguous().numpy()  # no copy when channels-last
            part = np.ascontiguousarray(rows[idx.numpy()])
            res = np.zeros((len(idx), output_size, output_size, c), np.float32)
            on_two_cores(lambda lo, hi: _pool_range(data, part, scale, output_size, sampling_ratio, res, lo, hi),
                         len(idx))
            out[idx.numpy()] = res
    return torch.from_numpy(out).permute(0, 3, 1, 2).contiguous()


class PyramidRoIAlign(MultiScaleRoIAlign):
    """:class:`~torchvision.ops.MultiScaleRoIAlign` whose inference on the CPU (no gradient,
    one image, float32 maps, ``sampling_ratio > 0``) runs :func:`roi_align_levels`; anything
    else runs torchvision's. The same arguments, the same outputs (to float rounding)."""

    def forward(self, x: dict[str, Tensor], boxes: list[Tensor], image_shapes: list[tuple[int, int]]) -> Tensor:
        levels = [x[name] for name in self.featmap_names]
        fast = (not torch.is_grad_enabled() and len(boxes) == 1 and self.sampling_ratio > 0
                and all(f.device.type == "cpu" and f.dtype == torch.float32 for f in levels)
                and self.output_size[0] == self.output_size[1])
        if not fast:
            return super().forward(x, boxes, image_shapes)
        size = (max(s[0] for s in image_shapes), max(s[1] for s in image_shapes))
        return roi_align_levels(levels, boxes[0], size, self.output_size[0], self.sampling_ratio)
