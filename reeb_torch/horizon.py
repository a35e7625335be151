"""The horizon from the images alone: where the road's lines meet.

Lines that lie along a flat road (lane markings, kerbs, the road's edges, and the level edges
of what stands beside it) meet at a vanishing point on the horizon. For each frame,
:func:`frame_vanishing_point` finds line segments (OpenCV's line segment detector, LSD, on the
grey image) and takes the point that the most segment length points at (a vote over a grid of
points, each segment's vote falling off with the angle between it and the direction to the
point). :func:`estimate_horizon` takes the mode of the frames' vanishing rows (a kernel density
over frames: frames that found a building's corner or a turning road fall away), with a
frame-bootstrap interval, and adds :data:`BOX_BOTTOM_OFFSET`: ``ReebConfig.horizon`` is the row
the 2D boxes' bottoms point to (what ``reeb calibrate`` fits from labelled boxes), which lies a
little below the vanishing point.

A frame counts when a quarter or more of its segment length points at its vanishing point, some
of it from below (road edges, lane markings); in a picture without a road (a room, a face) the
lines meet nowhere in particular, and :func:`estimate_horizon` says so.

>>> from reeb_torch import read_image
>>> est = estimate_horizon([read_image(p) for p in paths])      # uint8 (3, H, W) frames
>>> est.horizon, est.interval                                    # fractions of the height

The method, its settings and how it compares with others (REEB's road mask, its edge map,
REEB's own boxes) are measured in ``docs/results.md`` ("The horizon without labels").
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Iterable

import cv2
import numpy as np
import torch
from torch import Tensor

__all__ = ["FrameVanishingPoint", "HorizonEstimate", "HorizonError", "frame_vanishing_point", "vanishing_point",
           "line_segments", "steep_segments", "estimate_horizon", "BOX_BOTTOM_OFFSET", "MIN_FRAMES"]

BOX_BOTTOM_OFFSET = 0.006
"""How far (a fraction of the image height) the row the labelled boxes' bottoms point to lies
below the vanishing point: the gap on KITTI's object frames between ``reeb calibrate``'s fit to
their labelled boxes and their calibration's principal row (a level camera's horizon), where the
vanishing points agree with the latter (``docs/results.md``, "The horizon without labels"). A
2D box's bottom is its object's nearest corner, so box bottoms sit below the line through the
objects' centres; the gap grows with the focal length, which images alone do not tell."""

MIN_FRAMES = 5
"""Fewest frames :func:`estimate_horizon` takes: the mode over frames needs a few to outvote a
frame whose lines meet elsewhere (how the interval narrows with more frames:
``docs/results.md``, "The horizon without labels")."""

_WIDTH = 640  # frames are shrunk to this width for the line detector
_MIN_LENGTH = 0.03  # shortest segment, a fraction of the image width
_ANGLES = (10.0, 80.0)  # segments this steep (degrees from level), no flatter, no steeper
_SIGMA_DEG = 1.5  # how fast a segment's vote falls with its angle to the point
_ROWS = (0.10, 0.90, 0.0025)  # the vote's grid of rows (fractions of the height): from, to, step
_COLS = (-0.25, 1.25, 0.01)  # and of columns (fractions of the width)
_SUPPORT = 0.25  # a road frame: this share of its segment length points at the point
_BELOW = 0.03  # and this much (over the diagonal) of it from below (road edges, lane markings)
_BANDWIDTH = 0.01  # the kernel over the frames' rows
_AGREE = 0.02  # a frame agrees with the estimate when its row is this close


class HorizonError(ValueError):
    """The frames do not give a horizon (too few frames, or no road seen); a one-line message.
    ``notes``: the frames left out before it, and why (where the caller read the frames)."""

    notes: list[str] = []


@dataclass(frozen=True)
class FrameVanishingPoint:
    """Where one frame's lines meet.

    Attributes:
        row, column: the vanishing point, fractions of the image height and width (the column
            may lie outside [0, 1]); NaN when the frame has too few segments.
        support: the share of the frame's segment length that points at it, in [0, 1].
        left, right: segment length below the point that points at it, left and right of it,
            over the image diagonal (the road's sides, lane markings).
        segments: segments kept (steep enough, long enough).
    """

    row: float
    column: float
    support: float
    left: float
    right: float
    segments: int

    @property
    def road(self) -> bool:
        """Whether a road was seen: a quarter or more of the segment length points at the point,
        some of it from below (road edges, lane markings)."""
        return math.isfinite(self.row) and self.support >= _SUPPORT and self.left + self.right >= _BELOW


