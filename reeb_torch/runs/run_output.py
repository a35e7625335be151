"""The output file of a run that turns images into rows, from its lock to its last row.

:func:`plan_output` checks and locks ``-o`` before any work (a symbolic link: the file it
points to), takes over the finished rows a killed run left in its hidden ``.tmp`` file,
keeps the rows of the output with ``--resume`` and plans what is left to compute
(:class:`ResumePlan`); :class:`OrderedWriter` then writes the rows in input order as they
come, kept and new, and renames the finished file into place. ``reeb propose`` and ``reeb
detect`` share them through :mod:`.engine`.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence

import click

from .claim import claim_run_output
from .common import Failure, UsageProblem
from .output_files import (
    OutputError,
    open_writer,
    output_format,
    read_partial_results,
    read_results,
    stale_temp_files,
)
from .rows import row_key

__all__ = ["ResumePlan", "OutputPlan", "plan_output", "OrderedWriter", "resume_note", "resume_from"]


class ResumePlan:
    """Which inputs to compute, and the output rows in input order.

    Rows are matched on the resolved file (:func:`reeb_torch.runs.rows.row_key`, stored
    in each row as ``resolved``; rows of older files without it are resolved against the
    current folder), so a run from another folder, through a symlink or with an absolute
    path finds them. Per file the first ``ok`` row is kept, and other rows of it dropped;
    an ``error`` row is kept only for a file that is not among the inputs (the others are
    computed again). Kept rows of files not among the inputs come first in the output, in
    their old order; then one row per input, in input order.
    """

    def __init__(self, images: Sequence[Path]) -> None:
        self.images = list(images)
        self.keys = [row_key(p) for p in self.images]
        self.first_rows: list[dict] = []
        self.slots: dict[int, tuple[dict | None, bool]] = {}  # input position -> (row or None, new in this run)
        self.todo = list(range(len(self.images)))  # input positions to compute
        self.kept = self.duplicates = self.kept_written = 0
        self._next = 0

    def keep(self, rows: Sequence[dict]) -> None:
        """Take the rows of an earlier run (the output, then a killed run's temp files)."""
        def key(r: dict) -> str:
            return str(r.get("resolved") or row_key(str(r["image"])))

        best: dict[str, dict] = {}
        order: list[str] = []
        for r in rows:
            k = key(r)
            if k not in best:
                best[k] = r
                order.append(k)
            else:
                self.duplicates += 1
                if best[k].get("status") != "ok" and r.get("status") == "ok":
                    best[k] = r
        position = {k: i for i, k in enumerate(self.keys)}
        for k in order:
            r = best[k]
            ok = r.get("status") == "ok"
            self.kept += ok
            if k not in position:
                self.first_rows.append(r)
            elif ok:
                self.slots[position[k]] = (r, False)
        self.todo = [i for i in range(len(self.images)) if i not in self.slots]
        self.kept_written = len(self.first_rows)  # written first, before this run's rows

    def todo_paths(self) -> list[Path]:
        return [self.images[i] for i in self.todo]

    def kept_rows(self) -> list[dict]:
        """The ``ok`` rows kept from before: those of files not among the inputs, then the
        inputs' in input order (for side outputs made from rows, ``--kitti-dir``)."""
        return ([r for r in self.first_rows if r.get("status") == "ok"]
                + [row for _, (row, new) in sorted(self.slots.items()) if row is not None and not new])

    def put(self, todo_pos: int, row: dict | None) -> None:
        """This run's row for ``todo_paths()[todo_pos]`` (None: no output, only count)."""
        self.slots[self.todo[todo_pos]] = (row, True)

    def ready(self) -> list[tuple[dict, bool]]:
        """Rows that can be written now: the next ones in input order, no gap before them."""
        out = []
        while self._next in self.slots:
            out.append(self.slots.pop(self._next))
            self._next += 1
        return self._count([(row, new) for row, new in out if row is not None])

    def rest(self) -> list[tuple[dict, bool]]:
        """All rows still held back, in input order (at the end, or after an interrupt)."""
        out = [self.slots.pop(i) for i in sorted(self.slots)]
        self._next = len(self.images)
        return self._count([(row, new) for row, new in out if row is not None])

    def _count(self, rows: list[tuple[dict, bool]]) -> list[tuple[dict, bool]]:
        self.kept_written += sum(not new for _, new in rows)
        return rows


@dataclass
class OutputPlan:
    """What :func:`plan_output` settled before any work: the file written (``out``: a link's
    target; None without ``-o``), the rows to keep and the inputs to compute (``plan``), the
    killed runs' temporary files whose rows are taken over (``stale``, removed once saved),
    and ``work``: False when every input is already there."""

    out: str | None
    plan: ResumePlan
    stale: list[Path] = field(default_factory=list)
    work: bool = True


def resume_note(kept: int, out: str, among: int, todo: int, recovered: int = 0, duplicates: int = 0) -> str:
    """The line a resumed run starts with (the local and Ray engines; with ``-q`` too, as the
    closing summary)."""
    return (f"resume: {kept} images already in {out}"
            + (f" ({recovered} rows recovered from a killed run)" if recovered else "")
            + (f", {duplicates} duplicate rows dropped" if duplicates else "")
            + f", {among} of them among the inputs; {todo} to do")


def plan_output(out: str | None, images: Sequence[Path], *, resume: bool, overwrite: bool, made_by: str,
                other_maker: Callable[[str, list[str]], str], echo_err: Callable[[str], None]) -> OutputPlan:
    """Check and lock ``out`` (one writer per output: a second run fails here, exit 2), and
    plan the rows: with ``resume``, those of ``out`` and of killed runs' temporary files are
    kept where their ``config`` is ``made_by`` (another config: the usage error
    ``other_maker(out, configs)``); without it, an existing ``out`` or a killed run's
    finished rows are a usage error unless ``overwrite``. All before any work."""
    if resume and not out:
        raise UsageProblem("--resume needs --out (the file to continue)")
    plan = ResumePlan(images)
    if not out:
        return OutputPlan(None, plan)
    if os.path.islink(out):  # write the file the link points to (and lock that one), keep the link
        out = os.path.realpath(out)
    claim_run_output(out)
    exists = Path(out).exists()
    if exists and not (resume or overwrite):
        raise UsageProblem(f"{out} exists; add --resume to continue it or --overwrite to replace it")
    stale, stale_rows = _stale_rows(out, resume, overwrite, echo_err)
    if not (resume and (exists or stale_rows)):
        return OutputPlan(out, plan, stale)
    rows: list[dict] = []
    if exists:
        try:
            rows, problems = read_results(out)
        except OutputError as e:
            raise UsageProblem(str(e))
        for p in problems:
            echo_err(f"warning: {p}")
    plan = resume_from(rows + stale_rows, images, out, made_by, other_maker, recovered=len(stale_rows))
    return OutputPlan(out, plan, stale, work=bool(plan.todo or stale or plan.duplicates))


def resume_from(rows: Sequence[dict], images: Sequence[Path], out: str, made_by: str,
                other_maker: Callable[[str, list[str]], str], recovered: int = 0) -> ResumePlan:
    """``--resume``'s plan (the local and Ray engines): the inputs ``images`` matched with an
    earlier run's ``rows`` (:class:`ResumePlan`), its line printed (:func:`resume_note`;
    ``recovered``: of the rows, those taken from killed runs' files). ``ok`` rows made by
    another config than ``made_by`` are the usage error ``other_maker(out, configs)``."""
    other = {str(r.get("config")) for r in rows if r.get("status") == "ok"} - {made_by}
    if other:
        raise UsageProblem(other_maker(out, sorted(other)))
    plan = ResumePlan(images)
    plan.keep(rows)
    todo = len(plan.todo)
    click.echo(resume_note(plan.kept, out, len(images) - todo, todo, recovered, plan.duplicates), err=True)
    return plan


def _stale_rows(out: str, resume: bool, overwrite: bool, echo_err: Callable[[str], None]) -> tuple[list[Path], list[dict]]:
    """The temporary files killed runs left beside ``out`` whose finished rows are taken over,
    and those rows (we hold the lock: no live run owns one); files with nothing to keep,
    and all of them with ``overwrite``, are removed."""
    stale = stale_temp_files(out)
    stale_rows: list[dict] = []
    if stale and not overwrite:
        for t in stale:
            got, problems = read_partial_results(t, output_format(out))
            stale_rows += got
            for p in problems:
                echo_err(f"warning: {p}")
        if stale_rows and not resume:
            raise UsageProblem(
                f"{', '.join(t.name for t in stale)} beside {out} hold{'s' if len(stale) == 1 else ''} "
                f"{len(stale_rows)} finished rows of a run that was killed; add --resume to use "
                "them, or --overwrite to discard them")
    if overwrite or not stale_rows:
        for t in stale:  # nothing in them to keep
            t.unlink(missing_ok=True)
        return [], []
    return stale, stale_rows


class OrderedWriter:
    """The rows of a run written in input order: this run's (:meth:`put`, as they come,
    in any order) among the ones kept from before, each written as soon as no row before it
    is missing; :meth:`commit` writes the rest and renames the file into place. Without an
    output file it only places the rows. A failed write (a full disk, a quota) is one line
    naming the output (:class:`~.common.Failure`, exit 1); the old file stays as it was."""

    def __init__(self, output: OutputPlan) -> None:
        self.out, self.plan, self.stale = output.out, output.plan, output.stale
        self.saved_now = 0  # rows of this run in the writer
        self.writer = None
        if self.out is not None:
            try:
                self.writer = open_writer(self.out)
            except OutputError as e:
                raise UsageProblem(str(e))
            # an unexpected error or exit must not leave the temporary file behind
            click.get_current_context().call_on_close(self.writer.discard)
            self._write(self.plan.first_rows)

    @property
    def rows_written(self) -> int:
        return self.writer.rows_written if self.writer is not None else 0

    def put(self, todo_pos: int, row: dict | None) -> None:
        """This run's row of input ``todo_pos`` (a position in ``plan.todo_paths()``)."""
        self.plan.put(todo_pos, row)
        if self.writer is not None:
            rows = self.plan.ready()
            self._write([r for r, _ in rows])
            self.saved_now += sum(new for _, new in rows)

    def _write(self, rows: list[dict]) -> None:
        assert self.writer is not None  # only with an output file
        try:
            self.writer.write(rows)
        except OSError as e:
            raise Failure(f"{self.out}: cannot write the results ({e.strerror or e}); the old file, "
                          "if any, is unchanged") from None

    def commit(self) -> Path | None:
        """Write the rows held back (after an interrupt too: in input order), rename the
        file into place and remove the killed runs' files whose rows it now holds."""
        if self.writer is None:
            return None
        rows = self.plan.rest()
        try:
            self.writer.write(r for r, _ in rows)
            self.saved_now += sum(new for _, new in rows)
            saved = self.writer.commit()
        except OSError as e:
            raise Failure(f"{self.out}: cannot save the results ({e.strerror or e}); the old file, "
                          "if any, is unchanged") from None
        for t in self.stale:  # their rows are in the output now
            t.unlink(missing_ok=True)
        return saved
