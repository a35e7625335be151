"""Scale-out on Ray Data: the ``reeb propose`` pipeline over a local machine or a cluster.

The pipeline reads top to bottom, like the single-machine one in :mod:`reeb_torch.batch`:

1. :func:`paths_dataset` turns image paths into a ``ray.data.Dataset`` with one row per
   path (column ``image``: the path as given; column ``open``: the absolute path the
   workers open). Paths go through ``ray.data.from_items`` rather than
   ``ray.data.read_images``, so that decoding is the project's own reader
   (:class:`reeb_torch.batch.ImageFileDataset`: grey, RGBA and 16-bit images converted;
   a corrupt or non-image file becomes an ``error:`` row and never fails the job);
2. :func:`propose_dataset` maps :class:`ProposalActor` over it with ``map_batches`` on an
   actor pool. Each actor holds one :class:`~reeb_torch.ProposalGenerator` and sets
   torch's thread count to the CPUs it reserved. Its rows are built by
   :func:`reeb_torch.batch.result_row` / :func:`~reeb_torch.batch.error_row` and typed by
   :meth:`reeb_torch.batch.ParquetWriter.schema`, so they are exactly what ``reeb propose``
   writes (image, width, height, boxes, scores, status, config);
3. :func:`write_results` writes them with Ray's Parquet writer (``Dataset.write_parquet``)
   into a folder; :func:`read_result_dir` reads such a folder back (for ``--resume``, the
   summary and ``reeb export``).

Ray is an optional dependency (``pip install "reeb-torch[ray]"``), imported lazily.

Sizing (:func:`actor_cpus`): on a small machine an actor pool that reserves every CPU
starves the tasks Ray Data needs besides the actors (reading the input blocks, writing the
Parquet files) and the job stalls with no progress. By default the actors together reserve
at most ``CPUs - 1`` (fractions allowed), leaving one CPU to those tasks.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterable, Sequence

from .config import ReebConfig

if TYPE_CHECKING:  # pragma: no cover
    import ray.data

__all__ = [
    "RAY_INSTALL_HINT",
    "RayMissingError",
    "require_ray",
    "actor_cpus",
    "match_key",
    "row_key",
    "paths_dataset",
    "ProposalActor",
    "propose_dataset",
    "write_results",
    "result_files",
    "read_result_dir",
    "prune_rows",
]

RAY_INSTALL_HINT = 'pip install "reeb-torch[ray]"'


class RayMissingError(ImportError):
    """Ray (with Ray Data) is not installed; the message says how to install it."""


def require_ray():
    """Import and return ``ray`` (with ``ray.data``); :class:`RayMissingError` if absent."""
    try:
        import ray
        import ray.data  # noqa: F401
    except ImportError as e:
        raise RayMissingError(
            f"the Ray engine needs Ray Data, which is not installed ({e}); install it with: "
            f"{RAY_INSTALL_HINT}") from e
    return ray


# -- sizing --------------------------------------------------------------------------------

def actor_cpus(total_cpus: float, actors: int, cpus_per_actor: float | None = None) -> float:
    """CPUs each of ``actors`` actors reserves on a machine (or cluster) of ``total_cpus``.

    Given ``cpus_per_actor``, it is used as is (it must be > 0). Otherwise the actors
    together reserve ``total_cpus - 1`` (at least a quarter CPU each), so that one CPU is
    always left to Ray Data's read and write tasks: with every CPU reserved by actors those
    tasks never get scheduled and the job stalls (seen on a 2-CPU machine). On one CPU the
    actors share ``0.5``.
    """
    if actors < 1:
        raise ValueError(f"actors must be >= 1, got {actors}")
    if cpus_per_actor is not None:
        if not cpus_per_actor > 0:
            raise ValueError(f"cpus_per_actor must be > 0, got {cpus_per_actor}")
        return float(cpus_per_actor)
    free = total_cpus - 1 if total_cpus >= 2 else total_cpus / 2
    return max(0.25, round(free / actors, 2))


def torch_threads(cpus: float) -> int:
    """Torch threads for an actor that reserved ``cpus`` CPUs: ``max(1, floor(cpus))``."""
    return max(1, int(math.floor(cpus + 1e-9)))


# -- 1. inputs -----------------------------------------------------------------------------

def match_key(path: str | os.PathLike) -> str:
    """The absolute path that rows are matched on for ``--resume``: the single-machine
    path's :func:`reeb_torch.batch.resolved_path` (symlinks resolved) when it has one."""
    from . import batch as B

    return getattr(B, "resolved_path", os.path.abspath)(path)


def row_key(row: dict) -> str:
    """:func:`match_key` of a result row (its ``resolved`` field when it has one)."""
    return row.get("resolved") or match_key(row["image"])


