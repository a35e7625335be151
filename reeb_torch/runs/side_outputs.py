"""The folders a run writes one file per image into, beside its rows: ``--viz`` pictures
(``reeb propose``, ``reeb detect``) and ``--kitti-dir`` result files (``reeb detect``).

Each image's file name is fixed by the whole input list (:func:`unique_stems`), so a run
resumed after an interruption names its files as an uninterrupted run does. Both folders are
checked before any work. A ``--kitti-dir`` holds the results of one run only
(:meth:`KittiFolder.prepare`): a folder holding other files is refused, earlier results are
replaced only with ``--overwrite`` (or continued with ``--resume``), and each file is made
from the image's row, so the files of a resumed run are those of an uninterrupted one. A
file that cannot be written is named with its option and folder: a result file stops the
run (:class:`SideOutputError`; the rows done are kept), a picture stops the pictures.
"""

from __future__ import annotations

import math
import os
from collections import Counter
from pathlib import Path
from typing import Any, Callable, Sequence

from .claim import claim
from .common import UsageProblem, writable_folder

__all__ = ["unique_stems", "SideOutputError", "PictureFolder", "KittiFolder"]


def unique_stems(paths: Sequence[str | os.PathLike], taken: set[str] | frozenset[str] = frozenset()) -> list[str]:
    """A distinct file stem per path, in order: its own, or ``<stem>-<n>`` (``n`` its
    1-based position) where two paths share one or the stem is in ``taken``."""
    stems = Counter(Path(p).stem for p in paths)
    used = set(taken)
    names = []
    for i, p in enumerate(paths):
        stem = Path(p).stem
        name = stem if stems[stem] == 1 and stem not in used else f"{stem}-{i + 1}"
        while name in used:
            name = f"{stem}-{i + 1}-{len(used)}"
        used.add(name)
        names.append(name)
    return names


class SideOutputError(Exception):
    """A side output (a ``--kitti-dir`` file) could not be written: the run stops, its rows
    are saved; the message names the option, the folder and the file."""


def _why(e: OSError) -> str:
    return e.strerror or str(e)


class PictureFolder:
    """``--viz DIR``: a picture per image, ``<stem>.png``, never over an input image, and over
    a file already there only with ``--overwrite`` (or ``--resume``: :meth:`prepare`). When
    one cannot be written (a full disk) a warning names the folder, the picture and the
    cause, and no more are tried;
    :attr:`problem` is then the cause (the closing summary counts the pictures not written,
    the exit code is 1)."""

    option = "--viz"

    def __init__(self, path: str | os.PathLike, warn: Callable[[str], None]) -> None:
        self.path = Path(path)
        writable_folder(self.option, self.path)
        self.warn = warn
        self.problem: str | None = None
        self.written = self.not_written = 0

    def prepare(self, inputs: Sequence[str | os.PathLike], stems: Sequence[str], *, resume: bool,
                overwrite: bool) -> None:
        """Before any work: a usage error where a picture would be written over an input image
        (whatever the options), or over a file already there (unless ``overwrite``, or
        ``resume``: the pictures of the run it goes on with)."""
        names = {f"{stem}.png" for stem in stems}
        folder = self.path.resolve()
        for p in inputs:
            q = Path(p).resolve()
            if q.parent == folder and q.name in names:
                raise UsageProblem(f"{self.option} {self.path}: its pictures would be written over the input "
                                   f"image {p}; give a folder that holds no input")
        if overwrite or resume:
            return
        there = sorted(n for n in names if (self.path / n).exists())
        if there:
            shown = ", ".join(there[:3]) + (f" and {len(there) - 3} more" if len(there) > 3 else "")
            raise UsageProblem(f"{self.option} {self.path}: holds {shown} already; add --overwrite to replace "
                               "them, or give another folder")

    def save(self, stem: str, picture: Callable[[], Any]) -> None:
        """Write ``picture()`` (an RGB array) as ``<stem>.png``, unless pictures have stopped."""
        from .viz import save_png

        if self.problem is not None:
            self.not_written += 1
            return
        target = self.path / f"{stem}.png"
        try:
            save_png(target, picture())
            self.written += 1
        except OSError as e:
            self.not_written += 1
            self.problem = _why(e)
            self.warn(f"warning: {self.option} {self.path}: cannot write the picture {target.name} ({self.problem}); "
                      "no more pictures are written in this run")

    def summary(self) -> list[str]:
        """The closing summary's line on the pictures."""
        if self.problem is None:
            return [f"pictures in {self.path}/"] if self.written else []
        return [f"warning: {self.option} {self.path}: {self.not_written} pictures not written, "
                f"{self.written} written ({self.problem})"]


