"""Where the compiled (numba) kernels of reeb-torch are cached on disk, that nobody else can
write there, and that a damaged cache heals itself.

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

**The folder**: ``$REEB_TORCH_CACHE_DIR`` if set, else ``$XDG_CACHE_HOME/reeb-torch/numba``,
else ``~/.cache/reeb-torch/numba``; ``off``, ``0``, ``none`` or empty: nothing is cached,
every process compiles the kernels it uses. The folders it makes are made mode 0700.

**Private**: numba's cache files are pickles, and whoever can write them runs code in the
next process that loads them. So, as ssh does with its keys, a folder is used only if this
user owns it and neither group nor others can write it, and every folder above it is owned
by this user or root and not writable by group or others (unless sticky, as ``/tmp``).
A folder that fails (or is a file, or cannot be made or written) is named on stderr with
why, once per process; a ``$REEB_TORCH_CACHE_DIR`` that fails gives way to the default,
a default that fails to no cache. A cache file another user owns is not loaded.

**Healing**: every index and data file carries a SHA-256 of its contents, and a data file
the key it was saved under. A file that does not read back whole (truncated, overwritten,
copied from elsewhere, another user's), or whose kernel cannot be rebuilt, is removed with
the rest of its kernel's entry and counts as not cached: the kernel is compiled again,
which gives the same code, and one line on stderr says so (once per process). A cache that
cannot be written (a full disk) says so once and runs on uncached.

Kernels outside this package are left to numba. Imported first by :mod:`reeb_torch.stages`,
before any kernel is defined.
"""

from __future__ import annotations

import functools
import hashlib
import os
import pickle
import stat
import sys
import tempfile
import threading
from pathlib import Path
from typing import NamedTuple

from numba.core import caching as _caching
from numba.core import dispatcher as _dispatcher

__all__ = ["cache_dir", "cache_note", "warm_marker", "ENV", "OFF"]

ENV = "REEB_TORCH_CACHE_DIR"
OFF = ("", "0", "off", "none")  # values of $REEB_TORCH_CACHE_DIR that turn the cache off
FORMAT = 2  # of the files (a checksum, the key in the data): part of every folder's name
_PACKAGE = Path(__file__).resolve().parents[1]  # reeb_torch/
_MAGIC = b"reeb-nb2"
_SAID: set[str] = set()  # what this process has said on stderr (each kind once)
_SAYING = threading.Lock()  # the two halves of a CPU batch may reach the same line at once


def _say(kind: str, line: str) -> None:
    with _SAYING:
        first = kind not in _SAID
        _SAID.add(kind)
    if first:
        print(f"reeb-torch: {line}", file=sys.stderr, flush=True)


# -- the folder ------------------------------------------------------------------------------

class _Choice(NamedTuple):
    folder: Path | None  # where the kernels are cached; None: nowhere
    note: str  # why not where asked, or why nowhere ("" when all is as asked)


def _default_folder() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "reeb-torch" / "numba"


def cache_dir() -> Path | None:
    """The folder the package's kernels are cached in, checked private (made mode 0700 if
    missing), or ``None`` where ``$REEB_TORCH_CACHE_DIR`` turns the cache off or no private
    folder can be had (nothing is cached then; :func:`cache_note` says why)."""
    return _choose(os.environ.get(ENV), str(_default_folder())).folder


def cache_note() -> str:
    """Why the kernels are not cached where asked, or at all (``""`` when they are)."""
    return _choose(os.environ.get(ENV), str(_default_folder())).note


@functools.cache
def _choose(env: str | None, default: str) -> _Choice:
    """The folder for ``$REEB_TORCH_CACHE_DIR=env`` (``None``: unset) and the default
    folder; worked out (and a refusal said on stderr) once per process and setting."""
    if env is not None and env.strip().lower() in OFF:
        return _Choice(None, f"${ENV}={env!r} turns the kernel cache off")
    if env is not None:
        asked = Path(os.path.abspath(Path(env).expanduser()))
        why = _usable(asked)
        if why is None:
            return _Choice(asked, "")
        if _usable(Path(default)) is None:
            note = f"not caching kernels in {asked}: {why}; caching them in {default} instead"
            _say("folder", note)
            return _Choice(Path(default), note)
    else:
        why = _usable(Path(default))
        if why is None:
            return _Choice(Path(default), "")
        asked = Path(default)
    note = f"not caching kernels in {asked}: {why}; compiling them in every process instead"
    _say("folder", note)
    return _Choice(None, note)


