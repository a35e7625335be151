"""The fits' per-frame work on Ray Data (``reeb fit --engine ray``, ``reeb detector fit
--engine ray``): a local Ray instance or a cluster computes each frame's part, and the driver
keeps what comes back in frame order, as the single-machine fit does.

* :func:`ray_rows`: the ranking's training rows (:func:`~reeb_torch.ranker.frames.frame_samples`
  of each frame, on :class:`RowsActor` actors), appended to the fit's row store in frame
  order: the same rows as on one machine, and a fit stopped mid-way goes on from the store.
* :func:`ray_frames`: the detector's per-frame pass (:class:`FramesActor`: each image
  decoded, its REEB proposals, its frozen backbone maps written to the feature cache, its
  digests), which :func:`~reeb_torch.detection.fitting.stored_frames` then takes in place of
  computing them. The cache folder must be one that every worker writes (a shared file system
  on a cluster); the maps' bfloat16 numbers follow the worker's torch threads.

Training runs on the driver, from the store and the cache. Ray is the optional ``ray`` extra,
imported when a run starts.
"""

from __future__ import annotations

import dataclasses
import logging
import pickle
from collections.abc import Iterator, Sequence
from typing import Any

import numpy as np
import torch

from ..config import ReebConfig
from ..detection import ReebDetector
from ..detection.proposal_cache import StaleCacheError, image_digest
from ..detection.feature_cache import FeatureCache, compute_features
from ..detection.kitti import frame_image
from ..ranker import frame_hash
from ..ranker.frames import FitFrames, ImageFiles, frame_samples
from ..tuning import FrameCache
from .distributed import actor_cpus, require_ray, torch_threads

__all__ = ["start_ray", "RowsActor", "FramesActor", "ray_rows", "ray_frames"]


def start_ray(address: str | None, actors: int, cpus_per_actor: float | None, quiet: bool) -> float:
    """Start a local Ray instance (or reach the cluster at ``address``) with rows kept in
    order; the CPUs each of ``actors`` actors reserves (:func:`~reeb_torch.runs.distributed.actor_cpus`).

    Raises:
        RuntimeError: Ray cannot be started or reached (one line).
        ValueError: more CPUs asked for than Ray has.
    """
    ray = require_ray()
    if quiet:
        for name in ("ray", "ray.data", "ray._private", "ray.data._internal"):
            logging.getLogger(name).setLevel(logging.ERROR)
    if not ray.is_initialized():
        try:
            ray.init(address=address, include_dashboard=False, log_to_driver=not quiet, logging_level="ERROR",
                     configure_logging=True)
        except Exception as e:  # noqa: BLE001 - Ray raises many kinds when it cannot connect
            where = f"the Ray cluster at {address}" if address else "a local Ray instance"
            raise RuntimeError(f"cannot start or reach {where}: {' '.join(str(e).split())}") from None
    ctx = ray.data.DataContext.get_current()
    ctx.enable_progress_bars = not quiet
    ctx.print_on_execution_start = not quiet
    ctx.execution_options.preserve_order = True  # what comes back, in frame order
    total = ray.cluster_resources().get("CPU", 1.0)
    cpus = actor_cpus(total, actors, cpus_per_actor)
    if cpus * actors > total:
        raise ValueError(f"{actors} actors × {cpus:g} CPUs need more than the {total:g} CPUs Ray has; "
                         "lower --actors or --cpus-per-actor")
    return cpus


def _quiet_workers(cpus: float) -> None:
    torch.set_num_threads(torch_threads(cpus))
    try:
        import cv2

        cv2.setNumThreads(1)
    except Exception:  # noqa: BLE001 - cosmetic only
        pass


class RowsActor:
    """Holds the frames (images read when used), the config and the fit's options; called on
    a batch of frame indices, gives each frame's training rows (pickled numpy arrays)."""

    def __init__(self, frames: Any, config: dict, opts: Any, cpus: float = 1.0) -> None:
        _quiet_workers(cpus)
        self.cache = FrameCache(frames, budget=0)
        self.cfg, self.opts = ReebConfig.from_dict(config), opts

    def __call__(self, batch: dict) -> dict:
        indices = [int(i) for i in batch["frame"]]
        blobs = []
        for i in indices:
            sample = frame_samples(self.cache, self.cfg, self.opts, indices=[i])[0]
            blobs.append(pickle.dumps({f.name: getattr(sample, f.name).numpy()
                                       for f in dataclasses.fields(sample)}))
        return {"frame": np.asarray(indices, dtype=np.int64), "blob": np.asarray(blobs, dtype=object)}


