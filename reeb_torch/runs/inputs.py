"""Finding the images to process: files, folders and glob patterns expanded into a sorted
list of image paths (:func:`scan_images`), with a note for each argument that gave nothing
or each entry skipped, and :class:`NoImagesError` (a usage error) when nothing is found."""

from __future__ import annotations

import glob
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

from ..io import IMAGE_EXTENSIONS
from .rows import resolved_path

__all__ = ["NoImagesError", "FoundImages", "find_images", "scan_images", "same_file_note"]


class NoImagesError(ValueError):
    """The given paths name no image (a usage error: nothing to do)."""


_GLOB_CHARS = re.compile(r"[*?\[]")


def _natural_key(p: Path) -> list:
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", str(p))]


def _is_image_name(p: Path) -> bool:
    return p.suffix.lower() in IMAGE_EXTENSIONS


def _is_file(p: Path) -> bool:
    try:
        return p.is_file()
    except OSError:  # a file in a folder we may not enter
        return False


def _unreachable(p: Path) -> bool:
    """Whether ``p`` names something that is there but cannot be looked at (a file in a
    folder without search permission) or a broken symbolic link: such a path named on the
    command line is an input that fails with its own ``error:`` row, not a usage error."""
    try:
        os.stat(p)
    except PermissionError:
        return True
    except OSError:
        return os.path.islink(p)
    return False


def _skip_reason(p: Path) -> str:
    """The note for a folder entry with an image's name that is not a file."""
    if os.path.islink(p) and not os.path.exists(p):
        return f"{p}: skipped, a broken symbolic link (to {os.readlink(p)})"
    if p.is_dir():
        return f"{p}: skipped, a folder named like an image"
    return f"{p}: skipped, not a regular file"


def _folder_images(d: Path, recursive: bool, notes: list[str]) -> list[Path]:
    """The files with an image's extension in folder ``d`` (and its sub-folders if
    ``recursive``), sorted naturally; entries skipped are named in ``notes``."""
    it = d.rglob("*") if recursive else d.iterdir()
    found = []
    for p in it:
        if _is_image_name(p) and not _is_file(p):
            notes.append(_skip_reason(p))  # a broken link, a folder named x.png: named
        elif _is_image_name(p):
            found.append(p)
    if recursive:  # sub-folders that cannot be listed are skipped by rglob: name them
        for _ in os.walk(d, onerror=lambda e: notes.append(
                f"{e.filename}: skipped, cannot list this folder ({e.strerror or e})")):
            pass
    return sorted(found, key=_natural_key)


@dataclass
class FoundImages:
    """What :func:`scan_images` found: the ``images`` to process, the ``notes`` to show (see
    :func:`find_images`), and the paths left out as ``same_file`` as an earlier one, each
    ``(left out, the path kept)``."""

    images: list[Path]
    notes: list[str]
    same_file: list[tuple[Path, Path]]


def same_file_note(same_file: Sequence[tuple[Path, Path]], shown: int = 3) -> str:
    """One line for the paths left out as the same file as another: how many, the first few."""
    n = len(same_file)
    first = ", ".join(f"{p} (= {kept})" for p, kept in same_file[:shown])
    return (f"skipped {n} path{'s' if n != 1 else ''}, the same file as another: {first}"
            + (f", and {n - shown} more" if n > shown else ""))


def find_images(paths: Sequence[str | os.PathLike], recursive: bool = False) -> tuple[list[Path], list[str]]:
    """``(images, notes)`` of :func:`scan_images`."""
    found = scan_images(paths, recursive)
    return found.images, found.notes


def scan_images(paths: Sequence[str | os.PathLike], recursive: bool = False) -> FoundImages:
    """Expand ``paths`` into the image files to process.

    - a file is taken as given, whatever its extension (a file that is not an image then
      fails with a clear status, it is not silently skipped);
    - a folder contributes the files in it whose extension is an image extension
      (:data:`reeb_torch.io.IMAGE_EXTENSIONS`), and those of its sub-folders if
      ``recursive``; other files (labels, calibration) are ignored;
    - a pattern with ``*``, ``?`` or ``[`` that names no existing file is expanded as a
      glob (``**`` matches sub-folders); matched folders are expanded as above.

    The images are sorted naturally within each argument; a path to the same file as an
    earlier one (the same resolved path: a symbolic link, a file named twice) is left out
    and listed in ``same_file``. The notes: one line per argument that contributed nothing
    (an empty folder, a pattern that matched no image), per entry that was skipped
    (``"<path>: skipped, <why>"``: a broken symbolic link or a folder with an image's name, a
    sub-folder that cannot be listed), and one for the paths left out as the same file
    (:func:`same_file_note`). A file named as such that cannot be looked at (no permission,
    a broken link) is listed: it fails with an ``error:`` row. Raises
    :class:`NoImagesError` when a path does not exist or when no image is found at all.
    """
    images: list[Path] = []
    notes: list[str] = []
    seen: dict[str, Path] = {}  # resolved path -> the path kept for it
    same_file: list[tuple[Path, Path]] = []

    def add(p: Path) -> int:
        key = resolved_path(p)  # one file reached by two paths (a symlink) is listed once
        if key in seen:
            same_file.append((p, seen[key]))
            return 0
        seen[key] = p
        images.append(p)
        return 1

    for arg in paths:
        p = Path(arg)
        if _is_file(p) or _unreachable(p):  # a file we may not read still gets its error row
            add(p)
        elif p.is_dir():
            found = _folder_images(p, recursive, notes)
            n = sum(add(f) for f in found)
            if not found:
                where = "or its sub-folders " if recursive else ""
                hint = "" if recursive else " (use --recursive to look in sub-folders)"
                notes.append(f"{p}: no images in this folder {where}"
                             f"(looked for {', '.join(IMAGE_EXTENSIONS)}){hint}")
            elif n == 0:
                notes.append(f"{p}: all images already listed")
        elif _GLOB_CHARS.search(str(arg)):
            matched = sorted((Path(m) for m in glob.glob(str(arg), recursive=True)), key=_natural_key)
            n = 0
            for m in matched:
                if m.is_dir():
                    n += sum(add(f) for f in _folder_images(m, recursive, notes))
                elif m.is_file() and _is_image_name(m):
                    n += add(m)
            if n == 0:
                notes.append(f"{arg}: the pattern matched no image file")
        elif p.exists():
            raise NoImagesError(f"{p}: not a regular file or folder")
        else:
            raise NoImagesError(f"{p}: no such file or folder")
    if not images:
        detail = "; ".join(notes) if notes else "no paths given"
        raise NoImagesError(f"no images found: {detail}")
    if same_file:
        notes.append(same_file_note(same_file))
    return FoundImages(images, notes, same_file)
