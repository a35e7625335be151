"""Running a compiled (numba, ``nogil``) kernel on the two halves of a batch at once."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from typing import Callable

__all__ = ["on_two_cores"]


def on_two_cores(run: Callable[[int, int], None], b: int) -> None:
    """``run(lo, hi)`` over images ``[0, b)``: a compiled kernel that releases the GIL runs
    on the two halves of the batch at once (the images are independent, so the numbers are
    the same as in one call)."""
    if b < 2:
        run(0, b)
        return
    half = (b + 1) // 2
    with ThreadPoolExecutor(max_workers=1) as pool:
        other = pool.submit(run, half, b)
        run(0, half)
        other.result()