def paths_dataset(paths: Iterable[str | os.PathLike]) -> "ray.data.Dataset":
    """A dataset of image paths: columns ``image`` (as given) and ``open`` (:func:`match_key`).

    Relative paths are resolved against the caller's working folder here, in the driver,
    because Ray's workers run in other folders; the rows keep the path as given.
    """
    ray = require_ray()
    items = [{"image": str(p), "open": match_key(p)} for p in paths]
    if not items:
        raise ValueError("no image paths given")
    # several blocks, so that several actors get work (one block goes to one actor)
    return ray.data.from_items(items, override_num_blocks=max(1, min(len(items), 64)))


# -- 2. proposals ----------------------------------------------------------------------------

class ProposalActor:
    """The callable class of the ``map_batches`` step: one generator per actor.

    A batch is a dict of numpy arrays with column ``image`` (the path written in the row)
    and, optionally, ``open`` (the path to read; defaults to ``image``). Returns a
    ``pyarrow.Table`` with one row per input path, typed by
    :meth:`reeb_torch.batch.ParquetWriter.schema`. Images of equal size are computed
    together, as in ``reeb propose``; a batch that fails is redone one image at a time so
    that only the culprit gets an ``error:`` row.
    """

    def __init__(self, config: dict, cpus: float = 1.0, device: str = "cpu",
                 group_size: int = 4) -> None:
        import torch

        from .generator import ProposalGenerator

        torch.set_num_threads(torch_threads(cpus))
        try:
            import cv2

            cv2.setNumThreads(1)
            cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)
        except Exception:  # noqa: BLE001 - cosmetic only
            pass
        self.config = ReebConfig.from_dict(config)
        self.fingerprint = self.config.fingerprint()
        self.device = torch.device(device)
        self.group_size = group_size
        self.gen = ProposalGenerator(self.config).to(self.device).eval()

    def _decode(self, shown: str, opened: str):
        from . import batch as B

        item = B.ImageFileDataset([opened], min_side=self.config.min_window)[0]
        item.path = shown
        if item.error is not None and opened != shown:
            item.error = item.error.replace(opened, shown)
        return item

    def _run(self, items: list) -> list[dict]:
        import torch

        from . import batch as B

        x = torch.stack([it.image for it in items]).to(self.device)
        with torch.no_grad():
            results = self.gen(x)
        rows = []
        for it, r in zip(items, results):
            h, w = it.image.shape[-2:]
            rows.append(B.result_row(it.path, w, h, r["boxes"].cpu(), r["scores"].cpu(),
                                     self.fingerprint))
        return rows

    @staticmethod
    def _resolved(row: dict, opened: str) -> dict:
        # a relative path resolved here would name a file in the worker's folder: the
        # driver resolved it (column ``open``)
        if "resolved" in row:
            row["resolved"] = opened
        return row

    def rows(self, shown: Sequence[str], opened: Sequence[str]) -> list[dict]:
        """The result rows for ``shown`` paths read from ``opened``, in input order."""
        from . import batch as B

        items = [self._decode(str(s), str(o)) for s, o in zip(shown, opened)]
        for i, it in enumerate(items):
            it.index = i
        out: list[dict | None] = [None] * len(items)
        for group in B.size_batches(items, self.group_size):
            if not group[0].ok:
                out[group[0].index] = B.error_row(group[0].path, group[0].error, self.fingerprint,
                                                  getattr(group[0], "size", None))
                continue
            try:
                rows = self._run(group)
            except (ValueError, TypeError, RuntimeError):
                rows = []
                for it in group:
                    try:
                        rows += self._run([it])
                    except (ValueError, TypeError, RuntimeError) as e:
                        h, w = it.image.shape[-2:]
                        rows.append(B.error_row(it.path, B.file_error(it.path, e),
                                                self.fingerprint, (w, h)))
            for it, row in zip(group, rows):
                out[it.index] = row
        return [self._resolved(r, str(o)) for r, o in zip(out, opened)]  # type: ignore[return-value]

    def __call__(self, batch: dict) -> Any:
        import pyarrow as pa

        from .batch import ParquetWriter

        shown = [str(s) for s in batch["image"]]
        opened = [str(o) for o in batch["open"]] if "open" in batch else shown
        return pa.Table.from_pylist(self.rows(shown, opened), schema=ParquetWriter.schema())


