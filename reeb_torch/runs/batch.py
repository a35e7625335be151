"""Batch processing for the command line: find images, decode them in parallel, write results.

The pipeline that ``reeb propose`` runs over a folder reads top to bottom:

1. :func:`find_images` expands files, folders and glob patterns into a sorted list of image
   paths (a usage error, :class:`NoImagesError`, when nothing is found);
2. :func:`decoded_images` decodes them in DataLoader worker processes
   (:class:`ImageFileDataset`), so decoding overlaps with the algorithm. A worker never
   raises: a file that cannot be read becomes a :class:`Decoded` record with ``error`` set;
3. :func:`size_batches` groups decoded images of equal size into batches (the generator
   takes a ``B×3×H×W`` tensor), passing errors through at once;
4. :func:`open_writer` streams one row per image to a temporary file next to the output
   (:class:`JsonlWriter` or :class:`ParquetWriter`, chosen by extension) and
   :meth:`ResultWriter.commit` renames it into place, so the output is either the old file
   or a complete new one, never a partial one. Rows carried over by ``--resume`` come from
   :func:`read_results`.

Rows are written in input order (error rows included). While a run writes an output, it
holds a lock beside it (:func:`lock_output`): a second run on the same output fails at once
with :class:`OutputBusyError`. Rows left in a temporary file by a killed run are found by
:func:`stale_temp_files` and recovered by ``--resume``.

Row schema (one row per image, JSON Lines or Parquet; :data:`FORMAT_VERSION` 2, which
added ``labels``; rows of version 1 read the same, without it):

==============  ==========================  =============================================
field           type                        meaning
==============  ==========================  =============================================
format_version  int                         :data:`FORMAT_VERSION` of this schema
image           str                         the path as given (relative paths stay relative)
resolved        str                         absolute path, symlinks resolved
                                            (``os.path.realpath``); ``--resume`` matches on it
                                            (in both, a byte of a file name that is not
                                            UTF-8 is written ``\\xNN``: :func:`text_path`)
width           int or null                 image width in pixels as viewed (EXIF orientation
                                            applied); null if the file could not be decoded
height          int or null                 image height in pixels, likewise
boxes           list of [x1, y1, x2, y2]    proposals in image pixels, ranked best first
scores          list of float               one score per box, descending
labels          list of str or null         the class each box looks like (the learned
                                            ranking's class hint, one of
                                            ``ProposalGenerator.classes``), one per box;
                                            null where the settings give none
                                            (``ranker='none'``, or a model without a
                                            class head) and in an error row
status          str                         ``"ok"`` or ``"error: <file>: <reason>"``
config          str                         :meth:`ReebConfig.fingerprint` of the settings used
==============  ==========================  =============================================
"""

from __future__ import annotations

import errno
import glob
import json
import os
import re
import signal
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Generator, Iterable, Iterator, Sequence

import numpy as np
import torch

from ..io import IMAGE_EXTENSIONS, read_image

__all__ = [
    "FORMAT_VERSION",
    "NoImagesError",
    "OutputError",
    "OutputBusyError",
    "OutputLock",
    "lock_output",
    "stale_temp_files",
    "read_partial_results",
    "resolved_path",
    "text_path",
    "row_key",
    "CriticalSection",
    "find_images",
    "scan_images",
    "FoundImages",
    "same_file_note",
    "Decoded",
    "ImageFileDataset",
    "decoded_images",
    "size_batches",
    "result_row",
    "hint_names",
    "error_row",
    "OUTPUT_FORMATS",
    "output_format",
    "check_output",
    "read_results",
    "ResultWriter",
    "JsonlWriter",
    "ParquetWriter",
    "open_writer",
]


class NoImagesError(ValueError):
    """The given paths name no image (a usage error: nothing to do)."""


class OutputError(OSError):
    """The output file cannot be written (checked before any work is done)."""


class OutputBusyError(OutputError):
    """Another process is writing the same output file (it holds the lock beside it)."""


#: Version of the row schema (see the module docstring); written in every row.
FORMAT_VERSION = 2


def resolved_path(path: str | os.PathLike) -> str:
    """The absolute path of ``path`` with symbolic links resolved (what rows are matched on)."""
    return os.path.realpath(path)


