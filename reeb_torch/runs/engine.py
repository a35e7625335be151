"""The run engine: every command that turns images into rows runs on it.

::

    inputs  ->  output lock  ->  resume plan  ->  ordered writer  ->  side outputs  ->  summary, exit code
    find_inputs  plan_output      ResumePlan       OrderedWriter      PictureFolder      closing lines
                 (run_output)                                         KittiFolder

:class:`ImageRun` holds a run's steps; a command hands it a :class:`RunStep`, its model
(``reeb propose``: :class:`.propose_local.ProposeStep`, ``reeb detect``:
:class:`.detect_run.DetectStep`), which says how images are decoded and grouped
(:meth:`RunStep.stream`, :meth:`RunStep.groups`), computed (:meth:`RunStep.run_batch`) and
what each image's result is (:meth:`RunStep.found`: its boxes, scores, labels, picture).
The engine does the rest the same way for all of them: each image's row, its KITTI file and
its picture, the inputs (a file named on the command
line that cannot be read gets its ``error:`` row), the output checked and locked before any
work, a killed run's rows taken over, rows written in input order inside a
:class:`~.ctrl_c.CriticalSection`, a failed image retried alone and given its row, Ctrl-C and
SIGTERM saving what is done (exit 130), the ``--viz`` and ``--kitti-dir`` folders
(:mod:`.side_outputs`), and the closing summary with its exit code (1 when an image
failed or an output could not be written in full). ``reeb propose --engine ray``
(:mod:`.propose_ray`) runs on Ray and shares :func:`find_inputs`, the output's lock, the
resume lines and the closing summary's lines.
"""

from __future__ import annotations

import json
import signal
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Generator, Iterable, Iterator, Protocol, Sequence

import click
from tqdm import tqdm

from .common import UsageProblem
from .ctrl_c import CriticalSection, caused_by_interrupt
from .decoding import Decoded
from .inputs import NoImagesError, same_file_note, scan_images
from .rows import error_row, file_error, result_row
from .run_output import OrderedWriter, plan_output
from .side_outputs import KittiFolder, PictureFolder, SideOutputError, unique_stems

if TYPE_CHECKING:
    from torch import Tensor

__all__ = ["Inputs", "find_inputs", "count_line", "ms_per_img", "closing_tail", "mismatch_line", "Found", "RunStep",
           "ImageRun"]


@dataclass
class Inputs:
    """The images of a run (:func:`find_inputs`): ``images`` in input order, the folder
    entries ``skipped`` (one line each) and the paths left out as ``same_file`` as another."""

    images: list[Path]
    skipped: list[str]
    same_file: list[tuple[Path, Path]]


def find_inputs(paths: Sequence[str | Path], recursive: bool, echo_err: Callable[[str], None]) -> Inputs:
    """The images of ``paths`` (files, folders, globs: :func:`.inputs.scan_images`), each note
    shown; a usage error when there are none."""
    try:
        found = scan_images(paths, recursive)
    except NoImagesError as e:
        raise UsageProblem(str(e))
    for n in found.notes:
        echo_err(f"note: {n}")
    return Inputs(found.images, [n for n in found.notes if ": skipped, " in n], found.same_file)


# -- the closing summary's lines ------------------------------------------------------------

def count_line(done: int, ok: int, failed: int, boxes: int, noun: str = "proposals") -> str:
    """The first line of a run's closing summary."""
    return (f"{done} image{'s' if done != 1 else ''}: {ok} ok, {failed} failed; {boxes} {noun}"
            + (f" ({boxes / ok:.0f} per image)" if ok else ""))


def ms_per_img(seconds: float, n: int) -> str:
    """``seconds`` over ``n`` images as ``"12.3 ms/img"`` (``"n/a"`` for none)."""
    return f"{1000 * seconds / n:.1f} ms/img" if n else "n/a"


