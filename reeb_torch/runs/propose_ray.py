"""``reeb propose --engine ray``: the same inputs, rows, summary and exit codes as the local
run, with the output a folder of Parquet files written by Ray Data.

:func:`propose_ray` checks the inputs and the output folder (with ``--resume``, the rows
kept from before) before any work, starts or reaches Ray, runs
:func:`reeb_torch.runs.distributed.propose_dataset` and writes it with
:func:`~reeb_torch.runs.distributed.write_results`, then prints the closing summary. Ray
runs the images; what the run engine does for every command is shared with it: the inputs
(:func:`~.engine.find_inputs`), the output's lock (:func:`~.claim.claim`), the resume plan
(:func:`~.run_output.resume_from`) and the closing summary's lines (:mod:`.engine`). The Ray engine itself
(:mod:`.distributed`) is a library and knows nothing of the command.
"""

from __future__ import annotations

import logging
import os
import sys
import time
from pathlib import Path
from typing import Callable, Sequence

import click

from . import distributed as D
from .claim import claim
from .common import Failure, UsageProblem
from .engine import closing_tail, count_line, find_inputs, mismatch_line, ms_per_img
from .inputs import same_file_note
from .output_files import OutputError, check_output, read_result_dir, result_files
from .run_output import resume_from

__all__ = ["propose_ray"]


def propose_ray(paths: Sequence[str], cfg, dev, *, out: str | None, resume: bool, overwrite: bool,
                batch_size: int, recursive: bool, summary_json: str | None, quiet: bool, address: str | None,
                actors: int, cpus_per_actor: float | None, viz_dir: str | None = None) -> None:
    """``reeb propose --engine ray``: the same inputs, rows, summary and exit codes as the
    single-machine path, with the output a folder of Parquet files written by Ray; ``cfg``
    (a ReebConfig) and ``dev`` (a ``torch.device``) as the command line built them.

    Usage errors (exit 2) are raised as :class:`~.common.UsageProblem` before any work;
    the process exits 1 when an image failed, 130 when interrupted.
    """
    echo_err = (lambda m: None) if quiet else (lambda m: click.echo(m, err=True))
    try:
        ray = D.require_ray()
    except D.RayMissingError as e:
        raise UsageProblem(str(e))
    run = _RayRun(ray, cfg, dev, out=out, batch_size=batch_size, quiet=quiet, echo_err=echo_err)
    if viz_dir:
        raise UsageProblem("--viz is not available with --engine ray (use --engine local)")
    run.find_inputs(paths, recursive)  # 1. inputs
    # 2. the output folder, locked first, then checked, before any work (and before any
    # file in it is deleted: --overwrite)
    release = run.lock()
    try:
        if not run.check_out_dir(resume, overwrite):
            return  # nothing to do
        run.start_ray(address, actors, cpus_per_actor)  # 3. Ray, sized to the machine or the cluster
        run.compute()  # 4. the run
        run.summarise(resume, summary_json)
    finally:
        release()


