"""Running a compiled (numba, ``nogil``) kernel on the two halves of its work at once."""

from __future__ import annotations

import os
import threading
from contextlib import contextmanager
from typing import Callable, Iterator

import numpy as np
import torch

from . import _spin

__all__ = ["on_two_cores", "images_or_rows", "torch_single_threaded", "serially"]

_IDLE_READS = 80_000
"""Reads of the task counter (~2 ms here) the helper thread spins for after a task before
it sleeps: a single image hands it seven kernels, less than 2 ms apart but for the NMS
(~2 ms, between one image's last and the next one's first; 5 ms of spinning covered that
too, for 0.04 ms per image, and costs 3 ms more of the second core after every call: in
a batch run that is the decoding workers' time). A caller that runs one image every
100 ms pays ~2 % of the second core for it."""
_WAIT_READS = 80_000
"""Reads (~2 ms) a caller spins for while the helper finishes its half, before it sleeps."""


class _Helper:
    """One helper thread for the whole process, started on first use (a thread per call
    cost ~0.1 ms of start-up, a dozen times per batch); a forked child starts its own.

    The hand-over is a pair of counters, tasks posted and tasks done, that each side
    watches in compiled code for a bounded time (:func:`._spin.wait_while`) before it
    sleeps on :attr:`cond`: on the project's VM a thread asleep on a lock took 55–70 µs to
    wake, twice per hand-over, seven hand-overs per image (32 KITTI frames one at a time:
    9.7–10.1 ms/img with a sleeping helper, 8.2–9.0 with this one)."""

    def __init__(self) -> None:
        self.counts = np.zeros(2, np.int64)  # [tasks posted, tasks done]
        self.cond = threading.Condition()
        self.busy = threading.Lock()  # one caller at a time; others run serially
        self.task: Callable[[], None] | None = None
        self.error: BaseException | None = None
        threading.Thread(target=self._loop, name="reeb-half", daemon=True).start()

    def _loop(self) -> None:
        _inside.worker = True
        done = 0
        while True:
            if not _spin.SPINS or _spin.wait_while(self.counts, 0, done, _IDLE_READS) == done:
                with self.cond:
                    while self.counts[0] == done:
                        self.cond.wait()
            done = int(self.counts[0])
            try:
                self.task()  # type: ignore[misc]
            except BaseException as e:  # noqa: BLE001 - raised again in the caller
                self.error = e
            self.task = None
            with self.cond:
                self.counts[1] = done
                self.cond.notify_all()

    def both(self, mine: Callable[[], None], theirs: Callable[[], None]) -> None:
        """``theirs()`` on the helper thread while ``mine()`` runs here; returns when both
        are done, raising what either raised (the caller's first)."""
        with self.cond:
            self.task, self.error = theirs, None
            self.counts[0] += 1
            posted = int(self.counts[0])
            self.cond.notify_all()
        try:
            mine()
        finally:
            if not _spin.SPINS or _spin.wait_while(self.counts, 1, posted - 1, _WAIT_READS) != posted:
                with self.cond:
                    while self.counts[1] != posted:
                        self.cond.wait()
        if self.error is not None:
            error, self.error = self.error, None
            raise error


_helper: _Helper | None = None
_lock = threading.Lock()
_inside = threading.local()


def _the_helper() -> _Helper:
    global _helper
    with _lock:
        if _helper is None:
            _helper = _Helper()
        return _helper


def _forget_helper() -> None:
    global _helper, _lock
    _helper, _lock = None, threading.Lock()  # the parent's thread does not exist in the child


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_helper)


def on_two_cores(run: Callable[[int, int], None], b: int) -> None:
    """``run(lo, hi)`` over items ``[0, b)`` (the images of a batch, or the boxes of the
    refinement): a compiled kernel that releases the GIL runs on the two halves at once
    (the items are independent, so the numbers are the same as in one call). A call made
    while another thread's call holds the helper thread, or from the helper thread itself,
    or within :func:`serially`, runs both halves in the calling thread."""
    if b < 2 or getattr(_inside, "worker", False) or getattr(_inside, "serial", False):
        run(0, b)
        return
    helper = _the_helper()
    if not helper.busy.acquire(blocking=False):
        run(0, b)
        return
    half = (b + 1) // 2
    try:
        helper.both(lambda: run(0, half), lambda: run(half, b))
    finally:
        helper.busy.release()


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
    thread (measured: 15.1 against 12.3 ms/img at batch 8; ``GOMP_SPINCOUNT=0`` removes
    it too)."""
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
