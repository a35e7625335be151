"""``reeb propose --engine ray``: the same inputs, rows, summary and exit codes as the local
run, with the output a folder of Parquet files written by Ray Data.

:func:`propose_ray` checks the inputs and the output folder (with ``--resume``, the rows
kept from before) before any work, starts or reaches Ray, runs
:func:`reeb_torch.runs.distributed.propose_dataset` and writes it with
:func:`~reeb_torch.runs.distributed.write_results`, then prints the closing summary. The Ray
engine itself (:mod:`.distributed`) is a library and knows nothing of the command.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Sequence

import click

from .common import (
    Failure,
    UsageProblem,
    build_config,
    count_line,
    failures_and_summary,
    ms_per_img,
    resolve_device,
)

__all__ = ["propose_ray"]


def propose_ray(paths: Sequence[str], *, out: str | None, resume: bool, overwrite: bool,
                preset: str, config_file: str | None, sets: Sequence[str], top_k: int | None,
                device: str, batch_size: int, recursive: bool, summary_json: str | None,
                quiet: bool, address: str | None, actors: int, cpus_per_actor: float | None,
                viz_dir: str | None = None) -> None:
    """``reeb propose --engine ray``: the same inputs, rows, summary and exit codes as the
    single-machine path, with the output a folder of Parquet files written by Ray.

    Usage errors (exit 2) are raised as :class:`~.common.UsageProblem` before any work;
    the process exits 1 when an image failed, 130 when interrupted.
    """
    from . import batch as B
    from .distributed import (RayMissingError, actor_cpus, match_key, propose_dataset, prune_rows,
                              read_result_dir, require_ray, result_files, row_key, write_results)

    echo_err = (lambda m: None) if quiet else (lambda m: click.echo(m, err=True))
    try:
        ray = require_ray()
    except RayMissingError as e:
        raise UsageProblem(str(e))
    cfg = build_config(preset, config_file, sets, top_k)
    dev = resolve_device(device)
    fingerprint = cfg.fingerprint()
    if viz_dir:
        raise UsageProblem("--viz is not available with --engine ray (use --engine local)")

    # 1. inputs
    if not paths:
        raise UsageProblem("--engine ray needs PATHS (images, folders or glob patterns)")
    try:
        images, notes = B.find_images(paths, recursive)
    except B.NoImagesError as e:
        raise UsageProblem(str(e))
    for n in notes:
        echo_err(f"note: {n}")

    # 2. the output folder, checked before any work
    if not out:
        raise UsageProblem("--engine ray needs --out DIR (a folder of Parquet files, "
                           "e.g. --out proposals.parquet)")
    out_dir = Path(out)
    if out_dir.suffix.lower() in (".jsonl", ".ndjson", ".json"):
        raise UsageProblem(f"{out}: --engine ray writes a folder of Parquet files; give a folder "
                           "name such as proposals.parquet")
    if out_dir.exists() and not out_dir.is_dir():
        raise UsageProblem(f"{out}: exists and is not a folder; --engine ray writes a folder of "
                           "Parquet files")
    existing = result_files(out_dir) if out_dir.is_dir() else []
    kept = 0
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
    if resume and existing:
        try:
            rows = read_result_dir(out_dir)
        except OSError as e:
            raise UsageProblem(f"cannot read {out} for --resume: {e}")
        other = {r.get("config") for r in rows if r.get("status") == "ok"} - {fingerprint}
        if other:
            raise UsageProblem(
                f"{out} was made with different settings (config {', '.join(sorted(map(str, other)))}, "
                f"now {fingerprint}); use the same options, another --out, or --overwrite")
        done = {row_key(r) for r in rows if r.get("status") == "ok"}
        kept = len(done)
        before = len(images)
        images = [p for p in images if match_key(p) not in done]
        echo_err(f"resume: {kept} images already in {out}, {before - len(images)} of them among "
                 f"the inputs; {len(images)} to do")
        if not images:
            click.echo(f"Nothing to do: all {before} images are already in {out}.", err=True)
            return
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
        B.check_output(out_dir / "probe.parquet")
    except (OSError, B.OutputError) as e:
        raise UsageProblem(f"{out}: cannot write there ({getattr(e, 'strerror', None) or e})")
    lock_output = getattr(B, "lock_output", None)  # one writer per output, as reeb propose
    if lock_output is not None:
        try:
            lock = lock_output(out_dir)
        except B.OutputError as e:
            raise UsageProblem(str(e))
        release = lock.release
    else:
        release = (lambda: None)
    try:

        # 3. Ray: a local instance sized to the machine, or the cluster at --address
        t0 = time.perf_counter()
        if not ray.is_initialized():
            try:
                ray.init(address=address, include_dashboard=False, log_to_driver=not quiet,
                         logging_level="ERROR", configure_logging=True)
            except Exception as e:  # noqa: BLE001 - Ray raises many kinds when it cannot connect
                where = f"the Ray cluster at {address}" if address else "a local Ray instance"
                raise Failure(f"cannot start or reach {where}: {' '.join(str(e).split())}")
        startup_s = time.perf_counter() - t0
        ctx = ray.data.DataContext.get_current()
        ctx.enable_progress_bars = not quiet
        ctx.print_on_execution_start = not quiet
        ctx.execution_options.preserve_order = True  # rows in input order, as reeb propose
        total_cpus = ray.cluster_resources().get("CPU", 1.0)
        try:
            cpus = actor_cpus(total_cpus, actors, cpus_per_actor)
        except ValueError as e:
            raise UsageProblem(str(e))
        if cpus * actors > total_cpus:
            raise UsageProblem(f"{actors} actors × {cpus:g} CPUs need more than the {total_cpus:g} "
                               "CPUs Ray has; lower --actors or --cpus-per-actor")
        echo_err(f"ray: {total_cpus:g} CPUs, start-up {startup_s:.1f} s; {actors} actor"
                 f"{'s' if actors != 1 else ''} × {cpus:g} CPU; writing {out_dir}/")

        # 4. the run
        before_files = set(result_files(out_dir))
        ds = propose_dataset(images, cfg, actors=actors, cpus_per_actor=cpus, batch_size=batch_size,
                             device=str(dev))
        t1 = time.perf_counter()
        interrupted = False
        try:
            write_results(ds, out_dir)
        except KeyboardInterrupt:
            interrupted = True
        except Exception as e:  # noqa: BLE001 - a failed Ray job
            raise Failure(f"the Ray job failed: {' '.join(str(e).split())[:2000]}")
        wall = time.perf_counter() - t1
        new_files = set(result_files(out_dir)) - before_files
        rows = []
        for f in sorted(new_files):
            try:
                import pyarrow.parquet as pq

                rows += pq.read_table(f).to_pylist()
            except Exception:  # noqa: BLE001 - a file cut short by an interruption
                if not interrupted:
                    raise
        ok = [r for r in rows if r.get("status") == "ok"]
        failures = [r["status"][len("error: "):] for r in rows if r.get("status") != "ok"]
        redone = {row_key(r) for r in rows}  # tried again: the new row replaces the old error row
        if resume and existing:
            prune_rows(out_dir, redone, new_files)
        done = len(rows)
        proposals = sum(len(r["boxes"]) for r in ok)
        summary = dict(engine="ray", images=len(images), processed=done, ok=len(ok),
                       failed=len(failures), proposals=proposals,
                       ms_per_image=1000 * wall / done if done else None,
                       ray_startup_s=startup_s, ray_cpus=total_cpus, actors=actors,
                       cpus_per_actor=cpus, batch_size=batch_size, device=str(dev),
                       address=address, config=fingerprint, out=str(out_dir), rows=done,
                       interrupted=interrupted, failures=failures)
        lines = [count_line(done, len(ok), len(failures), proposals)]
        if done:
            lines.append(f"time: {wall:.1f} s, {ms_per_img(wall, done)} end to end ({actors} Ray actor"
                         f"{'s' if actors != 1 else ''} × {cpus:g} CPU, batch {batch_size}, {dev}); "
                         f"Ray start-up {startup_s:.1f} s not included")
            lines.append(f"wrote {out_dir}/ ({done} rows in {len(new_files)} new Parquet file"
                         f"{'s' if len(new_files) != 1 else ''}"
                         + (f", {kept} kept from before" if kept else "") + ")")
        lines += failures_and_summary(failures, summary_json, summary)
        if interrupted:
            lines.append(f"interrupted: {done} of {len(images)} images saved in {out_dir}/; run the "
                         "same command with --resume to do the rest")
        click.echo("\n".join(lines), err=True)
        if interrupted:
            sys.exit(130)
        if failures:
            sys.exit(1)
    finally:
        release()
