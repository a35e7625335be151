"""KITTI-format folders read whole: frame ranges that select frames by their numeric id,
each folder's frames decoded with their labels, and the folders' short names.

Frame ranges (``--frames``, :func:`parse_frame_range`) take both ends::

    0:39      # 000000-000039
    40:       # 000040 and later;  ":9" = up to 000009;  "7" = 000007 only
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

__all__ = [
    "FrameRange",
    "parse_frame_range",
    "select_frames",
    "load_kitti",
    "load_folders",
    "folder_names",
    "folder_splits",
    "folder_blocks",
]


@dataclass(frozen=True)
class FrameRange:
    """Frames whose numeric id lies in ``[first, last]`` (both included; ``None`` = open)."""

    first: int | None
    last: int | None
    text: str
    """The range as given (e.g. ``"0:39"``), used as its name in the tables."""

    def __contains__(self, frame_id: int) -> bool:
        return (self.first is None or frame_id >= self.first) and (
            self.last is None or frame_id <= self.last
        )


def parse_frame_range(text: str) -> FrameRange:
    """Parse ``"A:B"``, ``"A:"``, ``":B"`` or ``"A"`` (non-negative integers, A <= B).

    Raises:
        ValueError: anything else; the message quotes the text.
    """
    s = str(text).strip()
    parts = s.split(":")
    if len(parts) == 1:
        parts = [parts[0], parts[0]]
    if len(parts) != 2 or not any(parts):
        raise ValueError(f"frame range {text!r}: expected A:B, A:, :B or A (frame ids, both ends included)")
    bounds: list[int | None] = []
    for p in parts:
        p = p.strip()
        if not p:
            bounds.append(None)
        elif p.isdigit():
            bounds.append(int(p))
        else:
            raise ValueError(f"frame range {text!r}: {p!r} is not a non-negative integer frame id")
    first, last = bounds
    if first is not None and last is not None and first > last:
        raise ValueError(f"frame range {text!r}: first id {first} is after last id {last}")
    return FrameRange(first, last, s)


def select_frames(ids: Sequence[str], ranges: Sequence[FrameRange]) -> list[str]:
    """The ids (file stems such as ``"000041"``) that fall in any of ``ranges``, in order.

    Raises:
        ValueError: an id is not a number (``--frames`` needs numeric KITTI ids).
    """
    if not ranges:
        return list(ids)
    out = []
    for i in ids:
        if not i.isdigit():
            raise ValueError(f"frame id {i!r} is not numeric; --frames selects KITTI's numeric ids")
        if any(int(i) in r for r in ranges):
            out.append(i)
    return out


def load_kitti(
    root: str | os.PathLike,
    limit: int | None = None,
    frames: Sequence[FrameRange] = (),
    classes: Sequence[str] | None = None,
) -> tuple[list[dict[str, Any]], tuple[str, ...]]:
    """Decode the frames of a KITTI-format folder (:class:`reeb_torch.datasets.kitti.KittiDataset`).

    ``frames`` select by id first, then ``limit`` keeps the first N of those.

    Returns:
        ``(items, class names)``: each item is a dataset sample (``image`` uint8
        ``Tensor[3, H, W]``, ``boxes`` ``Tensor[N, 4]``, ``labels``, ``truncated``,
        ``occluded``, ``image_id``, ...).

    Raises:
        ValueError: not a KITTI folder, no images, a bad id, or no frame in ``frames``.
    """
    from .kitti import DEFAULT_CLASSES, KittiDataset

    cls = tuple(DEFAULT_CLASSES if classes is None else classes)
    ds = KittiDataset(root, classes=cls)
    ids = select_frames(ds.ids, frames)
    if not ids:
        raise ValueError(f"{root}: no frame with an id in {' '.join(r.text for r in frames)}")
    ds = KittiDataset(root, classes=cls, ids=ids, limit=limit)
    if ds.label_dir is None:
        raise ValueError(
            f"{root}: no label folder (labels/ or label_2/ beside {ds.image_dir.name}/): "
            "recall needs the ground-truth boxes"
        )
    return [ds[i] for i in range(len(ds))], ds.classes


def folder_names(roots: Sequence[str | os.PathLike]) -> list[str]:
    """A short name for each data folder, for the tables: its last path component, or more
    of its path where two folders would share a name (``a/kitti``, ``b/kitti``)."""
    parts = [os.path.normpath(os.path.abspath(r)).split(os.sep) for r in roots]
    depth = 1
    while depth < max((len(p) for p in parts), default=1):
        names = [os.sep.join(p[-depth:]) for p in parts]
        if len(set(names)) == len(names):
            return names
        depth += 1
    return [os.sep.join(p) for p in parts]


def load_folders(
    roots: Sequence[str | os.PathLike],
    limit: int | None = None,
    frames: Sequence[FrameRange] = (),
    classes: Sequence[str] | None = None,
) -> tuple[list[dict[str, Any]], tuple[str, ...]]:
    """:func:`load_kitti` of each folder in turn, the items of all of them in order, each
    with a ``folder`` entry (:func:`folder_names`). ``limit`` and ``frames`` apply to each
    folder (``frames`` needs numeric ids in every folder).

    Raises:
        ValueError: no folder, or one of them as :func:`load_kitti` raises it.
    """
    if not roots:
        raise ValueError("no data folder given")
    items: list[dict[str, Any]] = []
    names = folder_names(roots)
    cls: tuple[str, ...] = ()
    for root, name in zip(roots, names):
        got, cls = load_kitti(root, limit=limit, frames=frames, classes=classes)
        for it in got:
            it["folder"] = name
        items += got
    return items, cls


def folder_splits(items: Sequence[dict[str, Any]]) -> list[tuple[str, list[int]]]:
    """``[(folder name, item indices)]`` in the order the folders were given, for items of
    :func:`load_folders`; empty when all items come from one folder."""
    return folder_blocks([it.get("folder", "") for it in items])


def folder_blocks(folders: Sequence[str]) -> list[tuple[str, list[int]]]:
    """``[(folder name, indices)]`` of a list of per-frame folder names, in their first
    order; empty when all frames come from one folder."""
    out: dict[str, list[int]] = {}
    for i, f in enumerate(folders):
        out.setdefault(f, []).append(i)
    return list(out.items()) if len(out) > 1 else []
