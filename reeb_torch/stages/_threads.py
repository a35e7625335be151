"""Running a compiled (numba, ``nogil``) kernel on the two halves of its work at once."""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from typing import Callable, Iterator

import torch

__all__ = ["on_two_cores", "images_or_rows", "started", "torch_single_threaded", "serially"]

_pool: ThreadPoolExecutor | None = None
_lock = threading.Lock()
_inside = threading.local()


def _worker() -> ThreadPoolExecutor:
    """One helper thread for the whole process, started on first use (a pool per call would
    pay a thread's start-up a dozen times per batch); a forked child starts its own."""
    global _pool
    with _lock:
        if _pool is None:
            _pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="reeb-half",
                                       initializer=lambda: setattr(_inside, "worker", True))
        return _pool


def _forget_pool() -> None:
    global _pool, _lock
    _pool, _lock = None, threading.Lock()  # the parent's thread does not exist in the child


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_pool)


def _in_caller() -> bool:
    """Whether work handed to the helper runs in the calling thread instead: the caller is
    the helper itself, or within :func:`serially`."""
    return getattr(_inside, "worker", False) or getattr(_inside, "serial", False)


def on_two_cores(run: Callable[[int, int], None], b: int) -> None:
    """``run(lo, hi)`` over items ``[0, b)`` (the images of a batch, or the parts of
    one image): a compiled kernel that releases the GIL runs on the two halves at once
    (the items are independent, so the numbers are the same as in one call). Calls from
    several threads share the helper thread (their second halves queue); a call from the
    helper thread itself, or within :func:`serially`, runs both halves in the calling
    thread."""
    if b < 2 or _in_caller():
        run(0, b)
        return
    half = (b + 1) // 2
    other = _worker().submit(run, half, b)
    try:
        run(0, half)
    finally:
        other.result()


def started(run: Callable[[], None]) -> Callable[[], None]:
    """``run()`` started on the helper thread while the caller goes on; returns the
    function that waits for it to end (and raises what it raised). In the helper thread
    itself, or within :func:`serially`, ``run()`` runs here and now. The caller's own
    kernels meanwhile belong within :func:`serially`: a half handed to the helper would
    queue behind ``run``."""
    if _in_caller():
        run()
        return lambda: None
    job = _worker().submit(run)
    return lambda: job.result()


def images_or_rows(run: Callable[[int, int, int, int], None], b: int, rows: int) -> None:
    """``run(i0, i1, r0, r1)``: images ``[i0, i1)``, rows ``[r0, r1)`` of each, on the two
    cores: half the images each, or for one image half its ``rows`` each (the latency of
    a single image: a kernel whose output rows depend only on its input, each row computed
    the same way whichever part holds it, so the numbers are the same)."""
    if b == 1:
        on_two_cores(lambda lo, hi: run(0, 1, lo, hi), rows)
    else:
        on_two_cores(lambda lo, hi: run(lo, hi, 0, rows), b)


_torch_lock = threading.Lock()
_torch_users = 0
_torch_saved = 1


@contextmanager
def torch_single_threaded() -> Iterator[None]:
    """torch's intra-op threads set to 1 within the block (restored after the last of
    several concurrent blocks ends). The compiled kernels split their work onto their own
    helper thread; torch's ops between them are small, and after each op that opens
    torch's OpenMP pool its idle workers spin for milliseconds against that helper
    thread (``GOMP_SPINCOUNT=0`` removes it too; measured in docs/results.md, "What makes
    the CPU path fast")."""
    global _torch_users, _torch_saved
    with _torch_lock:
        if _torch_users == 0:
            _torch_saved = torch.get_num_threads()
            if _torch_saved != 1:
                torch.set_num_threads(1)
        _torch_users += 1
    try:
        yield
    finally:
        with _torch_lock:
            _torch_users -= 1
            if _torch_users == 0 and _torch_saved != 1:
                torch.set_num_threads(_torch_saved)


@contextmanager
def serially() -> Iterator[None]:
    """Within the block, :func:`on_two_cores` runs its work in the calling thread (for a
    caller that keeps the other core busy with work of its own)."""
    before = getattr(_inside, "serial", False)
    _inside.serial = True
    try:
        yield
    finally:
        _inside.serial = before
