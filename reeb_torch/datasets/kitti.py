"""KITTI 2D object data: the label reader and a ``torch`` dataset (the calibration reader
lives in :mod:`reeb_torch.camera`).

Box convention, kept everywhere in this package: ``Tensor[N, 4]`` of ``float32``,
``(x1, y1, x2, y2)`` in pixels of the full-resolution image, 0-based, ``x1 <= x2``,
``y1 <= y2``, exactly as written in KITTI's ``label_2`` files (fields 5-8).

Two folder layouts are recognised::

    root/images/<id>.png   root/labels/<id>.txt    root/calib/<id>.txt    (short names)
    root/image_2/<id>.png  root/label_2/<id>.txt   root/calib/<id>.txt    (KITTI's own)

KITTI's own layout is also found one level down, in ``root/training/``. Only the image
folder is required: without labels every target is empty, without calib ``calib`` is
``None``.

>>> ds = KittiDataset("data/kitti")                   # a KITTI-format folder
>>> item = ds[0]
>>> item["image"].shape, item["boxes"].shape          # (3, H, W) uint8, (N, 4) float32
>>> loader = torch.utils.data.DataLoader(ds, batch_size=4, collate_fn=collate_keep_sizes)
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from PIL import Image

from ..camera import read_kitti_calib
from ..io import IMAGE_EXTENSIONS, read_image

__all__ = [
    "DEFAULT_CLASSES",
    "KittiObject",
    "find_layout",
    "KittiDataset",
    "read_kitti_labels",
    "box_problem",
    "collate_keep_sizes",
]

DEFAULT_CLASSES: tuple[str, ...] = ("Car", "Pedestrian", "Cyclist", "Truck")
"""The four classes of the paper's evaluation (Table 3)."""

DONT_CARE = "DontCare"
"""KITTI's label for unlabelled regions: never a target."""

# (image folder, label folder, calib folder), in the order they are tried.
_LAYOUTS: tuple[tuple[str, str, str], ...] = (
    ("images", "labels", "calib"),
    ("image_2", "label_2", "calib"),
)

# ---------------------------------------------------------------------------------------
# labels
# ---------------------------------------------------------------------------------------


@dataclass(frozen=True)
class KittiObject:
    """One line of a KITTI ``label_2`` file.

    Attributes:
        type: class name as written (``Car``, ``Van``, ``Truck``, ``Pedestrian``,
            ``Person_sitting``, ``Cyclist``, ``Tram``, ``Misc`` or ``DontCare``).
        truncated: fraction of the object outside the image, in [0, 1].
        occluded: 0 fully visible, 1 partly occluded, 2 largely occluded, 3 unknown.
        alpha: observation angle, radians in [-pi, pi].
        box: 2D box ``(x1, y1, x2, y2)`` in pixels, 0-based.
        dimensions: 3D size ``(h, w, l)`` in metres.
        location: 3D centre of the bottom face ``(X, Y, Z)`` in camera coordinates, metres.
        rotation_y: yaw around the camera's Y axis, radians in [-pi, pi].
        score: detection confidence; only in result files (16 fields), else ``None``.
    """

    type: str
    truncated: float
    occluded: int
    alpha: float
    box: tuple[float, float, float, float]
    dimensions: tuple[float, float, float]
    location: tuple[float, float, float]
    rotation_y: float
    score: float | None = None


def _parse_label_line(fields: list[str]) -> KittiObject:
    values = [float(v) for v in fields[1:]]  # ValueError on a non-numeric field
    occluded = values[1]
    if occluded != int(occluded):
        raise ValueError(f"occluded must be an integer, got {fields[2]!r}")
    return KittiObject(
        type=fields[0],
        truncated=values[0],
        occluded=int(occluded),
        alpha=values[2],
        box=(values[3], values[4], values[5], values[6]),
        dimensions=(values[7], values[8], values[9]),
        location=(values[10], values[11], values[12]),
        rotation_y=values[13],
        score=values[14] if len(values) == 15 else None,
    )


