"""Weights files of the learned ranking: safetensors (no pickle), with what made them.

A file holds the tensors of a :class:`~reeb_torch.ranker.model.BoxRanker` (``mean``,
``scale``, ``members.<i>.<layer>.weight|bias``, ``prefilter.<layer>.weight|bias``, and with a
class head ``classifier.<layer>.weight|bias``, with a box refiner ``refiner.mean``,
``refiner.scale``, ``refiner.mlp.<layer>.weight|bias``, with a localisation-quality head
``quality.<layer>.weight|bias``) and one metadata entry, ``reeb-ranker``: a
JSON object (keys sorted, so the same model gives the same bytes) with

* ``features_version``: the :data:`~reeb_torch.ranker.features.FEATURES_VERSION` it was
  fitted on; ``feature_names``, ``hidden``, ``members``, ``prefilter``: its shape;
  ``classes``, ``class_hidden``: its class head's, where it has one (older files have none);
  ``refine_hidden``, ``refine_features``: its box refiner's widths and feature columns
  (:mod:`reeb_torch.ranker.refine`), where it has one (older files have none);
  ``quality_hidden``: its localisation-quality head's widths, where it has one (older files
  have none);
* ``provenance``: the frames it was fitted on (their folders, ids and, in files written
  since frame hashes were added, ``frame_hashes``: a :func:`frame_hash` of each image, so
  that :func:`fitted_frames` can say which of someone's frames the model saw whatever they
  are named), the command that refits it, its cross-validated recall, the fit's options and
  seed;
* ``config``: the :class:`~reeb_torch.ReebConfig` fields it was fitted with.

:func:`load_ranker` takes a shipped name (:data:`SHIPPED`, files inside the package) or a
path, and raises :class:`RankerWeightsError` (a ``ValueError``) with one line naming the
file and what is wrong: missing, a folder, unreadable, another format, fitted on other
features, metadata of the wrong type or out of bounds (:data:`LIMITS`), tensors missing,
extra or of another shape than the metadata gives, or values that are not finite (NaN, inf)
or a ``scale`` that is not positive. Everything is checked from the file's header and its
metadata before a tensor is read or a model is made, so that no file, however written, makes
the loader allocate more than the file holds.
"""

from __future__ import annotations

import json
import os
import re
import threading
from importlib import resources
from pathlib import Path

import torch
from safetensors import SafetensorError, safe_open
from safetensors.torch import save
from torch import Tensor

from ..io import replace_file
from .features import FEATURES_VERSION, cheap_count
from .model import BoxRanker
from .refine import refine_feature_names

__all__ = ["SHIPPED", "LIMITS", "RankerWeightsError", "load_ranker", "save_ranker", "resolve_ranker", "shipped_path",
           "ranker_bytes", "frame_hash", "hash_distance", "seen_hashes", "fitted_frames", "SAME_IMAGE_BITS"]

SHIPPED: dict[str, str] = {
    "kitti": "kitti.safetensors",
}
"""Shipped weights by name (``ReebConfig.ranker='kitti'``): files in ``reeb_torch/ranker/weights/``."""

FORMAT = "reeb-ranker"

LIMITS: dict[str, int] = {"members": 256, "layers": 16, "width": 65536, "features": 4096, "classes": 1024}
"""Bounds a weights file's metadata must keep: MLPs averaged (``members``), hidden layers
per MLP (``layers``), the width of each (``width``), feature columns (``features``), classes
of the class head (``classes``; 2 at least)."""

_FLOAT_DTYPES = ("F16", "BF16", "F32", "F64")

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
        what = ("the shipped weights are missing from the package" if spec in SHIPPED
                else "a folder, not a weights file" if path.is_dir() else "no such file")
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
    """The model of the file ``path``: its header and metadata checked first (:func:`_shapes`),
    then its tensors read and checked (:func:`_check_values`), then the model made."""

    where = f"ranker weights {spec!r} ({path})"
    try:
        with safe_open(str(path), framework="pt") as f:
            meta = f.metadata() or {}
            header = {k: (tuple(f.get_slice(k).get_shape()), f.get_slice(k).get_dtype()) for k in f.keys()}
            try:
                info = _meta(meta)
                expected = _shapes(info, header)
            except ValueError as e:
                raise RankerWeightsError(f"{where}: {e}") from None
            tensors = {k: f.get_tensor(k) for k in expected}
    except (SafetensorError, OSError, ValueError) as e:
        if isinstance(e, RankerWeightsError):
            raise
        reason = str(e).splitlines()[0] if str(e) else type(e).__name__
        raise RankerWeightsError(f"{where} are not a readable safetensors file: {reason}") from None
    try:
        _check_values(tensors, info["feature_names"])
        model = BoxRanker(info["feature_names"], info["hidden"], info["members"], info["prefilter"],
                          info["classes"], info["class_hidden"], info["refine_hidden"], info["quality_hidden"])
        model.load_state_dict({k: v.float() for k, v in tensors.items()}, strict=True)
    except (ValueError, RuntimeError) as e:
        reason = str(e).splitlines()[0] if str(e) else type(e).__name__
        raise RankerWeightsError(f"{where}: {reason}") from None
    model.meta = {k: info[k] for k in ("provenance", "config") if k in info}
    return model.eval().requires_grad_(False)


