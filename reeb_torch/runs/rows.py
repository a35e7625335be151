"""Result rows: one row per image, as ``reeb propose`` and the Ray engine write them.

:func:`result_row` formats a processed image (boxes rounded to pixels, scores to 6
significant digits), :func:`error_row` an image that failed (its ``status`` names the file
and the reason, :func:`file_error`). Paths are written as text UTF-8 can hold
(:func:`text_path`), and ``--resume`` matches rows on :func:`row_key`.

Row schema (one row per image, JSON Lines or Parquet; :data:`FORMAT_VERSION` 2, which
added ``labels``; rows of version 1 read the same, without it):

==============  ==========================  =============================================
field           type                        meaning
==============  ==========================  =============================================
format_version  int                         :data:`FORMAT_VERSION` of this schema
image           str                         the path as given (relative paths stay relative)
resolved        str                         absolute path, symlinks resolved
                                            (``os.path.realpath``); ``--resume`` matches on it
                                            (in both, a byte of a file name that is not
                                            UTF-8 is written ``\\xNN``: :func:`text_path`)
width           int or null                 image width in pixels as viewed (EXIF orientation
                                            applied); null if the file could not be decoded
height          int or null                 image height in pixels, likewise
boxes           list of [x1, y1, x2, y2]    proposals in image pixels, ranked best first
scores          list of float               one score per box, descending
labels          list of str or null         the class each box looks like (the learned
                                            ranking's class hint, one of
                                            ``ProposalGenerator.classes``), one per box;
                                            null where the settings give none
                                            (``ranker='none'``, or a model without a
                                            class head) and in an error row
status          str                         ``"ok"`` or ``"error: <file>: <reason>"``
config          str                         :meth:`ReebConfig.fingerprint` of the settings used
==============  ==========================  =============================================
"""

from __future__ import annotations

import os
from typing import Sequence

import numpy as np
import torch

__all__ = [
    "FORMAT_VERSION",
    "resolved_path",
    "text_path",
    "row_key",
    "one_line",
    "file_error",
    "round_like_python",
    "significant_like_python",
    "result_row",
    "hint_names",
    "error_row",
]

#: Version of the row schema (see the module docstring); written in every row.
FORMAT_VERSION = 2


def resolved_path(path: str | os.PathLike) -> str:
    """The absolute path of ``path`` with symbolic links resolved (what rows are matched on)."""
    return os.path.realpath(path)


def text_path(path: str | os.PathLike) -> str:
    """``path`` as text that UTF-8 can hold, as rows and messages write it.

    A file name that is not valid UTF-8 (an old Samba or FAT share, an archive from another
    locale) reaches Python with its undecodable bytes as surrogates (``os.fsdecode``); here
    each such byte is written as the four characters ``\\xNN`` (``x\\xff.png``), so JSON
    Lines and Parquet rows can hold it and ``--resume`` matches it (rows are matched on
    ``text_path(resolved_path(file))``). Valid names come back unchanged.
    """
    s = os.fsdecode(os.fspath(path))
    try:
        s.encode("utf-8")
        return s
    except UnicodeEncodeError:
        try:
            raw = s.encode("utf-8", "surrogateescape")
        except UnicodeEncodeError:  # a lone surrogate that is no escaped byte
            return s.encode("utf-8", "backslashreplace").decode("utf-8")
        return raw.decode("utf-8", "backslashreplace")


def row_key(path: str | os.PathLike) -> str:
    """What a row of ``path`` is matched on for ``--resume``: ``text_path(resolved_path(path))``."""
    return text_path(resolved_path(path))


def one_line(msg: object) -> str:
    """``msg`` as one line: its whitespace runs (newlines included) become single spaces."""
    return " ".join(str(msg).split())


def file_error(path: str | os.PathLike, exc: BaseException | str) -> str:
    """A one-line message ``"<path>: <reason>"`` (the path is not repeated if present)."""
    msg = text_path(one_line(exc if isinstance(exc, str) else (str(exc) or type(exc).__name__)))
    path = text_path(path)
    if msg.startswith(path):
        return msg
    return f"{path}: {msg}"