def closing_tail(skipped: Sequence[str], failures: Sequence[str], summary_json: str | None,
                 summary: dict) -> list[str]:
    """The closing summary's last lines: the folder entries skipped and the failed images,
    each named; writes ``summary`` (with both) to ``summary_json`` (a warning line instead
    if it cannot be written)."""
    lines = []
    if skipped:
        lines.append(f"skipped ({len(skipped)}, not images):")
        lines += [f"  {m}" for m in skipped]
    if failures:
        lines.append(f"failed ({len(failures)}):")
        lines += [f"  {m}" for m in failures]
    if summary_json:
        summary = dict(summary, skipped=list(skipped), failures=list(failures))
        try:
            Path(summary_json).write_text(json.dumps(summary, indent=2) + "\n", encoding="utf-8")
        except OSError as e:
            lines.append(f"warning: {summary_json}: cannot write the summary ({e.strerror or e})")
    return lines


def mismatch_line(out: str, configs: list[str], made_by: str) -> str:
    """The usage error for ``--resume`` on an output made with other settings."""
    return (f"{out} was made with different settings (config {', '.join(configs)}, now {made_by}); "
            "use the same options, another --out, or --overwrite")


# -- the run ----------------------------------------------------------------------------------

@dataclass
class Found:
    """One image's result, as :meth:`RunStep.found` gives it to the engine.

    Attributes:
        boxes: ``float32 [N, 4]`` xyxy, input pixels, best first; ``scores``: ``[N]``.
        labels: each box's class name, or ``None`` (no classes).
        picture: makes the image's ``--viz`` picture (called only when there is a folder).
        text: printed on stdout (``reeb propose``'s box tables); ``warning``: on stderr.
    """

    boxes: Tensor
    scores: Tensor
    labels: Sequence[str] | None = None
    picture: Callable[[], Any] | None = None
    text: str | None = None
    warning: str | None = None


class RunStep(Protocol):
    """What a command gives the engine: its model, and how images meet it. ``made_by`` is
    what every row's ``config`` holds (``--resume`` keeps only rows of the same), ``noun``
    what a row's boxes are (the summary's first line), ``desc`` the progress bar's name."""

    made_by: str
    noun: str
    desc: str

    def mismatch(self, out: str, configs: list[str]) -> str:
        """The usage error for ``--resume`` on an output made by something else."""

    def prepare(self, images: Sequence[Path]) -> None:
        """Before the clock starts: build the model, warm it up."""

    def stream(self, images: Sequence[Path]) -> Generator[Decoded, None, None]:
        """The decoded images, in input order (:func:`.decoding.decoded_images`: closing it
        stops its workers)."""

    def groups(self, stream: Iterator[Decoded]) -> Iterable[list[Decoded]]:
        """The decoded images in the groups :meth:`run_batch` computes."""

    def run_batch(self, items: list[Decoded]) -> list:
        """The model's result for each of ``items`` (decoded); raises when it fails."""

    def found(self, item: Decoded, result: Any) -> Found:
        """What the engine writes of an image's ``result``."""

    def after_group(self, done: int, ok: int, elapsed: float) -> None:
        """After each group (for the timings): ``done`` images so far, ``ok`` of them without
        error, ``elapsed`` seconds since the run's clock started."""

    def time_lines(self, done: int, ok: int, wall: float) -> list[str]:
        """The summary's lines on time (after the counts): ``done`` images, ``ok`` of them
        without error, in ``wall`` seconds."""

    def record(self, done: int, ok: int, wall: float) -> dict:
        """What ``--summary-json`` holds besides the counts (the arguments as
        :meth:`time_lines`')."""

    def extra_lines(self, ok: int) -> list[str]:
        """Lines on the step's own outputs (after the files written)."""


