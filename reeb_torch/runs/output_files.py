"""The output file of a run: its format (by extension), the check before any work, the
writers and the readers, and what a killed run left beside it.

:func:`open_writer` streams rows to a temporary file next to the output
(:class:`JsonlWriter` or :class:`ParquetWriter`, chosen by extension) and
:meth:`ResultWriter.commit` renames it into place, so the output is either the old file or
a complete new one, never a partial one. Rows carried over by ``--resume`` come from
:func:`read_results`; rows left in a temporary file by a killed run are found by
:func:`stale_temp_files` and read by :func:`read_partial_results`. A folder of Parquet
files (the Ray engine's output) is read by :func:`read_result_dir`."""

from __future__ import annotations

import hashlib
import json
import os
import re
import tempfile
from pathlib import Path
from typing import Iterable

from .rows import one_line

__all__ = [
    "OutputError",
    "OUTPUT_FORMATS",
    "hidden_stem",
    "output_format",
    "check_output",
    "read_results",
    "result_files",
    "read_result_dir",
    "ResultWriter",
    "JsonlWriter",
    "ParquetWriter",
    "open_writer",
    "stale_temp_files",
    "read_partial_results",
]


class OutputError(OSError):
    """The output file cannot be written (checked before any work is done)."""


#: Longest output name whose hidden companions (``.NAME.reeb-lock``, ``.NAME.XXXXXXXX.tmp``) are
#: named after it; a longer (legal) name gets companions named after its hash instead, so any
#: name the file system takes works as an output (255 bytes on most).
_PLAIN_NAME_BYTES = 200


def hidden_stem(path: str | os.PathLike) -> str:
    """The start of the hidden files beside output ``path``: ``.NAME``, or
    ``.reeb-<16 hex digits of NAME's SHA-256>`` when NAME is longer than 200 bytes."""
    name = os.fsencode(Path(path).name)
    if len(name) <= _PLAIN_NAME_BYTES:
        return f".{Path(path).name}"

    return f".reeb-{hashlib.sha256(name).hexdigest()[:16]}"


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
        raise OutputError(f"{p}: cannot read the results, not a readable {fmt} file ({one_line(e)})") from e
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


# -- what a killed run left ------------------------------------------------------------------

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
                        f"({one_line(e)})")
    return rows, problems