@dataclass(frozen=True)
class HorizonEstimate:
    """The horizon :func:`estimate_horizon` found.

    Attributes:
        horizon: ``ReebConfig.horizon``: the vanishing rows' mode plus ``offset``.
        interval: its frame-bootstrap percentile interval at ``level``.
        level: the interval's coverage.
        vanishing_row: the mode of the frames' vanishing rows (without ``offset``).
        offset: what was added (:data:`BOX_BOTTOM_OFFSET`).
        num_frames: frames given; num_road: frames in which a road was seen (those used).
        agree: frames used whose vanishing row lies within 0.02 of the mode.
        rows: ``float64 [num_frames]`` each frame's vanishing row (NaN: no road seen).
    """

    horizon: float
    interval: tuple[float, float]
    level: float
    vanishing_row: float
    offset: float
    num_frames: int
    num_road: int
    agree: int
    rows: np.ndarray = field(repr=False)

    def __str__(self) -> str:
        lo, hi = self.interval
        return (f"horizon {self.horizon:.4f} of the image height ({100 * self.level:g} % interval {lo:.4f}-{hi:.4f}); "
                f"road seen in {self.num_road} of {self.num_frames} frames, {self.agree} agree within {_AGREE}")


def _grey(image: Tensor | np.ndarray) -> np.ndarray:
    """``uint8 [H, W]`` grey of a ``(3, H, W)`` or ``(1, H, W)`` tensor (uint8, or float in
    [0, 1]) or an ``[H, W, 3]`` RGB / ``[H, W]`` grey array."""

    if isinstance(image, Tensor):
        t = image.detach().cpu()
        if t.ndim != 3 or t.shape[0] not in (1, 3):
            raise ValueError(f"expected an image tensor (3, H, W) or (1, H, W), got {tuple(t.shape)}")
        if t.dtype != torch.uint8:
            t = (t.float().clamp(0, 1) * 255).round().to(torch.uint8)
        a = t.permute(1, 2, 0).numpy()
    else:
        a = np.asarray(image)
        if a.dtype != np.uint8:
            a = (np.clip(a.astype(np.float64), 0, 1) * 255).round().astype(np.uint8)
    if a.ndim == 3 and a.shape[2] == 3:
        return cv2.cvtColor(np.ascontiguousarray(a), cv2.COLOR_RGB2GRAY)
    if a.ndim == 3 and a.shape[2] == 1:
        return np.ascontiguousarray(a[:, :, 0])
    if a.ndim == 2:
        return np.ascontiguousarray(a)
    raise ValueError(f"expected an RGB or grey image, got an array of shape {a.shape}")


def line_segments(image: Tensor | np.ndarray) -> np.ndarray:
    """``float64 [N, 4]`` line segments ``(x1, y1, x2, y2)`` in the image's pixels that may
    run along a road: OpenCV's line segment detector (LSD) on the grey image shrunk to 640
    pixels wide, those longer than 3 % of the width and 10°–80° from level kept.

    Args:
        image: as :func:`frame_vanishing_point` takes it.
    """

    grey = _grey(image)
    h, w = grey.shape
    s = min(1.0, _WIDTH / w)
    small = cv2.resize(grey, (max(1, round(w * s)), max(1, round(h * s))), interpolation=cv2.INTER_AREA) \
        if s < 1 else grey
    found = cv2.createLineSegmentDetector(cv2.LSD_REFINE_STD).detect(small)[0]
    if found is None:
        return np.zeros((0, 4))
    return steep_segments(found.reshape(-1, 4).astype(np.float64) / s, w)