BOX_SLACK = 1.0
"""Pixels by which a label's box may leave the image (rounding in converted labels)."""


def box_problem(box: Sequence[float], image_size: tuple[int, int] | None = None) -> str | None:
    """Why a label's box ``(x1, y1, x2, y2)`` (pixels) cannot be an object, or None.

    A box is refused when a coordinate is not a finite number, when it is inverted or has
    no area (``x2 <= x1`` or ``y2 <= y1``), when it reaches below ``-BOX_SLACK`` (negative
    coordinates), or, given ``image_size`` ``(W, H)``, past ``W + BOX_SLACK`` or
    ``H + BOX_SLACK`` (outside the image)."""
    x1, y1, x2, y2 = box
    if not all(math.isfinite(v) for v in box):
        return "a coordinate is not a finite number"
    if x2 <= x1 or y2 <= y1:
        return "the box is inverted or has no area (x2 <= x1 or y2 <= y1)"
    if min(x1, y1) < -BOX_SLACK:
        return "the box has negative coordinates"
    if image_size is not None and (x2 > image_size[0] + BOX_SLACK or y2 > image_size[1] + BOX_SLACK):
        return f"the box leaves the {image_size[0]}x{image_size[1]} image"
    return None


def read_kitti_labels(
    path: str | os.PathLike, classes: Iterable[str] | None = None,
    image_size: tuple[int, int] | None = None,
) -> list[KittiObject]:
    """Read a KITTI ``label_2`` file: one object per line, 15 whitespace-separated fields.

    ``type truncated occluded alpha x1 y1 x2 y2 h w l X Y Z ry``, plus an optional 16th
    field ``score`` in result files. Blank lines are skipped.

    Every command reads labels through this function (``reeb fit``, ``reeb eval``,
    ``reeb calibrate``, the recall tables, ``reeb show``), with one rule: a line whose box
    cannot be an object (:func:`box_problem`: a coordinate that is NaN or infinite, an
    inverted or zero-area box, negative coordinates, or, given ``image_size``, a box
    outside the image) is an error naming the file and the line, as a malformed line is;
    it is never scored, and never dropped without a word.

    Args:
        path: the label file.
        classes: keep only objects whose ``type`` is one of these (exact, case-sensitive
            names). ``None`` keeps every line as written, ``DontCare`` included.
        image_size: ``(W, H)`` of the frame's image, in pixels; None checks no upper bound.

    Returns:
        The objects in file order.

    Raises:
        FileNotFoundError: the file does not exist.
        ValueError: a line has the wrong number of fields, a non-numeric value or an
            impossible box; the message names the file and the 1-based line number.
    """
    p = Path(path)
    keep = None if classes is None else set(classes)
    objects: list[KittiObject] = []
    with open(p, encoding="utf-8") as f:
        for lineno, line in enumerate(f, start=1):
            fields = line.split()
            if not fields:
                continue
            if len(fields) not in (15, 16):
                raise ValueError(
                    f"{p}:{lineno}: expected 15 fields (16 with a score), got {len(fields)}"
                )
            try:
                obj = _parse_label_line(fields)
            except ValueError as e:
                raise ValueError(f"{p}:{lineno}: malformed KITTI label line ({e})") from None
            problem = box_problem(obj.box, image_size)
            if problem:
                raise ValueError(f"{p}:{lineno}: impossible box {list(obj.box)}: {problem}; "
                                 "correct or delete the line")
            if keep is None or obj.type in keep:
                objects.append(obj)
    return objects


# ---------------------------------------------------------------------------------------
# dataset
# ---------------------------------------------------------------------------------------