class _RayRun:
    """One ``reeb propose --engine ray`` run, step by step: the state its steps share."""

    def __init__(self, ray, cfg, dev, *, out: str | None, batch_size: int, quiet: bool,
                 echo_err: Callable[[str], None]) -> None:
        self.ray, self.cfg, self.dev = ray, cfg, dev
        self.fingerprint = cfg.fingerprint()
        self.out, self.batch_size, self.quiet, self.echo_err = out, batch_size, quiet, echo_err
        self.kept = 0

    def find_inputs(self, paths: Sequence[str], recursive: bool) -> None:
        if not paths:
            raise UsageProblem("--engine ray needs PATHS (images, folders or glob patterns)")
        found = find_inputs(paths, recursive, self.echo_err)
        self.images, self.same_file, self.skipped = found.images, found.same_file, found.skipped

    def check_out_dir(self, resume: bool, overwrite: bool) -> bool:
        """``--out`` must be a folder; its results are replaced (``--overwrite``) or kept
        (``--resume``); files an interrupted run left unfinished are set aside
        (:func:`~.distributed.set_aside_unfinished`). Call it holding :meth:`lock`. False
        when every image is already there (nothing to do)."""
        out, out_dir = self.out, self.out_dir
        if out_dir.is_dir():
            for f in D.set_aside_unfinished(out_dir):
                self.echo_err(f"warning: {f}: a Parquet file an interrupted run left unfinished; set "
                              "aside (its images are computed again)")
        existing = result_files(out_dir) if out_dir.is_dir() else []
        if existing and not (resume or overwrite):
            raise UsageProblem(f"{out} holds results; add --resume to continue it or --overwrite to "
                               "replace it")
        if existing and overwrite and not resume:
            others = [p for p in out_dir.rglob("*") if p.is_file() and p.suffix != ".parquet"
                      and not p.name.startswith(".")]
            if others:
                raise UsageProblem(f"{out}: --overwrite would delete the Parquet files there but the "
                                   f"folder also holds other files ({others[0]}); choose another --out")
            for p in existing:
                p.unlink()
            existing = []
        self.existing = existing
        if resume and existing and not self._resume():
            return False
        try:
            out_dir.mkdir(parents=True, exist_ok=True)
            check_output(out_dir / "probe.parquet")
        except (OSError, OutputError) as e:
            raise UsageProblem(f"{out}: cannot write there ({getattr(e, 'strerror', None) or e})")
        return True

    def _resume(self) -> bool:
        """``--resume``: skip the images with an ``ok`` row in the folder; False if none is left."""
        out = self.out
        try:
            rows = read_result_dir(self.out_dir)
        except OSError as e:
            raise UsageProblem(f"cannot read {out} for --resume: {e}")
        before = len(self.images)
        plan = resume_from(rows, self.images, str(out), self.fingerprint,
                           lambda where, configs: mismatch_line(where, configs, self.fingerprint))
        self.kept, self.images = plan.kept, plan.todo_paths()
        if not self.images:
            click.echo(f"Nothing to do: all {before} images are already in {out}.", err=True)
            return False
        return True

    def lock(self) -> Callable[[], None]:
        """Check that ``--out`` names a folder (or nothing yet) and take its lock, as
        ``reeb propose`` does, before anything in it is read or deleted: returns the lock's
        release."""
        out = self.out
        if not out:
            raise UsageProblem("--engine ray needs --out DIR (a folder of Parquet files, "
                               "e.g. --out proposals.parquet)")
        # a link to a folder: the folder it points to is locked and written (the link stays)
        self.out_dir = out_dir = Path(os.path.realpath(out) if os.path.islink(out) else out)
        if out_dir.suffix.lower() in (".jsonl", ".ndjson", ".json"):
            raise UsageProblem(f"{out}: --engine ray writes a folder of Parquet files; give a folder "
                               "name such as proposals.parquet")
        if out_dir.exists() and not out_dir.is_dir():
            raise UsageProblem(f"{out}: exists and is not a folder; --engine ray writes a folder of "
                               "Parquet files")
        try:
            out_dir.absolute().parent.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise UsageProblem(f"{out}: cannot write there ({e.strerror or e})") from None
        return claim([out_dir], hold=False)

    def start_ray(self, address: str | None, actors: int, cpus_per_actor: float | None) -> None:
        """A local Ray instance sized to the machine, or the cluster at ``address``; the CPUs
        each actor reserves."""
        ray, quiet = self.ray, self.quiet
        t0 = time.perf_counter()
        if quiet:  # -q: Ray's and Ray Data's INFO / WARNING lines too

            for name in ("ray", "ray.data", "ray._private", "ray.data._internal"):
                logging.getLogger(name).setLevel(logging.ERROR)
        if not ray.is_initialized():
            try:
                ray.init(address=address, include_dashboard=False, log_to_driver=not quiet,
                         logging_level="ERROR", configure_logging=True)
            except Exception as e:  # noqa: BLE001 - Ray raises many kinds when it cannot connect
                where = f"the Ray cluster at {address}" if address else "a local Ray instance"
                raise Failure(f"cannot start or reach {where}: {' '.join(str(e).split())}")
        self.startup_s = time.perf_counter() - t0
        ctx = ray.data.DataContext.get_current()
        ctx.enable_progress_bars = not quiet
        ctx.print_on_execution_start = not quiet
        ctx.execution_options.preserve_order = True  # rows in input order, as reeb propose
        self.total_cpus = total_cpus = ray.cluster_resources().get("CPU", 1.0)
        try:
            cpus = D.actor_cpus(total_cpus, actors, cpus_per_actor)
        except ValueError as e:
            raise UsageProblem(str(e))
        if cpus * actors > total_cpus:
            raise UsageProblem(f"{actors} actors × {cpus:g} CPUs need more than the {total_cpus:g} "
                               "CPUs Ray has; lower --actors or --cpus-per-actor")
        self.address, self.actors, self.cpus = address, actors, cpus
        self.echo_err(f"ray: {total_cpus:g} CPUs, start-up {self.startup_s:.1f} s; {actors} actor"
                      f"{'s' if actors != 1 else ''} × {cpus:g} CPU; writing {self.out_dir}/")

    def compute(self) -> None:
        """Run the dataset into the folder, then read back the rows this run wrote."""
        out_dir = self.out_dir
        before_files = set(result_files(out_dir))
        ds = D.propose_dataset(self.images, self.cfg, actors=self.actors, cpus_per_actor=self.cpus,
                               batch_size=self.batch_size, device=str(self.dev))
        t1 = time.perf_counter()
        self.interrupted = False
        try:
            D.write_results(ds, out_dir)
        except KeyboardInterrupt:
            self.interrupted = True
        except Exception as e:  # noqa: BLE001 - a failed Ray job
            raise Failure(f"the Ray job failed: {' '.join(str(e).split())[:2000]}")
        self.wall = time.perf_counter() - t1
        if self.interrupted:  # files cut short: set aside, their images are done by --resume
            D.set_aside_unfinished(out_dir, only=set(result_files(out_dir)) - before_files)
        self.new_files = set(result_files(out_dir)) - before_files
        rows = []
        for f in sorted(self.new_files):
            try:
                import pyarrow.parquet as pq

                rows += pq.read_table(f).to_pylist()
            except Exception:  # noqa: BLE001 - a file cut short by an interruption
                if not self.interrupted:
                    raise
        self.rows = rows

    def summarise(self, resume: bool, summary_json: str | None) -> None:
        """Drop the old error rows of images tried again, print the closing summary, and exit
        130 / 1 when interrupted / when an image failed."""
        rows, wall, out_dir, images = self.rows, self.wall, self.out_dir, self.images
        actors, cpus, dev = self.actors, self.cpus, self.dev
        ok = [r for r in rows if r.get("status") == "ok"]
        failures = [r["status"][len("error: "):] for r in rows if r.get("status") != "ok"]
        redone = {D.row_key(r) for r in rows}  # tried again: the new row replaces the old error row
        if resume and self.existing:
            D.prune_rows(out_dir, redone, self.new_files)
        done = len(rows)
        proposals = sum(len(r["boxes"]) for r in ok)
        summary = dict(engine="ray", images=len(images), processed=done, ok=len(ok),
                       failed=len(failures), proposals=proposals,
                       ms_per_image=1000 * wall / done if done else None,
                       ray_startup_s=self.startup_s, ray_cpus=self.total_cpus, actors=actors,
                       cpus_per_actor=cpus, batch_size=self.batch_size, device=str(dev),
                       address=self.address, config=self.fingerprint, out=str(out_dir), rows=done,
                       interrupted=self.interrupted, failures=failures)
        summary["same_file"] = len(self.same_file)
        lines = [count_line(done, len(ok), len(failures), proposals)]
        if self.same_file:
            lines.append(same_file_note(self.same_file))
        if done:
            lines.append(f"time: {wall:.1f} s, {ms_per_img(wall, done)} end to end ({actors} Ray actor"
                         f"{'s' if actors != 1 else ''} × {cpus:g} CPU, batch {self.batch_size}, {dev}); "
                         f"Ray start-up {self.startup_s:.1f} s not included")
            lines.append(f"wrote {out_dir}/ ({done} rows in {len(self.new_files)} new Parquet file"
                         f"{'s' if len(self.new_files) != 1 else ''}"
                         + (f", {self.kept} kept from before" if self.kept else "") + ")")
        lines += closing_tail(self.skipped, failures, summary_json, summary)
        if self.interrupted:
            lines.append(f"interrupted: {done} of {len(images)} images saved in {out_dir}/; run the "
                         "same command with --resume to do the rest")
        click.echo("\n".join(lines), err=True)
        if self.interrupted:
            sys.exit(130)
        if failures:
            sys.exit(1)
