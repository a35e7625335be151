"""KITTI-format frames in, KITTI result files out: the detector's data on disk.

:func:`load_frames` reads labelled KITTI-format folders (``images/`` + ``labels/``, or
KITTI's ``image_2/`` + ``label_2/``; :class:`reeb_torch.datasets.kitti.KittiDataset`) into the
items a detector trains on. :func:`result_lines` and :func:`write_results` write one KITTI
result file per image, the format KITTI's object devkit (and its Python ports) scores::

    Car -1 -1 -10 712.40 143.00 810.73 307.92 -1 -1 -1 -1000 -1000 -1000 -10 0.9731

(type, truncated, occluded, alpha, the 2D box ``x1 y1 x2 y2`` in pixels, the 3D size,
location and yaw unknown, the score). :func:`reeb_torch.datasets.kitti.read_kitti_labels`
reads them back.
"""

from __future__ import annotations

import os
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from PIL import Image
from torch import Tensor

from ..datasets.kitti import KittiDataset, read_kitti_labels
from ..io import read_image, replace_file
from .head_training import mirror_boxes

__all__ = ["KITTI_CLASSES", "NEIGHBOURS", "load_frames", "image_size", "frame_image", "FolderSurvey", "survey_folder", "distinct_folders",
           "mirrored", "result_lines", "write_results", "write_text"]

KITTI_CLASSES = ("Car", "Pedestrian", "Cyclist")
"""The classes KITTI's 2D benchmark scores, as its label files name them."""

NEIGHBOURS = ("Van", "Person_sitting")
"""KITTI's neighbouring classes of Car and Pedestrian: neither target nor background in
training (and ignored by KITTI's evaluation when it scores those classes)."""


def _boxes_of(objects: Sequence[Any], types: Sequence[str]) -> Tensor:
    return torch.tensor([o.box for o in objects if o.type in types], dtype=torch.float32).reshape(-1, 4)


def load_frames(folders: Sequence[str | os.PathLike], classes: Sequence[str] = KITTI_CLASSES,
                limit: int | None = None, lazy: bool = False) -> list[dict[str, Any]]:
    """Every labelled frame of ``folders``, in folder then id order. ``lazy``: no image is
    decoded (no ``image`` entry; ``size``, ``(H, W)`` from the file's header, in its place):
    for frames too many to hold, each decoded when its turn comes.

    Returns:
        One dict per frame: ``image`` (``uint8 [3, H, W]``), ``boxes`` (``float32 [N, 4]``
        xyxy pixels) and ``labels`` (``int64 [N]``, 1..C: the index in ``classes`` plus one,
        0 being the background) of the objects of ``classes``; ``ignore`` (``[M, 4]``, the
        :data:`NEIGHBOURS` not among ``classes``) and ``dontcare`` (``[K, 4]``); ``objects``
        (every label line, for KITTI's AP); ``occluded``, ``truncated``; ``image_id``,
        ``folder`` (the folder's name) and ``path``.

    Raises:
        ValueError: a folder without images or without labels (one line naming it).
    """

    neighbours = tuple(n for n in NEIGHBOURS if n not in classes)
    items = []
    for root in map(Path, folders):
        ds = KittiDataset(root, classes=tuple(classes), limit=limit)
        if ds.label_dir is None:
            raise ValueError(f"{root}: no label folder (labels/ or label_2/): a detector trains on labelled frames")
        for i in range(len(ds)):
            if lazy:
                size = image_size(ds.image_paths[i])
                it = ds.load_target(i, (size[1], size[0]))
                picture: dict[str, Any] = {"size": size}
            else:
                it = ds[i]
                picture = {"image": it["image"]}
            objects = read_kitti_labels(ds.label_dir / f"{it['image_id']}.txt")
            items.append({**picture, "boxes": it["boxes"], "labels": it["labels"] + 1,
                          "occluded": it["occluded"], "truncated": it["truncated"], "objects": objects,
                          "ignore": _boxes_of(objects, neighbours), "dontcare": _boxes_of(objects, ("DontCare",)),
                          "image_id": str(it["image_id"]), "folder": root.name, "path": str(it["path"])})
    return items


def image_size(path: str | os.PathLike) -> tuple[int, int]:
    """``(H, W)`` of an image file, from its header (the whole image decoded where the header
    cannot be read that way).

    Raises:
        ValueError: the file is no image that can be read (one line naming it).
    """

    try:
        with Image.open(path) as im:
            w, h = im.size
            return int(h), int(w)
    except Exception:  # noqa: BLE001 - a format PIL does not read: the image reader's turn

        image = read_image(path)
        return int(image.shape[-2]), int(image.shape[-1])


