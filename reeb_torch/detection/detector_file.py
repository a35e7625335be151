"""The file of a trained :class:`~reeb_torch.detection.ReebDetector`: safetensors, no pickle.

A file holds the trained tensors (the neck, ``backbone.neck.*``, and the box head and
predictor, ``roi_heads.*``; the frozen EfficientNet-Lite0 is not stored: it is the ``detect``
extra's file, named by its SHA-256) and one metadata entry, ``reeb-detector``, a JSON object
(keys sorted, so the same detector gives the same bytes)::

    {"version": 1,
     "classes": ["Car", "Pedestrian", "Cyclist"],        # labels 1..C; 0 is the background
     "settings": {"min_size": 576, "max_size": 2048, "neck_channels": 128, ...},
     "backbone": {"name": "efficientnet-lite0", "sha256": "..."},
     "proposals": {"spec": "default", "config": {ReebConfig fields}, "fingerprint": "...",
                   "ranker_sha256": "..." or null},
     "provenance": {"frames": ["kitti/000001", ...], "frame_hashes": {"kitti/000001": ...},
                    "command": "reeb detector fit ...", "seed": 0, "epochs": 12, ...}}

:func:`read_detector_file` refuses a file it cannot use with :class:`DetectorFileError` (a
``ValueError``) and one line naming the file and what is wrong: missing, not safetensors,
not a detector's, another version, tensors missing, extra, of the wrong shape or not
finite, or made on other backbone weights.
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from ..io import replace_file

__all__ = ["FORMAT", "VERSION", "DetectorFileError", "write_detector_file", "read_detector_file", "trained_keys",
           "check_tensors"]

FORMAT = "reeb-detector"
VERSION = 1
_TRAINED = ("backbone.neck.", "roi_heads.")


class DetectorFileError(ValueError):
    """A detector file that cannot be used: missing, damaged, or made for something else."""


def trained_keys(state: Mapping[str, Tensor]) -> dict[str, Tensor]:
    """The entries of a detector's ``state_dict`` that training changes (what a file holds)."""
    return {k: v for k, v in state.items() if k.startswith(_TRAINED)}


def write_detector_file(path: str | os.PathLike, tensors: Mapping[str, Tensor], meta: dict[str, Any]) -> Path:
    """Write ``tensors`` (float32, CPU) and ``meta`` (JSON-able) to ``path`` atomically (a
    temporary file beside it, then renamed); the same inputs give the same bytes."""
    from safetensors.torch import save

    info = {"version": VERSION, **meta}
    data = save({k: v.detach().to("cpu", torch.float32).contiguous() for k, v in sorted(tensors.items())},
                metadata={FORMAT: json.dumps(info, sort_keys=True, default=list)})
    return replace_file(path, data)


def _first_line(e: BaseException) -> str:
    return str(e).splitlines()[0] if str(e) else type(e).__name__


def read_detector_file(path: str | os.PathLike) -> tuple[dict[str, Tensor], dict[str, Any]]:
    """``(tensors, meta)`` of a detector file, checked for what the file alone can tell.

    Raises:
        DetectorFileError: missing, not a readable safetensors file, no ``reeb-detector``
            metadata or not a JSON object, another version, no classes, non-finite tensors.
    """
    from safetensors import SafetensorError, safe_open

    p = Path(os.path.expanduser(str(path)))
    if not p.is_file():
        raise DetectorFileError(f"detector {p}: no such file")
    try:
        with safe_open(str(p), framework="pt") as f:
            raw = (f.metadata() or {}).get(FORMAT)
            tensors = {k: f.get_tensor(k) for k in f.keys()}
    except (SafetensorError, OSError, ValueError, RuntimeError) as e:
        raise DetectorFileError(f"detector {p}: not a readable safetensors file ({_first_line(e)})") from None
    if raw is None:
        raise DetectorFileError(f"detector {p}: not a reeb-torch detector (no {FORMAT!r} metadata)")
    try:
        meta = json.loads(raw)
    except ValueError as e:
        raise DetectorFileError(f"detector {p}: its {FORMAT!r} metadata is not JSON ({_first_line(e)})") from None
    if not isinstance(meta, dict):
        raise DetectorFileError(f"detector {p}: its {FORMAT!r} metadata is not a JSON object")
    if meta.get("version") != VERSION:
        raise DetectorFileError(f"detector {p}: file version {meta.get('version')!r}, this reeb-torch reads "
                                f"version {VERSION}")
    classes = meta.get("classes")
    if not (isinstance(classes, list) and classes and all(isinstance(c, str) and c for c in classes)):
        raise DetectorFileError(f"detector {p}: its metadata names no classes (a list of names)")
    for key in ("settings", "backbone", "proposals"):
        if not isinstance(meta.get(key), dict):
            raise DetectorFileError(f"detector {p}: its metadata has no {key!r} object")
    bad = [k for k, v in tensors.items() if v.is_floating_point() and not bool(torch.isfinite(v).all())]
    if bad:
        raise DetectorFileError(f"detector {p}: tensor {bad[0]!r} holds non-finite values (NaN or inf)"
                                + (f", and {len(bad) - 1} more" if len(bad) > 1 else ""))
    return tensors, meta


def check_tensors(path: str | os.PathLike, tensors: Mapping[str, Tensor], expected: Mapping[str, Tensor]) -> None:
    """Raise :class:`DetectorFileError` unless ``tensors`` has exactly the keys and shapes of
    ``expected`` (the trained entries of the detector the metadata describes)."""
    missing = sorted(set(expected) - set(tensors))
    extra = sorted(set(tensors) - set(expected))
    if missing or extra:
        what = (f"{len(missing)} tensors missing ({missing[0]}, ...)" if missing else
                f"{len(extra)} unexpected tensors ({extra[0]}, ...)")
        raise DetectorFileError(f"detector {path}: {what}: not the network its metadata describes")
    for k, v in expected.items():
        if tuple(tensors[k].shape) != tuple(v.shape):
            raise DetectorFileError(f"detector {path}: tensor {k!r} has shape {tuple(tensors[k].shape)}, "
                                    f"the network its metadata describes needs {tuple(v.shape)}")
