"""The one-time cost of the compiled kernels: the picture :func:`reeb_torch.warmup` runs on,
the notice a first run prints, and the marker left once the kernels are cached."""

from __future__ import annotations

import sys
import time

import torch

from .stages import _cache

__all__ = ["warm_picture", "Notice", "COMPILE_ESTIMATE_S"]

#: What compiling every kernel of the default took (``reeb warmup`` with an empty cache:
#: 56 s on two cores shared with other work, about 20 s on quiet ones); the notice says it.
COMPILE_ESTIMATE_S = "30-60 s"


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
    cached (no :func:`reeb_torch.stages._cache.warm_marker`), and leaves the marker after."""

    def __init__(self, quiet: bool = False) -> None:
        self.marker = _cache.warm_marker()
        self.first = self.marker is not None and not self.marker.exists()
        self.quiet = quiet
        self.t0 = time.perf_counter()

    def __enter__(self) -> Notice:
        if self.first and not self.quiet:
            print(f"reeb-torch: compiling kernels once for this install, about {COMPILE_ESTIMATE_S} "
                  f"(cached in {_cache.cache_dir()}; `reeb warmup` does it ahead of time) ...",
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
