"""What depends on the image size only, kept per window grid, and tensors copied once per device."""

from __future__ import annotations

import threading
from collections import OrderedDict
from typing import Callable, TypeVar

import torch
from torch import Tensor

from ..stages import windows as _windows

__all__ = ["GridCache", "PLAN_GRIDS"]

T = TypeVar("T")

PLAN_GRIDS = 16
"""Window grids (image sizes) whose per-size tables :class:`GridCache` keeps, the latest used."""

_ORDER = threading.Lock()  # the two halves of a CPU batch share a cache: one of them reorders it at a time


class GridCache:
    """Per-grid tables and per-device copies (:meth:`grid_cached`, :meth:`device_tensor`),
    shared by the window selection's parts and the learned ranking's features."""

    def __init__(self) -> None:
        self._device_cache: dict = {}
        self._plan_cache: OrderedDict[int, tuple[_windows.WindowGrid, dict]] = OrderedDict()

    def grid_cached(self, key: tuple, grid: _windows.WindowGrid, build: Callable[[], T]) -> T:
        """``build()``, cached per ``key`` and window grid (grids are cached themselves, so
        one is recognised by identity; the entry keeps it alive so its id is not reused).
        The values of the :data:`PLAN_GRIDS` grids used last are kept, whatever their number
        of keys: a cap on entries cleared every value at each batch once the image sizes
        times the keys per grid (8 for the default) passed it (KITTI's 4 sizes are 32)."""
        with _ORDER:
            slot = self._plan_cache.get(id(grid))
            if slot is None or slot[0] is not grid:
                slot = (grid, {})
                self._plan_cache[id(grid)] = slot
                while len(self._plan_cache) > PLAN_GRIDS:
                    self._plan_cache.popitem(last=False)
            else:
                self._plan_cache.move_to_end(id(grid))
        values = slot[1]
        if key not in values:
            values[key] = build()
        return values[key]

    def device_tensor(self, t: Tensor, device: torch.device) -> Tensor:
        """``t`` on ``device``, copied once per tensor and device."""
        if t.device == device:
            return t
        key = (id(t), str(device))
        hit = self._device_cache.get(key)
        if hit is None or hit[0] is not t:
            if len(self._device_cache) >= 256:  # grids of many image sizes: start afresh
                self._device_cache.clear()
            hit = (t, t.to(device))
            self._device_cache[key] = hit
        return hit[1]
