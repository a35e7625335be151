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
                   "ranker_sha256": "..." or null, "ranker_embedded": true (only where it is)},
     "provenance": {"frames": ["kitti/000001", ...], "frame_hashes": {"kitti/000001": ...},
                    "command": "reeb detector fit ...", "seed": 0, "epochs": 12, ...}}

Proposals ranked with a user's weights file (``reeb fit``'s, not a shipped name) carry that
file inside (``"ranker_embedded": true``): its tensors under ``proposals_ranker.`` (their
dtypes kept) and its metadata entries in the JSON object's ``"proposals_ranker"`` (the
file keeps one metadata entry: safetensors writes several in no fixed order), so that
:func:`ranker_file_bytes` gives back the very bytes of the file, whose SHA-256 is
``ranker_sha256`` (safetensors lays a file out the same way whatever the order of its
tensors). A detector of the shipped ranking, or of none, holds no such entries.

:func:`read_detector_file` refuses a file it cannot use with :class:`DetectorFileError` (a
``ValueError``) and one line naming the file and what is wrong: missing, a folder or a
special file, not safetensors, not a detector's, another version, a class named twice,
tensors missing, extra, of the wrong shape or not finite, settings of the wrong type or out
of range (:meth:`~reeb_torch.detection.DetectorSettings.from_dict`), or made on other
backbone weights.
"""

from __future__ import annotations

import json
import os
import stat
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch
from safetensors import SafetensorError, safe_open
from safetensors.torch import load, save
from torch import Tensor

from ..io import replace_file

__all__ = ["FORMAT", "VERSION", "RANKER_PREFIX", "DetectorFileError", "write_detector_file", "read_detector_file",
           "trained_keys", "check_tensors", "ranker_parts", "ranker_file_bytes", "not_a_file"]

FORMAT = "reeb-detector"
VERSION = 1
RANKER_PREFIX = "proposals_ranker."
"""The prefix of an embedded ranker's tensors in a detector file."""
_RANKER_META = "proposals_ranker"
_TRAINED = ("backbone.neck.", "roi_heads.")


class DetectorFileError(ValueError):
    """A detector file that cannot be used: missing, damaged, or made for something else."""


def trained_keys(state: Mapping[str, Tensor]) -> dict[str, Tensor]:
    """The entries of a detector's ``state_dict`` that training changes (what a file holds)."""
    return {k: v for k, v in state.items() if k.startswith(_TRAINED)}


def ranker_parts(data: bytes) -> tuple[dict[str, Tensor], dict[str, str]]:
    """The tensors and metadata entries of the safetensors bytes ``data`` (a ranker weights
    file); :func:`ranker_file_bytes` of them gives ``data`` back for a file laid out as
    safetensors writes it.

    Raises:
        ValueError: ``data`` is not safetensors.
    """

    try:
        tensors = load(data)
        size = int.from_bytes(data[:8], "little")
        metadata = json.loads(data[8: 8 + size]).get("__metadata__") or {}
    except (SafetensorError, ValueError, AttributeError, RecursionError) as e:
        raise ValueError(f"not a safetensors file ({_first_line(e)})") from None
    return tensors, dict(metadata)


def ranker_file_bytes(tensors: Mapping[str, Tensor], metadata: Mapping[str, str]) -> bytes:
    """The safetensors file of ``tensors`` (dtypes kept) and ``metadata``: a ranker weights
    file's bytes from its :func:`ranker_parts`."""

    return save({k: v.detach().cpu().contiguous() for k, v in tensors.items()}, metadata=dict(metadata))


def write_detector_file(path: str | os.PathLike, tensors: Mapping[str, Tensor], meta: dict[str, Any],
                        ranker: bytes | None = None) -> Path:
    """Write ``tensors`` (CPU; floating ones as float32, int8 ones as they are) and ``meta``
    (JSON-able) to ``path`` atomically (a
    temporary file beside it, then renamed); the same inputs give the same bytes. ``ranker``:
    the bytes of a ranker weights file to embed (:data:`RANKER_PREFIX`), or None."""

    info = {"version": VERSION, **meta}
    out = {k: v.detach().to("cpu", v.dtype if v.dtype == torch.int8 else torch.float32).contiguous()
           for k, v in sorted(tensors.items())}
    if ranker is not None:
        r_tensors, info[_RANKER_META] = ranker_parts(ranker)
        out.update({RANKER_PREFIX + k: v.contiguous() for k, v in r_tensors.items()})
    return replace_file(path, save(out, metadata={FORMAT: json.dumps(info, sort_keys=True, default=list)}))