def find_layout(root: str | os.PathLike) -> tuple[Path, Path, Path]:
    """The image, label and calib folders of a KITTI-format folder (the last two may not
    exist); a ``ValueError`` when ``root`` is not one (it has no image folder of either
    layout), without reading any file."""
    root = Path(root)
    for base in (root, root / "training"):
        for images, labels, calib in _LAYOUTS:
            if (base / images).is_dir():
                return base / images, base / labels, base / calib
    raise ValueError(
        f"{root}: not a KITTI folder: expected an image folder 'images/' (with 'labels/', "
        "'calib/') or KITTI's 'image_2/' (with 'label_2/', 'calib/'), here or in 'training/'"
    )


class KittiDataset(torch.utils.data.Dataset):
    """Frames of a KITTI-format folder, with their 2D boxes and camera calibration.

    Args:
        root: the folder; its layout is detected (module docstring).
        classes: the class names that are targets, in label-index order. Objects of other
            types are dropped; ``DontCare`` is always dropped.
        transform: optional callable applied to each sample ``dict`` (returns a ``dict``),
            so that geometric transforms can move image and boxes together.
        ids: only these frames (file stems, e.g. ``"000001"``), in sorted order. An id
            with no image raises ``ValueError``.
        limit: keep only the first ``limit`` frames (after ``ids``), in sorted order.

    When a label (calib) folder exists, every selected frame must have its label (calib)
    file: a missing file raises ``ValueError`` here rather than silently yielding an
    empty target.

    Each sample is a ``dict``:

    - ``image``: ``uint8`` ``Tensor[3, H, W]``, RGB, values in [0, 255].
    - ``boxes``: ``float32`` ``Tensor[N, 4]``, ``(x1, y1, x2, y2)`` pixels.
    - ``labels``: ``int64`` ``Tensor[N]``, index into ``classes``.
    - ``class_names``: ``list[str]`` of length N, the class name of each box.
    - ``truncated``: ``float32`` ``Tensor[N]`` in [0, 1]; ``occluded``: ``int64``
      ``Tensor[N]`` in {0, 1, 2, 3} (KITTI's difficulty cues).
    - ``image_id``: ``str``, the file stem; ``path``: ``str``, the image file.
    - ``calib``: ``dict[str, Tensor]`` from :func:`~reeb_torch.camera.read_kitti_calib` (``P2`` is
      ``float64`` ``Tensor[3, 4]``), or ``None`` without a calib folder.
    """

    def __init__(
        self,
        root: str | os.PathLike,
        classes: Sequence[str] = DEFAULT_CLASSES,
        transform: Callable[[dict[str, Any]], dict[str, Any]] | None = None,
        ids: Iterable[str] | None = None,
        limit: int | None = None,
    ) -> None:
        self.root = Path(root)
        if not self.root.is_dir():
            raise ValueError(f"{self.root}: no such folder")
        if isinstance(classes, str):
            raise TypeError("classes must be a sequence of names, not one string")
        self.classes: tuple[str, ...] = tuple(classes)
        if len(set(self.classes)) != len(self.classes):
            raise ValueError(f"classes has duplicates: {self.classes}")
        self._class_index = {c: i for i, c in enumerate(self.classes) if c != DONT_CARE}
        self.transform = transform

        self.image_dir, label_dir, calib_dir = find_layout(self.root)
        self.label_dir: Path | None = label_dir if label_dir.is_dir() else None
        self.calib_dir: Path | None = calib_dir if calib_dir.is_dir() else None

        images: dict[str, Path] = {}
        for f in sorted(self.image_dir.iterdir()):
            if f.is_file() and f.suffix.lower() in IMAGE_EXTENSIONS:
                if f.stem in images:
                    raise ValueError(
                        f"{self.image_dir}: two images for id {f.stem!r}: "
                        f"{images[f.stem].name}, {f.name}"
                    )
                images[f.stem] = f
        if not images:
            raise ValueError(
                f"{self.image_dir}: no images (looked for {', '.join(IMAGE_EXTENSIONS)})"
            )

        selected = sorted(images)
        if ids is not None:
            wanted = sorted({str(i) for i in ids})
            missing = [i for i in wanted if i not in images]
            if missing:
                raise ValueError(f"{self.image_dir}: no image for ids {missing[:10]}")
            selected = wanted
        if limit is not None:
            if limit < 0:
                raise ValueError(f"limit must be >= 0, got {limit}")
            selected = selected[:limit]

        for folder, what in ((self.label_dir, "label"), (self.calib_dir, "calib")):
            if folder is not None:
                missing = [i for i in selected if not (folder / f"{i}.txt").is_file()]
                if missing:
                    raise ValueError(f"{folder}: no {what} file for ids {missing[:10]}")

        self.ids: list[str] = selected
        self.image_paths: list[Path] = [images[i] for i in selected]

    def __len__(self) -> int:
        return len(self.ids)

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(root={str(self.root)!r}, n={len(self)}, "
            f"classes={self.classes}, labels={self.label_dir is not None}, "
            f"calib={self.calib_dir is not None})"
        )

    def load_target(self, index: int, image_size: tuple[int, int] | None = None) -> dict[str, Any]:
        """The sample of frame ``index`` without decoding its image (no ``image`` key,
        no ``transform``): cheap access to the ground truth, e.g. for recall tables.
        ``image_size`` ``(W, H)``: the image's, where known (else read from its header),
        against which the labels' boxes are checked (:func:`read_kitti_labels`)."""
        image_id = self.ids[index]
        objects: list[KittiObject] = []
        if self.label_dir is not None:
            size = image_size if image_size is not None else _image_size(self.image_paths[index])
            objects = [
                o
                for o in read_kitti_labels(self.label_dir / f"{image_id}.txt", image_size=size)
                if o.type in self._class_index
            ]
        calib = None
        if self.calib_dir is not None:
            calib = read_kitti_calib(self.calib_dir / f"{image_id}.txt")
        return {
            "boxes": torch.tensor([o.box for o in objects], dtype=torch.float32).reshape(-1, 4),
            "labels": torch.tensor([self._class_index[o.type] for o in objects], dtype=torch.int64),
            "class_names": [o.type for o in objects],
            "truncated": torch.tensor([o.truncated for o in objects], dtype=torch.float32),
            "occluded": torch.tensor([o.occluded for o in objects], dtype=torch.int64),
            "image_id": image_id,
            "path": str(self.image_paths[index]),
            "calib": calib,
        }

    def __getitem__(self, index: int) -> dict[str, Any]:
        if not -len(self) <= index < len(self):
            raise IndexError(f"index {index} out of range for {len(self)} frames")
        index = index % len(self)
        image = read_image(self.image_paths[index])
        sample = {"image": image, **self.load_target(index, (image.shape[-1], image.shape[-2]))}
        if self.transform is not None:
            sample = self.transform(sample)
        return sample


def _image_size(path: Path) -> tuple[int, int] | None:
    """``(W, H)`` of an image from its header, or None where it cannot be read that way."""

    try:
        with Image.open(path) as im:
            return im.size
    except Exception:  # noqa: BLE001 - a format PIL does not read: the reader's error comes later
        return None


def collate_keep_sizes(batch: Sequence[Mapping[str, Any]]) -> dict[str, list[Any]]:
    """``collate_fn`` for :class:`torch.utils.data.DataLoader` that keeps every value as is.

    Images of different sizes cannot be stacked, so each key maps to the list of the
    batch's values: ``{"image": [Tensor[3, H_i, W_i], ...], "boxes": [Tensor[N_i, 4], ...],
    ...}``. All samples must have the same keys.
    """
    if len(batch) == 0:
        return {}
    keys = list(batch[0].keys())
    for i, sample in enumerate(batch):
        if set(sample.keys()) != set(keys):
            raise ValueError(
                f"collate_keep_sizes: sample {i} has keys {sorted(sample)}, "
                f"sample 0 has {sorted(keys)}"
            )
    return {k: [sample[k] for sample in batch] for k in keys}
