"""Sec. 3.5, eqs. 3–4 — road segmentation in HSV.

The road colour is the per-channel median of ``n`` random pixels sampled where road is
likely (a bottom-centre band); a pixel is road when each HSV channel lies within a
tolerance of that median (eq. 3) in all three channels (eq. 4's AND).
"""

from __future__ import annotations

import math

import kornia
import torch
from torch import Tensor

__all__ = ["sample_positions", "road_mask"]


def sample_positions(h: int, w: int, n: int, band: tuple[float, float, float, float], seed: int,
                     device: torch.device | str = "cpu") -> Tensor:
    """``n`` seeded random flat pixel indices (``int64 [n]``) inside ``band`` (fractions
    x1, y1, x2, y2 of an ``h × w`` image). The same seed and size give the same pixels."""
    g = torch.Generator().manual_seed(seed)
    x1, y1, x2, y2 = band
    cx0, cx1 = int(x1 * w), max(int(x1 * w) + 1, int(math.ceil(x2 * w)))
    cy0, cy1 = int(y1 * h), max(int(y1 * h) + 1, int(math.ceil(y2 * h)))
    xs = torch.randint(cx0, min(cx1, w), (n,), generator=g)
    ys = torch.randint(cy0, min(cy1, h), (n,), generator=g)
    return (ys * w + xs).to(device)


def road_mask(
    images: Tensor,
    samples: int = 300,
    band: tuple[float, float, float, float] = (0.3, 0.8, 0.7, 1.0),
    tolerance: tuple[float, float, float] = (0.5, 0.12, 0.12),
    seed: int = 0,
) -> Tensor:
    """Binary road mask of RGB ``(B, 3, H, W)`` images in [0, 1] → bool ``(B, H, W)``.

    HSV as in :func:`kornia.color.rgb_to_hsv` (hue in [0, 2π), circular; S, V in [0, 1]).
    ``tolerance`` is the half-width of the in-range test per channel.
    """
    b, _, h, w = images.shape
    hsv = kornia.color.rgb_to_hsv(images).flatten(2)  # (B, 3, HW)
    pos = sample_positions(h, w, samples, band, seed, images.device)
    picked = hsv[:, :, pos]  # (B, 3, n)
    # circular median of hue: rotate so that the circular mean sits at pi, then median
    ang = picked[:, 0]
    mean = torch.atan2(ang.sin().mean(1), ang.cos().mean(1))  # (B,)
    rot = torch.remainder(ang - mean[:, None] + math.pi, 2 * math.pi)
    hue_med = torch.remainder(rot.median(1).values + mean - math.pi, 2 * math.pi)
    med = torch.stack([hue_med, picked[:, 1].median(1).values, picked[:, 2].median(1).values], 1)
    diff = (hsv - med[:, :, None]).abs()
    diff[:, 0] = torch.minimum(diff[:, 0], 2 * math.pi - diff[:, 0])
    tol = torch.tensor(tolerance, dtype=hsv.dtype, device=hsv.device).view(1, 3, 1)
    inside = diff <= tol
    out = inside.all(1)
    return out.view(b, h, w)
