"""Claiming what a command writes, before any work (the rule: :data:`~.common.OUTPUT_RULE`).

Every output of every command is claimed through :func:`claim`: files (a ranker's weights and
the config beside them, a detector, a tuned config and its plots, an export, a run's results)
and folders (``--viz`` and ``--kitti-dir``, a Ray run's Parquet folder). Each is locked for the
command's length (:func:`.output_lock.lock_output`: a second run on the same output exits 2 at
once, naming the first).

:func:`claim_files` (:func:`check_files`, then :func:`claim`) is the whole claim of files
written whole (each renamed into place): not a folder, not a file the command reads, a folder
it can write to (made where missing), not there yet unless ``--overwrite``; locked, and the
temporary files a killed write of them left removed. A run's results file
(:func:`claim_run_output`) keeps a killed run's rows for ``--resume``. Each refusal is a
:class:`~.common.UsageProblem`: one line, exit code 2.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path

import click

from .common import UsageProblem
from .output_files import OutputError, check_output, hidden_stem, stale_temp_files
from .output_lock import OutputLock, lock_output

__all__ = ["claim", "claim_files", "check_files", "claim_run_output", "unwritable"]


def claim(paths: Sequence[str | os.PathLike], *, option: str = "", hold: bool = True,
          clear: bool = False) -> Callable[[], None]:
    """Lock each of ``paths`` (files or folders).

    Args:
        paths: the outputs.
        option: the option that named them, put before a refusal (``"--viz"``).
        hold: keep the locks until the click command ends (where one runs); otherwise the
            caller releases them.
        clear: remove the temporary files killed writes of them left (files written whole;
            not a run's results, whose killed rows ``--resume`` goes on from).

    Returns:
        A function that releases the locks (harmless to call twice).

    Raises:
        UsageProblem: another run holds one of them, or a lock file cannot be made; the locks
            taken so far are released.
    """
    locks: list[OutputLock] = []

    def release() -> None:
        while locks:
            locks.pop().release()

    try:
        for path in paths:
            locks.append(lock_output(path))
            for stale in stale_temp_files(path) if clear else ():  # no live run owns them: the lock is ours
                stale.unlink(missing_ok=True)
    except OutputError as e:
        release()
        raise UsageProblem(" ".join(f"{option} {e}".split())) from None
    ctx = click.get_current_context(silent=True) if hold else None
    if ctx is not None:
        ctx.call_on_close(release)
    return release


def claim_files(paths: Sequence[str | os.PathLike], overwrite: bool, *,
                inputs: Mapping[str | os.PathLike, str] | None = None, example: str = "out.json",
                hold: bool = True) -> tuple[list[Path], Callable[[], None]]:
    """:func:`check_files`, then :func:`claim`: the paths (``~`` expanded) and the function
    that releases them."""
    out = check_files(paths, overwrite, inputs=inputs, example=example)
    return out, claim(out, hold=hold, clear=True)


def check_files(paths: Sequence[str | os.PathLike], overwrite: bool, *,
                inputs: Mapping[str | os.PathLike, str] | None = None, example: str = "out.json") -> list[Path]:
    """The files a command writes whole, checked before any work: the paths, ``~`` expanded.

    Args:
        paths: the files.
        overwrite: whether files already there may be replaced.
        inputs: the files the command reads, each with the name its usage line gives it
            (``{path: "RESULTS"}``): none of ``paths`` may be one of them.
        example: a file name for the message where a path is a folder.

    Raises:
        UsageProblem: a path is empty, a folder, an input, cannot be written
            (:func:`unwritable`), or is there already without ``overwrite``.
    """
    out = []
    for text in (str(os.fspath(p)) for p in paths):
        if not text.strip():
            raise UsageProblem(f"-o/--out is empty: give the file to write, e.g. -o {example}")
        out.append(Path(os.path.expanduser(text)))
    read = {os.path.realpath(os.path.expanduser(os.fspath(p))): name for p, name in (inputs or {}).items()}
    for p in out:
        if os.path.realpath(p) in read:
            raise UsageProblem(f"-o {p}: is {read[os.path.realpath(p)]}, the file read; give another name")
        problem = unwritable(p, example)
        if problem:
            raise UsageProblem(problem)
    there = [str(p) for p in out if p.exists() or p.is_symlink()]
    if there and not overwrite:
        raise UsageProblem(f"{' and '.join(there)} exist{'s' if len(there) == 1 else ''}; add --overwrite to "
                           f"replace {'it' if len(there) == 1 else 'them'}")
    return out


def claim_run_output(out: str | os.PathLike) -> None:
    """A run's results file (``reeb propose``/``reeb detect -o``, which ``--resume`` goes on
    from): its format and folder checked (:func:`.output_files.check_output`), then
    :func:`claim`ed until the command ends."""

    try:
        check_output(out)
    except OutputError as e:
        raise UsageProblem(str(e)) from None
    claim([out])


def unwritable(path: Path, example: str = "out.json") -> str | None:
    """Why ``path`` cannot be written as an output file (its folder made where missing), or
    None: a folder, under a file, a folder that cannot be made or written, a read-only file."""
    if path.is_dir():
        return f"{path}: is a folder; give a file name such as {path / example}"
    parent = path.parent
    above = next((q for q in (parent, *parent.parents) if q.exists()), None)
    if above is not None and not above.is_dir():
        return f"{path}: cannot write, {above} is a file, not a folder"
    try:
        parent.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        return f"{path}: cannot write, cannot make the folder {parent} ({e.strerror or e})"
    if path.exists() and not os.access(path, os.W_OK):
        return f"{path}: cannot write, the file is read-only"
    try:
        fd, probe = tempfile.mkstemp(prefix=f"{hidden_stem(path)}.", suffix=".probe", dir=parent)
    except OSError as e:
        return f"{path}: cannot write to the folder {parent} ({e.strerror or e})"
    os.close(fd)
    os.unlink(probe)
    return None
