"""Sec. 3.6, eqs. 5–8 — region division from the camera.

The largest object (``W`` metres wide) is nearest at the distance ``d`` where the ground
enters the vertical field of view (eq. 5: tan(θv/2) = h/d); there the horizontal field
of view spans ``2M`` metres (eq. 6: tan(θh/2) = M/d), so an object fills at most
``W / 2M`` of the image width (eq. 7). Regions are full-height strips that wide, spaced
``overlap`` of their width apart (eq. 8, corrected: n = 1/(w_r·overlap) − 1, reading 8 in ``docs/results.md``).
"""

from __future__ import annotations

import math

from typing import TYPE_CHECKING

if TYPE_CHECKING:  # torch is imported where a tensor is made: ReebConfig's checks use this
    from torch import Tensor  # module's arithmetic, and the ``reeb`` command starts without torch

__all__ = ["region_width_fraction", "region_count", "region_bounds"]


def region_width_fraction(camera_height_m: float, vertical_fov_deg: float, horizontal_fov_deg: float,
                          max_object_width_m: float, round_to: float | None = 0.125) -> float:
    """Eqs. 5–7: the region width as a fraction of the image width, in (0, 1].

    KITTI (h = 1.65 m, θv = 35°, θh = 90°, W = 2.55 m): d ≈ 5.23 m, M ≈ 5.23 m,
    w_r ≈ 0.244, rounded up to 0.25 with ``round_to=0.125``.
    """
    d = camera_height_m / math.tan(math.radians(vertical_fov_deg) / 2)  # eq. 5
    m = d * math.tan(math.radians(horizontal_fov_deg) / 2)  # eq. 6
    wr = max_object_width_m / (2 * m)  # eq. 7 (as a fraction, not percent)
    if round_to is not None:
        wr = math.ceil(wr / round_to - 1e-9) * round_to
    return min(1.0, wr)


def region_count(width_fraction: float, overlap: float) -> int:
    """Eq. 8 corrected: the number of strips of ``width_fraction`` spaced
    ``width_fraction · overlap`` apart that cover the image, ``1 + ceil((1 − w_r)/(w_r·overlap))``
    (= 1/(w_r·overlap) − 1 when that is whole: 7 for w_r = 0.25, overlap = 0.5)."""
    if width_fraction >= 1.0:
        return 1
    return 1 + math.ceil((1.0 - width_fraction) / (width_fraction * overlap) - 1e-9)


def region_bounds(width: int, width_fraction: float, overlap: float) -> Tensor:
    """Column bounds ``int64 [R, 2]`` (x_start inclusive, x_end exclusive) of the regions
    of an image ``width`` pixels wide; strips are spread evenly so the last one ends at the
    right border."""
    import torch

    n = region_count(width_fraction, overlap)
    rw = max(1, int(round(width_fraction * width)))
    if n == 1:
        return torch.tensor([[0, width]])
    starts = [int(round(i * (width - rw) / (n - 1))) for i in range(n)]
    return torch.tensor([[s, s + rw] for s in starts])