def round_like_python(values: np.ndarray, decimals: int) -> np.ndarray:
    """``[round(v, decimals) for v in values]`` (Python's correctly rounded ``round``) for a
    float64 array, vectorised: ``N = rint(v·10^d)`` is the right integer wherever ``v·10^d``
    is not within 1e-6 of a half-integer (its rounding error is far smaller), and the IEEE
    quotient ``N / 10^d`` is the double nearest to the decimal, as ``round`` returns. The
    few values near a tie, huge or not finite go through ``round`` itself. Same numbers
    bit for bit (tested against ``round``)."""
    v = np.asarray(values, np.float64)
    if not 0 <= decimals <= 15:
        return np.array([round(float(x), decimals) for x in v.ravel()]).reshape(v.shape)
    scale = 10.0 ** decimals
    with np.errstate(invalid="ignore", over="ignore"):  # huge values overflow: taken by round below
        t = v * scale
        out = np.rint(t) / scale
        risky = ~(np.abs(t) < 1e9) | (np.abs(t - np.floor(t) - 0.5) < 1e-6)
    if risky.any():
        out[risky] = [round(float(x), decimals) for x in v[risky]]
    return out


def significant_like_python(values: np.ndarray, digits: int = 6) -> np.ndarray:
    """``[float(f"{v:.{digits}g}") for v in values]`` for a float64 array, vectorised the
    same way as :func:`round_like_python` (the power of ten from ``log10``; values whose
    scaled mantissa is near a tie or whose digit count comes out wrong, zeros, huge, tiny
    and non-finite values go through the format itself). Same numbers bit for bit."""
    v = np.asarray(values, np.float64)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        e = np.floor(np.log10(np.abs(v)))
        k = (digits - 1) - e
        ok = np.isfinite(k) & (np.abs(k) <= 22)
        k = np.where(ok, k, 0.0)
        p = 10.0 ** np.abs(k)  # exact for |k| <= 22
        t = np.where(k >= 0, v * p, v / p)
        n = np.rint(t)
        out = np.where(k >= 0, n / p, n * p)
        lo, hi = 10.0 ** (digits - 1), 10.0 ** digits
        risky = (~ok | ~(np.abs(n) >= lo) | ~(np.abs(n) < hi) | (np.abs(t - np.floor(t) - 0.5) < 1e-6)
                 | (k < 0))  # v / p is rounded: only scaled-up values are taken as they come
    if risky.any():
        out[risky] = [float(f"{float(x):.{digits}g}") for x in v[risky]]
    return out


def result_row(path: str, width: int, height: int, boxes: torch.Tensor, scores: torch.Tensor,
               config: str, decimals: int = 2, labels: Sequence[str] | None = None) -> dict:
    """The output row of one processed image (boxes rounded to ``decimals`` pixels, scores
    to 6 significant digits, as Python's ``round`` and ``.6g`` format give them; ``labels``:
    the class hint of each box, or None for none); an :func:`error_row` where a box or a
    score is not finite. Raises ValueError when ``labels`` is not one per box."""
    if labels is not None and len(labels) != len(boxes):
        raise ValueError(f"result_row: {len(labels)} labels for {len(boxes)} boxes (one per box)")
    b = boxes.detach().to("cpu", torch.float64).numpy()
    s = scores.detach().to("cpu", torch.float64).numpy()
    bad = int((~np.isfinite(s)).sum() + (~np.isfinite(b)).reshape(-1, 4).any(axis=1).sum())
    if bad:  # never a bare NaN in a row (JSON has none): the image is an error
        return error_row(path, f"{text_path(path)}: {bad} boxes or scores are not finite numbers (NaN or "
                         "infinity; the ranker's weights may be damaged)", config, (width, height))
    return {
        "format_version": FORMAT_VERSION,
        "image": text_path(path),
        "resolved": row_key(path),
        "width": int(width),
        "height": int(height),
        "boxes": round_like_python(b, decimals).reshape(-1, 4).tolist(),
        "scores": significant_like_python(s).tolist(),
        "labels": None if labels is None else [str(x) for x in labels],
        "status": "ok",
        "config": config,
    }


def hint_names(classes: Sequence[str] | None, labels: torch.Tensor | None) -> list[str] | None:
    """The class hint of each box as a name: ``labels`` (``int64 [N]``, a generator output's
    ``"labels"``) indexes ``classes`` (:attr:`ProposalGenerator.classes
    <reeb_torch.ProposalGenerator.classes>`); None where the settings give none."""
    if classes is None or labels is None:
        return None
    return [classes[i] for i in labels.tolist()]


def error_row(path: str, message: str, config: str, size: tuple[int, int] | None = None) -> dict:
    """The output row of an image that failed; ``message`` names the file."""
    w, h = (int(size[0]), int(size[1])) if size is not None else (None, None)
    return {"format_version": FORMAT_VERSION, "image": text_path(path), "resolved": row_key(path),
            "width": w, "height": h, "boxes": [], "scores": [], "labels": None,
            "status": f"error: {text_path(one_line(message))}", "config": config}
