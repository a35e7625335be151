"""Where the compiled (numba) kernels of reeb-torch are cached on disk, and whether they are.

numba's ``cache=True`` writes beside the source (``__pycache__``), which a reinstall of the
package wipes, so a fresh install of the same version compiled every kernel again (about
20 s on two busy cores). Here the package's kernels are cached in a per-user folder,
one subfolder per source file *and the content hash of every source file that defines a
kernel*: the same sources, reinstalled or in another checkout, find their kernels; a change
to any of them gets new folders. (A kernel's cache entry holds the kernels it calls from
other files, compiled in, and numba checks only the file that defines it: with one hash
per file, a change to ``_radix.py`` left ``scoring.py``'s cached kernels running the old
``_radix`` code.) numba still keys each entry by its own version, the Python version and
the CPU.

The folder: ``$REEB_TORCH_CACHE_DIR`` if set (``off``, ``0`` or empty: numba's own
places), else ``$XDG_CACHE_HOME/reeb-torch/numba``, else ``~/.cache/reeb-torch/numba``.
Kernels outside this package are left to numba. Imported first by :mod:`reeb_torch.stages`,
before any kernel is defined.
"""

from __future__ import annotations

import functools
import hashlib
import os
import sys
from pathlib import Path

from numba.core import caching as _caching

__all__ = ["cache_dir", "warm_marker", "ENV"]

ENV = "REEB_TORCH_CACHE_DIR"
_PACKAGE = Path(__file__).resolve().parents[1]  # reeb_torch/


def cache_dir() -> Path | None:
    """The folder the package's kernels are cached in, or ``None`` where
    ``$REEB_TORCH_CACHE_DIR`` turns it off (numba's own places are used then)."""
    env = os.environ.get(ENV)
    if env is not None:
        return None if env.strip().lower() in ("", "0", "off", "none") else Path(env).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "reeb-torch" / "numba"


@functools.cache
def kernels_hash() -> str:
    """One hash of every source file of the package that defines a kernel, with the numba
    and Python versions (worked out once per process): what every kernel's cache folder and
    :func:`warm_marker` are named after."""
    import numba

    h = hashlib.sha256(f"{numba.__version__} {sys.version}".encode())
    for p in sorted(_PACKAGE.rglob("*.py")):
        text = p.read_bytes()
        if b"numba.njit" in text:
            h.update(p.relative_to(_PACKAGE).as_posix().encode() + text)
    return h.hexdigest()[:16]


def warm_marker() -> Path | None:
    """The file :func:`reeb_torch.warmup` (or a first call) leaves once every kernel of the
    default is compiled into :func:`cache_dir`; ``None`` where the cache is off."""
    root = cache_dir()
    return None if root is None else root / f"warm-{kernels_hash()}"


class _PackageCacheLocator(_caching._SourceFileBackedLocatorMixin, _caching._CacheLocator):
    """numba cache locator for this package's kernels: :func:`cache_dir` /
    ``<file>-<kernels_hash()>``."""

    def __init__(self, py_func, py_file: str) -> None:
        self._py_file = py_file
        self._lineno = py_func.__code__.co_firstlineno
        self._cache_path = str(cache_dir() / f"{Path(py_file).stem}-{kernels_hash()}")

    def get_cache_path(self) -> str:
        return self._cache_path

    @classmethod
    def from_function(cls, py_func, py_file):
        try:
            inside = Path(py_file).resolve().is_relative_to(_PACKAGE)
        except (OSError, ValueError):
            return None
        if not inside or cache_dir() is None or not os.path.exists(py_file):
            return None
        return super().from_function(py_func, py_file)  # None where the folder is not writable


if _PackageCacheLocator not in _caching.CacheImpl._locator_classes:
    _caching.CacheImpl._locator_classes.insert(0, _PackageCacheLocator)
