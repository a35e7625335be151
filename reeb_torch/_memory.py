"""Freed heap memory handed back to the system during the fits' long passes over frames.

A pass that runs REEB and then the backbone on one frame after another frees what each
frame used, but glibc's allocator keeps the freed pages of a fragmented heap: measured on
848 frames, the detector fit's per-frame pass grew by about 0.85 MB a frame that way, and
stayed flat with the pages handed back every few frames (``docs/results.md``, "Fits at
scale"). :func:`trim_heap` is glibc's ``malloc_trim(0)``; elsewhere (macOS, Windows, musl)
it does nothing.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import sys
from typing import Any

__all__ = ["trim_heap"]

_TRIM: list[Any] = []


def trim_heap() -> None:
    """Hand the heap's free pages back to the system (glibc's ``malloc_trim(0)``; a no-op
    where the C library has no such call)."""
    if not _TRIM:
        trim = None
        if sys.platform.startswith("linux"):
            try:
                trim = getattr(ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6"), "malloc_trim", None)
            except OSError:
                trim = None
        _TRIM.append(trim)
    if _TRIM[0] is not None:
        _TRIM[0](0)