#: Longest output name whose hidden companions (``.NAME.lock``, ``.NAME.XXXXXXXX.tmp``) are
#: named after it; a longer (legal) name gets companions named after its hash instead, so any
#: name the file system takes works as an output (255 bytes on most).
_PLAIN_NAME_BYTES = 200


def hidden_stem(path: str | os.PathLike) -> str:
    """The start of the hidden files beside output ``path``: ``.NAME``, or
    ``.reeb-<16 hex digits of NAME's SHA-256>`` when NAME is longer than 200 bytes."""
    name = os.fsencode(Path(path).name)
    if len(name) <= _PLAIN_NAME_BYTES:
        return f".{Path(path).name}"
    import hashlib

    return f".reeb-{hashlib.sha256(name).hexdigest()[:16]}"


def text_path(path: str | os.PathLike) -> str:
    """``path`` as text that UTF-8 can hold, as rows and messages write it.

    A file name that is not valid UTF-8 (an old Samba or FAT share, an archive from another
    locale) reaches Python with its undecodable bytes as surrogates (``os.fsdecode``); here
    each such byte is written as the four characters ``\\xNN`` (``x\\xff.png``), so JSON
    Lines and Parquet rows can hold it and ``--resume`` matches it (rows are matched on
    ``text_path(resolved_path(file))``). Valid names come back unchanged.
    """
    s = os.fsdecode(os.fspath(path))
    try:
        s.encode("utf-8")
        return s
    except UnicodeEncodeError:
        try:
            raw = s.encode("utf-8", "surrogateescape")
        except UnicodeEncodeError:  # a lone surrogate that is no escaped byte
            return s.encode("utf-8", "backslashreplace").decode("utf-8")
        return raw.decode("utf-8", "backslashreplace")


def row_key(path: str | os.PathLike) -> str:
    """What a row of ``path`` is matched on for ``--resume``: ``text_path(resolved_path(path))``."""
    return text_path(resolved_path(path))


# -- 1. finding images -------------------------------------------------------------------

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


# -- 2. parallel decoding ----------------------------------------------------------------

@dataclass
class Decoded:
    """One decoded image, or the reason it could not be decoded.

    ``image`` is an RGB ``uint8`` tensor ``(3, H, W)`` or ``None``; ``error`` is ``None``
    or a one-line message that names the file. ``index`` is the position in the input list.
    ``size`` is ``(width, height)`` when known (also for an image rejected as too small).
    """

    index: int
    path: str
    image: torch.Tensor | None = None
    error: str | None = None
    size: tuple[int, int] | None = None

    @property
    def ok(self) -> bool:
        return self.error is None


def _one_line(msg: object) -> str:
    return " ".join(str(msg).split())


def file_error(path: str | os.PathLike, exc: BaseException | str) -> str:
    """A one-line message ``"<path>: <reason>"`` (the path is not repeated if present)."""
    msg = text_path(_one_line(exc if isinstance(exc, str) else (str(exc) or type(exc).__name__)))
    path = text_path(path)
    if msg.startswith(path):
        return msg
    return f"{path}: {msg}"


class ImageFileDataset(torch.utils.data.Dataset):
    """Map-style dataset over image files; item ``i`` is a :class:`Decoded` record.

    ``__getitem__`` never raises for a bad file (missing, corrupt, truncated, not an image,
    unsupported pixel type): it returns a record with ``error`` set, so that one bad file
    becomes one failed row instead of stopping the DataLoader. ``min_side``, if given, is
    the smallest accepted image side (the smallest window): smaller images fail here with a
    message giving both sizes, before any work is spent on them.
    """

    def __init__(self, paths: Sequence[str | os.PathLike], min_side: int | None = None,
                 quiet_decoders: bool = False) -> None:
        self.paths = [str(p) for p in paths]
        self.min_side = min_side
        self.quiet_decoders = quiet_decoders  # the decoders' own stderr lines ("libpng error") dropped

    def __len__(self) -> int:
        return len(self.paths)

    def __getitem__(self, index: int) -> Decoded:
        path = self.paths[index]
        try:
            if self.quiet_decoders:
                with _stderr_dropped():
                    image = read_image(path)
            else:
                image = read_image(path)
        except Exception as e:  # noqa: BLE001 - every failure becomes a record, by design
            return Decoded(index, path, error=file_error(path, e))
        h, w = image.shape[-2:]
        if self.min_side is not None and min(h, w) < self.min_side:
            return Decoded(index, path, size=(int(w), int(h)), error=file_error(
                path, f"image is {w}×{h} px, smaller than the smallest window "
                      f"({self.min_side} px; see ReebConfig.min_window)"))
        return Decoded(index, path, image=image, size=(int(w), int(h)))


