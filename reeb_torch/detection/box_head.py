"""Smaller and faster box heads for a trained detector: its first layer factorised
(:class:`LowRankLinear`, :func:`factorise_box_head`) and its layers in int8
(:class:`Int8Linear`, :func:`quantise_box_head`).

The box head (torchvision's ``TwoMLPHead``: ``fc6``, ``neck_channels * 49`` inputs by
``representation_size``, then ``fc7``) holds most of a detector's trained weights and, per
box, most of its work after the backbone. Both changes are made to trained weights and kept
in the detector's file (``DetectorSettings.box_head_rank``, ``box_head_int8``).

:class:`Int8Linear` stores one int8 weight per entry and one float scale per output unit
(symmetric, per channel). On the CPU each input row is rounded to int8 with its own scale
(a compiled kernel), the product is torch's int8 matrix product with int32 sums, which are
exact (:func:`int8_product`; the same sums in float64 where a build lacks the kernel), and
the scales are applied after: a row's output depends on that row alone, and is
the same on every CPU. On a GPU it computes the product from the dequantised weight in
float32.
"""

from __future__ import annotations

from typing import Any

import numba
import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ..stages._threads import on_two_cores

__all__ = ["LowRankLinear", "Int8Linear", "factorise_box_head", "quantise_box_head", "quantise_rows", "int8_product"]


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _quantise_range(x, q, scales, lo, hi):  # pragma: no cover - compiled
    """Rows ``lo..hi-1`` of ``x`` (``float32 [M, K]``) rounded to int8 into ``q`` with each
    row's scale (its largest magnitude over 127; 1 for a row of zeros) into ``scales``."""
    k = x.shape[1]
    for i in range(lo, hi):
        top = np.float32(0.0)
        for j in range(k):
            a = abs(x[i, j])
            if a > top:
                top = a
        s = top / np.float32(127.0) if top > 0 else np.float32(1.0)
        scales[i] = s
        for j in range(k):
            q[i, j] = np.int8(min(max(np.round(x[i, j] / s), -127.0), 127.0))


def int8_product(q: Tensor, w: Tensor) -> Tensor:
    """``q @ w.T`` of int8 ``q [M, K]`` and ``w [N, K]`` as exact int32 sums ``[M, N]``:
    torch's int8 kernel (``torch._int_mm``), or where this build has none for the CPU, the
    same sums in float64 (exact for ``K`` under 2**39, slower)."""
    try:
        return torch._int_mm(q, w.t())
    except (RuntimeError, NotImplementedError, AttributeError):
        return (q.double() @ w.double().t()).to(torch.int32)


def quantise_rows(x: Tensor) -> tuple[Tensor, Tensor]:
    """``x`` (``float32 [M, K]``, CPU) as ``(int8 [M, K], float32 [M])``: each row rounded
    (half to even) to int8 with its own scale, its largest magnitude over 127, so that
    ``q * scale[:, None]`` is ``x`` to half a step."""

    a = x.detach().float().contiguous().numpy()
    q = np.empty(a.shape, np.int8)
    scales = np.empty(a.shape[0], np.float32)
    on_two_cores(lambda lo, hi: _quantise_range(a, q, scales, lo, hi), a.shape[0])
    return torch.from_numpy(q), torch.from_numpy(scales)


class LowRankLinear(nn.Module):
    """``nn.Linear(in_features, out_features)`` of rank at most ``rank``: ``up(down(x))``,
    ``down`` without a bias. ``x``: ``[..., in_features]`` -> ``[..., out_features]``; its
    cost and size are ``rank * (in_features + out_features)`` against ``in * out``."""

    def __init__(self, in_features: int, out_features: int, rank: int) -> None:
        super().__init__()
        self.in_features, self.out_features, self.rank = in_features, out_features, rank
        self.down = nn.Linear(in_features, rank, bias=False)
        self.up = nn.Linear(rank, out_features)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.up(self.down(x))

    @classmethod
    def from_linear(cls, layer: nn.Linear, rank: int) -> "LowRankLinear":
        """The best approximation of ``layer`` of rank ``rank`` (its weight's truncated SVD,
        computed in float64, each factor given the square root of the singular values; the
        bias kept)."""
        w = layer.weight.detach().double()
        u, sv, vh = torch.linalg.svd(w, full_matrices=False)
        root = sv[:rank].sqrt()
        out = cls(layer.in_features, layer.out_features, rank)
        with torch.no_grad():
            out.down.weight.copy_((root[:, None] * vh[:rank]).to(layer.weight.dtype))
            out.up.weight.copy_((u[:, :rank] * root[None, :]).to(layer.weight.dtype))
            out.up.bias.copy_(layer.bias.detach())
        return out.to(layer.weight.device)


