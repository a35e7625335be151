"""The one-time cost of the compiled kernels: the picture :func:`reeb_torch.warmup` runs on,
the notice a first run prints, the marker left once the kernels are cached, and the
helper process that compiles part of them on the other core meanwhile."""

from __future__ import annotations

import gc
import os
import subprocess
import sys
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

import numpy as np
import torch

from .stages import _kernel_cache, enclosed, nms, scoring
from .stages._threads import serially

__all__ = ["warm_picture", "Notice", "COMPILE_ESTIMATE_S", "gc_paused", "start_helper", "stop_helper",
           "compile_helper_part"]

#: What compiling every kernel of the default takes, as the notice says it (measured with
#: ``benchmarks/speed_ab.py --first-call``: docs/results.md, "The first call").
COMPILE_ESTIMATE_S = "10-40 s"


def warm_picture(height: int = 160, width: int = 480) -> torch.Tensor:
    """A synthetic ``uint8 (3, height, width)`` road scene (sky, a road, a few boxes and
    poles, mild noise), deterministic: enough edges, groups and windows for every compiled
    kernel of the default to run on it, and small enough to take milliseconds."""
    g = torch.Generator().manual_seed(0)
    img = torch.empty(3, height, width)
    rows = torch.linspace(0, 1, height)[:, None].expand(height, width)
    img[0], img[1], img[2] = 0.55 + 0.3 * (1 - rows), 0.6 + 0.2 * (1 - rows), 0.7 + 0.25 * (1 - rows)
    road = int(height * 0.55)
    img[:, road:] = 0.35
    for i in range(6):  # boxes on the road and poles, of a few sizes and colours
        x0 = 20 + i * width // 7
        bw, bh = 18 + 9 * i, 14 + 7 * i
        y1 = min(height - 2, road + 6 + 4 * i)
        img[:, max(0, y1 - bh): y1, x0: min(width, x0 + bw)] = torch.tensor([0.1 + 0.12 * i, 0.5, 0.8 - 0.1 * i])[:, None, None]
        img[1, max(0, y1 - bh - 20): y1 - bh, x0 + bw // 2: x0 + bw // 2 + 3] = 0.9  # a green pole above
    img += 0.03 * torch.randn(img.shape, generator=g)
    return (img.clamp_(0, 1) * 255).round_().to(torch.uint8)


class Notice:
    """Tells the user, on stderr, that the kernels are being compiled when they are not yet
    cached (no :func:`reeb_torch.stages._kernel_cache.warm_marker`), and leaves the marker after."""

    def __init__(self, quiet: bool = False) -> None:
        self.marker = _kernel_cache.warm_marker()
        self.first = self.marker is not None and not self.marker.exists()
        self.quiet = quiet
        self.t0 = time.perf_counter()

    def __enter__(self) -> Notice:
        if self.first and not self.quiet:
            print(f"reeb-torch: compiling kernels once for this install, about {COMPILE_ESTIMATE_S} "
                  f"(cached in {_kernel_cache.cache_dir()}; `reeb warmup` does it ahead of time) ...",
                  file=sys.stderr, flush=True)
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is not None or self.marker is None:
            return
        if self.first and not self.quiet:
            print(f"reeb-torch: kernels compiled in {time.perf_counter() - self.t0:.1f} s", file=sys.stderr,
                  flush=True)
        try:
            self.marker.parent.mkdir(parents=True, exist_ok=True)
            self.marker.touch()
        except OSError:
            pass  # a read-only cache: the notice comes again next time, nothing worse


@contextmanager
def gc_paused() -> Iterator[None]:
    """Python's cyclic garbage collector off within the block, one collection after it (where
    it was on). numba's compiler leaves many long-lived objects, and the full collections
    they set off take a noticeable share of a compile (at a lower peak of memory without
    them); with the kernels cached, the collection after takes the full one that the first
    call would otherwise meet."""
    was = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if was:
            gc.enable()
            gc.collect()


HELPER_ENV = "REEB_TORCH_WARM_HELPER"
"""Set in the helper process (so that it starts none of its own); set it (to any value)
to compile in one process only."""


def start_helper() -> subprocess.Popen | None:
    """Start a second Python process that compiles :func:`compile_helper_part`'s kernels
    into the same cache while this one runs the warm-up (numba compiles in one thread per
    process; a kernel this process reaches after the helper has cached it is loaded, not
    compiled). ``None`` on one core, inside the helper, in a frozen application, or where
    it cannot start."""
    if os.environ.get(HELPER_ENV) is not None or (os.cpu_count() or 1) < 2 or getattr(sys, "frozen", False):
        return None  # (a frozen application's executable is not a Python to run -c with)
    env = dict(os.environ, **{HELPER_ENV: "1"})
    here = str(Path(__file__).resolve().parents[1])  # this copy of the package, first
    env["PYTHONPATH"] = here + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    try:
        return subprocess.Popen([sys.executable, "-c", "from reeb_torch._warm import compile_helper_part as c; c()"],
                                env=env, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                stderr=subprocess.DEVNULL)
    except OSError:
        return None


def stop_helper(helper: subprocess.Popen | None) -> None:
    """End the helper once the warm-up is done: whatever it has not cached by then this
    process compiled (and cached) itself. numba writes each cache file whole (a temporary
    file, then a rename), so stopping it mid-way leaves nothing half-written."""
    if helper is None:
        return
    if helper.poll() is None:
        helper.terminate()
    try:
        helper.wait(timeout=10)
    except subprocess.TimeoutExpired:
        helper.kill()
        helper.wait()


def compile_helper_part() -> None:
    """In the helper process: the kernels the warm-up reaches last (the window scores, the
    per-region cut and the window NMS's three), in the order it reaches them, on synthetic
    inputs of the types the pipeline passes them, so that they are cached under the same
    signatures (``tests/test_warmup.py`` checks that they add none)."""

    g = torch.Generator().manual_seed(0)
    n = 9000  # more than 3 · 2000 candidates: the prefix path of the window NMS
    xy = torch.rand(n, 2, generator=g) * 400
    boxes = torch.cat([xy, xy + 8 + torch.rand(n, 2, generator=g) * 60], 1)
    scores = torch.rand(2, n, generator=g)
    table = torch.zeros(1, 9, 9, dtype=torch.float64)  # no window sizes: typed and compiled, nothing run
    with serially(), gc_paused():  # one core: the warm-up has the other
        scoring.score_grid_cpu(table, enclosed.EnclosedTables(table, table, table, table, 1),
                               np.zeros((0, len(scoring.PLAN_COLUMNS)), np.int64), np.zeros(0), np.zeros(0, np.float32),
                               1.0, 1.0, 0.0, 0.0, torch.empty(1, 0))
        scoring.select_per_region_cpu(scores, np.arange(n, dtype=np.int64), np.array([0, n // 2, n], np.int64),
                                      torch.full((2, 2), 300, dtype=torch.int64))
        nms.nms_windows_cpu(torch.rand(2, n, generator=g) < 0.9, boxes, scores, 0.7, 2000)