def propose_dataset(
    source: "Sequence[str | os.PathLike] | ray.data.Dataset",
    config: ReebConfig | None = None,
    *,
    actors: int = 1,
    cpus_per_actor: float | None = None,
    batch_size: int = 4,
    device: str = "cpu",
) -> "ray.data.Dataset":
    """Proposals for every image of ``source``, lazily, as a ``ray.data.Dataset`` of rows.

    ``source`` is a list of image paths or a dataset with a string column ``image`` (and,
    optionally, ``open``, see :func:`paths_dataset`). ``actors`` actors each hold one
    generator built from ``config`` (default :class:`ReebConfig`); each reserves
    ``cpus_per_actor`` CPUs (default: :func:`actor_cpus` of the cluster's CPUs, which
    leaves room for Ray Data's read and write tasks) and runs that many torch threads.
    ``batch_size`` paths go to an actor at a time.

    The rows are those ``reeb propose`` writes (image, width, height, boxes
    ``[[x1, y1, x2, y2], ...]`` in input pixels ranked best first, scores, status,
    config); one per input path, failures included. Ray must be initialised (or it is
    started locally on first use). Nothing runs until the dataset is consumed
    (:func:`write_results`, ``take_all``, ``iter_rows``...).
    """
    ray = require_ray()
    cfg = config or ReebConfig()
    if isinstance(source, ray.data.Dataset):
        ds = source
    else:
        ds = paths_dataset(source)
    if cpus_per_actor is None:
        if not ray.is_initialized():
            ray.init(include_dashboard=False)
        cpus_per_actor = actor_cpus(ray.cluster_resources().get("CPU", 1.0), actors)
    cpus = actor_cpus(1, actors, cpus_per_actor)
    return ds.map_batches(
        ProposalActor,
        fn_constructor_kwargs=dict(config=cfg.to_dict(), cpus=cpus, device=device,
                                   group_size=batch_size),
        batch_size=batch_size,
        batch_format="numpy",
        concurrency=actors,
        num_cpus=cpus,
        num_gpus=1 if str(device).startswith("cuda") else None,
    )


# -- 3. output -------------------------------------------------------------------------------

def write_results(ds: "ray.data.Dataset", out_dir: str | os.PathLike) -> None:
    """Run ``ds`` and write its rows with Ray's Parquet writer into the folder ``out_dir``.

    New files are added beside any already there (``--resume`` relies on this).
    """
    ds.write_parquet(str(out_dir))


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


def prune_rows(out_dir: str | os.PathLike, drop: set[str], keep_new: set[Path]) -> int:
    """Remove, from the files of ``out_dir`` not in ``keep_new``, the error rows of images
    in ``drop`` (:func:`row_key` values): after ``--resume`` redid them (with a new ``ok`` or
    ``error:`` row), one row per image is left.

    Each file is rewritten to a temporary file and renamed into place. Returns the number
    of rows removed.
    """
    import pyarrow as pa
    import pyarrow.parquet as pq

    removed = 0
    for f in result_files(out_dir):
        if f in keep_new:
            continue
        table = pq.read_table(f)
        rows = table.to_pylist()
        kept = [r for r in rows if not (r.get("status") != "ok" and row_key(r) in drop)]
        if len(kept) == len(rows):
            continue
        removed += len(rows) - len(kept)
        tmp = f.with_name(f".{f.name}.tmp")
        if kept:
            pq.write_table(pa.Table.from_pylist(kept, schema=table.schema), tmp)
            os.replace(tmp, f)
        else:
            f.unlink()
    return removed


# -- the command line: reeb propose --engine ray ---------------------------------------------

def cli_propose(paths: Sequence[str], *, out: str | None, resume: bool, overwrite: bool,
                preset: str, config_file: str | None, sets: Sequence[str], top_k: int | None,
                device: str, batch_size: int, recursive: bool, summary_json: str | None,
                quiet: bool, address: str | None, actors: int, cpus_per_actor: float | None,
                viz_dir: str | None = None) -> None:
    """``reeb propose --engine ray``: the same inputs, rows, summary and exit codes as the
    single-machine path, with the output a folder of Parquet files written by Ray.

    Usage errors (exit 2) are raised as :class:`reeb_torch.cli.UsageProblem` before any
    work; the process exits 1 when an image failed, 130 when interrupted.
    """
    import sys
    import time

    import click

    from . import batch as B
    from .cli import Failure, UsageProblem, _count_line, _failures_and_summary, _ms, build_config, resolve_device

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
        lines = [_count_line(done, len(ok), len(failures), proposals)]
        if done:
            lines.append(f"time: {wall:.1f} s, {_ms(wall, done)} end to end ({actors} Ray actor"
                         f"{'s' if actors != 1 else ''} × {cpus:g} CPU, batch {batch_size}, {dev}); "
                         f"Ray start-up {startup_s:.1f} s not included")
            lines.append(f"wrote {out_dir}/ ({done} rows in {len(new_files)} new Parquet file"
                         f"{'s' if len(new_files) != 1 else ''}"
                         + (f", {kept} kept from before" if kept else "") + ")")
        lines += _failures_and_summary(failures, summary_json, summary)
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