class ImageRun:
    """One run of a command that turns images into rows, step by step (module doc), on the
    ``step`` the command gives it (:class:`RunStep`): the state its steps share."""

    def __init__(self, step: RunStep, *, out: str | None, quiet: bool, summary_json: str | None = None) -> None:
        self.step, self.made_by, self.noun = step, step.made_by, step.noun
        self.out, self.quiet = out, quiet
        self.summary_json = summary_json
        self.echo_err: Callable[[str], None] = (lambda m: None) if quiet else (lambda m: click.echo(m, err=True))
        self.failures: list[str] = []
        self.stats: dict[str, Any] = dict(ok=0, failed=0, boxes=0)
        self.interrupted = False
        self.stopped: str | None = None  # why a side output stopped the run
        self.pictures: PictureFolder | None = None
        self.kitti: KittiFolder | None = None
        self.t_start = 0.0
        self.wall = 0.0

    # -- 1. inputs -------------------------------------------------------------------------------
    def find_inputs(self, paths: Sequence[str | Path], recursive: bool) -> None:
        self.inputs = find_inputs(paths, recursive, self.echo_err)
        self.images = self.inputs.images

    # -- 2. the output, checked and locked before any work ---------------------------------------
    def plan_output(self, resume: bool, overwrite: bool) -> bool:
        """Lock ``--out``, keep what earlier runs left (``--resume``); False when every image
        is already there."""
        self.output = plan_output(self.out, self.inputs.images, resume=resume, overwrite=overwrite,
                                  made_by=self.made_by, other_maker=self.step.mismatch, echo_err=self.echo_err)
        self.out, plan = self.output.out, self.output.plan
        self.images = plan.todo_paths()
        # file names of the side outputs: fixed by the whole input list (then the kept rows of
        # other images), the same with and without --resume
        self.stems = unique_stems(self.inputs.images)
        self.first_stems = unique_stems([str(r["image"]) for r in plan.first_rows], taken=set(self.stems))
        return self.output.work

    # -- 3. the side outputs ---------------------------------------------------------------------
    def side_outputs(self, viz_dir: str | None, kitti_dir: str | None = None, categories: Sequence[str] = (),
                     *, resume: bool = False, overwrite: bool = False) -> None:
        """Check the ``--viz`` and ``--kitti-dir`` folders (before any work)."""
        warn = (lambda m: click.echo(m, err=True)) if self.quiet else (lambda m: self._bar_write(m))
        self.pictures = PictureFolder(viz_dir, warn) if viz_dir else None
        if self.pictures is not None:
            self.pictures.prepare(self.inputs.images, self.stems, resume=resume, overwrite=overwrite)
        if kitti_dir:
            self.kitti = KittiFolder(kitti_dir, categories)
            self.kitti.prepare({stem for stem, _ in self._kept_rows()}, resume=resume, overwrite=overwrite)

    def _kept_rows(self) -> list[tuple[str, dict]]:
        """The ``ok`` rows kept from before with the stem of their side-output files."""
        plan = self.output.plan
        rows = [(stem, r) for stem, r in zip(self.first_stems, plan.first_rows) if r.get("status") == "ok"]
        return rows + [(self.stems[pos], row) for pos, (row, new) in sorted(plan.slots.items())
                       if row is not None and not new]

    def _write_kept(self) -> None:
        """The ``--kitti-dir`` files of the rows kept from before, made from the rows."""
        if self.kitti is not None:
            for stem, row in self._kept_rows():
                self.kitti.write(stem, row)

    def nothing_to_do(self) -> None:
        """Every input is in the output already: its side files are made, and that is said."""
        try:
            self._write_kept()
        except SideOutputError as e:
            self.stopped = str(e)
            click.echo(f"error: {e}", err=True)
            sys.exit(1)
        click.echo(f"Nothing to do: all {len(self.inputs.images)} images are already in {self.out}.", err=True)

    # -- 4. the run: the loop ----------------------------------------------------------------------
    def run(self) -> None:
        """Compute every image left, write each row in input order; Ctrl-C and SIGTERM stop it
        (what is done is kept), as does a side output that cannot be written."""

        self.step.prepare(self.images)
        self.rows = OrderedWriter(self.output)
        self.cs = CriticalSection()  # a row is written whole, and counted, or not at all
        self.bar = tqdm(total=len(self.images), unit="img", disable=True if self.quiet else None, file=sys.stderr,
                        dynamic_ncols=True, desc=self.step.desc)
        self.t_start = time.perf_counter()
        stream = self.step.stream(self.images)
        self.previous_handlers = self.cs.install()  # Ctrl-C, and a polite kill (SIGTERM) treated like it
        try:
            self._write_kept()
            self._loop(stream)
        except KeyboardInterrupt:
            self.interrupted = True
        except SideOutputError as e:
            self.stopped = str(e)
        except Exception as e:  # a Ctrl-C that a library wrapped on its way out (caused_by_interrupt)
            if not caused_by_interrupt(e):
                self._restore_handlers()
                raise
            self.interrupted = True
        finally:
            for sig in self.previous_handlers:  # a second Ctrl-C must not break the saving
                signal.signal(sig, signal.SIG_IGN)
            stream.close()
            self.bar.close()
        self.wall = time.perf_counter() - self.t_start

    def _loop(self, stream: Iterator[Decoded]) -> None:
        for group in self.step.groups(stream):
            good = [it for it in group if it.ok]
            results = iter(self._compute(good) if good else [])
            for it in group:
                # only the computing is retried image by image (to find the culprit): a row
                # that was written is never put back, and an error in writing is not an
                # image's fault (it stops the run, as it must)
                result = next(results) if it.ok else None
                if not it.ok:
                    self.fail(it, it.error or "")
                elif isinstance(result, BaseException):
                    self.fail(it, file_error(it.path, result))
                else:
                    self.finish(it, result)
            self.bar.update(len(group))
            self.step.after_group(self.stats["ok"] + self.stats["failed"], self.stats["ok"],
                                  time.perf_counter() - self.t_start)
            if self.stats["failed"]:
                self.bar.set_postfix(failed=self.stats["failed"], refresh=False)

    def _compute(self, group: list[Decoded]) -> list:
        """:meth:`RunStep.run_batch` of the group at once, and when it fails one image at a time (the
        culprits get their error)."""
        try:
            return self.step.run_batch(group)
        except (ValueError, TypeError, RuntimeError) as e0:
            if caused_by_interrupt(e0):
                raise
        out: list = []
        for it in group:
            try:
                out += self.step.run_batch([it])
            except (ValueError, TypeError, RuntimeError) as e1:
                if caused_by_interrupt(e1):
                    raise
                out.append(e1)
        return out

    def finish(self, item: Decoded, result: Any) -> None:
        """An image computed: its row, its KITTI file, its picture, what the step prints."""
        found = self.step.found(item, result)
        row = None
        if (self.rows.writer is not None or self.kitti is not None) and item.image is not None:
            h, w = item.image.shape[-2:]
            row = result_row(item.path, w, h, found.boxes, found.scores, self.made_by, labels=found.labels)
        self.emit(item, row if self.rows.writer is not None else None, len(found.boxes))
        if found.text:
            self.bar.write(found.text, file=sys.stdout)
        if found.warning:
            self.bar.write(found.warning, file=sys.stderr)
        stem = self.stem(item)
        if self.kitti is not None and row is not None and row["status"] == "ok":
            self.kitti.write(stem, row)
        if self.pictures is not None and found.picture is not None:
            self.pictures.save(stem, found.picture)

    def emit(self, item: Decoded, row: dict | None, boxes: int) -> None:
        """An image done: its row (None: no output to write) placed in input order, counted."""
        with self.cs:
            self.stats["ok"] += 1
            self.stats["boxes"] += boxes
            self.rows.put(item.index, row)

    def fail(self, item: Decoded, message: str) -> None:
        """An image failed: its ``error:`` row, and its name in the summary."""
        with self.cs:
            self.stats["failed"] += 1
            self.failures.append(message)
            self.rows.put(item.index, error_row(item.path, message, self.made_by, item.size)
                          if self.rows.writer is not None else None)
        if not self.quiet:
            self._bar_write(f"error: {message}")

    def stem(self, item: Decoded) -> str:
        """The stem of an image's side-output files (:func:`.side_outputs.unique_stems`)."""
        return self.stems[self.output.plan.todo[item.index]]

    def _bar_write(self, message: str) -> None:
        bar = getattr(self, "bar", None)
        if bar is not None:
            bar.write(message, file=sys.stderr)
        else:
            click.echo(message, err=True)

    def _restore_handlers(self) -> None:
        for sig, h in getattr(self, "previous_handlers", {}).items():
            signal.signal(sig, h)

    # -- 5. save and summarise ---------------------------------------------------------------------
    def save_and_summarise(self) -> None:
        """Commit the output, print the closing summary, and exit 130 when interrupted, 1 when
        an image failed or an output could not be written in full."""
        try:
            saved = self.rows.commit()
        finally:
            self._restore_handlers()
        click.echo("\n".join(self.summary_lines(saved)), err=True)
        if self.interrupted:
            sys.exit(130)
        if self.stats["failed"] or self.stopped or (self.pictures is not None and self.pictures.problem):
            sys.exit(1)

    def summary_lines(self, saved: Path | None) -> list[str]:
        """The closing summary (and ``--summary-json``)."""
        stats, n = self.stats, len(self.images)
        done = stats["ok"] + stats["failed"]
        rows = self.rows
        lines = [count_line(done, stats["ok"], stats["failed"], stats["boxes"], self.noun)]
        if self.inputs.same_file:
            lines.append(same_file_note(self.inputs.same_file))
        if done:
            lines += self.step.time_lines(done, stats["ok"], self.wall)
        if saved is not None:
            kept = self.output.plan.kept_written
            lines.append(f"wrote {saved} ({rows.rows_written} rows" + (f", {kept} kept from before" if kept else "")
                         + ")")
        if self.kitti is not None and self.kitti.written:
            lines.append(f"KITTI result files in {self.kitti.path}/")
        if self.pictures is not None:
            lines += self.pictures.summary()
        lines += self.step.extra_lines(stats["ok"])
        summary = dict(images=n, processed=done, ok=stats["ok"], failed=stats["failed"], **{self.noun: stats["boxes"]},
                       **self.step.record(done, stats["ok"], self.wall), config=self.made_by, out=str(saved) if saved else None,
                       rows=rows.rows_written if rows.writer is not None else None,
                       saved=rows.saved_now if rows.writer is not None else None,
                       interrupted=self.interrupted, stopped=self.stopped, same_file=len(self.inputs.same_file))
        lines += closing_tail(self.inputs.skipped, self.failures, self.summary_json, summary)
        if self.stopped or self.interrupted:
            lines.append(self._stop_line(saved, done, n))
        return lines

    def _stop_line(self, saved: Path | None, done: int, n: int) -> str:
        """The last line of a run that stopped early: what is saved, and how to go on."""
        if saved is None:
            kept = [f"in {f.path}/" for f in (self.kitti, self.pictures) if f is not None and f.written]
            where = f"; their files are {' and '.join(kept)}" if kept else "; nothing was saved (no --out)"
            head = f"error: {self.stopped}; stopped" if self.stopped else "interrupted"
            return f"{head} after {done} of {n} images{where}"
        left = n - self.rows.saved_now  # counted as written: the summary matches the file
        how = f"run the same command with --resume to do the {left} left"
        if "--resume" in sys.argv:
            how = f"run the same command again to do the {left} left"
        if self.stopped:
            return f"error: {self.stopped}; stopped: {self.rows.saved_now} of {n} images saved in {saved}; {how}"
        return f"interrupted: {self.rows.saved_now} of {n} images saved in {saved}; {how}"
