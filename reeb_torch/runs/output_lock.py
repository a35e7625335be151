"""One writer per output: a run holds a lock beside the output it writes
(:func:`lock_output`), and a second run on the same output fails at once with
:class:`OutputBusyError`."""

from __future__ import annotations

import errno
import fcntl
import os
from pathlib import Path

from .output_files import OutputError, hidden_stem

__all__ = ["OutputBusyError", "OutputLock", "lock_output", "sweep_dead_locks", "LOCK_SUFFIX"]


class OutputBusyError(OutputError):
    """Another process is writing the same output file (it holds the lock beside it)."""


LOCK_SUFFIX = ".reeb-lock"


def _lock_path(path: str | os.PathLike) -> Path:
    p = Path(path)
    return p.with_name(f"{hidden_stem(p)}{LOCK_SUFFIX}")


def sweep_dead_locks(folder: Path, keep: Path | None = None) -> None:
    """Remove the lock files in ``folder`` that no live run holds (those a ``kill -9`` left).

    Each is locked, checked to be the file at its name, unlinked and closed, as
    :meth:`OutputLock.release` does: a run that opened it just before finds the file gone
    after its own ``flock`` and starts again on a new one (:func:`lock_output`), so no two
    runs ever hold one output. Only ``.*.reeb-lock`` files are touched; errors are ignored.
    """

    try:
        names = [q for q in folder.iterdir() if q.name.startswith(".") and q.name.endswith(LOCK_SUFFIX)]
    except OSError:
        return
    for q in names:
        if keep is not None and q.name == keep.name:
            continue
        try:
            fd = os.open(q, os.O_RDWR | os.O_NOFOLLOW)
        except OSError:
            continue
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            if os.path.samestat(os.fstat(fd), os.stat(q, follow_symlinks=False)):
                q.unlink()
        except OSError:
            pass  # held by a live run, or gone
        finally:
            os.close(fd)


class OutputLock:
    """An exclusive lock on an output file, held by this process (see :func:`lock_output`).

    The lock is ``fcntl.flock`` on a hidden ``.<name>.reeb-lock`` file beside the output,
    which holds the owner's process id. The operating system drops the lock when its process
    ends in any way (also ``kill -9``); the file such a run leaves is taken over, or removed
    by the next run that takes a lock in its folder (:func:`sweep_dead_locks`): there is no
    stale lock to clear by hand. :meth:`release` removes the file.
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
        sweep_dead_locks(lock.parent, keep=lock)
        return OutputLock(lock, fd)