def _run(ds: Any, actor: type, kwargs: dict, actors: int, cpus: float, batch: int) -> Iterator[tuple[int, Any]]:
    """``(index, result)`` of each row of ``ds`` mapped by ``actor``, in order."""
    mapped = ds.map_batches(actor, fn_constructor_kwargs=kwargs, batch_size=batch, batch_format="numpy",
                            concurrency=actors, num_cpus=cpus)
    for out in mapped.iter_batches(batch_size=None, batch_format="numpy"):
        for i, blob in zip(out["frame"], out["blob"]):
            yield int(i), pickle.loads(blob)


def ray_rows(store: Any, frames: Any, config: Any, opts: Any, actors: int, cpus: float,
             progress: Any = None) -> None:
    """Append the rows of ``frames``' frames the ``store`` lacks, computed on Ray
    (:class:`RowsActor`), in frame order; ``progress`` wraps the loop (a progress bar)."""

    ray = require_ray()
    todo = list(range(len(store), len(frames)))
    if not todo:
        return
    images: Any = ImageFiles(frames.images.paths, budget=0)  # read when used, none kept
    shipped = FitFrames(images, frames.gts, frames.labels, frames.classes, frames.ids, frames.folders,
                        ignore=frames.ignore)
    ds = ray.data.from_items([{"frame": i} for i in todo])
    kwargs = dict(frames=shipped, config=config.unranked().to_dict(), opts=opts, cpus=cpus)
    results = _run(ds, RowsActor, kwargs, actors, cpus, 1)
    for i, rows in (progress(results) if progress else results):
        if i != len(store):
            raise RuntimeError(f"Ray gave frame {i}'s rows where frame {len(store)}'s were due")
        store.append({k: torch.from_numpy(v) for k, v in rows.items()})


class FramesActor:
    """Holds a detector of the fit's settings; called on a batch of frames (pickled items),
    computes each one's REEB proposals and frozen backbone maps (written to the feature
    cache) and gives back the proposals and the image's digests."""

    def __init__(self, classes: Sequence[str], proposals: str, settings: Any, cache: dict, cpus: float = 1.0,
                 config: dict | None = None) -> None:
        _quiet_workers(cpus)
        self.det = ReebDetector(classes, proposals, settings,
                                config=ReebConfig.from_dict(config) if config is not None else None)
        self.cache = FeatureCache(**cache)

    def __call__(self, batch: dict) -> dict:
        blobs = []
        with torch.no_grad():
            for raw in batch["item"]:
                item = pickle.loads(raw)
                image = frame_image(item)
                digest = image_digest(image)
                r = self.det.model.rpn.generator([image])[0]
                try:
                    self.cache.load(digest)
                except (FileNotFoundError, StaleCacheError):
                    self.cache.save(digest, compute_features(self.det.model, image, self.cache.crop_top))
                blobs.append(pickle.dumps({"digest": digest, "hash": frame_hash(image),
                                           "size": (int(image.shape[-2]), int(image.shape[-1])),
                                           "boxes": r["boxes"].float().cpu().numpy(),
                                           "scores": r["scores"].float().cpu().numpy()}))
        return {"frame": np.asarray(batch["frame"], dtype=np.int64), "blob": np.asarray(blobs, dtype=object)}


def ray_frames(det: Any, items: Sequence[dict], cache: Any, actors: int, cpus: float) -> Iterator[dict]:
    """Per item of ``items`` (lazy: paths, no image), in order, what :class:`FramesActor`
    computed on Ray: ``{"digest", "hash", "size", "boxes", "scores"}``, its maps in ``cache``
    (a :class:`~reeb_torch.detection.feature_cache.FeatureCache`)."""
    ray = require_ray()
    rows = [{"frame": i, "item": pickle.dumps({k: it[k] for k in ("path", "flipped") if k in it})}
            for i, it in enumerate(items)]
    key = cache.key
    kwargs = dict(classes=det.classes, proposals=det.proposals["spec"], settings=det.settings,
                  config=det.proposals["config"],  # REEB's settings as the detector has them (--set)
                  cache=dict(root=str(cache.folder.parent.parent), weights=key["weights"], min_size=key["min_size"],
                             max_size=key["max_size"], precision=key["precision"], crop_top=key["crop_top"]),
                  cpus=cpus)
    for _, out in _run(ray.data.from_items(rows), FramesActor, kwargs, actors, cpus, 1):
        yield out
