"""An on-disk store of a fit's per-frame training rows, read back as memory maps.

``reeb fit`` computes each frame's training rows once (REEB's candidates, their feature
rows, the negatives sampled per frame as they are made) and appends them here, so no step of
the fit holds every frame's rows in memory and a killed fit goes on from the last frame it
finished. The store is a folder::

    manifest.json   {"format": "reeb-fit-rows", "version": 1, "key": <digest of what made
                     the rows>, "fields": {name: [dtype, [trailing dims]]}}
    index.jsonl     one line per finished frame: {"frame": i, "rows": {field: count},
                     "crc": {field: crc32 of its bytes}}
    <field>.bin     each field's rows of every finished frame, in frame order (raw,
                     little-endian, C order)

A frame is finished when its index line is written: bytes past the last indexed frame (a
kill mid-append) are cut away when the store is opened again. A store made with another key
(other settings, frames, version) is emptied and made again; a damaged one (a field file
shorter than its index, a checksum that differs) too, never mixed in.

:class:`RowStore.frames` gives the finished frames' rows as a sequence of
:class:`StoredRows` whose tensors are views of the memory-mapped files: training reads its
minibatches from them (:meth:`RowView.rows`), and the pages it read are handed back to the
page cache (:meth:`RowStore.release`), so the process's memory does not grow with the frames.
"""

from __future__ import annotations

import json
import mmap
import os
import shutil
import warnings
import zlib
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from ..io import replace_file

__all__ = ["RowStore", "StoredRows", "StoredFrames", "RowView", "StoreError", "Checkpoints", "CheckpointSlot"]

_FORMAT = "reeb-fit-rows"
_VERSION = 1


class StoreError(OSError):
    """The store cannot be written (a full disk, a read-only folder): one line naming it."""


@dataclass(frozen=True)
class _Field:
    dtype: np.dtype
    dims: tuple[int, ...]

    @property
    def row_bytes(self) -> int:
        return int(self.dtype.itemsize * int(np.prod(self.dims, dtype=np.int64)))


