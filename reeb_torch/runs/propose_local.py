"""``reeb propose`` on this machine: images in, one row per image out, in input order.

:func:`propose_local` runs the command's local engine: the inputs (files, folders, globs,
or the bundled sample), the output checked and locked before any work (with ``--resume``,
the rows kept from before, :class:`_ResumePlan`), the run (decoding in DataLoader workers
beside the algorithm, batches of equal-sized images, a failed image becomes an ``error:``
row), and the closing summary. The building blocks are :mod:`.inputs`, :mod:`.decoding`,
:mod:`.rows`, :mod:`.output_files`, :mod:`.output_lock` and :mod:`.ctrl_c`; the Ray engine is
:mod:`.propose_ray`.
"""

from __future__ import annotations

import os
import signal
import sys
import time
from pathlib import Path
from typing import Any, Sequence

import click

from .common import (
    Failure,
    UsageProblem,
    box_table,
    build_config,
    bundled_sample,
    claim_output,
    count_line,
    failures_and_summary,
    label_for,
    ms_per_img,
    read_labels,
    resolve_device,
)
from .ctrl_c import CriticalSection, caused_by_interrupt
from .decoding import decoded_images, default_workers, size_batches
from .inputs import NoImagesError, same_file_note, scan_images
from .output_files import (
    OutputError,
    check_output,
    open_writer,
    output_format,
    read_partial_results,
    read_results,
    stale_temp_files,
)
from .rows import error_row, file_error, hint_names, result_row, row_key, text_path

__all__ = ["propose_local"]


def propose_local(paths: Sequence[str], *, out: str | None, resume: bool, overwrite: bool, preset: str,
                  config_file: str | None, sets: Sequence[str], top_k: int | None, device: str, batch_size: int,
                  workers: int | None, viz_dir: str | None, viz_top: int, recursive: bool, print_top: int | None,
                  summary_json: str | None, quiet: bool) -> None:
    """``reeb propose`` with ``--engine local`` (the options as the command takes them).

    Usage errors (exit 2) are raised as :class:`~.common.UsageProblem` before any work;
    the process exits 1 when an image failed, 130 when interrupted.
    """
    run = _LocalRun(preset=preset, config_file=config_file, sets=sets, top_k=top_k, device=device, out=out,
                    batch_size=batch_size, workers=workers, viz_top=viz_top, summary_json=summary_json, quiet=quiet)
    run.find_inputs(paths, recursive)  # 1. inputs
    if not run.check_output(resume, overwrite):  # 2. outputs, checked before any work
        return  # nothing to do
    run.check_pictures(viz_dir, print_top)
    run.compute()  # 3. the run
    run.save_and_summarise()  # 4. save and summarise