class _stderr_dropped:
    """Send file descriptor 2 to /dev/null for a moment: the C decoders (libpng, libjpeg)
    write their complaints there, which duplicate the one-line message a failed file gets."""

    _saved: int | None = None

    def __enter__(self) -> None:
        try:
            self._saved = os.dup(2)
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, 2)
            os.close(devnull)
        except OSError:  # pragma: no cover - keep stderr then
            self._saved = None

    def __exit__(self, *exc: object) -> None:
        if self._saved is not None:
            os.dup2(self._saved, 2)
            os.close(self._saved)


def _keep(item: Any) -> Any:  # batch_size=None: the loader hands each item on as it is
    return item


def _die_with_parent() -> None:
    """Linux: the kernel kills this worker when the thread that started it (the one that
    first iterated the loader) ends, as it does when the run is killed (``kill -9``),
    instead of the worker living on until DataLoader's watchdog notices, seconds later or,
    stuck flushing its queue, never."""
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, signal.SIGKILL, 0, 0, 0)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):  # pragma: no cover - not Linux
        pass


def _init_worker(_: int) -> None:
    # Decoding is one image per worker; leave the cores to the other workers and the
    # algorithm. The decoders' own complaints ("libpng error: ...") duplicate the one-line
    # message each failed file gets, and would break the progress bar: a worker's stderr
    # goes to /dev/null (every failure reaches the main process as a Decoded record), and
    # so does its stdout (it prints nothing; a forked worker holding the run's stdout pipe
    # would keep a caller reading it waiting after the run itself has been killed).
    torch.set_num_threads(1)
    _die_with_parent()
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, 1)
        os.dup2(devnull, 2)
        os.close(devnull)
    except OSError:  # pragma: no cover - keep stdout and stderr then
        pass
    try:
        import cv2

        cv2.setNumThreads(1)
        cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)
    except Exception:  # noqa: BLE001 - cosmetic only
        pass


def default_workers() -> int:
    """``min(2, usable CPUs)``: decoding is cheaper than the algorithm, two keep up."""
    try:
        n = len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        n = os.cpu_count() or 1
    return max(0, min(2, n))


def decoded_images(
    paths: Sequence[str | os.PathLike],
    workers: int = 2,
    min_side: int | None = None,
    prefetch: int = 4,
    pin_memory: bool = False,
    quiet: bool = False,
) -> Generator[Decoded, None, None]:
    """Decode ``paths`` with ``workers`` DataLoader processes (0 = in this process).

    Yields one :class:`Decoded` per path, in input order; ``quiet``: the C decoders' own
    stderr lines are dropped also when decoding in this process. Up to ``prefetch`` images per
    worker are decoded ahead of the consumer. Closing the iterator (or interrupting it)
    shuts the workers down; so does the end of the thread that began iterating it (on
    Linux the workers die with it), so iterate it to its end in that thread.
    """
    dataset = ImageFileDataset(paths, min_side=min_side)
    workers = max(0, min(workers, len(dataset)))
    dataset.quiet_decoders = quiet and workers == 0  # (workers send their stderr to /dev/null)
    kwargs: dict = {}
    if workers > 0:
        kwargs = dict(prefetch_factor=max(2, prefetch), worker_init_fn=_init_worker,
                      persistent_workers=False)
    loader = torch.utils.data.DataLoader(
        dataset, batch_size=None, shuffle=False, num_workers=workers,
        collate_fn=_keep, pin_memory=pin_memory, **kwargs,
    )
    it = iter(loader)
    try:
        yield from it
    finally:
        # Stop the workers now rather than when the iterator is garbage-collected.
        shutdown = getattr(it, "_shutdown_workers", None)
        if shutdown is not None:
            shutdown()


