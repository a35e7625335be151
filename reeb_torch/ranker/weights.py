"""Weights files of the learned ranking: safetensors (no pickle), with what made them.

A file holds the tensors of a :class:`~reeb_torch.ranker.model.BoxRanker` (``mean``,
``scale``, ``members.<i>.<layer>.weight|bias``, ``prefilter.<layer>.weight|bias``, and with a
class head ``classifier.<layer>.weight|bias``) and one metadata entry, ``reeb-ranker``: a
JSON object (keys sorted, so the same model gives the same bytes) with

* ``features_version``: the :data:`~reeb_torch.ranker.features.FEATURES_VERSION` it was
  fitted on; ``feature_names``, ``hidden``, ``members``, ``prefilter``: its shape;
  ``classes``, ``class_hidden``: its class head's, where it has one (older files have none);
* ``provenance``: the frames it was fitted on (their folders, ids and, in files written
  since frame hashes were added, ``frame_hashes``: a :func:`frame_hash` of each image, so
  that :func:`fitted_frames` can say which of someone's frames the model saw whatever they
  are named), the command that refits it, its cross-validated recall, the fit's options and
  seed;
* ``config``: the :class:`~reeb_torch.ReebConfig` fields it was fitted with.

:func:`load_ranker` takes a shipped name (:data:`SHIPPED`, files inside the package) or a
path, and raises :class:`RankerWeightsError` (a ``ValueError``) with one line naming the
file and what is wrong: missing, unreadable, another format, or fitted on other features.
"""

from __future__ import annotations

import json
import os
import re
import threading
from importlib import resources
from pathlib import Path

import torch
from torch import Tensor

from .features import FEATURES_VERSION
from .model import BoxRanker

__all__ = ["SHIPPED", "RankerWeightsError", "load_ranker", "save_ranker", "resolve_ranker", "shipped_path",
           "frame_hash", "hash_distance", "seen_hashes", "fitted_frames", "SAME_IMAGE_BITS"]

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
        bad = [k for k, v in model.meta.items() if not isinstance(v, dict)]
        if bad:
            raise ValueError(f"its {bad[0]!r} metadata is not a JSON object")
    except (KeyError, ValueError, RuntimeError, TypeError) as e:
        reason = str(e).splitlines()[0] if str(e) else type(e).__name__
        raise RankerWeightsError(f"ranker weights {spec!r} ({path}) do not hold a ranker: {reason}") from None
    return model.eval().requires_grad_(False)


def save_ranker(model: BoxRanker, path: str | os.PathLike, provenance: dict | None = None,
                config: dict | None = None) -> Path:
    """Write ``model`` to ``path`` (safetensors; the same model gives the same bytes).

    ``provenance`` and ``config`` (JSON-able dicts) are kept as metadata (:data:`BoxRanker.meta`
    once loaded)."""
    from safetensors.torch import save

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
    # the bytes through Python's open: the file gets the umask's permissions (safetensors'
    # save_file made it readable by its owner alone: 0600, whatever the umask)
    out.write_bytes(save(tensors, metadata=meta))
    return out


_HASH_SIDE = 16
_HEX = re.compile(f"[0-9a-f]{{{_HASH_SIDE * _HASH_SIDE // 4}}}")
SAME_IMAGE_BITS = 12
"""Most bits of :func:`frame_hash`'s 256 by which two images may differ and still count as the
same picture. On the 106 dev frames: the same frame as float or uint8, or re-encoded as JPEG
at quality 70, 0 bits; at half its size, 6; two distinct frames 19 or more (two moments of
one drive), 122 at the median. Among more frames, a near-copy (the same street a moment
later) may come within it: for a recall, nearly as in-sample as the frame itself."""


def frame_hash(image: Tensor) -> str:
    """A 256-bit difference hash of ``image`` (``[3, H, W]`` RGB, uint8 or float in [0, 1]),
    as 64 hex digits: its grey (the channels' mean) shrunk to 16 × 17 by area averaging, one
    bit per pair of horizontal neighbours (set where the right one is brighter). Survives
    re-encoding and resizing (:data:`SAME_IMAGE_BITS`); not a cryptographic hash."""
    if image.ndim != 3 or image.shape[0] != 3:
        raise ValueError(f"frame_hash expects an RGB image [3, H, W], got shape {tuple(image.shape)}")
    x = image.detach().to("cpu", torch.float32)
    if image.dtype == torch.uint8:
        x = x / 255.0
    grey = x.mean(0)[None, None]
    small = torch.nn.functional.interpolate(grey, size=(_HASH_SIDE, _HASH_SIDE + 1), mode="area")[0, 0]
    bits = (small[:, 1:] > small[:, :-1]).flatten().tolist()
    return f"{int(''.join('1' if b else '0' for b in bits), 2):0{_HASH_SIDE * _HASH_SIDE // 4}x}"


def hash_distance(a: str, b: str) -> int:
    """How many bits two :func:`frame_hash` values differ by (0–256)."""
    return bin(int(a, 16) ^ int(b, 16)).count("1")


def seen_hashes(provenance: dict) -> dict[str, str]:
    """The :func:`frame_hash` of every frame a model's ``provenance`` says it learned from,
    by ``"folder/id"``: its own frames and, for a fine-tuned model, those of the model it
    started from (``provenance["init"]["frame_hashes"]``, named ``"<start>:folder/id"``)."""
    def valid(table: object) -> dict[str, str]:  # a hand-edited file's stray entries are left out
        if not isinstance(table, dict):
            return {}
        return {str(k): v for k, v in table.items() if isinstance(v, str) and _HEX.fullmatch(v)}

    if not isinstance(provenance, dict):
        return {}
    out = valid(provenance.get("frame_hashes"))
    init = provenance.get("init")
    if isinstance(init, dict):
        out.update({f"{init.get('model')}:{k}": v for k, v in valid(init.get("frame_hashes")).items()})
    return out


def fitted_frames(model: BoxRanker, images: "list[Tensor] | tuple[Tensor, ...]",
                  max_bits: int = SAME_IMAGE_BITS) -> list[str | None]:
    """For each of ``images`` (``[3, H, W]``), the frame ``model`` was fitted on that shows the
    same picture (``"folder/id"``, within ``max_bits`` of its :func:`frame_hash`), or None:
    where a recall measured with the model is in-sample. All None for a model whose file
    records no frame hashes (written before they were added, or a model made here)."""
    known = seen_hashes(model.meta.get("provenance", {}))
    if not known:
        return [None] * len(images)
    names, values = list(known), [int(v, 16) for v in known.values()]
    out: list[str | None] = []
    for image in images:
        h = int(frame_hash(image), 16)
        bits = [bin(h ^ v).count("1") for v in values]
        best = min(range(len(bits)), key=bits.__getitem__)
        out.append(names[best] if bits[best] <= max_bits else None)
    return out
