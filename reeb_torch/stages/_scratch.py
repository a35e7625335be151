"""Scratch buffers that one ``ProposalGenerator.forward`` call reuses from the last.

A batch's large per-image arrays (the integral images and the enclosed-sum tables, several
MB per KITTI image; the score and candidate arrays; the edge maps) are needed only until the
batch's boxes are chosen. Freshly allocated each batch, they cost the machine a page fault
per 4 KiB on first touch, more on the helper thread, whose half of each array lies past the
memory the allocator had mapped (measured in docs/results.md, "What makes the CPU path
fast"). Inside :func:`reusing` (the generator's ``forward`` only), :func:`empty`
hands out the same memory batch after batch, per thread and per call site (``key``).

Nothing returned to a caller may be such a buffer: the generator's results are copies
(indexed), and code that keeps the intermediate maps (``inspect``, ``reeb tune``'s cache
of the front end) runs outside :func:`reusing`, where :func:`empty` is ``np.empty``.
The buffers of a thread stay allocated (at the size of the largest batch seen) until
:func:`release` or the thread's end.
"""

from __future__ import annotations

import math
import threading
from contextlib import contextmanager
from typing import Iterator

import numpy as np

__all__ = ["empty", "reusing", "release"]

_local = threading.local()


@contextmanager
def reusing() -> Iterator[None]:
    """Within this block (of this thread), :func:`empty` reuses its buffers; a nested
    block (a call made while another is in progress, such as the warm-up of a
    generator's first call) gets fresh arrays, so it cannot overwrite the outer one's."""
    depth = getattr(_local, "depth", 0)
    _local.depth = depth + 1
    try:
        yield
    finally:
        _local.depth = depth


def empty(key: str, shape: tuple[int, ...], dtype: type | np.dtype = np.float64) -> np.ndarray:
    """An uninitialised C-contiguous array of ``shape`` and ``dtype``: inside the outermost
    :func:`reusing` block of this thread the same memory for the same ``key`` each time
    (grown when a larger one is asked for), elsewhere ``np.empty``."""
    if getattr(_local, "depth", 0) != 1:
        return np.empty(shape, dtype)
    dt = np.dtype(dtype)
    n = math.prod(shape) * dt.itemsize
    bufs = getattr(_local, "bufs", None)
    if bufs is None:
        bufs = _local.bufs = {}
    buf = bufs.get(key)
    if buf is None or buf.nbytes < n:
        buf = bufs[key] = np.empty(max(n, 64) // 8 + 1, np.float64)  # 8-byte aligned for any dtype
    return buf.view(np.uint8)[:n].view(dt).reshape(shape)


def release() -> None:
    """Free this thread's buffers (they are allocated again on the next batch)."""
    _local.bufs = {}