def size_batches(items: Iterable[Decoded], batch_size: int,
                 max_lag: int | None = None) -> Iterator[list[Decoded]]:
    """Group decoded images of equal size into batches of at most ``batch_size``.

    A failed record is yielded at once as a batch of one. Images wait in a group until it
    is full; groups that never fill are yielded at the end, largest first. With
    ``max_lag``, a group is also yielded (not full) once its first image is more than
    ``max_lag`` inputs behind the newest one, which bounds how long results wait to be
    written in input order. Batches may come out of input order (use
    :attr:`Decoded.index` to restore it).
    """
    if batch_size < 1:
        raise ValueError(f"batch_size must be >= 1, got {batch_size}")
    pending: dict[tuple[int, int], list[Decoded]] = {}
    for item in items:
        if max_lag is not None:
            for key in [k for k, g in pending.items() if item.index - g[0].index > max_lag]:
                yield pending.pop(key)
        if not item.ok:
            yield [item]
            continue
        assert item.image is not None  # an ok item holds its image
        key = (item.image.shape[-2], item.image.shape[-1])
        group = pending.setdefault(key, [])
        group.append(item)
        if len(group) >= batch_size:
            yield pending.pop(key)
    for key in sorted(pending, key=lambda k: -len(pending[k])):
        yield pending[key]


# -- 4. result rows and writers ----------------------------------------------------------

def round_like_python(values: np.ndarray, decimals: int) -> np.ndarray:
    """``[round(v, decimals) for v in values]`` (Python's correctly rounded ``round``) for a
    float64 array, vectorised: ``N = rint(v·10^d)`` is the right integer wherever ``v·10^d``
    is not within 1e-6 of a half-integer (its rounding error is far smaller), and the IEEE
    quotient ``N / 10^d`` is the double nearest to the decimal, as ``round`` returns. The
    few values near a tie, huge or not finite go through ``round`` itself. Same numbers
    bit for bit (tested against ``round``)."""
    v = np.asarray(values, np.float64)
    if not 0 <= decimals <= 15:
        return np.array([round(float(x), decimals) for x in v.ravel()]).reshape(v.shape)
    scale = 10.0 ** decimals
    with np.errstate(invalid="ignore", over="ignore"):  # huge values overflow: taken by round below
        t = v * scale
        out = np.rint(t) / scale
        risky = ~(np.abs(t) < 1e9) | (np.abs(t - np.floor(t) - 0.5) < 1e-6)
    if risky.any():
        out[risky] = [round(float(x), decimals) for x in v[risky]]
    return out


def significant_like_python(values: np.ndarray, digits: int = 6) -> np.ndarray:
    """``[float(f"{v:.{digits}g}") for v in values]`` for a float64 array, vectorised the
    same way as :func:`round_like_python` (the power of ten from ``log10``; values whose
    scaled mantissa is near a tie or whose digit count comes out wrong, zeros, huge, tiny
    and non-finite values go through the format itself). Same numbers bit for bit."""
    v = np.asarray(values, np.float64)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        e = np.floor(np.log10(np.abs(v)))
        k = (digits - 1) - e
        ok = np.isfinite(k) & (np.abs(k) <= 22)
        k = np.where(ok, k, 0.0)
        p = 10.0 ** np.abs(k)  # exact for |k| <= 22
        t = np.where(k >= 0, v * p, v / p)
        n = np.rint(t)
        out = np.where(k >= 0, n / p, n * p)
        lo, hi = 10.0 ** (digits - 1), 10.0 ** digits
        risky = (~ok | ~(np.abs(n) >= lo) | ~(np.abs(n) < hi) | (np.abs(t - np.floor(t) - 0.5) < 1e-6)
                 | (k < 0))  # v / p is rounded: only scaled-up values are taken as they come
    if risky.any():
        out[risky] = [float(f"{float(x):.{digits}g}") for x in v[risky]]
    return out


def result_row(path: str, width: int, height: int, boxes: torch.Tensor, scores: torch.Tensor,
               config: str, decimals: int = 2, labels: Sequence[str] | None = None) -> dict:
    """The output row of one processed image (boxes rounded to ``decimals`` pixels, scores
    to 6 significant digits, as Python's ``round`` and ``.6g`` format give them; ``labels``:
    the class hint of each box, or None for none); an :func:`error_row` where a box or a
    score is not finite. Raises ValueError when ``labels`` is not one per box."""
    if labels is not None and len(labels) != len(boxes):
        raise ValueError(f"result_row: {len(labels)} labels for {len(boxes)} boxes (one per box)")
    b = boxes.detach().to("cpu", torch.float64).numpy()
    s = scores.detach().to("cpu", torch.float64).numpy()
    bad = int((~np.isfinite(s)).sum() + (~np.isfinite(b)).reshape(-1, 4).any(axis=1).sum())
    if bad:  # never a bare NaN in a row (JSON has none): the image is an error
        return error_row(path, f"{text_path(path)}: {bad} boxes or scores are not finite numbers (NaN or "
                         "infinity; the ranker's weights may be damaged)", config, (width, height))
    return {
        "format_version": FORMAT_VERSION,
        "image": text_path(path),
        "resolved": row_key(path),
        "width": int(width),
        "height": int(height),
        "boxes": round_like_python(b, decimals).reshape(-1, 4).tolist(),
        "scores": significant_like_python(s).tolist(),
        "labels": None if labels is None else [str(x) for x in labels],
        "status": "ok",
        "config": config,
    }