def steep_segments(segments: np.ndarray, width: int) -> np.ndarray:
    """The ``[N, 4]`` segments ``(x1, y1, x2, y2)`` longer than 3 % of ``width`` and 10°–80°
    from level: those that may run along a road, neither level nor upright."""
    seg = np.asarray(segments, dtype=np.float64).reshape(-1, 4)
    d = seg[:, 2:] - seg[:, :2]
    length = np.hypot(d[:, 0], d[:, 1])
    angle = np.degrees(np.arctan2(np.abs(d[:, 1]), np.abs(d[:, 0])))
    keep = (length >= _MIN_LENGTH * width) & (angle >= _ANGLES[0]) & (angle <= _ANGLES[1])
    return seg[keep]


def _votes(seg: np.ndarray, xs: np.ndarray, ys: np.ndarray, chunk: int = 64) -> np.ndarray:
    """``float32 [len(ys), len(xs), 3]``: per grid point, the segment length that points at it
    (all segments; those below it and left of it; below and right), each segment's vote
    ``length · exp(−½ (sin θ / σ)²)`` with θ its angle to the direction from its middle to the
    point, σ the larger of :data:`_SIGMA_DEG` and 1 px over its length; a point on the
    segment itself gets no vote."""
    mid = (seg[:, :2] + seg[:, 2:]) / 2
    d = seg[:, 2:] - seg[:, :2]
    length = np.hypot(d[:, 0], d[:, 1])
    u = d / length[:, None]
    sig = np.maximum(math.radians(_SIGMA_DEG), 1.0 / length)
    gx, gy = np.meshgrid(xs, ys)
    out = np.zeros((*gx.shape, 3), np.float64)
    for a in range(0, len(seg), chunk):
        b = slice(a, a + chunk)
        vx = gx[None] - mid[b, 0, None, None]
        vy = gy[None] - mid[b, 1, None, None]
        dist = np.hypot(vx, vy) + 1e-6
        sin = (u[b, 0, None, None] * vy - u[b, 1, None, None] * vx) / dist
        vote = length[b, None, None] * np.exp(-0.5 * (sin / sig[b, None, None]) ** 2)
        vote *= dist > 0.5 * length[b, None, None] + 2
        below = vy < -2  # the segment's middle lies below the point
        out[..., 0] += vote.sum(0)
        out[..., 1] += (vote * (below & (vx > 0))).sum(0)
        out[..., 2] += (vote * (below & (vx < 0))).sum(0)
    return out


def frame_vanishing_point(image: Tensor | np.ndarray) -> FrameVanishingPoint:
    """Where one frame's line segments meet: :func:`vanishing_point` of its
    :func:`line_segments`.

    Args:
        image: ``uint8`` (or float in [0, 1]) ``Tensor[3, H, W]`` RGB (as
            :func:`reeb_torch.read_image` gives), ``Tensor[1, H, W]`` grey, or an
            ``[H, W, 3]`` RGB / ``[H, W]`` grey array.
    """
    grey = _grey(image)
    return vanishing_point(line_segments(grey), *grey.shape)


def vanishing_point(segments: np.ndarray, height: int, width: int) -> FrameVanishingPoint:
    """The point the most segment length points at (:class:`FrameVanishingPoint`): the best
    of a coarse grid of points (steps of 0.01 of the height, 0.02 of the width), then of a fine
    grid around it (0.0025, 0.005).

    Args:
        segments: ``[N, 4]`` line segments ``(x1, y1, x2, y2)`` in pixels of a ``height ×
            width`` image (e.g. :func:`line_segments`); fewer than 3 give no point (NaN).
    """
    seg = np.asarray(segments, dtype=np.float64).reshape(-1, 4)
    h, w = height, width
    if len(seg) < 3:
        return FrameVanishingPoint(math.nan, math.nan, 0.0, 0.0, 0.0, len(seg))
    r0, r1, rs = _ROWS
    c0, c1, cs = _COLS
    rows, cols = np.arange(r0, r1 + 1e-9, 4 * rs), np.arange(c0, c1 + 1e-9, 2 * cs)
    coarse = _votes(seg, cols * w, rows * h)[..., 0]
    iy, ix = np.unravel_index(int(coarse.argmax()), coarse.shape)
    rows = np.clip(rows[iy] + np.arange(-6, 7) * rs, r0, r1)
    cols = np.clip(cols[ix] + np.arange(-4, 5) * cs / 2, c0, c1)
    v = _votes(seg, cols * w, rows * h)
    iy, ix = np.unravel_index(int(v[..., 0].argmax()), v.shape[:2])
    total = float(np.hypot(seg[:, 2] - seg[:, 0], seg[:, 3] - seg[:, 1]).sum())
    diag = math.hypot(h, w)
    return FrameVanishingPoint(float(rows[iy]), float(cols[ix]), float(v[iy, ix, 0]) / total,
                               float(v[iy, ix, 1]) / diag, float(v[iy, ix, 2]) / diag, len(seg))