def factorise_box_head(model: nn.Module, rank: int) -> None:
    """Replace the trained box head's first layer (``roi_heads.box_head.fc6``, the largest
    of the detector's trained tensors) by its rank-``rank`` approximation, in place
    (:meth:`LowRankLinear.from_linear`); ``rank`` 0 or at least the layer's: nothing."""
    head: Any = model.roi_heads.box_head  # type: ignore[union-attr]
    fc6 = head.fc6
    if isinstance(fc6, Int8Linear):
        raise ValueError("the box head is in int8: factorise it before it is quantised")
    if not isinstance(fc6, nn.Linear):
        raise ValueError(f"the box head's first layer is already factorised (rank {getattr(fc6, 'rank', '?')})")
    if 0 < rank < min(fc6.in_features, fc6.out_features):
        head.fc6 = LowRankLinear.from_linear(fc6, rank)


class Int8Linear(nn.Module):
    """``nn.Linear(in_features, out_features)`` with int8 weights: ``weight_int8``
    ``int8 [out, in]`` times ``scale`` ``float32 [out]`` is the weight, ``bias`` ``float32
    [out]`` (buffers: they are saved and loaded, not trained). ``x``: ``[..., in_features]``
    (any float dtype) -> ``float32 [..., out_features]``. A quarter of the float layer's
    size; on the CPU, an int8 product with int32 sums (module doc)."""

    weight_int8: Tensor
    scale: Tensor
    bias: Tensor

    def __init__(self, in_features: int, out_features: int) -> None:
        super().__init__()
        self.in_features, self.out_features = in_features, out_features
        self.register_buffer("weight_int8", torch.zeros(out_features, in_features, dtype=torch.int8))
        self.register_buffer("scale", torch.ones(out_features))
        self.register_buffer("bias", torch.zeros(out_features))

    @classmethod
    def from_linear(cls, layer: nn.Linear) -> "Int8Linear":
        """``layer``'s weight rounded to int8 as :func:`quantise_rows` rounds an input, one
        scale per output unit, its bias kept."""
        q, scale = quantise_rows(layer.weight.detach().float().cpu())
        out = cls(layer.in_features, layer.out_features)
        out.weight_int8.copy_(q)
        out.scale.copy_(scale)
        if layer.bias is not None:
            out.bias.copy_(layer.bias.detach().float())
        return out.to(layer.weight.device)

    def dequantised(self) -> Tensor:
        """The dequantised weight, ``float32 [out, in]``."""
        return self.weight_int8.float() * self.scale[:, None]

    def forward(self, x: Tensor) -> Tensor:
        lead = x.shape[:-1]
        flat = x.reshape(-1, self.in_features).float()
        if x.device.type != "cpu" or torch.is_grad_enabled() and x.requires_grad:
            y = F.linear(flat, self.dequantised(), self.bias)
        else:
            q, row_scales = quantise_rows(flat)
            y = int8_product(q, self.weight_int8).float() * row_scales[:, None] * self.scale + self.bias
        return y.reshape(*lead, self.out_features)

    def extra_repr(self) -> str:
        return f"in_features={self.in_features}, out_features={self.out_features}, int8"


def quantise_box_head(model: nn.Module) -> None:
    """Replace the box head's layers (``fc6``, or its two factors; ``fc7``) by
    :class:`Int8Linear` copies, in place; layers that are int8 already stay."""
    head: Any = model.roi_heads.box_head  # type: ignore[union-attr]
    if isinstance(head.fc6, LowRankLinear):
        for name in ("down", "up"):
            layer = getattr(head.fc6, name)
            if isinstance(layer, nn.Linear):
                setattr(head.fc6, name, Int8Linear.from_linear(layer))
    elif isinstance(head.fc6, nn.Linear):
        head.fc6 = Int8Linear.from_linear(head.fc6)
    if isinstance(head.fc7, nn.Linear):
        head.fc7 = Int8Linear.from_linear(head.fc7)
