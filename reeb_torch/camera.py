"""The camera: KITTI calibration files and pinhole intrinsics.

Used by :meth:`reeb_torch.ReebConfig.with_kitti_calib` (opening angles from ``P2``) and by
the KITTI reader (:class:`reeb_torch.eval.data.KittiDataset` returns each frame's calib). It
depends on nothing else in the package, so the config can use it without the dataset.

A KITTI ``calib`` file has lines ``KEY: v1 v2 ...``; ``P2`` is the 3×4 projection matrix of
the left colour camera (the ``image_2`` frames), whose intrinsics are
``fx = P2[0,0]``, ``fy = P2[1,1]``, ``cx = P2[0,2]``, ``cy = P2[1,2]`` in pixels.

>>> cam = Camera.from_kitti_calib("examples/data/kitti_000001_calib.txt")
>>> cam.fx, cam.cy                     # (721.5377, 172.854)
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor

__all__ = ["Camera", "read_kitti_calib", "camera_intrinsics"]

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
    with open(p, encoding="utf-8") as f:
        for lineno, line in enumerate(f, start=1):
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
        return cls.from_matrix(calib[key])

    def fov_deg(self, width: int, height: int) -> tuple[float, float]:
        """Horizontal and vertical opening angles in degrees for a ``width × height``
        image: ``2·atan(W / 2fx)``, ``2·atan(H / 2fy)``."""
        if not (width > 0 and height > 0):
            raise ValueError(f"fov_deg needs a positive width and height, got {width} x {height}")
        return (
            math.degrees(2 * math.atan(width / (2 * self.fx))),
            math.degrees(2 * math.atan(height / (2 * self.fy))),
        )