class _LocalRun:
    """One local ``reeb propose`` run, step by step: the state its steps share."""

    def __init__(self, *, preset: str, config_file: str | None, sets: Sequence[str], top_k: int | None, device: str,
                 out: str | None, batch_size: int, workers: int | None, viz_top: int, summary_json: str | None,
                 quiet: bool) -> None:
        self.cfg = build_config(preset, config_file, sets, top_k)
        self.dev = resolve_device(device)
        self.fingerprint = self.cfg.fingerprint()
        self.workers = default_workers() if workers is None else workers
        self.out, self.batch_size, self.viz_top = out, batch_size, viz_top
        self.summary_json, self.quiet = summary_json, quiet
        self.echo_err = (lambda m: None) if quiet else (lambda m: click.echo(m, err=True))
        self.stale: list[Path] = []  # temporary files of killed runs whose rows are taken over
        self.failures: list[str] = []
        self.saved_now = 0  # rows of this run in the writer
        self.interrupted = False
        self.first_done: tuple[float, float, float] | None = None
        """(time, images done, algorithm seconds) after the first computed batch."""
        self.compile_s = self.size_warm_s = 0.0  # warm-up, kept out of the times (compute)
        self.sized = False

    # -- 1. inputs ------------------------------------------------------------------------
    def find_inputs(self, paths: Sequence[str], recursive: bool) -> None:
        """The images (the bundled sample without ``paths``); a usage error when there are none."""
        self.sample_mode = not paths
        try:
            found = scan_images([bundled_sample()] if self.sample_mode else paths, recursive)
        except NoImagesError as e:
            raise UsageProblem(str(e))
        for n in found.notes:
            self.echo_err(f"note: {n}")
        self.images = found.images
        self.skipped = [n for n in found.notes if ": skipped, " in n]  # named again in the summary
        self.same_file = found.same_file  # and these, with -q too

    # -- 2. outputs, checked before any work ------------------------------------------------
    def check_output(self, resume: bool, overwrite: bool) -> bool:
        """Check and lock ``--out``, take over what earlier runs left (``--resume``); False
        when every image is already there (nothing to do)."""
        out = self.out
        if resume and not out:
            raise UsageProblem("--resume needs --out (the file to continue)")
        # rows are written in input order: ``slots`` maps an input position to its row (kept
        # from before, or computed), ``first_rows`` are kept rows of images not among the inputs
        self.plan = _ResumePlan(self.images)
        if not out:
            return True
        if os.path.islink(out):  # write the file the link points to (and lock that one), keep the link
            out = self.out = os.path.realpath(out)
        claim_output(out)  # one writer per output: a second run fails here, before any work (exit 2)
        exists = Path(out).exists()
        if exists and not (resume or overwrite):
            raise UsageProblem(f"{out} exists; add --resume to continue it or --overwrite to "
                               "replace it")
        stale_rows = self._stale_rows(resume, overwrite)
        if resume and (exists or stale_rows):
            return self._resume(exists, stale_rows)
        return True

    def _stale_rows(self, resume: bool, overwrite: bool) -> list[dict]:
        """The finished rows in the temporary files killed runs left beside ``--out`` (we hold
        the lock: none is live); files with nothing to keep are removed."""
        out = self.out
        assert out is not None  # only with an output file
        stale = stale_temp_files(out)
        stale_rows: list[dict] = []
        if stale and not overwrite:
            for t in stale:
                got, problems = read_partial_results(t, output_format(out))
                stale_rows += got
                for p in problems:
                    self.echo_err(f"warning: {p}")
            if stale_rows and not resume:
                raise UsageProblem(
                    f"{', '.join(t.name for t in stale)} beside {out} hold{'s' if len(stale) == 1 else ''} "
                    f"{len(stale_rows)} finished rows of a run that was killed; add --resume to use "
                    "them, or --overwrite to discard them")
        if overwrite or not stale_rows:
            for t in stale:  # nothing in them to keep
                t.unlink(missing_ok=True)
            stale = []
        self.stale = stale
        return stale_rows

    def _resume(self, exists: bool, stale_rows: list[dict]) -> bool:
        """``--resume``: keep the rows of ``--out`` and of killed runs, compute only the rest."""
        out = self.out
        assert out is not None  # only with an output file
        rows: list[dict] = []
        if exists:
            try:
                rows, problems = read_results(out)
            except OutputError as e:
                raise UsageProblem(str(e))
            for p in problems:
                self.echo_err(f"warning: {p}")
        other = {r.get("config") for r in rows + stale_rows
                 if r.get("status") == "ok"} - {self.fingerprint}
        if other:
            raise UsageProblem(
                f"{out} was made with different settings (config {', '.join(sorted(map(str, other)))}, "
                f"now {self.fingerprint}); use the same options, another --out, or --overwrite")
        plan = self.plan
        before = len(self.images)
        plan.keep(rows + stale_rows)
        self.images = plan.todo_paths()
        self.echo_err(f"resume: {plan.kept} images already in {out}"
                      + (f" ({len(stale_rows)} rows recovered from a killed run)" if stale_rows else "")
                      + (f", {plan.duplicates} duplicate rows dropped" if plan.duplicates else "")
                      + f", {before - len(self.images)} of them among the inputs; {len(self.images)} to do")
        if not self.images and not self.stale and not plan.duplicates:
            click.echo(f"Nothing to do: all {before} images are already in {out}.", err=True)
            return False
        return True

    def check_pictures(self, viz_dir: str | None, print_top: int | None) -> None:
        """Where pictures go (``--viz``, or ``reeb_proposals.png`` for the sample) and how many
        boxes are printed per image."""
        self.viz_path = viz_path = Path(viz_dir) if viz_dir else None
        if viz_path is not None:
            try:
                viz_path.mkdir(parents=True, exist_ok=True)
                check_output(viz_path / "probe.jsonl")
            except (OSError, OutputError) as e:
                raise UsageProblem(f"--viz {viz_path}: cannot write pictures there "
                                   f"({getattr(e, 'strerror', None) or e})")
        sample_png = Path("reeb_proposals.png") if self.sample_mode and viz_path is None else None
        if sample_png is not None and not os.access(sample_png.parent.resolve(), os.W_OK):
            raise UsageProblem(f"cannot write {sample_png.resolve()}: the current folder is not "
                               "writable (use --viz DIR)")
        self.sample_png = sample_png
        if print_top is None:
            print_top = 0 if self.out else 10
        self.print_top = print_top
        if not self.out and not self.sample_mode and viz_path is None:
            self.echo_err("note: no --out given: proposals are printed, not saved")
        self.viz_names = _viz_names(self.images) if viz_path is not None else {}

    # -- 3. the run -------------------------------------------------------------------------
    def compute(self) -> None:
        """Decode in workers, propose batch by batch, write each row in input order; Ctrl-C
        and SIGTERM stop it (what is done is kept)."""
        from ..generator import ProposalGenerator

        try:
            self.gen = ProposalGenerator(self.cfg).to(self.dev).eval()
        except (TypeError, ValueError, ArithmeticError) as e:
            raise UsageProblem(f"the settings are not usable: {' '.join(str(e).split())}")
        self.compile_s, self.sized, self.size_warm_s = self._warm_up(), False, 0.0
        try:
            self.writer = open_writer(self.out) if self.out else None
        except OutputError as e:
            raise UsageProblem(str(e))
        if self.writer is not None:
            # an unexpected error or exit must not leave the temporary file behind
            click.get_current_context().call_on_close(self.writer.discard)
            self._write(self.plan.first_rows)
        self.cs = CriticalSection()  # a row is written whole, and counted, or not at all
        images = self.images
        label = label_for(images[0]) if self.sample_mode else None
        self.gt = read_labels(label) if label else None
        self.stats: dict[str, Any] = dict(images=len(images), ok=0, failed=0, proposals=0, algo_s=0.0)
        from tqdm import tqdm

        self.bar = tqdm(total=len(images), unit="img", disable=True if self.quiet else None, file=sys.stderr,
                        dynamic_ncols=True, desc="reeb propose")
        self.t_start = time.perf_counter()
        stream = decoded_images(images, workers=self.workers, min_side=self.cfg.min_window,
                                  prefetch=self.batch_size, pin_memory=self.dev.type == "cuda", quiet=self.quiet)
        self.previous_handlers = self.cs.install()  # Ctrl-C, and a polite kill (SIGTERM) treated like it
        try:
            self._batches(stream)
        except KeyboardInterrupt:
            self.interrupted = True
        except Exception as e:  # a Ctrl-C that a library wrapped on its way out (caused_by_interrupt)
            if not caused_by_interrupt(e):
                raise
            self.interrupted = True
        finally:
            for sig in self.previous_handlers:  # a second Ctrl-C must not break the saving
                signal.signal(sig, signal.SIG_IGN)
            stream.close()
            self.bar.close()
        self.wall = time.perf_counter() - self.t_start

    def _warm_up(self) -> float:
        """Before the clock starts: compile (or load) the CPU kernels; the seconds it took,
        which the summary gives apart (``compile_s``, with the first batch's warm-up:
        :meth:`_run_batch`)."""
        from ..generator import _warm_for

        return _warm_for(self.cfg) if self.dev.type == "cpu" else 0.0

    def _batches(self, stream) -> None:
        stats = self.stats
        # max_lag: a group of a rare size waits at most this many inputs, which bounds the
        # rows held back to be written in input order
        for group in size_batches(stream, self.batch_size, max_lag=max(64, 4 * self.batch_size)):
            if not group[0].ok:
                self._fail(group[0], group[0].error or "")
            else:
                # only the computing is retried image by image (to find the culprit): a row
                # that was written is never put back, and an error in writing is not an
                # image's fault (it stops the run, as it must)
                for it, result in zip(group, self._compute_group(group)):
                    if isinstance(result, BaseException):
                        self._fail(it, file_error(it.path, result))
                    else:
                        self._finish(it, result)
            self.bar.update(len(group))
            if self.first_done is None and stats["ok"]:
                self.first_done = (time.perf_counter(), stats["ok"] + stats["failed"], stats["algo_s"])
            if stats["failed"]:
                self.bar.set_postfix(failed=stats["failed"], refresh=False)

    def _compute_group(self, group: list) -> list:
        """The generator's result per image of ``group``, or the error an image gave: the
        batch at once, and when it fails one image at a time (the culprits get their error)."""
        try:
            return self._run_batch(group)
        except (ValueError, TypeError, RuntimeError) as e0:
            if caused_by_interrupt(e0):
                raise
        out: list = []
        for it in group:
            try:
                out += self._run_batch([it])
            except (ValueError, TypeError, RuntimeError) as e1:
                if caused_by_interrupt(e1):
                    raise
                out.append(e1)
        return out

    def _run_batch(self, items: list) -> list:
        import torch

        x = torch.stack([it.image for it in items]).to(self.dev, non_blocking=True)
        if not self.sized:  # the tables of the first image size (window grid, score plan), untimed
            t0 = time.perf_counter()
            self.gen(x[:1])
            self.size_warm_s = time.perf_counter() - t0  # in the wall time: taken out of it
            self.compile_s += self.size_warm_s
            self.sized = True
        t0 = time.perf_counter()
        results = self.gen(x)
        results = [{k: v.cpu() for k, v in r.items()} for r in results]
        self.stats["algo_s"] += time.perf_counter() - t0
        return results

    def _emit(self, todo_pos: int, row: dict | None) -> None:
        """Place this run's row for input ``todo_pos`` and write what is next in input order."""
        self.plan.put(todo_pos, row)
        if self.writer is not None:
            rows = self.plan.ready()
            self._write([r for r, _ in rows])
            self.saved_now += sum(new for _, new in rows)

    def _write(self, rows: list[dict]) -> None:
        assert self.writer is not None  # only with an output file
        try:
            self.writer.write(rows)
        except OSError as e:  # a full disk, a quota, a lost network share: one line, exit 1
            raise Failure(f"{self.out}: cannot write the results ({e.strerror or e}); the old file, "
                          "if any, is unchanged") from None

    def _fail(self, item, message: str, size=None) -> None:
        with self.cs:
            self.stats["failed"] += 1
            self.failures.append(message)
            self._emit(item.index, error_row(item.path, message, self.fingerprint, size or item.size))
        if not self.quiet:
            self.bar.write(f"error: {message}", file=sys.stderr)

    def _finish(self, item, result) -> None:
        h, w = item.image.shape[-2:]
        boxes, scores = result["boxes"].cpu(), result["scores"].cpu()
        hints = hint_names(self.gen.classes, result.get("labels"))
        with self.cs:
            self.stats["ok"] += 1
            self.stats["proposals"] += len(boxes)
            self._emit(item.index, result_row(item.path, w, h, boxes, scores, self.fingerprint, labels=hints)
                       if self.writer is not None else None)
        if self.print_top:
            self.bar.write(box_table(text_path(item.path), (w, h), boxes, scores, self.print_top, len(boxes),
                                     hints) + "\n", file=sys.stdout)
        self._pictures(item, boxes, scores, hints)

    def _pictures(self, item, boxes, scores, hints=None) -> None:
        """The ``--viz`` picture of an image (and ``reeb_proposals.png`` for the sample)."""
        from .viz import draw_proposals, save_png

        pictures = []
        if self.viz_path is not None:
            pictures.append(self.viz_path / self.viz_names[item.path])
        if self.sample_png is not None:
            pictures.append(self.sample_png)
        viz_top = self.viz_top
        for pic in pictures:
            title = f"{Path(item.path).name}: top {min(viz_top, len(boxes))} of {len(boxes)} proposals"
            try:
                save_png(pic, draw_proposals(item.image, boxes, scores, top=viz_top,
                                             gt=self.gt if pic == self.sample_png else None, title=title,
                                             hints=hints))
            except OSError as e:
                self.bar.write(f"warning: {pic}: cannot write picture ({e.strerror or e})", file=sys.stderr)

    # -- 4. save and summarise ----------------------------------------------------------------
    def save_and_summarise(self) -> None:
        """Commit the output, print the closing summary, and exit 130 / 1 when interrupted /
        when an image failed."""
        saved = self._save()
        click.echo("\n".join(self._summary_lines(saved)), err=True)
        if self.interrupted:
            sys.exit(130)
        if self.stats["failed"]:
            sys.exit(1)

    def _save(self) -> Path | None:
        saved = None
        try:
            if self.writer is not None:
                rows = self.plan.rest()  # after an interrupt: the rows held back, still in input order
                try:
                    self.writer.write(r for r, _ in rows)
                    self.saved_now += sum(new for _, new in rows)
                    saved = self.writer.commit()
                except OSError as e:
                    raise Failure(f"{self.out}: cannot save the results ({e.strerror or e}); the old file, "
                                  "if any, is unchanged")
                for t in self.stale:  # their rows are in the output now
                    t.unlink(missing_ok=True)
        finally:
            for sig, h in self.previous_handlers.items():
                signal.signal(sig, h)
        return saved

    def _summary_lines(self, saved: Path | None) -> list[str]:
        """The closing summary (and ``--summary-json``)."""
        stats, writer, images, wall = self.stats, self.writer, self.images, self.wall - self.size_warm_s
        workers, dev = self.workers, self.dev
        done = stats["ok"] + stats["failed"]
        summary = dict(images=len(images), processed=done, ok=stats["ok"], failed=stats["failed"],
                       proposals=stats["proposals"],
                       ms_per_image=1000 * wall / done if done else None,
                       algorithm_ms_per_image=1000 * stats["algo_s"] / stats["ok"] if stats["ok"] else None,
                       compile_s=self.compile_s,
                       workers=workers, batch_size=self.batch_size, device=str(dev), config=self.fingerprint,
                       **_steady(self.first_done, self.t_start + self.wall, done, stats),
                       out=str(saved) if saved else None, rows=writer.rows_written if writer else None,
                       saved=self.saved_now if writer else None,
                       interrupted=self.interrupted, failures=self.failures)
        lines = [count_line(done, stats["ok"], stats["failed"], stats["proposals"])]
        if self.same_file:
            lines.append(same_file_note(self.same_file))
        summary["same_file"] = len(self.same_file)
        if done:
            lines.append(f"time: {wall:.1f} s, {ms_per_img(wall, done)} end to end; "
                         f"{ms_per_img(stats['algo_s'], stats['ok'])} "
                         f"in the algorithm ({workers} decoding worker{'s' if workers != 1 else ''}, "
                         f"batch {self.batch_size}, {dev})"
                         + (f"; warm-up before (kernels compiled or loaded, tables for the image size) "
                            f"{self.compile_s:.1f} s, not counted" if self.compile_s >= 0.05 else ""))
        if saved and writer is not None:
            lines.append(f"wrote {saved} ({writer.rows_written} rows"
                         + (f", {self.plan.kept_written} kept from before" if self.plan.kept_written else "") + ")")
        if self.viz_path is not None and stats["ok"]:
            lines.append(f"pictures in {self.viz_path}/")
        if self.sample_png is not None and stats["ok"]:
            lines.append(f"wrote {self.sample_png.resolve()} (top {self.viz_top} proposals"
                         + (", ground truth in green" if self.gt else "") + ")")
        if self.skipped:
            lines.append(f"skipped ({len(self.skipped)}, not images):")
            lines += [f"  {m}" for m in self.skipped]
        summary["skipped"] = self.skipped
        lines += failures_and_summary(self.failures, self.summary_json, summary)
        if self.interrupted:
            if saved:
                left = len(images) - self.saved_now  # counted as written: the summary matches the file
                how = f"run the same command with --resume to do the {left} left"
                if "--resume" in sys.argv:
                    how = f"run the same command again to do the {left} left"
                lines.append(f"interrupted: {self.saved_now} of {len(images)} images saved in {saved}; {how}")
            else:
                lines.append(f"interrupted after {done} of {len(images)} images; nothing was saved "
                             "(no --out)")
        return lines


class _ResumePlan:
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


def _steady(first_done, t_end: float, done: int, stats: dict) -> dict:
    """Throughput after the first computed batch (which pays the one-off warm-up)."""
    if first_done is None or done <= first_done[1]:
        return dict(steady_ms_per_image=None, steady_algorithm_ms_per_image=None)
    t1, n1, a1 = first_done
    n = done - n1
    return dict(steady_ms_per_image=1000 * (t_end - t1) / n,
                steady_algorithm_ms_per_image=1000 * (stats["algo_s"] - a1) / n)


def _viz_names(images: Sequence[Path]) -> dict[str, str]:
    """A distinct PNG file name per image: ``<stem>.png``, ``<stem>-<n>.png`` on clashes."""
    from collections import Counter

    stems = Counter(Path(p).stem for p in images)
    names: dict[str, str] = {}
    used: set[str] = set()
    for i, p in enumerate(images):
        stem = Path(p).stem
        name = f"{stem}.png" if stems[stem] == 1 else f"{stem}-{i + 1}.png"
        while name in used:
            name = f"{stem}-{i + 1}-{len(used)}.png"
        used.add(name)
        names[str(p)] = name
    return names
