"""Hand-off to detector frameworks: result rows to detectron2's precomputed proposals.

detectron2 trains and tests Fast R-CNN on precomputed proposals with
``MODEL.LOAD_PROPOSALS: True``, ``MODEL.PROPOSAL_GENERATOR.NAME: "PrecomputedProposals"`` and
``DATASETS.PROPOSAL_FILES_TRAIN/TEST`` naming a pickle of a dict (detectron2's
``data/detection_utils.py``, ``load_proposals_into_dataset``):

=================  ============================================================
key                value
=================  ============================================================
ids                list of image ids (``str(id)`` is matched to ``image_id``)
boxes              list of ``float32`` arrays ``(N, 4)``: ``x1, y1, x2, y2`` in
                   image pixels (``XYXY_ABS``), ranked best first
objectness_logits  list of ``float32`` arrays ``(N,)``, one per image
bbox_mode          ``0`` (``detectron2.structures.BoxMode.XYXY_ABS``)
=================  ============================================================

REEB scores are not logits, but detectron2 only ranks by them (it keeps the top
``POST_NMS_TOPK_TRAIN/TEST`` after sorting), and the order is what the scores carry.

The input is what ``reeb propose`` writes: a JSON Lines or Parquet file, or the folder of
Parquet files of ``reeb propose --engine ray``. detectron2 is not needed to write the file.
"""

from __future__ import annotations

import csv
import json
import os
import pickle
import typing
from pathlib import Path
from typing import Iterable, Mapping

import numpy as np

from .output_files import OutputError, hidden_stem, read_result_dir, read_results

__all__ = ["XYXY_ABS", "ExportError", "read_rows", "read_id_map", "image_ids", "check_row",
           "detectron2_proposals", "write_detectron2"]

#: ``detectron2.structures.BoxMode.XYXY_ABS`` (an IntEnum; its value is 0).
XYXY_ABS = 0


class ExportError(ValueError):
    """The results or the id mapping cannot be exported (the message names the file)."""


def read_rows(results: str | os.PathLike) -> list[dict]:
    """The rows of a results file (``.jsonl``/``.parquet``) or a folder of Parquet files."""

    p = Path(results)
    if p.is_dir():
        try:
            rows = read_result_dir(p)
        except OSError as e:
            raise ExportError(str(e)) from e
        if not rows:
            raise ExportError(f"{p}: no Parquet result files in this folder")
        return rows
    if not p.exists():
        raise ExportError(f"{p}: no such file or folder")
    try:
        rows, problems = read_results(p)
    except OutputError as e:
        raise ExportError(str(e)) from e
    if problems:
        first = problems[0].removesuffix("; skipped")  # the reader skips them; the export takes none
        raise ExportError(f"{p}: not a clean results file ({len(problems)} bad line{'s' if len(problems) > 1 else ''}; "
                          f"first {first}): nothing exported")
    return rows