def _usable(folder: Path) -> str | None:
    """Why ``folder`` cannot hold the kernels, or ``None``: made (mode 0700) if missing,
    a folder, private (:func:`_not_private`) and writable."""
    try:
        _make_private(folder)
    except NotADirectoryError as e:
        return "it is not a folder" if str(e) == str(folder) else f"{e} is not a folder"
    except OSError as e:
        return f"cannot make it ({e.strerror or e})"
    why = _not_private(folder)
    if why is not None:
        return why
    try:
        tempfile.TemporaryFile(dir=folder).close()
    except OSError as e:
        return f"cannot write in it ({e.strerror or e})"
    return None


def _make_private(folder: Path) -> None:
    """``mkdir -p`` with mode 0700 for every folder it makes (``NotADirectoryError`` naming
    ``folder``, or the folder above it, that is there but not a folder)."""
    missing = []
    p = folder
    while not p.is_dir():
        if p.exists() or p.is_symlink():
            raise NotADirectoryError(str(p))
        missing.append(p)
        p = p.parent
    for p in reversed(missing):
        try:
            p.mkdir(mode=0o700)
        except FileExistsError:
            if not p.is_dir():
                raise NotADirectoryError(str(p)) from None


def _not_private(folder: Path) -> str | None:
    """Why others could write into ``folder`` (an existing folder), or ``None``: it must be
    this user's and writable by nobody else, and every folder above it (links resolved)
    this user's or root's and writable by nobody else unless sticky. (No such check where
    the system has no user ids.)"""
    if not hasattr(os, "getuid"):
        return None
    me = os.getuid()
    real = Path(os.path.realpath(folder))
    st = os.stat(real)
    if st.st_uid != me:
        return f"another user owns it (uid {st.st_uid})"
    if st.st_mode & 0o022:
        return f"group or others can write it (mode {stat.S_IMODE(st.st_mode):o})"
    for parent in real.parents:
        st = os.stat(parent)
        if st.st_uid not in (me, 0):
            return f"{parent} is another user's (uid {st.st_uid})"
        if st.st_mode & 0o022 and not st.st_mode & stat.S_ISVTX:
            return f"group or others can write {parent} (mode {stat.S_IMODE(st.st_mode):o})"
    return None


@functools.cache
def kernels_hash() -> str:
    """One hash of every source file of the package that defines a kernel, with the numba
    and Python versions and the cache's file format (worked out once per process): what
    every kernel's cache folder and :func:`warm_marker` are named after."""
    import numba

    h = hashlib.sha256(f"{numba.__version__} {sys.version} {FORMAT}".encode())
    for p in sorted(_PACKAGE.rglob("*.py")):
        text = p.read_bytes()
        if b"numba.njit" in text:
            h.update(p.relative_to(_PACKAGE).as_posix().encode() + text)
    return h.hexdigest()[:16]


def warm_marker() -> Path | None:
    """The file :func:`reeb_torch.warmup` (or a first call) leaves once every kernel of the
    default is compiled into :func:`cache_dir`; ``None`` where nothing is cached."""
    root = cache_dir()
    return None if root is None else root / f"warm-{kernels_hash()}"


# -- numba's hooks: the locator, the cache, its files -----------------------------------------

class _PackageCacheLocator(_caching._SourceFileBackedLocatorMixin, _caching._CacheLocator):
    """numba cache locator for this package's kernels: :func:`cache_dir` /
    ``<file>-<kernels_hash()>``, or nowhere (``root`` None: :class:`_KernelCache` then
    neither loads nor saves)."""

    def __init__(self, py_func, py_file: str) -> None:
        self._py_file = py_file
        self._lineno = py_func.__code__.co_firstlineno
        self.root = cache_dir()
        where = self.root or Path(os.devnull)  # no folder: a path nothing is written to (disabled)
        self._cache_path = str(where / f"{Path(py_file).stem}-{kernels_hash()}")

    def get_cache_path(self) -> str:
        return self._cache_path

    def ensure_cache_path(self) -> None:
        """The kernel's folder, made mode 0700, this user's and writable by nobody else."""
        path = Path(self._cache_path)
        _make_private(path)
        why = _not_private(path)
        if why is not None:
            raise PermissionError(f"{path}: {why}")
        tempfile.TemporaryFile(dir=path).close()

    @classmethod
    def from_function(cls, py_func, py_file):
        try:
            inside = Path(py_file).resolve().is_relative_to(_PACKAGE)
        except (OSError, ValueError):
            return None
        if not inside or not os.path.exists(py_file):
            return None
        self = cls(py_func, py_file)
        if self.root is not None:
            try:
                self.ensure_cache_path()
            except OSError as e:
                _say("subfolder", f"not caching kernels in {self._cache_path}: {e}")
                self.root = None
        return self


class _Damaged(Exception):
    """A cache file that does not read back as written."""