def frame_image(item: dict[str, Any]) -> Tensor:
    """An item's ``uint8 [3, H, W]`` image: its ``image``, or decoded from its ``path`` (and
    flipped left to right where it is a lazy mirror, :func:`mirrored`)."""
    if "image" in item:
        return item["image"]

    image = read_image(item["path"])
    return image.flip(-1).contiguous() if item.get("flipped") else image


@dataclass
class FolderSurvey:
    """What a labelled KITTI-format folder holds, read from its file names and label files
    alone (no image decoded): what a command checks before any work.

    Attributes:
        folder: the folder.
        frames: the frames taken (the first ``limit`` images, in id order).
        labelled: whether it has a label folder (``labels/`` or ``label_2/``).
        objects: label lines of the frames taken, by type (``DontCare`` too).
        orphans: ids of the label files that have no image (never used).
    """

    folder: Path
    frames: int
    labelled: bool
    objects: Counter[str]
    orphans: list[str]


def survey_folder(folder: str | os.PathLike, limit: int | None = None) -> FolderSurvey:
    """The :class:`FolderSurvey` of ``folder`` (its first ``limit`` frames).

    Raises:
        ValueError: not a KITTI-format folder, no images, a frame without its label file,
            or a label line that cannot be read (one line naming the file).
    """

    ds = KittiDataset(folder, classes=(), limit=limit)
    objects: Counter[str] = Counter()
    orphans: list[str] = []
    if ds.label_dir is not None:
        for i in ds.ids:
            objects.update(o.type for o in read_kitti_labels(ds.label_dir / f"{i}.txt"))
        images = {p.stem for p in ds.image_dir.iterdir()}
        orphans = sorted(p.stem for p in ds.label_dir.glob("*.txt") if p.stem not in images)
    return FolderSurvey(Path(folder), len(ds), ds.label_dir is not None, objects, orphans)


def distinct_folders(folders: Sequence[str | os.PathLike]) -> tuple[list[str | os.PathLike], list[str | os.PathLike]]:
    """``(kept, repeated)``: ``folders`` with each folder once (the first naming of each
    resolved path, in order), and the namings left out."""
    seen: set[Path] = set()
    kept: list[str | os.PathLike] = []
    repeated: list[str | os.PathLike] = []
    for f in folders:
        key = Path(os.path.expanduser(str(f))).resolve()
        (repeated if key in seen else kept).append(f)
        seen.add(key)
    return kept, repeated


def mirrored(item: dict[str, Any]) -> dict[str, Any]:
    """A training item flipped left to right (the image and every box)."""

    if "image" not in item:  # a lazy item: flipped when decoded (frame_image)
        w = item["size"][1]
        return {**item, "flipped": True, "boxes": mirror_boxes(item["boxes"], w),
                "ignore": mirror_boxes(item["ignore"], w), "dontcare": mirror_boxes(item["dontcare"], w),
                "image_id": f"{item['image_id']}-mirror"}
    w = item["image"].shape[-1]
    return {**item, "image": item["image"].flip(-1).contiguous(), "boxes": mirror_boxes(item["boxes"], w),
            "ignore": mirror_boxes(item["ignore"], w), "dontcare": mirror_boxes(item["dontcare"], w),
            "image_id": f"{item['image_id']}-mirror"}


def result_lines(boxes: Tensor, labels: Tensor, scores: Tensor, categories: Sequence[str]) -> list[str]:
    """KITTI result lines (module doc) of one image's detections.

    Args:
        boxes: ``float [D, 4]`` xyxy pixels; ``labels``: ``int64 [D]`` indices into
            ``categories`` (``categories[0]`` the background); ``scores``: ``float [D]``.
        categories: the class names (``ReebDetector.categories``); a name with a space is
            written with ``_`` (KITTI's type is one field).
    """
    lines = []
    for (x1, y1, x2, y2), label, score in zip(boxes.tolist(), labels.tolist(), scores.tolist()):
        name = str(categories[int(label)]).replace(" ", "_")
        lines.append(f"{name} -1 -1 -10 {x1:.2f} {y1:.2f} {x2:.2f} {y2:.2f} -1 -1 -1 -1000 -1000 -1000 -10 "
                     f"{score:.4f}")
    return lines


def write_text(path: str | os.PathLike, text: str) -> Path:
    """Write ``text`` to ``path`` atomically: a temporary file beside it, then renamed."""
    return replace_file(path, text.encode("utf-8"))


def write_results(path: str | os.PathLike, detection: dict[str, Tensor], categories: Sequence[str]) -> Path:
    """One image's KITTI result file (:func:`result_lines`, one line each), written
    atomically; an image without detections gets an empty file."""
    lines = result_lines(detection["boxes"], detection["labels"], detection["scores"], categories)
    return write_text(path, "".join(line + "\n" for line in lines))