def read_id_map(path: str | os.PathLike) -> dict[str, object]:
    """A mapping from image (path, file name or stem) to id: a JSON object, or a CSV/TSV
    file of two columns ``image,id`` (a header row is allowed). Integer ids stay integers."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as e:
        raise ExportError(f"{p}: cannot read the id mapping ({e.strerror or e})") from e
    if p.suffix.lower() == ".json":
        try:
            data = json.loads(text)
        except json.JSONDecodeError as e:
            raise ExportError(f"{p}: not valid JSON ({e})") from e
        if not isinstance(data, dict):
            raise ExportError(f"{p}: expected a JSON object {{image: id}}")
        return {str(k): v for k, v in data.items()}
    delim = "\t" if p.suffix.lower() == ".tsv" else ","
    out: dict[str, object] = {}
    for n, rec in enumerate(csv.reader(text.splitlines(), delimiter=delim), 1):
        if not rec or not "".join(rec).strip():
            continue
        if len(rec) != 2:
            raise ExportError(f"{p}:{n}: expected two columns image{delim}id, got {len(rec)}")
        key, value = rec[0].strip(), rec[1].strip()
        if n == 1 and key.lower() in ("image", "path", "file", "file_name") and not value.isdigit():
            continue  # header
        out[key] = int(value) if value.lstrip("-").isdigit() else value
    return out


def image_ids(images: Iterable[str], id_map: Mapping[str, object] | None = None,
              id_type: str = "str") -> list:
    """One id per image path: the mapping's entry for the path as written, its absolute
    path, its file name or its stem (tried in that order), else the file stem.

    ``id_type`` ``"int"`` turns stems such as ``000123`` into ``123`` (for datasets whose
    ``image_id`` is a number). Raises :class:`ExportError` when an image has no entry in
    ``id_map`` or two images get the same id.
    """
    if id_type not in ("str", "int"):
        raise ValueError(f"id_type must be 'str' or 'int', got {id_type!r}")
    ids: list = []
    seen: dict[str, str] = {}
    for image in images:
        p = Path(image)
        if id_map is not None:
            for key in (str(image), os.path.abspath(image), p.name, p.stem):
                if key in id_map:
                    id_ = id_map[key]
                    break
            else:
                raise ExportError(f"{image}: not in the id mapping (looked up the path, the "
                                  f"absolute path, {p.name!r} and {p.stem!r})")
        else:
            id_ = p.stem
        if id_type == "int":
            try:
                id_ = int(typing.cast("typing.SupportsInt | str", id_))  # a mapping's value, or a stem
            except (TypeError, ValueError):
                raise ExportError(f"{image}: id {id_!r} is not an integer (--id-type int)") from None
        if str(id_) in seen:
            raise ExportError(f"{image} and {seen[str(id_)]} both get id {id_!r}; give a "
                              "mapping file (--ids) with one id per image")
        seen[str(id_)] = str(image)
        ids.append(id_)
    return ids


def _numbers(value) -> bool:
    return all(isinstance(v, (int, float)) and not isinstance(v, bool) and np.isfinite(v) for v in value)


def check_row(row: object, n: int) -> None:
    """Raise :class:`ExportError` naming row ``n`` (1-based) and its image unless ``row``
    follows the row schema (:mod:`reeb_torch.runs.rows`): a dict with ``image`` (str) and
    ``status`` (str); with status ``ok`` also ``boxes``, a list of ``[x1, y1, x2, y2]``
    (4 finite numbers each), and ``scores``, one finite number per box."""
    if not isinstance(row, dict) or not isinstance(row.get("image"), str):
        raise ExportError(f"row {n}: not a result row (no 'image' path)")
    where = f"row {n} ({row['image']})"
    status = row.get("status")
    if not isinstance(status, str):
        raise ExportError(f"{where}: 'status' must be 'ok' or 'error: ...', got {status!r}")
    if status != "ok":
        return
    boxes, scores = row.get("boxes"), row.get("scores")
    if not isinstance(boxes, (list, tuple, np.ndarray)):
        raise ExportError(f"{where}: status ok but 'boxes' is {type(boxes).__name__ if boxes is not None else 'null'}"
                          "; expected a list of [x1, y1, x2, y2]")
    if not isinstance(scores, (list, tuple, np.ndarray)):
        raise ExportError(f"{where}: status ok but 'scores' is {type(scores).__name__ if scores is not None else 'null'}"
                          "; expected one number per box")
    for i, b in enumerate(boxes):
        if not isinstance(b, (list, tuple, np.ndarray)) or len(b) != 4 or not _numbers(b):
            raise ExportError(f"{where}: box {i} is {list(b) if isinstance(b, (list, tuple, np.ndarray)) else b!r}; "
                              "expected 4 finite numbers [x1, y1, x2, y2]")
    if len(scores) != len(boxes) or not _numbers(scores):
        raise ExportError(f"{where}: {len(boxes)} boxes but {len(scores)} scores (one finite number per box)")


def detectron2_proposals(rows: Iterable[dict], id_map: Mapping[str, object] | None = None,
                         id_type: str = "str") -> tuple[dict, list[str]]:
    """detectron2's precomputed-proposals dict from result rows, and the failed images.

    Each row is checked against the row schema first (:func:`check_row`: an
    :class:`ExportError` names the bad row). Rows whose status is not ``"ok"`` are left out
    (returned as the second value). When an
    image has several rows (a resumed run), its ``ok`` row is used. Boxes are ``float32``
    ``(N, 4)`` ``XYXY_ABS`` arrays in the rows' order (best first); ``objectness_logits``
    are the scores as ``float32`` ``(N,)``.
    """
    by_image: dict[str, dict] = {}
    failed: dict[str, str] = {}
    for n, r in enumerate(rows, 1):
        check_row(r, n)
        image = str(r["image"])
        if r.get("status") == "ok":
            by_image[image] = r
            failed.pop(image, None)
        elif image not in by_image:
            failed[image] = str(r.get("status"))
    images = list(by_image)
    ids = image_ids(images, id_map, id_type)
    boxes, logits = [], []
    for image in images:
        r = by_image[image]
        boxes.append(np.asarray(r["boxes"], dtype=np.float32).reshape(-1, 4))
        logits.append(np.asarray(r["scores"], dtype=np.float32).reshape(-1))
    return ({"ids": ids, "boxes": boxes, "objectness_logits": logits, "bbox_mode": XYXY_ABS},
            [f"{k}: {v}" for k, v in failed.items()])


def write_detectron2(proposals: dict, out: str | os.PathLike) -> Path:
    """Pickle ``proposals`` to ``out`` (through a temporary file renamed into place; a
    symbolic link at ``out`` stays a link, the file it points to is written)."""

    out = Path(os.path.realpath(out) if os.path.islink(out) else out)  # a link stays a link: its target is written
    tmp = out.with_name(f"{hidden_stem(out)}.tmp")
    try:
        with open(tmp, "wb") as f:
            pickle.dump(proposals, f, protocol=pickle.HIGHEST_PROTOCOL)
        os.replace(tmp, out)
    except OSError as e:
        tmp.unlink(missing_ok=True)
        raise ExportError(f"{out}: cannot write ({e.strerror or e})") from e
    return out
