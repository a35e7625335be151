"""Weights files of the learned ranking: safetensors (no pickle), with what made them.

A file holds the tensors of a :class:`~reeb_torch.ranker.model.BoxRanker` (``mean``,
``scale``, ``members.<i>.<layer>.weight|bias``, ``prefilter.<layer>.weight|bias``, and with a
class head ``classifier.<layer>.weight|bias``) and one metadata entry, ``reeb-ranker``: a
JSON object (keys sorted, so the same model gives the same bytes) with

* ``features_version``: the :data:`~reeb_torch.stages.features.FEATURES_VERSION` it was
  fitted on; ``feature_names``, ``hidden``, ``members``, ``prefilter``: its shape;
  ``classes``, ``class_hidden``: its class head's, where it has one (older files have none);
* ``provenance``: the frames it was fitted on, the command that refits it, its
  cross-validated recall, the fit's options and seed;
* ``config``: the :class:`~reeb_torch.ReebConfig` fields it was fitted with.

:func:`load_ranker` takes a shipped name (:data:`SHIPPED`, files inside the package) or a
path, and raises :class:`RankerWeightsError` (a ``ValueError``) with one line naming the
file and what is wrong: missing, unreadable, another format, or fitted on other features.
"""

from __future__ import annotations

import json
import os
import threading
from importlib import resources
from pathlib import Path

import torch

from ..stages.features import FEATURES_VERSION
from .model import BoxRanker

__all__ = ["SHIPPED", "RankerWeightsError", "load_ranker", "save_ranker", "resolve_ranker", "shipped_path"]

SHIPPED: dict[str, str] = {
    "kitti": "kitti.safetensors",
}
"""Shipped weights by name (``ReebConfig.ranker='kitti'``): files in ``reeb_torch/ranker/weights/``."""

FORMAT = "reeb-ranker"

_LOADED: dict[tuple, BoxRanker] = {}
_LOCK = threading.Lock()


class RankerWeightsError(ValueError):
    """A ranker weights file that cannot be used: missing, unreadable, or made for other features."""


def shipped_path(name: str) -> Path:
    """The file of the shipped weights ``name`` (:data:`SHIPPED`)."""
    return Path(str(resources.files("reeb_torch.ranker").joinpath("weights", SHIPPED[name])))


def resolve_ranker(spec: str) -> Path:
    """The weights file ``spec`` names: a shipped name (:data:`SHIPPED`) or a path.

    Raises:
        RankerWeightsError: no such name and no such file.
    """
    path = shipped_path(spec) if spec in SHIPPED else Path(os.path.expanduser(spec))
    if not path.is_file():
        what = "the shipped weights are missing from the package" if spec in SHIPPED else "no such file"
        raise RankerWeightsError(f"ranker weights {spec!r}: {what} ({path}); ReebConfig.ranker takes 'none', "
                                 f"a shipped name ({', '.join(sorted(SHIPPED))}) or a .safetensors file "
                                 "that `reeb fit` wrote")
    return path


def load_ranker(spec: str, feature_names: tuple[str, ...] | None = None) -> BoxRanker:
    """The :class:`BoxRanker` of the weights ``spec`` (a shipped name or a path), in eval
    mode, on the CPU; loaded once per file and modification time, then shared (read-only).

    Args:
        spec: ``"kitti"`` (:data:`SHIPPED`) or the path of a file :func:`save_ranker` wrote.
        feature_names: the features the caller computes; the file must read exactly these.

    Raises:
        RankerWeightsError: the file is missing, not a readable safetensors file, not a
            ranker's, or was fitted on other features (naming both versions).
    """
    path = resolve_ranker(spec)
    key = (str(path.resolve()), path.stat().st_mtime_ns, path.stat().st_size)
    with _LOCK:
        model = _LOADED.get(key)
        if model is None:
            model = _read(path, spec)
            _LOADED[key] = model
    if feature_names is not None and tuple(feature_names) != model.feature_names:
        raise RankerWeightsError(
            f"ranker weights {spec!r} read {len(model.feature_names)} features "
            f"({_differ(model.feature_names, feature_names)}) but this config gives {len(feature_names)}: "
            "fit weights for this config with `reeb fit`")
    return model


def _differ(have: tuple[str, ...], want: tuple[str, ...]) -> str:
    extra = [n for n in have if n not in want]
    missing = [n for n in want if n not in have]
    parts = ([f"not computed here: {', '.join(extra[:4])}"] if extra else []) + \
        ([f"without {', '.join(missing[:4])}"] if missing else [])
    return "; ".join(parts) or "in another order"


def _read(path: Path, spec: str) -> BoxRanker:
    from safetensors import SafetensorError, safe_open

    try:
        with safe_open(str(path), framework="pt") as f:
            meta = f.metadata() or {}
            tensors = {k: f.get_tensor(k) for k in f.keys()}
    except (SafetensorError, OSError, ValueError) as e:
        reason = str(e).splitlines()[0] if str(e) else type(e).__name__
        raise RankerWeightsError(f"ranker weights {spec!r} ({path}) are not a readable safetensors file: "
                                 f"{reason}") from None
    try:
        info = json.loads(meta[FORMAT])
    except (KeyError, ValueError):
        raise RankerWeightsError(f"ranker weights {spec!r} ({path}) are not a reeb-torch ranker's "
                                 f"(no {FORMAT!r} metadata)") from None
    version = info.get("features_version")
    if version != FEATURES_VERSION:
        raise RankerWeightsError(f"ranker weights {spec!r} ({path}) were fitted on features version {version}, "
                                 f"but this reeb-torch computes version {FEATURES_VERSION}: refit them with `reeb fit`")
    try:
        model = BoxRanker(info["feature_names"], info["hidden"], info["members"], info["prefilter"],
                          info.get("classes"), info.get("class_hidden", (32,)))
        model.load_state_dict(tensors, strict=True)
        model.meta = {k: info[k] for k in ("provenance", "config") if k in info}
    except (KeyError, ValueError, RuntimeError, TypeError) as e:
        reason = str(e).splitlines()[0] if str(e) else type(e).__name__
        raise RankerWeightsError(f"ranker weights {spec!r} ({path}) do not hold a ranker: {reason}") from None
    return model.eval().requires_grad_(False)


def save_ranker(model: BoxRanker, path: str | os.PathLike, provenance: dict | None = None,
                config: dict | None = None) -> Path:
    """Write ``model`` to ``path`` (safetensors; the same model gives the same bytes).

    ``provenance`` and ``config`` (JSON-able dicts) are kept as metadata (:data:`BoxRanker.meta`
    once loaded)."""
    from safetensors.torch import save_file

    info = {"features_version": FEATURES_VERSION, "feature_names": list(model.feature_names),
            "hidden": list(model.hidden), "members": len(model.members),
            "prefilter": None if model.prefilter_hidden is None else list(model.prefilter_hidden)}
    if model.classes is not None:  # files without a class head keep the earlier bytes
        info["classes"], info["class_hidden"] = list(model.classes), list(model.class_hidden)
    if provenance is not None:
        info["provenance"] = provenance
    if config is not None:
        info["config"] = config
    meta = {FORMAT: json.dumps(info, sort_keys=True, default=list)}  # one entry: its place is fixed
    tensors = {k: v.detach().to("cpu", torch.float32).contiguous() for k, v in model.state_dict().items()}
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    save_file(tensors, str(out), metadata=meta)
    return out
