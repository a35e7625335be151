"""Scale-out on Ray Data: the ``reeb propose`` pipeline over a local machine or a cluster.

The pipeline reads top to bottom, like the single-machine one
(:mod:`reeb_torch.runs.propose_local`):

1. :func:`paths_dataset` turns image paths into a ``ray.data.Dataset`` with one row per
   path (column ``image``: the path as given, as text; column ``open``: the absolute path
   the workers open, as bytes, so that a file name that is not UTF-8 is read as it is).
   Paths go through ``ray.data.from_items`` rather than ``ray.data.read_images``, so that
   decoding is the project's own reader (:class:`reeb_torch.runs.decoding.ImageFileDataset`:
   grey, RGBA and 16-bit images converted; a corrupt or non-image file becomes an
   ``error:`` row and never fails the job);
2. :func:`propose_dataset` maps :class:`ProposalActor` over it with ``map_batches`` on an
   actor pool. Each actor holds one :class:`~reeb_torch.ProposalGenerator` and sets
   torch's thread count to the CPUs it reserved. Its rows are built by
   :func:`reeb_torch.runs.rows.result_row` / :func:`~reeb_torch.runs.rows.error_row` and typed by
   :meth:`reeb_torch.runs.output_files.ParquetWriter.schema`, so they are exactly what ``reeb propose``
   writes (image, width, height, boxes, scores, status, config);
3. :func:`write_results` writes them with Ray's Parquet writer (``Dataset.write_parquet``)
   into a folder; :func:`reeb_torch.runs.output_files.read_result_dir` reads such a folder
   back (for ``--resume``, the summary and ``reeb export``).

``reeb propose --engine ray`` is :mod:`reeb_torch.runs.propose_ray`, which calls this module;
this module does not import the command line.

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
from typing import TYPE_CHECKING, Any, Iterable, Sequence, cast

import torch

from ..config import ReebConfig
from ..generator import ProposalGenerator
from .decoding import ImageFileDataset, size_batches
from .output_files import ParquetWriter, result_files
from .rows import error_row, file_error, hint_names, resolved_path, result_row, text_path

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
    "prune_rows",
    "set_aside_unfinished",
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
    path's :func:`reeb_torch.runs.rows.resolved_path` (symlinks resolved)."""

    return resolved_path(path)


def row_key(row: dict) -> str:
    """:func:`match_key` of a result row (its ``resolved`` field when it has one)."""
    return row.get("resolved") or match_key(row["image"])


def paths_dataset(paths: Iterable[str | os.PathLike]) -> "ray.data.Dataset":
    """A dataset of image paths: columns ``image`` (the path as given, as text:
    :func:`reeb_torch.runs.rows.text_path`) and ``open`` (:func:`match_key`, as bytes:
    ``os.fsencode``).

    Relative paths are resolved against the caller's working folder here, in the driver,
    because Ray's workers run in other folders; the rows keep the path as given. A file name
    that is not UTF-8 is ``image`` in the rows' ``\\xNN`` form and read from the exact bytes
    of ``open`` (both columns plain Arrow types, never pickled Python objects).
    """

    ray = require_ray()
    items = [{"image": text_path(p), "open": os.fsencode(match_key(p))} for p in paths]
    if not items:
        raise ValueError("no image paths given")
    # several blocks, so that several actors get work (one block goes to one actor)
    return ray.data.from_items(items, override_num_blocks=max(1, min(len(items), 64)))


# -- 2. proposals ----------------------------------------------------------------------------

class ProposalActor:
    """The callable class of the ``map_batches`` step: one generator per actor.

    A batch is a dict of numpy arrays with column ``image`` (the path written in the row)
    and, optionally, ``open`` (the path to read, ``str`` or ``bytes``; defaults to
    ``image``). Returns a ``pyarrow.Table`` with one row per input path, typed by
    :meth:`reeb_torch.runs.output_files.ParquetWriter.schema`. Images of equal size are computed
    together, as in ``reeb propose``; a batch that fails is redone one image at a time so
    that only the culprit gets an ``error:`` row.
    """

    def __init__(self, config: dict, cpus: float = 1.0, device: str = "cpu",
                 group_size: int = 4) -> None:
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
        item = ImageFileDataset([opened], min_side=self.config.min_window)[0]
        item.path = shown
        if item.error is not None and opened != shown:
            item.error = item.error.replace(text_path(opened), shown).replace(opened, shown)
        return item

    def _run(self, items: list) -> list[dict]:
        x = torch.stack([it.image for it in items]).to(self.device)
        with torch.no_grad():
            results = self.gen(x)
        rows = []
        for it, r in zip(items, results):
            h, w = it.image.shape[-2:]
            rows.append(result_row(it.path, w, h, r["boxes"].cpu(), r["scores"].cpu(),
                                   self.fingerprint, labels=hint_names(self.gen.classes, r.get("labels"))))
        return rows

    @staticmethod
    def _resolved(row: dict, opened: str) -> dict:
        # a relative path resolved here would name a file in the worker's folder: the
        # driver resolved it (column ``open``)
        if "resolved" in row:
            row["resolved"] = text_path(opened)
        return row

    def rows(self, shown: Sequence[str], opened: Sequence[str]) -> list[dict]:
        """The result rows for ``shown`` paths read from ``opened``, in input order."""

        items = [self._decode(str(s), str(o)) for s, o in zip(shown, opened)]
        for i, it in enumerate(items):
            it.index = i
        out: list[dict | None] = [None] * len(items)
        for group in size_batches(items, self.group_size):
            if not group[0].ok:
                out[group[0].index] = error_row(group[0].path, group[0].error or "", self.fingerprint,
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
                        assert it.image is not None  # an ok item holds its image
                        h, w = it.image.shape[-2:]
                        rows.append(error_row(it.path, file_error(it.path, e),
                                              self.fingerprint, (w, h)))
            for it, row in zip(group, rows):
                out[it.index] = row
        return [self._resolved(cast(dict, r), str(o)) for r, o in zip(out, opened)]  # every row is set

    def __call__(self, batch: dict) -> Any:
        import pyarrow as pa

        shown = [_path_text(s) for s in batch["image"]]
        opened = [_path_text(o) for o in batch["open"]] if "open" in batch else shown
        return pa.Table.from_pylist(self.rows(shown, opened), schema=ParquetWriter.schema())


def _path_text(p: Any) -> str:
    """A path from a dataset column as ``str``: bytes (``open``) through ``os.fsdecode``, so a
    name that is not UTF-8 comes back as the file system's own name."""
    if isinstance(p, (bytes, bytearray, memoryview)):
        return os.fsdecode(bytes(p))
    return str(p)


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


def set_aside_unfinished(out_dir: str | os.PathLike, only: set[Path] | None = None) -> list[Path]:
    """Rename the Parquet files of ``out_dir`` that cannot be read (a run interrupted or
    killed while Ray wrote them: no footer) to hidden ``.<name>.unfinished`` files, which
    :func:`result_files` skips; returns their new paths. ``only``: look at these files only.

    The rows in such a file are not recovered (Parquet keeps its index in the footer); the
    images are computed again by ``--resume``. Call it holding the output's lock.
    """
    import pyarrow.parquet as pq

    moved = []
    for f in result_files(out_dir):
        if only is not None and f not in only:
            continue
        try:
            pq.read_metadata(f)
        except Exception:  # noqa: BLE001 - pyarrow has its own error types
            aside = f.with_name(f".{f.name}.unfinished")
            os.replace(f, aside)
            moved.append(aside)
    return moved