def hint_names(classes: Sequence[str] | None, labels: torch.Tensor | None) -> list[str] | None:
    """The class hint of each box as a name: ``labels`` (``int64 [N]``, a generator output's
    ``"labels"``) indexes ``classes`` (:attr:`ProposalGenerator.classes
    <reeb_torch.ProposalGenerator.classes>`); None where the settings give none."""
    if classes is None or labels is None:
        return None
    return [classes[i] for i in labels.tolist()]


def error_row(path: str, message: str, config: str, size: tuple[int, int] | None = None) -> dict:
    """The output row of an image that failed; ``message`` names the file."""
    w, h = (int(size[0]), int(size[1])) if size is not None else (None, None)
    return {"format_version": FORMAT_VERSION, "image": text_path(path), "resolved": row_key(path),
            "width": w, "height": h, "boxes": [], "scores": [], "labels": None,
            "status": f"error: {text_path(_one_line(message))}", "config": config}


OUTPUT_FORMATS = {".jsonl": "jsonl", ".ndjson": "jsonl", ".parquet": "parquet", ".pq": "parquet"}


def output_format(path: str | os.PathLike) -> str:
    """``"jsonl"`` or ``"parquet"`` from the file extension; :class:`OutputError` otherwise.

    ``.json`` is refused rather than written as JSON Lines under a name that promises one
    JSON document (``json.load`` would fail on it): the message suggests ``.jsonl``.
    """
    ext = Path(path).suffix.lower()
    if ext == ".json":
        raise OutputError(f"{path}: the output is JSON Lines (one row per line), not a single "
                          f"JSON document; name it {Path(path).with_suffix('.jsonl')}")
    try:
        return OUTPUT_FORMATS[ext]
    except KeyError:
        raise OutputError(f"{path}: unknown output format {ext or '(no extension)'!r}; "
                          f"use one of {', '.join(OUTPUT_FORMATS)}") from None


def check_output(path: str | os.PathLike) -> None:
    """Raise :class:`OutputError` unless ``path`` can be written as an output file.

    Checks the format, that the path is not a folder, that its folder exists, and that a
    file can be created there (by creating and removing one), so that a run never computes
    for an hour and then fails to save.
    """
    p = Path(path)
    if p.is_dir():
        raise OutputError(f"{p}: is a folder; give a file name such as {p / 'proposals.jsonl'}")
    output_format(p)
    parent = p.parent if str(p.parent) else Path(".")
    if not parent.is_dir():
        raise OutputError(f"{p}: cannot write, folder {parent} does not exist")
    if p.exists() and not os.access(p, os.W_OK):
        raise OutputError(f"{p}: cannot write, the file is read-only")
    try:
        fd, probe = tempfile.mkstemp(prefix=f"{hidden_stem(p)}.", suffix=".probe", dir=parent)
    except OSError as e:
        raise OutputError(f"{p}: cannot write to folder {parent} ({e.strerror or e})") from e
    os.close(fd)
    os.unlink(probe)


