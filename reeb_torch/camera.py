"""The camera: KITTI calibration files and pinhole intrinsics.

Used by :meth:`reeb_torch.ReebConfig.with_kitti_calib` (opening angles from ``P2``) and by
the KITTI reader (:class:`reeb_torch.datasets.kitti.KittiDataset` returns each frame's calib). It
depends on nothing else in the package, so the config can use it without the dataset.

A KITTI ``calib`` file has lines ``KEY: v1 v2 ...``; ``P2`` is the 3×4 projection matrix of
the left colour camera (the ``image_2`` frames), whose intrinsics are
``fx = P2[0,0]``, ``fy = P2[1,1]``, ``cx = P2[0,2]``, ``cy = P2[1,2]`` in pixels.

>>> cam = Camera.from_kitti_calib("examples/data/kitti_000001_calib.txt")
>>> cam.fx, cam.cy                     # (721.5377, 172.854)

:func:`fit_camera` goes the other way, for any camera: it fits the horizon row and the
camera height from labelled 2D boxes of objects standing on a flat road (``reeb calibrate``).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

import torch
from torch import Tensor

__all__ = ["Camera", "read_kitti_calib", "camera_intrinsics", "fit_camera", "CameraFit", "ClassResidual",
           "KITTI_CLASS_HEIGHTS_M", "BOX_HEIGHT_FACTOR"]

# Number of values of the calibration matrices whose shape is known.
_CALIB_SHAPES: dict[str, tuple[int, int]] = {
    "P": (3, 4),  # P0..P3: 3x4 projection matrices of the four cameras
    "R0_rect": (3, 3),  # rectifying rotation of the reference camera
    "R_rect": (3, 3),  # same, as named in KITTI's tracking benchmark
    "Tr_": (3, 4),  # Tr_velo_to_cam, Tr_imu_to_velo: rigid transforms [R | t]
}


def _calib_shape(key: str) -> tuple[int, int] | None:
    if len(key) == 2 and key[0] == "P" and key[1].isdigit():
        return _CALIB_SHAPES["P"]
    if key in _CALIB_SHAPES:
        return _CALIB_SHAPES[key]
    if key.startswith("Tr_"):
        return _CALIB_SHAPES["Tr_"]
    return None


CALIB_MAX_BYTES = 64 * 1024
"""The most a calib file is read: KITTI's are under 1 KiB."""


def read_kitti_calib(path: str | os.PathLike) -> dict[str, Tensor]:
    """Read a KITTI ``calib`` file: lines ``KEY: v1 v2 ...`` (the colon may be missing).

    Known keys get their matrix shape: ``P0``..``P3`` → ``(3, 4)``, ``R0_rect`` /
    ``R_rect`` → ``(3, 3)``, ``Tr_*`` (``Tr_velo_to_cam``, ``Tr_imu_to_velo``) → ``(3, 4)``.
    Other keys are kept as 1-D tensors. Missing keys are simply absent from the result.

    Returns:
        ``dict`` from key to a ``float64`` tensor, in file order.

    Raises:
        FileNotFoundError: the file does not exist.
        ValueError: a line has no values, a non-numeric value, or the wrong number of
            values for its key; the message names the file and the 1-based line number.
    """
    p = Path(path)
    calib: dict[str, Tensor] = {}
    if p.exists() and not p.is_file():  # a FIFO, a device: it could block, or never end
        raise ValueError(f"{p}: not a regular file (a calib file is a small text file)")
    with open(p, "rb") as fb:
        raw = fb.read(CALIB_MAX_BYTES + 1)
    if len(raw) > CALIB_MAX_BYTES:
        raise ValueError(f"{p}: over {CALIB_MAX_BYTES // 1024} KiB: not a KITTI calib file")
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as e:
        raise ValueError(f"{p}: not a text file (byte {e.start} is not UTF-8): not a KITTI calib file") from None
    for lineno, line in enumerate(text.splitlines(), start=1):
        if not line.strip():
            continue
        if ":" in line:
            key, _, rest = line.partition(":")
            key, fields = key.strip(), rest.split()
        else:
            key, *fields = line.split()
        if not key or not fields:
            raise ValueError(f"{p}:{lineno}: expected 'KEY: v1 v2 ...', got {line.strip()!r}")
        try:
            values = [float(v) for v in fields]
        except ValueError as e:
            raise ValueError(f"{p}:{lineno}: non-numeric value for {key} ({e})") from None
        t = torch.tensor(values, dtype=torch.float64)
        shape = _calib_shape(key)
        if shape is not None:
            if t.numel() != shape[0] * shape[1]:
                raise ValueError(
                    f"{p}:{lineno}: {key} needs {shape[0] * shape[1]} values "
                    f"({shape[0]}x{shape[1]}), got {t.numel()}"
                )
            t = t.reshape(shape)
        calib[key] = t
    return calib