def _meta(meta: dict[str, str]) -> dict:
    """The ``reeb-ranker`` metadata entry, its fields checked and normalised (lists to
    tuples, absent ``classes``/``class_hidden`` filled in); ValueError naming the field."""
    if FORMAT not in meta:
        raise ValueError(f"not a reeb-torch ranker's (no {FORMAT!r} metadata)")
    try:
        info = json.loads(meta[FORMAT])
    except ValueError:
        raise ValueError(f"its {FORMAT!r} metadata is not valid JSON") from None
    if not isinstance(info, dict):
        raise ValueError(f"its {FORMAT!r} metadata is a JSON {_json_type(info)}, expected a JSON object")
    version = info.get("features_version")
    if version != FEATURES_VERSION:
        raise ValueError(f"fitted on features version {version!r}, but this reeb-torch computes version "
                         f"{FEATURES_VERSION}: refit them with `reeb fit`")
    for key in ("feature_names", "hidden", "members", "prefilter"):
        if key not in info:
            raise ValueError(f"metadata field {key!r} is missing")
    lim = LIMITS
    out = dict(info)
    out["feature_names"] = _names(info["feature_names"], "feature_names", 1, lim["features"])
    out["members"] = _int(info["members"], "members", 1, lim["members"])
    out["hidden"] = _widths(info["hidden"], "hidden", 1)
    out["prefilter"] = None if info["prefilter"] is None else _widths(info["prefilter"], "prefilter", 0)
    classes = info.get("classes")
    out["classes"] = None if classes is None else _names(classes, "classes", 2, lim["classes"])
    out["class_hidden"] = _widths(info.get("class_hidden", [32]), "class_hidden", 0)
    refine = info.get("refine_hidden")
    out["refine_hidden"] = None if refine is None else _widths(refine, "refine_hidden", 1)
    if out["refine_hidden"] is not None:
        if "refine_features" not in info:
            raise ValueError("metadata field 'refine_features' is missing (the file has a refiner)")
        names = _names(info["refine_features"], "refine_features", 1, lim["features"])
        if names != refine_feature_names():
            raise ValueError(f"its box refiner reads {len(names)} features ({_differ(names, refine_feature_names())})"
                             f" but this reeb-torch computes {len(refine_feature_names())}: refit them with `reeb fit`")
    quality = info.get("quality_hidden")
    out["quality_hidden"] = None if quality is None else _widths(quality, "quality_hidden", 0)
    for key in ("provenance", "config"):
        if key in info and not isinstance(info[key], dict):
            raise ValueError(f"its {key!r} metadata is not a JSON object (a JSON {_json_type(info[key])})")
    return out