class RowStore:
    """The store in ``folder`` for rows made under ``key`` (any JSON-able value naming the
    settings, frames and version that made them), with the tensor ``fields``
    ``{name: (torch dtype, trailing dims)}`` per frame.

    Opening it keeps the frames finished under the same key and cuts away what a killed
    append left; a store of another key, or a damaged one, is emptied.

    Raises:
        StoreError: the folder cannot be made or written.
    """

    def __init__(self, folder: str | os.PathLike, key: Any, fields: Mapping[str, tuple[torch.dtype, Sequence[int]]]
                 ) -> None:
        self.folder = Path(folder)
        self.key = json.loads(json.dumps(key, sort_keys=True, default=str))
        self.fields = {n: _Field(np.dtype(torch.empty(0, dtype=d).numpy().dtype), tuple(int(x) for x in dims))
                       for n, (d, dims) in fields.items()}
        self._index: list[dict[str, Any]] = []
        self._starts: dict[str, list[int]] = {}
        self._maps: dict[str, tuple[mmap.mmap, np.ndarray]] = {}
        self.rebuilt: str | None = None
        """Why the store was emptied when opened (another key, damage), or None."""
        try:
            self._open()
        except OSError as e:
            raise StoreError(f"{self.folder}: cannot write the fit's row store ({e.strerror or e})") from None

    # -- opening -----------------------------------------------------------------------------

    def _manifest(self) -> dict[str, Any]:
        return {"format": _FORMAT, "version": _VERSION, "key": self.key,
                "fields": {n: [f.dtype.str, list(f.dims)] for n, f in self.fields.items()}}

    def _open(self) -> None:
        manifest = self.folder / "manifest.json"
        try:
            found = json.loads(manifest.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            found = None
        if found != self._manifest():
            self.rebuilt = None if found is None else "made with other settings, frames or version"
            self._reset()
            return
        problem = self._read_index()
        if problem:
            self.rebuilt = problem
            self._reset()

    def _reset(self) -> None:
        if self.folder.exists():
            shutil.rmtree(self.folder)
        self.folder.mkdir(parents=True)
        for name in self.fields:
            (self.folder / f"{name}.bin").touch()
        (self.folder / "index.jsonl").touch()
        replace_file(self.folder / "manifest.json", json.dumps(self._manifest(), sort_keys=True).encode())
        self._index = []
        self._starts = {}

    def _read_index(self) -> str | None:
        """Read the index; cut each field file to its indexed length. A reason where the
        store is damaged."""
        lines = []
        path = self.folder / "index.jsonl"
        try:
            raw = path.read_bytes()
        except OSError:
            return "no index"
        good = raw[: raw.rfind(b"\n") + 1]  # a line cut by a kill is no frame
        for line in good.splitlines():
            try:
                lines.append(json.loads(line))
            except ValueError:
                return "a damaged index line"
        if len(good) != len(raw):
            path.write_bytes(good)
        if [e.get("frame") for e in lines] != list(range(len(lines))):
            return "an index out of order"
        for name, f in self.fields.items():
            want = sum(int(e["rows"][name]) for e in lines) * f.row_bytes
            file = self.folder / f"{name}.bin"
            size = file.stat().st_size if file.exists() else -1
            if size < want:
                return f"{name}.bin is shorter than its index"
            if size > want:
                os.truncate(file, want)
        self._index = lines
        for name, f in self.fields.items():  # every frame's bytes as written
            with open(self.folder / f"{name}.bin", "rb") as fh:
                for e in lines:
                    if zlib.crc32(fh.read(int(e["rows"][name]) * f.row_bytes)) != e["crc"][name]:
                        return f"frame {e['frame']}'s {name} rows differ from their checksum"
        return None

    # -- writing ------------------------------------------------------------------------------

    def __len__(self) -> int:
        """Finished frames."""
        return len(self._index)

    def append(self, tensors: Mapping[str, Tensor]) -> None:
        """Add the next frame's rows (every field, ``[n, *dims]``), flushed to disk before its
        index line, so a kill leaves either the frame or nothing of it.

        Raises:
            StoreError: it cannot be written (the store keeps the frames before it).
        """
        self._close_maps()
        self._starts = {}
        entry: dict[str, Any] = {"frame": len(self._index), "rows": {}, "crc": {}}
        arrays = {}
        for name, f in self.fields.items():
            a = np.ascontiguousarray(tensors[name].detach().cpu().numpy()).astype(f.dtype, copy=False)
            if tuple(a.shape[1:]) != f.dims:
                raise ValueError(f"{name}: rows of shape {tuple(a.shape[1:])}, the store holds {f.dims}")
            arrays[name] = a
            entry["rows"][name] = int(a.shape[0])
            entry["crc"][name] = zlib.crc32(a.tobytes())
        sizes = {n: (self.folder / f"{n}.bin").stat().st_size for n in self.fields}
        try:
            for name, a in arrays.items():
                with open(self.folder / f"{name}.bin", "ab") as fh:
                    fh.write(a.tobytes())
                    fh.flush()
                    os.fsync(fh.fileno())
            with open(self.folder / "index.jsonl", "a", encoding="utf-8") as fh:
                fh.write(json.dumps(entry, sort_keys=True) + "\n")
                fh.flush()
                os.fsync(fh.fileno())
        except OSError as e:
            for name, size in sizes.items():  # what this frame began to write
                try:
                    os.truncate(self.folder / f"{name}.bin", size)
                except OSError:
                    pass
            raise StoreError(f"{self.folder}: cannot write the fit's row store ({e.strerror or e})") from None
        self._index.append(entry)

    # -- reading ------------------------------------------------------------------------------

    def _array(self, name: str) -> np.ndarray:
        if name not in self._maps:
            f = self.fields[name]
            total = self.starts(name)[-1]
            if total == 0:
                arr = np.zeros((0, *f.dims), dtype=f.dtype)
                self._maps[name] = (None, arr)  # type: ignore[assignment]
            else:
                with open(self.folder / f"{name}.bin", "rb") as fh:
                    mm = mmap.mmap(fh.fileno(), total * f.row_bytes, access=mmap.ACCESS_COPY)
                arr = np.frombuffer(mm, dtype=f.dtype).reshape(total, *f.dims)
                self._maps[name] = (mm, arr)
        return self._maps[name][1]

    def tensor(self, name: str) -> Tensor:
        """Every finished frame's rows of field ``name``, ``[N, *dims]``: a view of the
        memory-mapped file (read-only by contract: writes stay in this process)."""
        return torch.from_numpy(self._array(name))

    def starts(self, name: str) -> list[int]:
        """Per finished frame, the first row of field ``name`` (and the total, last)."""
        if name not in self._starts:
            out = [0]
            for e in self._index:
                out.append(out[-1] + int(e["rows"][name]))
            self._starts[name] = out
        return self._starts[name]

    def frames(self) -> "StoredFrames":
        """The finished frames' rows, a sequence of :class:`StoredRows`."""
        return StoredFrames(self, list(range(len(self))))

    def release(self) -> None:
        """Hand the pages read so far back to the page cache (they leave this process's
        resident memory; the next read maps them again)."""
        for mm, _ in self._maps.values():
            if mm is not None and hasattr(mm, "madvise"):
                mm.madvise(mmap.MADV_DONTNEED)

    def _close_maps(self) -> None:
        self._maps = {}  # the arrays keep their maps alive while a view of them lives

    def remove(self) -> None:
        """Delete the store's folder (after a finished fit)."""
        self._close_maps()
        shutil.rmtree(self.folder, ignore_errors=True)


class StoredRows:
    """One frame's rows in a :class:`RowStore`: each field an attribute (``features``,
    ``target``, ...), a view of the memory map."""

    def __init__(self, store: RowStore, frame: int) -> None:
        self._store, self.frame = store, frame

    def __getattr__(self, name: str) -> Tensor:
        if name.startswith("_") or name not in self._store.fields:
            raise AttributeError(name)
        starts = self._store.starts(name)
        return self._store.tensor(name)[starts[self.frame]: starts[self.frame + 1]]


class StoredFrames(Sequence[StoredRows]):
    """Some frames of a :class:`RowStore` (by index, in that order): a sequence of
    :class:`StoredRows`; a slice or a list of indices gives another."""

    def __init__(self, store: RowStore, frames: list[int]) -> None:
        self.store, self.indices = store, frames

    def __len__(self) -> int:
        return len(self.indices)

    def __getitem__(self, i):  # type: ignore[override]
        if isinstance(i, slice):
            return StoredFrames(self.store, self.indices[i])
        return StoredRows(self.store, self.indices[i])

    def __iter__(self) -> Iterator[StoredRows]:
        return (StoredRows(self.store, i) for i in self.indices)

    def subset(self, positions: Sequence[int]) -> "StoredFrames":
        """The frames at ``positions`` of this sequence."""
        return StoredFrames(self.store, [self.indices[p] for p in positions])

    def row_index(self, name: str) -> Tensor:
        """``int64 [n]``: the store's rows of field ``name`` that these frames hold, in order."""
        starts = self.store.starts(name)
        parts = [torch.arange(starts[i], starts[i + 1]) for i in self.indices]
        return torch.cat(parts) if parts else torch.zeros(0, dtype=torch.long)

    def gathered(self, name: str) -> Tensor:
        """These frames' rows of field ``name`` together, in memory (a copy)."""
        whole = self.store.tensor(name)
        if self.indices == list(range(len(self.store))):
            return whole.clone()
        starts = self.store.starts(name)
        parts = [whole[starts[i]: starts[i + 1]] for i in self.indices]
        return torch.cat(parts) if parts else whole[:0].clone()

    def view(self, name: str, columns: Sequence[int] | None = None) -> "RowView":
        """These frames' rows of field ``name`` as a :class:`RowView` (read by minibatch)."""
        return RowView(self.store, name, self.row_index(name), columns)


class RowView:
    """Rows of one field of a :class:`RowStore`, read by minibatch from the memory map:
    ``len(view)`` rows; ``view.rows(b)`` the rows at positions ``b`` (``int64 [m]``) as a
    float32 ``[m, F]`` tensor in memory (the columns ``columns`` of the field, all by default)."""

    def __init__(self, store: RowStore, name: str, index: Tensor, columns: Sequence[int] | Tensor | None = None) -> None:
        self.store, self.name, self.index = store, name, index
        self.columns = None if columns is None else torch.as_tensor(list(columns), dtype=torch.long)

    def __len__(self) -> int:
        return len(self.index)

    def rows(self, b: Tensor) -> Tensor:
        x = self.store.tensor(self.name)[self.index[b]]
        if self.columns is not None:
            x = x[:, self.columns]
        return x.float()

    def subset(self, positions: Tensor) -> "RowView":
        """The rows at ``positions`` of this view."""
        return RowView(self.store, self.name, self.index[positions], self.columns)

    def __getitem__(self, which: Tensor) -> Tensor:
        """The rows a ``bool [n]`` mask or an ``int64`` index picks, in memory."""
        return self.rows(which.nonzero().flatten() if which.dtype == torch.bool else which)

    def whole(self, chunk: int = 1 << 18) -> Tensor:
        """All its rows in memory, in order (a copy), read ``chunk`` rows at a time with
        the pages handed back after each."""
        width = self.store.fields[self.name].dims
        cols = len(self.columns) if self.columns is not None else int(np.prod(width, dtype=np.int64))
        out = torch.empty(len(self), cols)
        for s in range(0, len(self), chunk):
            b = torch.arange(s, min(len(self), s + chunk))
            out[s: s + len(b)] = self.rows(b)
            self.store.release()
        return out

    def moments(self) -> tuple[Tensor, Tensor]:
        """The columns' mean and standard deviation over the rows (``float32 [F]`` each), the
        same bits as ``x.mean(0)``, ``x.std(0)`` of :meth:`whole`."""
        whole = self.store.tensor(self.name)
        if self.columns is None and len(self) == len(whole) and bool((self.index == torch.arange(len(whole))).all()):
            x = whole.float()  # the map itself (float32 already): no copy
        else:
            x = self.whole()
        try:
            return x.mean(0), x.std(0)
        finally:
            del x
            self.store.release()


class Checkpoints:
    """Training states kept in ``folder``, one file per part (``slot(name)``), each written
    atomically (a temporary file renamed into place), so a fit killed at any moment finds the
    last finished epoch of each part. ``key``: what the states belong to (the options and
    rows); a file saved under another key is not read."""

    def __init__(self, folder: str | os.PathLike, key: Any) -> None:
        self.folder = Path(folder)
        self.key = json.dumps(key, sort_keys=True, default=str)
        self.failed: str | None = None
        """Why a state could not be written (the training then goes on without keeping any)."""

    def slot(self, name: str) -> "CheckpointSlot":
        return CheckpointSlot(self, name)


class CheckpointSlot:
    """One part's state in :class:`Checkpoints` (:class:`~reeb_torch.ranker.training.Checkpoint`)."""

    def __init__(self, owner: Checkpoints, name: str) -> None:
        self.owner, self.path = owner, owner.folder / f"{name}.pt"

    def load(self) -> dict | None:
        """The saved state, or None: none, another key's, or one that cannot be read."""
        try:
            state = torch.load(self.path, map_location="cpu", weights_only=True)
        except Exception:  # noqa: BLE001 - missing or damaged: start the part again
            return None
        if not isinstance(state, dict) or state.get("key") != self.owner.key:
            return None
        return state["state"]

    def save(self, state: dict) -> None:
        """Keep ``state``. Where it cannot be written (a full disk), the state saved before
        stays, one ``RuntimeWarning`` says so, and no later state of these checkpoints is
        written: the training goes on, and a fit stopped after that starts its training again."""
        if self.owner.failed is not None:
            return
        tmp = self.path.with_name(f".{self.path.name}.{os.getpid()}.tmp")
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            torch.save({"key": self.owner.key, "state": state}, tmp)
            os.replace(tmp, self.path)
        except (OSError, RuntimeError) as e:
            tmp.unlink(missing_ok=True)
            reason = (e.strerror or str(e)) if isinstance(e, OSError) else "write failed (the disk may be full)"
            self.owner.failed = reason
            warnings.warn(f"{self.path.parent}: not keeping the training state, cannot write ({reason}); a fit "
                          "stopped from here starts its training again", RuntimeWarning, stacklevel=2)