def camera_intrinsics(P: Tensor) -> tuple[float, float, float, float]:
    """Focal lengths and principal point ``(fx, fy, cx, cy)`` in pixels of a projection matrix.

    Args:
        P: ``Tensor[3, 4]`` projection matrix (e.g. KITTI's ``P2``, the left colour camera)
            or ``Tensor[3, 3]`` intrinsic matrix K. ``fx = P[0,0]``, ``fy = P[1,1]``,
            ``cx = P[0,2]``, ``cy = P[1,2]``.

    Raises:
        ValueError: ``P`` is not a 3x4 or 3x3 tensor.
    """
    if not isinstance(P, Tensor) or P.ndim != 2 or P.shape[0] != 3 or P.shape[1] not in (3, 4):
        shape = tuple(P.shape) if isinstance(P, Tensor) else type(P).__name__
        raise ValueError(f"camera_intrinsics: expected a 3x4 or 3x3 matrix, got {shape}")
    return float(P[0, 0]), float(P[1, 1]), float(P[0, 2]), float(P[1, 2])


@dataclass(frozen=True)
class Camera:
    """Pinhole intrinsics in pixels: focal lengths ``fx``, ``fy`` (> 0) and principal
    point ``(cx, cy)`` (column, row; 0-based, may lie outside the image)."""

    fx: float
    fy: float
    cx: float
    cy: float

    def __post_init__(self) -> None:
        for name in ("fx", "fy", "cx", "cy"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise ValueError(f"Camera.{name} must be a finite number, got {v!r}")
        if self.fx <= 0 or self.fy <= 0:
            raise ValueError(f"Camera focal lengths must be > 0, got fx={self.fx}, fy={self.fy}")

    @classmethod
    def from_matrix(cls, P: Tensor) -> "Camera":
        """From a ``Tensor[3, 4]`` projection matrix or a ``Tensor[3, 3]`` K
        (:func:`camera_intrinsics`)."""
        return cls(*camera_intrinsics(P))

    @classmethod
    def from_kitti_calib(cls, path: str | os.PathLike, key: str = "P2") -> "Camera":
        """From the projection matrix ``key`` (default ``P2``, the left colour camera) of a
        KITTI ``calib`` file.

        Raises:
            FileNotFoundError: no such file.
            ValueError: the file is malformed, or has no ``key`` matrix (both named).
        """
        calib = read_kitti_calib(path)
        if key not in calib:
            what = " (the left colour camera)" if key == "P2" else ""
            raise ValueError(f"{path}: no {key} matrix{what} in this calib file")
        try:
            return cls.from_matrix(calib[key])
        except ValueError as e:  # a focal length of 0, a principal point of nan: name the file
            raise ValueError(f"{path}: its {key} gives no camera ({e})") from None

    def fov_deg(self, width: int, height: int) -> tuple[float, float]:
        """Horizontal and vertical opening angles in degrees for a ``width × height``
        image: ``2·atan(W / 2fx)``, ``2·atan(H / 2fy)``."""
        if not (width > 0 and height > 0):
            raise ValueError(f"fov_deg needs a positive width and height, got {width} x {height}")
        return (
            math.degrees(2 * math.atan(width / (2 * self.fx))),
            math.degrees(2 * math.atan(height / (2 * self.fy))),
        )


# -- fitting the camera from labelled boxes (reeb calibrate) ----------------------------------

KITTI_CLASS_HEIGHTS_M: dict[str, float] = {
    "Car": 1.53, "Van": 2.21, "Truck": 3.25, "Pedestrian": 1.76, "Cyclist": 1.74, "Tram": 3.53,
}
"""Mean 3D heights (metres) of KITTI's labelled object classes (the training labels' ``h``
column), the default ``class_heights`` of :func:`fit_camera`."""

BOX_HEIGHT_FACTOR = 1.055
"""How much taller a 2D box is than its object's 3D height at the depth of its bottom row: the
box spans the object's footprint in depth (its bottom is the nearest corner, its top the
farthest top edge), so ``box_h / (bottom − horizon)`` exceeds ``H / camera_height``. Fitted with
KITTI's 3D heights, the camera comes out at 1.564 m on 60 KITTI object frames against the
known 1.65 m (1.65 / 1.564 = 1.055), and at 1.556 m on 46 frames of two KITTI tracking
sequences (other drives of the same car; 1.642 m once corrected). :func:`fit_camera` multiplies the class
heights by it, so its camera height is in the unit ``ReebConfig.camera_height_m`` assumes."""

_TUKEY_C = 4.685  # 95 % efficiency at the normal model
_HUBER_C = 1.345


@dataclass(frozen=True)
class ClassResidual:
    """How one class's boxes sit around the fitted line.

    Attributes:
        count: boxes of the class used in the fit.
        median_px, mad_px: median and median absolute deviation of the bottom row's residual
            (observed − fitted), in pixels of each box's image.
        implied_height_m: the class height that would put the median box on the line
            (median of ``box_h · camera_height / (bottom − horizon)``); compare with the one given.
        outliers: boxes the robust fit gave no weight.
    """

    count: int
    median_px: float
    mad_px: float
    implied_height_m: float
    outliers: int


@dataclass(frozen=True)
class CameraFit:
    """The camera :func:`fit_camera` found.

    Attributes:
        horizon: horizon row as a fraction of the image height (``ReebConfig.horizon``).
        camera_height_m: camera height above the road, in the unit of the class heights.
        horizon_interval, camera_height_interval: frame-bootstrap percentile intervals.
        level: their coverage (e.g. 0.95).
        num_boxes, num_frames: what was fitted (after dropping boxes cut by the image's top or
            bottom border); num_outliers: boxes with no weight in the robust fit.
        scale: robust standard deviation of the bottom rows' residuals (fraction of the image height).
        per_class: :class:`ClassResidual` per class name, in the order first seen.
        x, y, weight, classes: the fitted points: ``x = box_h / (H_img · H_class)``,
            ``y = bottom / H_img`` (so ``y = horizon + camera_height · x``), the final robust
            weights in [0, 1] and each point's class name (for the picture).
    """

    horizon: float
    camera_height_m: float
    horizon_interval: tuple[float, float]
    camera_height_interval: tuple[float, float]
    level: float
    num_boxes: int
    num_frames: int
    num_outliers: int
    scale: float
    per_class: dict[str, ClassResidual]
    x: np.ndarray = field(repr=False)
    y: np.ndarray = field(repr=False)
    weight: np.ndarray = field(repr=False)
    classes: tuple[str, ...] = field(repr=False)

    def config_changes(self) -> dict[str, float]:
        """``{"horizon": ..., "camera_height_m": ...}`` for ``ReebConfig.replace`` / a JSON config."""
        return {"horizon": float(self.horizon), "camera_height_m": float(self.camera_height_m)}

    def __str__(self) -> str:
        lo, hi = self.horizon_interval
        clo, chi = self.camera_height_interval
        pct = f"{100 * self.level:g} %"
        return (f"horizon {self.horizon:.4f} of the image height ({pct} interval {lo:.4f}-{hi:.4f}), "
                f"camera height {self.camera_height_m:.3f} ({pct} interval {clo:.3f}-{chi:.3f}); "
                f"{self.num_boxes} boxes in {self.num_frames} frames, {self.num_outliers} outliers")


def _wls(x: np.ndarray, y: np.ndarray, w: np.ndarray) -> np.ndarray | None:
    """Weighted least squares of ``y = a + b·x``: ``[a, b]``, or None when degenerate."""
    sw = w.sum()
    if sw <= 0:
        return None
    mx, my = (w * x).sum() / sw, (w * y).sum() / sw
    sxx = (w * (x - mx) ** 2).sum()
    if sxx <= 1e-12 * max(sw, 1.0) * max(mx * mx, 1e-12):
        return None
    b = (w * (x - mx) * (y - my)).sum() / sxx
    return np.array([my - b * mx, b])


def _robust_scale(r: np.ndarray) -> float:
    return float(1.4826 * np.median(np.abs(r - np.median(r))))


def _irls(x: np.ndarray, y: np.ndarray, theta: np.ndarray, scale: float, kind: str,
          iters: int = 100) -> tuple[np.ndarray, np.ndarray]:
    """Iteratively reweighted least squares from ``theta`` with a fixed residual ``scale``:
    Huber (convex, a safe start) or Tukey's biweight (outliers get weight 0)."""
    s = max(scale, 1e-12)
    w = np.ones_like(x)
    for _ in range(iters):
        u = (y - theta[0] - theta[1] * x) / s
        if kind == "huber":
            w = np.minimum(1.0, _HUBER_C / np.maximum(np.abs(u), 1e-300))
        else:
            w = np.where(np.abs(u) < _TUKEY_C, (1 - (u / _TUKEY_C) ** 2) ** 2, 0.0)
        new = _wls(x, y, w)
        if new is None:
            break
        done = np.abs(new - theta).max() < 1e-12
        theta = new
        if done:
            break
    return theta, w


def _robust_line(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, float] | None:
    """Least squares, then Huber, then Tukey's biweight at the Huber fit's robust scale
    (an MM-style fit: up to about half the points may be outliers). ``(theta, weights, scale)``."""
    theta = _wls(x, y, np.ones_like(x))
    if theta is None:
        return None
    scale = _robust_scale(y - theta[0] - theta[1] * x)
    theta, _ = _irls(x, y, theta, scale, "huber")
    scale = _robust_scale(y - theta[0] - theta[1] * x)
    theta, w = _irls(x, y, theta, scale, "tukey")
    return theta, w, scale


def _points(boxes: Sequence, classes: Sequence[Sequence[str]], image_heights: int | Sequence[int],
            heights: Mapping[str, float], border_px: float) -> tuple[np.ndarray, ...]:
    """Per usable box: x, y, frame index, image height, class name (numpy arrays)."""
    if len(boxes) != len(classes):
        raise ValueError(f"fit_camera: {len(boxes)} frames of boxes but {len(classes)} frames of classes")
    hs = [image_heights] * len(boxes) if isinstance(image_heights, (int, float)) else list(image_heights)
    if len(hs) != len(boxes):
        raise ValueError(f"fit_camera: {len(boxes)} frames of boxes but {len(hs)} image heights")
    xs, ys, fr, hi, names = [], [], [], [], []
    for f, (b, c, h_img) in enumerate(zip(boxes, classes, hs)):
        b = np.asarray(b, dtype=np.float64).reshape(-1, 4)
        if len(b) != len(c):
            raise ValueError(f"fit_camera: frame {f} has {len(b)} boxes but {len(c)} class names")
        if not h_img > 0:
            raise ValueError(f"fit_camera: frame {f}: image height must be > 0, got {h_img}")
        for (x1, y1, x2, y2), name in zip(b, c):
            bh = y2 - y1
            if name not in heights or not bh > 0 or y1 <= border_px or y2 >= h_img - 1 - border_px:
                continue
            xs.append(bh / h_img / heights[name])
            ys.append(y2 / h_img)
            fr.append(f)
            hi.append(h_img)
            names.append(name)
    return np.array(xs), np.array(ys), np.array(fr, dtype=np.int64), np.array(hi, dtype=np.float64), np.array(names)


def _bootstrap(x: np.ndarray, y: np.ndarray, frames: np.ndarray, samples: int, level: float,
               seed: int) -> tuple[tuple[float, float], tuple[float, float]]:
    """Percentile intervals of (horizon, camera height) over fits to frames drawn with replacement."""
    rng = np.random.default_rng(seed)
    ids = np.unique(frames)
    members = [np.flatnonzero(frames == i) for i in ids]
    got = []
    for _ in range(samples):
        pick = np.concatenate([members[j] for j in rng.integers(len(ids), size=len(ids))])
        fit = _robust_line(x[pick], y[pick])
        if fit is not None:
            got.append(fit[0])
    if not got:
        raise ValueError("fit_camera: no bootstrap sample could be fitted (too few distinct depths)")
    arr = np.array(got)
    q = [(1 - level) / 2, (1 + level) / 2]
    a, b = np.quantile(arr[:, 0], q), np.quantile(arr[:, 1], q)
    return (float(a[0]), float(a[1])), (float(b[0]), float(b[1]))


def _per_class(theta: np.ndarray, x: np.ndarray, y: np.ndarray, w: np.ndarray, h_img: np.ndarray,
               names: np.ndarray, heights: Mapping[str, float]) -> dict[str, ClassResidual]:
    out: dict[str, ClassResidual] = {}
    r_px = (y - theta[0] - theta[1] * x) * h_img
    for name in dict.fromkeys(names.tolist()):
        m = names == name
        r = r_px[m]
        depth_ratio = (y[m] - theta[0]) / theta[1]  # (bottom − horizon) / (H_img · camera height)
        ok = depth_ratio > 0
        implied = float(np.median(x[m][ok] * heights[name] / depth_ratio[ok])) if ok.any() else float("nan")
        out[name] = ClassResidual(int(m.sum()), float(np.median(r)), float(np.median(np.abs(r - np.median(r)))),
                                  implied, int((w[m] == 0).sum()))
    return out


def fit_camera(
    boxes: Sequence,
    classes: Sequence[Sequence[str]],
    image_heights: int | Sequence[int],
    class_heights: Mapping[str, float] | None = None,
    level: float = 0.95,
    samples: int = 500,
    seed: int = 0,
    min_boxes: int = 8,
    border_px: float = 1.0,
    box_height_factor: float = BOX_HEIGHT_FACTOR,
) -> CameraFit:
    """Fit the horizon row and the camera height from labelled 2D boxes of one camera.

    An object of real height ``H`` standing on a flat road at depth ``Z`` has a box of height
    ``h = f·H/Z`` whose bottom row is ``f·cam_h/Z`` below the horizon, so
    ``bottom − horizon = h · cam_h / H``: a line in the two unknowns. It is solved by least
    squares, then robustly (Huber, then Tukey's biweight by iteratively reweighted least
    squares), so truncated, occluded and sitting objects and hills get little or no weight.
    Rows are taken as fractions of each frame's image height, so frames may differ in size.
    The intervals come from refitting to frames drawn with replacement (``samples`` times).

    Args:
        boxes: per frame, ``[N_i, 4]`` boxes ``(x1, y1, x2, y2)`` in pixels (tensor or array).
        classes: per frame, the ``N_i`` class names; boxes of a class absent from
            ``class_heights`` are left out.
        image_heights: the image height in pixels, one for all frames or one per frame.
        class_heights: real height per class name (default :data:`KITTI_CLASS_HEIGHTS_M`); the
            camera height comes out in the same unit.
        level: coverage of the intervals, in (0, 1).
        samples: bootstrap samples (>= 1).
        seed: seed of the bootstrap.
        min_boxes: fewest usable boxes accepted (>= 3).
        border_px: boxes whose top or bottom lies within this many pixels of the image border
            are left out (their height or bottom row is cut).
        box_height_factor: the class heights are multiplied by this (:data:`BOX_HEIGHT_FACTOR`,
            2D boxes against 3D heights; 1.0: the plain model, e.g. for boxes of flat objects).

    Raises:
        ValueError: inputs of mismatched lengths, no usable box (no class with a known height),
            fewer than ``min_boxes`` usable boxes or than two frames, all boxes at one depth,
            or a fit that puts the camera below the road.
    """
    heights = dict(KITTI_CLASS_HEIGHTS_M if class_heights is None else class_heights)
    bad = {k: v for k, v in heights.items() if not (isinstance(v, (int, float)) and v > 0)}
    if bad or not heights or not box_height_factor > 0:
        raise ValueError(f"fit_camera: class_heights must map class names to heights > 0 and box_height_factor "
                         f"be > 0, got {heights}, {box_height_factor}")
    given = heights
    heights = {k: v * box_height_factor for k, v in heights.items()}
    if not 0 < level < 1 or samples < 1 or min_boxes < 3:
        raise ValueError(f"fit_camera: need 0 < level < 1, samples >= 1, min_boxes >= 3; got {level}, {samples}, "
                         f"{min_boxes}")
    x, y, frames, h_img, names = _points(boxes, classes, image_heights, heights, border_px)
    if len(x) == 0:
        raise ValueError(f"fit_camera: no usable labelled box (classes with a known height: "
                         f"{', '.join(heights)}; boxes cut by the top or bottom border are left out)")
    if len(x) < min_boxes:
        raise ValueError(f"fit_camera: only {len(x)} usable boxes, need at least {min_boxes}")
    if len(np.unique(frames)) < 2:
        raise ValueError("fit_camera: the boxes come from one frame; the uncertainty needs at least two frames")
    fit = _robust_line(x, y)
    if fit is None:
        raise ValueError("fit_camera: all boxes have the same height ratio (one depth): the line is undetermined")
    theta, w, scale = fit
    if not theta[1] > 0:
        raise ValueError(f"fit_camera: the fitted camera height is {theta[1]:.3g} (not above the road): "
                         "are the class names or the heights right?")
    hor_iv, cam_iv = _bootstrap(x, y, frames, samples, level, seed)
    return CameraFit(float(theta[0]), float(theta[1]), hor_iv, cam_iv, level, len(x), len(np.unique(frames)),
                     int((w == 0).sum()), scale, _per_class(theta, x, y, w, h_img, names, given),
                     x, y, w, tuple(names.tolist()))