def read_results(path: str | os.PathLike) -> tuple[list[dict], list[str]]:
    """Read the rows of an existing output file (for ``--resume``).

    Returns ``(rows, problems)``. Lines of a JSON Lines file that do not parse (an output
    edited by hand, or appended to by another tool) are reported in ``problems`` and
    skipped, never fatal. Raises :class:`OutputError` when the file cannot be read at all.
    """
    p = Path(path)
    fmt = output_format(p)
    problems: list[str] = []
    rows: list[dict] = []
    try:
        if fmt == "jsonl":
            with open(p, encoding="utf-8") as f:
                for n, line in enumerate(f, 1):
                    if not line.strip():
                        continue
                    try:
                        row = json.loads(line)
                    except json.JSONDecodeError as e:
                        problems.append(f"{p}:{n}: not a JSON line ({e.msg}); skipped")
                        continue
                    except RecursionError:
                        problems.append(f"{p}:{n}: not a result row (nested too deeply); skipped")
                        continue
                    if not isinstance(row, dict) or "image" not in row:
                        problems.append(f"{p}:{n}: not a result row; skipped")
                        continue
                    rows.append(row)
        else:
            import pyarrow.parquet as pq

            rows = pq.read_table(p).to_pylist()
    except OSError as e:
        raise OutputError(f"{p}: cannot read the results ({e.strerror or e})") from e
    except Exception as e:  # noqa: BLE001 - pyarrow raises its own error types
        raise OutputError(f"{p}: cannot read the results, not a readable {fmt} file ({_one_line(e)})") from e
    return rows, problems


def result_files(out_dir: str | os.PathLike) -> list[Path]:
    """The Parquet files of a result folder, sorted by name (hidden files skipped)."""
    d = Path(out_dir)
    return sorted(p for p in d.rglob("*.parquet") if p.is_file()
                  and not any(part.startswith(".") for part in p.relative_to(d).parts))


def read_result_dir(out_dir: str | os.PathLike) -> list[dict]:
    """All rows of the Parquet files in the folder ``out_dir`` (an empty folder: none).

    Raises ``OSError`` naming the file when one cannot be read.
    """
    import pyarrow.parquet as pq

    rows: list[dict] = []
    for f in result_files(out_dir):
        try:
            rows += pq.read_table(f).to_pylist()
        except Exception as e:  # noqa: BLE001 - pyarrow has its own error types
            raise OSError(f"{f}: cannot read ({' '.join(str(e).split())})") from e
    return rows


class ResultWriter:
    """Streams rows to a temporary file beside ``path``; :meth:`commit` renames it into place.

    Until :meth:`commit`, ``path`` keeps its old content (or does not exist). After a crash
    that skips both :meth:`commit` and :meth:`discard` (a kill -9, a power cut) a hidden
    ``.<name>.<random>.tmp`` file may be left beside the output; it can be deleted.
    """

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = Path(path)
        self.rows_written = 0
        parent = self.path.parent if str(self.path.parent) else Path(".")
        try:
            fd, tmp = tempfile.mkstemp(prefix=f"{hidden_stem(self.path)}.", suffix=".tmp", dir=parent)
        except OSError as e:
            raise OutputError(f"{self.path}: cannot write ({e.strerror or e})") from e
        os.close(fd)
        self.tmp = Path(tmp)
        self._closed = False
        try:
            self._open()
        except BaseException:
            self.tmp.unlink(missing_ok=True)
            raise

    # subclasses: open the temporary file, write rows, close it
    def _open(self) -> None:
        raise NotImplementedError

    def _write(self, rows: list[dict]) -> None:
        raise NotImplementedError

    def _close(self) -> None:
        raise NotImplementedError

    def write(self, rows: Iterable[dict]) -> None:
        rows = list(rows)
        if rows:
            self._write(rows)
            self.rows_written += len(rows)

    def commit(self) -> Path:
        """Finish the temporary file, flush it to disk and rename it to ``path``."""
        if self._closed:
            raise RuntimeError("writer already closed")
        self._closed = True
        try:
            self._close()
            mode = 0o666 & ~_umask()
            os.chmod(self.tmp, mode)
            os.replace(self.tmp, self.path)
        except BaseException:
            self.tmp.unlink(missing_ok=True)
            raise
        return self.path

    def discard(self) -> None:
        """Drop the temporary file; ``path`` is left as it was."""
        if self._closed:
            return
        self._closed = True
        try:
            self._close()
        except Exception:  # noqa: BLE001 - discarding anyway
            pass
        self.tmp.unlink(missing_ok=True)

    def __enter__(self) -> "ResultWriter":
        return self

    def __exit__(self, *exc: object) -> None:
        self.discard()


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


