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

Row schema (one row per image, JSON Lines or Parquet):

=========  ==========================  ==============================================
field      type                        meaning
=========  ==========================  ==============================================
image      str                         the path as found (relative paths stay relative)
width      int or null                 image width in pixels (null if undecodable)
height     int or null                 image height in pixels
boxes      list of [x1, y1, x2, y2]    proposals in input pixels, ranked best first
scores     list of float               one score per box, descending
status     str                         ``"ok"`` or ``"error: <file>: <reason>"``
config     str                         :meth:`ReebConfig.fingerprint` of the settings used
=========  ==========================  ==============================================
"""

from __future__ import annotations

import glob
import json
import os
import re
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Iterator, Sequence

import torch

from .io import IMAGE_EXTENSIONS, read_image

__all__ = [
    "NoImagesError",
    "OutputError",
    "find_images",
    "Decoded",
    "ImageFileDataset",
    "decoded_images",
    "size_batches",
    "result_row",
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


# -- 1. finding images -------------------------------------------------------------------

_GLOB_CHARS = re.compile(r"[*?\[]")


def _natural_key(p: Path) -> list:
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", str(p))]


def _is_image_name(p: Path) -> bool:
    return p.suffix.lower() in IMAGE_EXTENSIONS


def find_images(paths: Sequence[str | os.PathLike], recursive: bool = False) -> tuple[list[Path], list[str]]:
    """Expand ``paths`` into the image files to process.

    - a file is taken as given, whatever its extension (a file that is not an image then
      fails with a clear status, it is not silently skipped);
    - a folder contributes the files in it whose extension is an image extension
      (:data:`reeb_torch.io.IMAGE_EXTENSIONS`), and those of its sub-folders if
      ``recursive``; other files (labels, calibration) are ignored;
    - a pattern with ``*``, ``?`` or ``[`` that names no existing file is expanded as a
      glob (``**`` matches sub-folders); matched folders are expanded as above.

    Returns ``(images, notes)``: the images, sorted naturally within each argument and with
    duplicates removed, and one line per argument that contributed nothing (an empty
    folder, a pattern that matched no image). Raises :class:`NoImagesError` when a path
    does not exist or when no image is found at all.
    """
    images: list[Path] = []
    notes: list[str] = []
    seen: set[str] = set()

    def add(p: Path) -> int:
        key = os.path.abspath(p)
        if key in seen:
            return 0
        seen.add(key)
        images.append(p)
        return 1

    def from_folder(d: Path) -> list[Path]:
        it = d.rglob("*") if recursive else d.iterdir()
        return sorted((p for p in it if p.is_file() and _is_image_name(p)), key=_natural_key)

    for arg in paths:
        p = Path(arg)
        if p.is_file():
            add(p)
        elif p.is_dir():
            found = from_folder(p)
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
                    n += sum(add(f) for f in from_folder(m))
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
    return images, notes


# -- 2. parallel decoding ----------------------------------------------------------------

@dataclass
class Decoded:
    """One decoded image, or the reason it could not be decoded.

    ``image`` is an RGB ``uint8`` tensor ``(3, H, W)`` or ``None``; ``error`` is ``None``
    or a one-line message that names the file. ``index`` is the position in the input list.
    """

    index: int
    path: str
    image: torch.Tensor | None = None
    error: str | None = None

    @property
    def ok(self) -> bool:
        return self.error is None


def _one_line(msg: str) -> str:
    return " ".join(str(msg).split())


def file_error(path: str | os.PathLike, exc: BaseException | str) -> str:
    """A one-line message ``"<path>: <reason>"`` (the path is not repeated if present)."""
    msg = _one_line(exc if isinstance(exc, str) else (str(exc) or type(exc).__name__))
    path = str(path)
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

    def __init__(self, paths: Sequence[str | os.PathLike], min_side: int | None = None) -> None:
        self.paths = [str(p) for p in paths]
        self.min_side = min_side

    def __len__(self) -> int:
        return len(self.paths)

    def __getitem__(self, index: int) -> Decoded:
        path = self.paths[index]
        try:
            image = read_image(path)
        except Exception as e:  # noqa: BLE001 - every failure becomes a record, by design
            return Decoded(index, path, error=file_error(path, e))
        h, w = image.shape[-2:]
        if self.min_side is not None and min(h, w) < self.min_side:
            return Decoded(index, path, error=file_error(
                path, f"image is {w}×{h} px, smaller than the smallest window "
                      f"({self.min_side} px; see ReebConfig.min_window)"))
        return Decoded(index, path, image=image)


def _keep(item: Decoded) -> Decoded:
    return item


def _init_worker(_: int) -> None:
    # Decoding is one image per worker; leave the cores to the other workers and the
    # algorithm. The decoders' own complaints ("libpng error: ...") duplicate the one-line
    # message each failed file gets, and would break the progress bar: a worker's stderr
    # goes to /dev/null (every failure reaches the main process as a Decoded record).
    torch.set_num_threads(1)
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, 2)
        os.close(devnull)
    except OSError:  # pragma: no cover - keep stderr then
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
) -> Iterator[Decoded]:
    """Decode ``paths`` with ``workers`` DataLoader processes (0 = in this process).

    Yields one :class:`Decoded` per path, in input order. Up to ``prefetch`` images per
    worker are decoded ahead of the consumer. Closing the iterator (or interrupting it)
    shuts the workers down.
    """
    dataset = ImageFileDataset(paths, min_side=min_side)
    workers = max(0, min(workers, len(dataset)))
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


def size_batches(items: Iterable[Decoded], batch_size: int) -> Iterator[list[Decoded]]:
    """Group decoded images of equal size into batches of at most ``batch_size``.

    A failed record is yielded at once as a batch of one. Images wait in a group until it
    is full; groups that never fill are yielded at the end, largest first. Batches may
    therefore come out of input order (use :attr:`Decoded.index` to restore it).
    """
    if batch_size < 1:
        raise ValueError(f"batch_size must be >= 1, got {batch_size}")
    pending: dict[tuple[int, int], list[Decoded]] = {}
    for item in items:
        if not item.ok:
            yield [item]
            continue
        key = tuple(item.image.shape[-2:])
        group = pending.setdefault(key, [])
        group.append(item)
        if len(group) >= batch_size:
            yield pending.pop(key)
    for key in sorted(pending, key=lambda k: -len(pending[k])):
        yield pending[key]


# -- 4. result rows and writers ----------------------------------------------------------

def result_row(path: str, width: int, height: int, boxes: torch.Tensor, scores: torch.Tensor,
               config: str, decimals: int = 2) -> dict:
    """The output row of one processed image (boxes rounded to ``decimals`` pixels)."""
    b = boxes.detach().to("cpu", torch.float64)
    s = scores.detach().to("cpu", torch.float64)
    return {
        "image": str(path),
        "width": int(width),
        "height": int(height),
        "boxes": [[round(v, decimals) for v in row] for row in b.tolist()],
        "scores": [float(f"{v:.6g}") for v in s.tolist()],
        "status": "ok",
        "config": config,
    }


def error_row(path: str, message: str, config: str, size: tuple[int, int] | None = None) -> dict:
    """The output row of an image that failed; ``message`` names the file."""
    w, h = size if size is not None else (None, None)
    return {"image": str(path), "width": w, "height": h, "boxes": [], "scores": [],
            "status": f"error: {_one_line(message)}", "config": config}


OUTPUT_FORMATS = {".jsonl": "jsonl", ".ndjson": "jsonl", ".json": "jsonl",
                  ".parquet": "parquet", ".pq": "parquet"}


def output_format(path: str | os.PathLike) -> str:
    """``"jsonl"`` or ``"parquet"`` from the file extension; :class:`OutputError` otherwise."""
    ext = Path(path).suffix.lower()
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
        fd, probe = tempfile.mkstemp(prefix=f".{p.name}.", suffix=".probe", dir=parent)
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
                    if not isinstance(row, dict) or "image" not in row:
                        problems.append(f"{p}:{n}: not a result row; skipped")
                        continue
                    rows.append(row)
        else:
            import pyarrow.parquet as pq

            rows = pq.read_table(p).to_pylist()
    except OSError as e:
        raise OutputError(f"{p}: cannot read for --resume ({e.strerror or e})") from e
    except Exception as e:  # noqa: BLE001 - pyarrow raises its own error types
        raise OutputError(f"{p}: cannot read for --resume ({_one_line(e)})") from e
    return rows, problems


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
            fd, tmp = tempfile.mkstemp(prefix=f".{self.path.name}.", suffix=".tmp", dir=parent)
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
            self._f.flush()
            os.fsync(self._f.fileno())
            self._f.close()


class ParquetWriter(ResultWriter):
    """Parquet via pyarrow, written in row groups of ``group_rows`` rows."""

    group_rows = 256

    @staticmethod
    def schema():
        import pyarrow as pa

        return pa.schema([
            ("image", pa.string()),
            ("width", pa.int32()),
            ("height", pa.int32()),
            ("boxes", pa.list_(pa.list_(pa.float32(), 4))),
            ("scores", pa.list_(pa.float32())),
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
