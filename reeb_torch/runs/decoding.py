"""Decoding images in parallel for a run: DataLoader worker processes read the files
(:func:`decoded_images`, over :class:`ImageFileDataset`) while the algorithm runs, and
:func:`size_batches` groups the decoded images of equal size into batches (the generator
takes a ``B×3×H×W`` tensor).

A worker never raises: a file that cannot be read becomes a :class:`Decoded` record with
``error`` set, which the run writes as one ``error:`` row."""

from __future__ import annotations

import os
import signal
from dataclasses import dataclass
from typing import Any, Generator, Iterable, Iterator, Sequence

import torch

from ..io import read_image
from .rows import file_error

__all__ = ["Decoded", "ImageFileDataset", "decoded_images", "default_workers", "size_batches"]


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