def _result_file_problem(p: Path) -> str | None:
    """None when ``p`` is a KITTI result file (lines of 16 fields, the last a score; empty
    for an image without detections), else why it is not one."""
    if not p.is_file() or p.is_symlink():
        return "not a plain file"
    if p.suffix != ".txt":
        return "not a .txt file"
    try:
        with open(p, "rb") as f:
            data = f.read(1 << 20)
        lines = data.decode("utf-8", "replace").splitlines()
    except OSError as e:
        return f"not readable ({_why(e)})"
    if len(data) == 1 << 20:  # a long file: its lines read whole
        lines = lines[:-1]
    for n, line in enumerate(lines, 1):
        fields = line.split()
        if not fields:
            continue
        if len(fields) == 15:
            return f"line {n} has 15 fields: a label file, not results"
        try:
            ok = len(fields) == 16 and math.isfinite(float(fields[15]))
        except ValueError:
            ok = False
        if not ok:
            return f"line {n} is not a KITTI result line"
    return None


class KittiFolder:
    """``--kitti-dir DIR``: one KITTI result file per image with an ``ok`` row
    (``<stem>.txt``, :func:`reeb_torch.detection.result_lines`), made from the row itself.

    :meth:`prepare` (before any work) locks the folder (one run at a time, as an output
    file) and keeps it to one run's results: files that are
    not KITTI result files (label files, anything else) are refused whatever the options;
    result files of an earlier run are refused unless ``--overwrite`` (they are removed) or,
    with ``--resume``, they are those of the rows the output keeps (written again from them)."""

    option = "--kitti-dir"

    def __init__(self, path: str | os.PathLike, categories: Sequence[str]) -> None:
        self.path = Path(path)
        self.index = {str(c): i for i, c in enumerate(categories)}
        self.categories = tuple(categories)
        self.written = 0

    def prepare(self, kept: set[str], *, resume: bool, overwrite: bool) -> None:
        """Check the folder before any work: with ``resume`` it may hold the files of the
        rows kept from before (``kept``: their stems; they are written again from the rows),
        else nothing; other result files only with ``overwrite`` (they are removed)."""
        writable_folder(self.option, self.path)
        self._lock()
        entries = sorted(p for p in self.path.iterdir() if not p.name.startswith("."))
        others = [(p, why) for p in entries if (why := _result_file_problem(p))]
        if others:
            p, why = others[0]
            raise UsageProblem(
                f"{self.option} {self.path}: holds {len(others)} file{'s' if len(others) != 1 else ''} that "
                f"{'are' if len(others) != 1 else 'is'} not KITTI result files ({p.name}: {why}); it takes the "
                "results of one run: choose an empty folder")
        foreign = [p for p in entries if not (resume and p.stem in kept)]
        if foreign and not overwrite:
            what = "that are not of the rows kept in the output" if resume else "of an earlier run"
            raise UsageProblem(
                f"{self.option} {self.path}: holds {len(foreign)} KITTI result files {what} (e.g. {foreign[0].name}); "
                "add --overwrite to replace them, or choose an empty folder")
        for p in foreign:  # --overwrite: the results of the run before go (this run's are written again)
            p.unlink()

    def _lock(self) -> None:
        """One run per folder, as per output file (:func:`.claim.claim`: a hidden
        ``.NAME.reeb-lock`` beside it), held until the command ends; a usage error when another
        run holds it."""
        claim([self.path], option=self.option)

    def write(self, stem: str, row: dict) -> None:
        """The result file of an ``ok`` row (its boxes, labels and scores);
        :class:`SideOutputError` when it cannot be written."""
        import torch

        from ..detection.kitti import result_lines, write_text

        labels = row.get("labels") or []
        lines = result_lines(torch.tensor(row["boxes"], dtype=torch.float64).reshape(-1, 4),
                             torch.tensor([self.index[str(n)] for n in labels], dtype=torch.int64),
                             torch.tensor(row["scores"], dtype=torch.float64), self.categories)
        target = self.path / f"{stem}.txt"
        try:
            write_text(target, "".join(line + "\n" for line in lines))
        except OSError as e:
            raise SideOutputError(f"{self.option} {self.path}: cannot write the KITTI result file {target.name} "
                                  f"({_why(e)})") from None
        self.written += 1