def _mode(rows: np.ndarray, weights: np.ndarray) -> float:
    """The mode of ``rows`` (each with its weight) under a Gaussian kernel of
    :data:`_BANDWIDTH`, refined as the weighted mean of the rows within 1.5 bandwidths of the
    grid's peak."""
    grid = np.arange(_ROWS[0], _ROWS[1] + 1e-9, _ROWS[2])
    density = (weights[:, None] * np.exp(-0.5 * ((grid[None] - rows[:, None]) / _BANDWIDTH) ** 2)).sum(0)
    peak = grid[int(density.argmax())]
    near = np.abs(rows - peak) < 1.5 * _BANDWIDTH
    return float(np.average(rows[near], weights=weights[near])) if near.any() else float(peak)


def estimate_horizon(
    images: Iterable[Tensor | np.ndarray],
    level: float = 0.95,
    samples: int = 500,
    seed: int = 0,
    min_frames: int = MIN_FRAMES,
    offset: float = BOX_BOTTOM_OFFSET,
    points: Iterable[FrameVanishingPoint] | None = None,
) -> HorizonEstimate:
    """The horizon row of one camera from its frames, without labels.

    Each frame's vanishing point (:func:`frame_vanishing_point`); the mode of the rows of the
    frames in which a road was seen, each weighted by its support; ``offset`` added; a
    percentile interval over ``samples`` draws of frames with replacement. A third of the
    frames (and at least 3) must show a road.

    Args:
        images: frames of one camera, as :func:`frame_vanishing_point` takes them (sizes may
            differ: rows are fractions of each frame's height).
        level: coverage of the interval, in (0, 1).
        samples: bootstrap draws (>= 1).
        seed: seed of the draws.
        min_frames: fewest frames accepted (>= 2).
        offset: added to the vanishing rows' mode (:data:`BOX_BOTTOM_OFFSET`).
        points: the frames' vanishing points when already computed (then ``images`` is
            not read).

    Raises:
        HorizonError: fewer than ``min_frames`` frames, or a road seen in fewer than a third
            of them (or than 3).
        ValueError: a bad argument or image.
    """
    if not 0 < level < 1 or samples < 1 or min_frames < 2 or not math.isfinite(offset):
        raise ValueError(f"estimate_horizon: need 0 < level < 1, samples >= 1, min_frames >= 2 and a finite offset; "
                         f"got {level}, {samples}, {min_frames}, {offset}")
    found = list(points) if points is not None else [frame_vanishing_point(im) for im in images]
    if len(found) < min_frames:
        raise HorizonError(f"{len(found)} frame{'s' if len(found) != 1 else ''}: too few to estimate the horizon "
                           f"from images; give at least {min_frames} frames of the camera")
    rows = np.array([p.row if p.road else math.nan for p in found], dtype=np.float64)
    road = np.isfinite(rows)
    used, weights = rows[road], np.array([p.support for p in found])[road]
    need = max(3, math.ceil(len(found) / 3))
    if len(used) < need:
        raise HorizonError(f"no road seen: in {len(used)} of {len(found)} frames do the road's lines meet at a "
                           f"vanishing point (at least {need} needed); are these frames of a camera on a road?")
    mode = _mode(used, weights)
    rng = np.random.default_rng(seed)
    draws = []
    for _ in range(samples):
        pick = rng.integers(len(used), size=len(used))
        draws.append(_mode(used[pick], weights[pick]))
    lo, hi = np.quantile(draws, [(1 - level) / 2, (1 + level) / 2])
    agree = int((np.abs(used - mode) <= _AGREE).sum())
    return HorizonEstimate(mode + offset, (float(lo) + offset, float(hi) + offset), level, mode, offset,
                           len(found), len(used), agree, rows)