def not_a_file(path: Path) -> str | None:
    """Why ``path`` is no file to read a detector (or any weights) from, or None: missing, a
    folder, or a special file (a named pipe, a device, a socket), named without opening it
    (opening a named pipe waits for a writer)."""

    try:
        mode = path.stat().st_mode
    except FileNotFoundError:
        return "no such file"
    except OSError as e:
        return f"cannot read it ({e.strerror or e})"
    if stat.S_ISREG(mode):
        return None
    kinds = ((stat.S_ISDIR, "a folder"), (stat.S_ISFIFO, "a named pipe (FIFO)"),
             (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket"))
    kind = next((word for test, word in kinds if test(mode)), "a special file")
    return f"is {kind}, not a file"


def _first_line(e: BaseException) -> str:
    return str(e).splitlines()[0] if str(e) else type(e).__name__


def read_detector_file(path: str | os.PathLike) -> tuple[dict[str, Tensor], dict[str, Any], bytes | None]:
    """``(tensors, meta, ranker)`` of a detector file, checked for what the file alone can tell:
    the network's tensors, the ``reeb-detector`` metadata, and the bytes of the ranker weights
    file it embeds (:func:`ranker_file_bytes`; None where it embeds none).

    Raises:
        DetectorFileError: missing, a folder or a special file (a FIFO, a device), not a
            readable safetensors file, no ``reeb-detector`` metadata or not a JSON object,
            another version, no classes or a class named twice, non-finite tensors.
    """

    p = Path(os.path.expanduser(str(path)))
    what = not_a_file(p)
    if what:
        raise DetectorFileError(f"detector {p}: {what}")
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
    except RecursionError:  # brackets nested past any real file's
        raise DetectorFileError(f"detector {p}: its {FORMAT!r} metadata is nested too deep to read") from None
    if not isinstance(meta, dict):
        raise DetectorFileError(f"detector {p}: its {FORMAT!r} metadata is not a JSON object")
    if meta.get("version") != VERSION:
        raise DetectorFileError(f"detector {p}: file version {meta.get('version')!r}, this reeb-torch reads "
                                f"version {VERSION}")
    classes = meta.get("classes")
    if not (isinstance(classes, list) and classes and all(isinstance(c, str) and c.strip() for c in classes)):
        raise DetectorFileError(f"detector {p}: its metadata names no classes (a list of names)")
    twice = sorted({c for c in classes if classes.count(c) > 1})
    if twice:
        raise DetectorFileError(f"detector {p}: its metadata names the class {twice[0]!r} twice (classes "
                                f"{', '.join(classes)})")
    for key in ("settings", "backbone", "proposals"):
        if not isinstance(meta.get(key), dict):
            raise DetectorFileError(f"detector {p}: its metadata has no {key!r} object")
    bad = [k for k, v in tensors.items() if v.is_floating_point() and not bool(torch.isfinite(v).all())]
    if bad:
        raise DetectorFileError(f"detector {p}: tensor {bad[0]!r} holds non-finite values (NaN or inf)"
                                + (f", and {len(bad) - 1} more" if len(bad) > 1 else ""))
    n = len(RANKER_PREFIX)
    r_tensors = {k[n:]: tensors.pop(k) for k in [k for k in tensors if k.startswith(RANKER_PREFIX)]}
    r_meta = meta.pop(_RANKER_META, None)
    if r_meta is not None and not (isinstance(r_meta, dict) and all(isinstance(v, str) for v in r_meta.values())):
        raise DetectorFileError(f"detector {p}: its {_RANKER_META!r} metadata is not a JSON object of strings")
    return tensors, meta, (ranker_file_bytes(r_tensors, r_meta or {}) if r_tensors or r_meta else None)


def check_tensors(path: str | os.PathLike, tensors: Mapping[str, Tensor], expected: Mapping[str, Tensor]) -> None:
    """Raise :class:`DetectorFileError` unless ``tensors`` has exactly the keys and shapes of
    ``expected``, int8 where it is (the trained entries of the detector the metadata describes)."""
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
        if (tensors[k].dtype == torch.int8) != (v.dtype == torch.int8):
            raise DetectorFileError(f"detector {path}: tensor {k!r} is {tensors[k].dtype}, the network its "
                                    f"metadata describes needs {v.dtype}")