class _CheckedCacheFile(_caching.IndexDataCacheFile):
    """numba's index and data files of one kernel, each sealed with a SHA-256 of its bytes
    (and a data file holding the key it was saved under), read only when this user owns
    them; a file that fails is removed with the rest of the kernel's entry: a cache miss."""

    def _seal(self, payload: bytes) -> bytes:
        return _MAGIC + hashlib.sha256(payload).digest() + payload

    def _read(self, path: str) -> bytes:
        with open(path, "rb") as f:
            owner = os.fstat(f.fileno()).st_uid
            blob = f.read()
        if hasattr(os, "getuid") and owner != os.getuid():
            raise _Damaged(f"another user's file (uid {owner})")
        head = len(_MAGIC) + 32
        if blob[: len(_MAGIC)] != _MAGIC or hashlib.sha256(blob[head:]).digest() != blob[len(_MAGIC): head]:
            raise _Damaged("its checksum does not match (truncated or overwritten)")
        return blob[head:]

    def _load_index(self) -> dict:
        try:
            version, stamp, overloads = pickle.loads(self._read(self._index_path))
        except FileNotFoundError:
            return {}
        except Exception as e:  # noqa: BLE001 - any failure to read a cache file is a miss
            self.drop(self._index_path, e)
            return {}
        return overloads if (version, stamp) == (self._version, self._source_stamp) else {}

    def _save_index(self, overloads: dict) -> None:
        blob = self._seal(self._dump((self._version, self._source_stamp, overloads)))
        with self._open_for_write(self._index_path) as f:
            f.write(blob)

    def _load_data(self, name: str):
        return pickle.loads(self._read(self._data_path(name)))

    def _save_data(self, name: str, data) -> None:
        blob = self._seal(self._dump(data))
        with self._open_for_write(self._data_path(name)) as f:
            f.write(blob)

    def save(self, key, data) -> None:
        super().save(key, (key, data))

    def load(self, key):
        name = self._load_index().get(key)
        if name is None:
            return None
        try:
            stored, data = self._load_data(name)
        except FileNotFoundError:
            return None
        except Exception as e:  # noqa: BLE001
            self.drop(self._data_path(name), e)
            return None
        if stored != key:
            self.drop(self._data_path(name), _Damaged("it holds another kernel"))
            return None
        return data

    def drop(self, path: str, why: BaseException) -> None:
        """Remove this kernel's index and data files, and say so (once per process)."""
        base = os.path.basename(self._index_path)[: -len(".nbi")] + "."
        try:
            names = [n for n in os.listdir(self._cache_path) if n.startswith(base)]
        except OSError:
            names = []
        for n in names:
            try:
                os.unlink(os.path.join(self._cache_path, n))
            except OSError:
                pass
        _say("damaged", f"removed a damaged kernel cache entry ({path}: {str(why) or type(why).__name__}); "
                        "compiling it again")


class _KernelCache(_caching.FunctionCache):
    """numba's per-kernel cache; for this package's kernels with :class:`_CheckedCacheFile`,
    a miss where a cached kernel cannot be rebuilt, nothing done where there is no folder,
    and a cache that cannot be written said once, not raised."""

    def __init__(self, py_func) -> None:
        super().__init__(py_func)
        self._ours = isinstance(self._impl.locator, _PackageCacheLocator)
        if self._ours:
            old = self._cache_file  # type: ignore[has-type]  # numba's attribute
            self._cache_file = _CheckedCacheFile(self._cache_path, self._impl.filename_base, old._source_stamp)
            if self._impl.locator.root is None:
                self.disable()

    def load_overload(self, sig, target_context):
        if not self._ours:
            return super().load_overload(sig, target_context)
        try:
            return super().load_overload(sig, target_context)
        except Exception as e:  # noqa: BLE001 - the entry read back but does not rebuild
            self._cache_file.drop(self._cache_path, e)
            return None

    def save_overload(self, sig, data) -> None:
        if not self._ours:
            return super().save_overload(sig, data)
        try:
            super().save_overload(sig, data)
        except OSError as e:
            _say("unwritable", f"cannot write the kernel cache in {self._cache_path} ({e.strerror or e}); "
                               "the kernels compiled now are not cached")

    def flush(self) -> None:
        if self._enabled:
            super().flush()


if _PackageCacheLocator not in _caching.CacheImpl._locator_classes:
    _caching.CacheImpl._locator_classes.insert(0, _PackageCacheLocator)
if _dispatcher.FunctionCache is _caching.FunctionCache:  # type: ignore[attr-defined]  # what njit(cache=True) makes
    _dispatcher.FunctionCache = _KernelCache  # type: ignore[attr-defined]