class JsonlWriter(ResultWriter):
    """JSON Lines: one JSON object per line, UTF-8; each row is flushed as it is written."""

    def _open(self) -> None:
        self._f = open(self.tmp, "w", encoding="utf-8")

    def _write(self, rows: list[dict]) -> None:
        for row in rows:
            self._f.write(json.dumps(row, ensure_ascii=False, separators=(",", ":")) + "\n")
        self._f.flush()

    def _close(self) -> None:
        if not self._f.closed:
            try:  # a full disk raises here: the file is closed all the same
                self._f.flush()
                os.fsync(self._f.fileno())
            finally:
                self._f.close()


class ParquetWriter(ResultWriter):
    """Parquet via pyarrow, written in row groups of ``group_rows`` rows."""

    group_rows = 256

    @staticmethod
    def schema():
        import pyarrow as pa

        return pa.schema([
            ("format_version", pa.int32()),
            ("image", pa.string()),
            ("resolved", pa.string()),
            ("width", pa.int32()),
            ("height", pa.int32()),
            ("boxes", pa.list_(pa.list_(pa.float32(), 4))),
            ("scores", pa.list_(pa.float32())),
            ("labels", pa.list_(pa.string())),
            ("status", pa.string()),
            ("config", pa.string()),
        ])

    def _open(self) -> None:
        import pyarrow.parquet as pq

        self._schema = self.schema()
        self._buffer: list[dict] = []
        self._w = pq.ParquetWriter(str(self.tmp), self._schema)

    def _flush(self) -> None:
        import pyarrow as pa

        if self._buffer:
            names = self._schema.names
            cols = {n: [r.get(n) for r in self._buffer] for n in names}
            self._w.write_table(pa.table(cols, schema=self._schema))
            self._buffer = []

    def _write(self, rows: list[dict]) -> None:
        self._buffer.extend(rows)
        if len(self._buffer) >= self.group_rows:
            self._flush()

    def _close(self) -> None:
        if self._w is not None:
            try:
                self._flush()
            finally:
                self._w.close()
                self._w = None


def open_writer(path: str | os.PathLike) -> ResultWriter:
    """A :class:`JsonlWriter` or :class:`ParquetWriter` for ``path``, by its extension."""
    fmt = output_format(path)
    if fmt == "parquet":
        try:
            import pyarrow  # noqa: F401
        except ImportError:
            raise OutputError(f"{path}: Parquet output needs pyarrow "
                              "(pip install 'reeb-torch[extras]'), or use a .jsonl file") from None
        return ParquetWriter(path)
    return JsonlWriter(path)


# -- 5. one writer per output, and what a killed run left ------------------------------------

def _lock_path(path: str | os.PathLike) -> Path:
    p = Path(path)
    return p.with_name(f"{hidden_stem(p)}.lock")


class OutputLock:
    """An exclusive lock on an output file, held by this process (see :func:`lock_output`).

    The lock is ``fcntl.flock`` on a hidden ``.<name>.lock`` file beside the output, which
    holds the owner's process id. The operating system drops the lock when its process
    ends in any way (also ``kill -9``), so a lock file left behind by a dead run is simply
    taken over: there is no stale lock to clear by hand. :meth:`release` removes the file.
    """

    def __init__(self, path: Path, fd: int) -> None:
        self.path = path
        self._fd: int | None = fd

    def release(self) -> None:
        """Remove the lock file and drop the lock (idempotent)."""
        if self._fd is None:
            return
        try:
            self.path.unlink(missing_ok=True)  # unlink while locked: no one can take a stale inode
        finally:
            os.close(self._fd)  # closing the descriptor drops the flock
            self._fd = None

    def __enter__(self) -> "OutputLock":
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()


def lock_output(path: str | os.PathLike) -> OutputLock:
    """Take the lock of output ``path``, or raise :class:`OutputBusyError` at once.

    The error names the process that holds it. A second ``reeb propose`` on the same output
    therefore fails before any work (it does not wait), and never overwrites the first
    one's rows. Raises :class:`OutputError` when the lock file cannot be created.
    """
    import fcntl

    lock = _lock_path(path)
    while True:
        try:
            fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o666)
        except OSError as e:
            raise OutputError(f"{path}: cannot create the lock file {lock} ({e.strerror or e})") from e
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as e:
            try:
                owner = os.pread(fd, 64, 0).decode("ascii", "replace").strip() or "unknown"
            finally:
                os.close(fd)
            if e.errno in (errno.EAGAIN, errno.EACCES, errno.EWOULDBLOCK):
                raise OutputBusyError(
                    f"{path}: another reeb run (pid {owner}) is writing this output; wait for it "
                    f"to finish, or choose another --out (lock file: {lock})") from None
            raise OutputError(f"{path}: cannot lock {lock} ({e.strerror or e})") from e
        # the holder before us may have removed the file between our open and our flock:
        # then we locked an orphan inode; start again on the current file
        try:
            same = os.path.samestat(os.fstat(fd), os.stat(lock))
        except FileNotFoundError:
            same = False
        if not same:
            os.close(fd)
            continue
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        return OutputLock(lock, fd)