def _int(value: object, field: str, low: int, high: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
        raise ValueError(f"metadata field {field!r} is {_shown(value)}, expected an integer from {low} to {high}")
    return value


def _widths(value: object, field: str, fewest: int) -> tuple[int, ...]:
    lim = LIMITS
    if not isinstance(value, list) or not fewest <= len(value) <= lim["layers"]:
        raise ValueError(f"metadata field {field!r} is {_shown(value)}, expected a list of {fewest} to "
                         f"{lim['layers']} layer widths (integers from 1 to {lim['width']})")
    return tuple(_int(v, field, 1, lim["width"]) for v in value)


def _names(value: object, field: str, fewest: int, most: int) -> tuple[str, ...]:
    if not isinstance(value, list) or not fewest <= len(value) <= most \
            or not all(isinstance(v, str) and v for v in value):
        raise ValueError(f"metadata field {field!r} is {_shown(value)}, expected a list of {fewest} to {most} "
                         "names (non-empty strings)")
    twice = sorted({v for v in value if value.count(v) > 1})
    if twice:
        raise ValueError(f"metadata field {field!r} names {', '.join(map(repr, twice[:3]))} more than once, "
                         "expected distinct names")
    return tuple(value)


def _json_type(value: object) -> str:
    return {dict: "object", list: "array", str: "string", bool: "boolean", int: "number",
            float: "number"}.get(type(value), "null")


def _shown(value: object) -> str:
    text = json.dumps(value)
    return text if len(text) <= 40 else text[:37] + "..."


def _shapes(info: dict, header: dict[str, tuple[tuple[int, ...], str]]) -> dict[str, tuple[int, ...]]:
    """The tensors (name: shape) a model of the metadata ``info`` has, checked against the
    file's ``header`` (name: (shape, dtype)): the same names, shapes, and floating dtypes;
    ValueError naming the first tensor that differs."""
    f = len(info["feature_names"])
    expected: dict[str, tuple[int, ...]] = {"mean": (f,), "scale": (f,)}

    def mlp(prefix: str, inputs: int, hidden: tuple[int, ...], outputs: int) -> None:
        for i, width in enumerate((*hidden, outputs)):
            expected[f"{prefix}.{2 * i}.weight"], expected[f"{prefix}.{2 * i}.bias"] = (width, inputs), (width,)
            inputs = width

    for m in range(info["members"]):
        mlp(f"members.{m}", f, info["hidden"], 1)
    if info["prefilter"] is not None:
        mlp("prefilter", cheap_count(sum(1 for n in info["feature_names"] if n.startswith("class_fit_"))),
            info["prefilter"], 1)
    if info["classes"] is not None:
        mlp("classifier", f, info["class_hidden"], len(info["classes"]))
    if info.get("quality_hidden") is not None:
        mlp("quality", f, info["quality_hidden"], 1)
    if info.get("refine_hidden") is not None:
        r = len(refine_feature_names())
        expected["refiner.mean"], expected["refiner.scale"] = (r,), (r,)
        mlp("refiner.mlp", r, info["refine_hidden"], 4)
    missing = [k for k in expected if k not in header]
    if missing:
        raise ValueError(f"tensor {missing[0]!r} is missing ({len(missing)} missing; the metadata gives "
                         f"{len(expected)} tensors, the file holds {len(header)})")
    extra = sorted(k for k in header if k not in expected)
    if extra:
        raise ValueError(f"tensor {extra[0]!r} is not one of the model's ({len(extra)} unexpected)")
    for k, shape in expected.items():
        have, dtype = header[k]
        if have != shape:
            raise ValueError(f"tensor {k!r} has shape {list(have)}, expected {list(shape)} from the metadata")
        if dtype not in _FLOAT_DTYPES:
            raise ValueError(f"tensor {k!r} is {dtype}, expected floating point ({', '.join(_FLOAT_DTYPES)})")
    return expected


def _check_values(tensors: dict[str, Tensor], feature_names: tuple[str, ...]) -> None:
    """ValueError naming the first tensor with a NaN or infinite value, or a ``scale`` that
    is not positive (features are divided by it)."""
    for k, v in tensors.items():
        bad = ~torch.isfinite(v.float())
        if bad.any():
            at = int(bad.flatten().nonzero()[0])
            n = int(bad.sum())
            raise ValueError(f"tensor {k!r} holds {n} value{'s' if n > 1 else ''} that {'are' if n > 1 else 'is'} "
                             f"not finite (element {at} is {float(v.flatten()[at])}), expected finite numbers")
    for key, names in (("scale", feature_names), ("refiner.scale", refine_feature_names())):
        if key not in tensors:
            continue
        low = tensors[key].float() <= 0
        if low.any():
            at = int(low.nonzero()[0])
            raise ValueError(f"tensor {key!r} is {float(tensors[key][at])} for feature {names[at]!r}, "
                             "expected positive values (each feature is divided by its scale)")


def ranker_bytes(model: BoxRanker, provenance: dict | None = None, config: dict | None = None) -> bytes:
    """The safetensors bytes of ``model`` (the same model gives the same bytes), with
    ``provenance`` and ``config`` (JSON-able dicts) as metadata (:data:`BoxRanker.meta` once
    loaded).

    Raises:
        RankerWeightsError: a tensor holds NaN or infinite values (a fit that diverged), or
            ``scale`` is not positive: such weights are never written.
    """

    info = {"features_version": FEATURES_VERSION, "feature_names": list(model.feature_names),
            "hidden": list(model.hidden), "members": len(model.members),
            "prefilter": None if model.prefilter_hidden is None else list(model.prefilter_hidden)}
    if model.classes is not None:  # files without a class head keep the earlier bytes
        info["classes"], info["class_hidden"] = list(model.classes), list(model.class_hidden)
    if model.refiner is not None:  # files without a refiner keep the earlier bytes
        info["refine_hidden"] = list(model.refiner.hidden)
        info["refine_features"] = list(model.refiner.feature_names)
    if model.quality_hidden is not None:  # files without a quality head keep the earlier bytes
        info["quality_hidden"] = list(model.quality_hidden)
    if provenance is not None:
        info["provenance"] = provenance
    if config is not None:
        info["config"] = config
    meta = {FORMAT: json.dumps(info, sort_keys=True, default=list)}  # one entry: its place is fixed
    tensors = {k: v.detach().to("cpu", torch.float32).contiguous() for k, v in model.state_dict().items()}
    try:
        _check_values(tensors, model.feature_names)
    except ValueError as e:
        raise RankerWeightsError(f"these ranker weights are not written: {e}") from None
    return save(tensors, metadata=meta)


def save_ranker(model: BoxRanker, path: str | os.PathLike, provenance: dict | None = None,
                config: dict | None = None) -> Path:
    """Write ``model`` to ``path`` (:func:`ranker_bytes`): through a temporary file beside it,
    flushed to disk and renamed into place, so that a failed write (a full disk) leaves the
    file that was there; the file gets the umask's permissions.

    Raises:
        RankerWeightsError: weights that are not finite (:func:`ranker_bytes`); nothing is written.
        OSError: the file cannot be written; ``path`` is left as it was.
    """
    return replace_file(path, ranker_bytes(model, provenance, config))


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