def stale_temp_files(path: str | os.PathLike) -> list[Path]:
    """The temporary files of ``path`` left by runs that were killed (``kill -9``, power cut).

    These are ``.<name>.<8 random characters>.tmp`` beside the output, as
    :class:`ResultWriter` makes them. Call it while holding :func:`lock_output`: then no
    live run owns any of them. Sorted oldest first.
    """
    p = Path(path)
    parent = p.parent if str(p.parent) else Path(".")
    pattern = re.compile(rf"^{re.escape(hidden_stem(p))}\.[a-z0-9_]{{8}}\.tmp$")
    try:
        found = [q for q in parent.iterdir() if pattern.match(q.name) and q.is_file()]
    except OSError:
        return []
    return sorted(found, key=lambda q: (q.stat().st_mtime, q.name))


def read_partial_results(path: str | os.PathLike, fmt: str) -> tuple[list[dict], list[str]]:
    """The complete rows in a killed run's temporary file (see :func:`stale_temp_files`).

    A JSON Lines file loses at most its last, unfinished line (not reported); a Parquet
    file without its footer cannot be read and gives no rows, with a line in ``problems``.
    """
    rows: list[dict] = []
    problems: list[str] = []
    p = Path(path)
    if fmt == "jsonl":
        try:
            text = p.read_text(encoding="utf-8", errors="replace")
        except OSError as e:
            return [], [f"{p}: cannot read ({e.strerror or e}); its rows are not recovered"]
        for line in text.splitlines():
            try:
                row = json.loads(line)
            except (json.JSONDecodeError, RecursionError):
                continue
            if isinstance(row, dict) and "image" in row:
                rows.append(row)
        return rows, problems
    try:
        import pyarrow.parquet as pq

        rows = pq.read_table(p).to_pylist()
    except Exception as e:  # noqa: BLE001 - an unfinished Parquet file has no footer
        problems.append(f"{p}: an unfinished Parquet file, its rows cannot be recovered "
                        f"({_one_line(e)})")
    return rows, problems


def caused_by_interrupt(e: BaseException) -> bool:
    """Whether ``e`` is, or was raised while handling, a :class:`KeyboardInterrupt`: a
    Ctrl-C that lands inside a library's own Python code can come out wrapped (numba,
    loading a cached kernel, turns it into a ``SystemError``)."""
    seen = set()
    while e is not None and id(e) not in seen:
        if isinstance(e, KeyboardInterrupt):
            return True
        seen.add(id(e))
        e = e.__cause__ or e.__context__  # type: ignore[assignment]
    return False


class CriticalSection:
    """Defers Ctrl-C (and SIGTERM) while a row is being written, so that a row is either
    wholly in the output or not at all, and the counts in the summary match the file.

    Install :meth:`handler` for SIGINT/SIGTERM; outside a ``with`` block it raises
    :class:`KeyboardInterrupt` at once, inside it the interrupt is raised when the block
    ends.
    """

    def __init__(self) -> None:
        self._depth = 0
        self._pending = False

    def interrupt(self) -> None:
        """What the signal handler does: interrupt now, or at the end of the write."""
        if self._depth:
            self._pending = True
        else:
            raise KeyboardInterrupt

    def handler(self, signum: int, frame: object) -> None:
        self.interrupt()

    def install(self) -> dict:
        """Install :meth:`handler` for SIGINT and SIGTERM; return the previous handlers."""
        previous = {}
        for sig in (signal.SIGINT, signal.SIGTERM):
            previous[sig] = signal.getsignal(sig)
            signal.signal(sig, self.handler)
        return previous

    def __enter__(self) -> "CriticalSection":
        self._depth += 1
        return self

    def __exit__(self, exc_type, *exc: object) -> None:
        self._depth -= 1
        if not self._depth and self._pending and exc_type is None:
            self._pending = False
            raise KeyboardInterrupt
