"""The kernels' disk cache (stages/_kernel_cache.py): it heals itself when its files are
damaged, it is private (nobody else can write where it loads pickles from), and it says
where the kernels actually go.

The folder rules and the file checks are tested in this process on temporary folders; what
a user meets (a damaged cache under a real run, a folder others can write) in subprocesses
with their own ``$REEB_TORCH_CACHE_DIR``."""

from __future__ import annotations

import hashlib
import os
import shutil
import stat
import subprocess
import sys
from pathlib import Path

import pytest

from reeb_torch import _warm
from reeb_torch.stages import _kernel_cache

REPO = Path(__file__).resolve().parents[2]
SAMPLE = REPO / "examples" / "data" / "kitti_000001.png"
ROOT_ONLY = pytest.mark.skipif(not hasattr(os, "geteuid") or os.geteuid() != 0,
                               reason="needs root to make a file or folder another user's")


@pytest.fixture(autouse=True)
def fresh_lines(monkeypatch):
    """Each test sees the one-line reports as a new process would (each kind once)."""
    monkeypatch.setattr(_kernel_cache, "_SAID", set(), raising=False)


def _mode(p: Path) -> int:
    return stat.S_IMODE(p.stat().st_mode)


# -- the folder: private, made 0700, refused where others can write ----------------------------

def test_the_folders_it_makes_are_private(tmp_path):
    folder = tmp_path / "a" / "b" / "numba"
    assert _kernel_cache._choose(str(folder), str(tmp_path / "default")) == (folder, "")
    assert [_mode(p) for p in (tmp_path / "a", tmp_path / "a" / "b", folder)] == [0o700] * 3


@pytest.mark.parametrize("where", ["itself", "parent"])
def test_a_folder_others_can_write_is_refused_with_one_line(tmp_path, capsys, where):
    shared = tmp_path / "shared" / "numba"
    shared.mkdir(parents=True)
    (shared if where == "itself" else shared.parent).chmod(0o777)
    default = tmp_path / "home" / "numba"
    folder, note = _kernel_cache._choose(str(shared), str(default))
    assert folder == default and _mode(default) == 0o700
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("reeb-torch: not caching kernels in ") and str(shared) in err
    assert "group or others can write" in err and "777" in err and f"caching them in {default} instead" in err
    assert note in err
    assert not any(shared.iterdir())


def test_a_sticky_parent_such_as_tmp_is_allowed(tmp_path):
    parent = tmp_path / "tmp"
    parent.mkdir()
    parent.chmod(0o1777)  # others may add entries, but not rename or remove this user's
    assert _kernel_cache._choose(str(parent / "mine"), str(tmp_path / "d")) == (parent / "mine", "")


@ROOT_ONLY
@pytest.mark.parametrize("where", ["itself", "parent"])
def test_a_folder_another_user_owns_is_refused(tmp_path, capsys, where):
    theirs = tmp_path / "theirs" / "numba"
    theirs.mkdir(parents=True, mode=0o755)
    os.chown(theirs if where == "itself" else theirs.parent, 12345, -1)
    folder, note = _kernel_cache._choose(str(theirs), str(tmp_path / "home"))
    assert folder == tmp_path / "home" and "uid 12345" in note and note in capsys.readouterr().err


def test_a_file_as_the_folder_says_where_the_kernels_go(tmp_path, monkeypatch, capsys):
    afile = tmp_path / "afile"
    afile.write_text("")
    monkeypatch.setenv(_kernel_cache.ENV, str(afile))
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    default = tmp_path / "xdg" / "reeb-torch" / "numba"
    assert _kernel_cache.cache_dir() == default
    with _warm.Notice():  # the first-run notice names the folder actually used
        pass
    err = capsys.readouterr().err
    assert f"not caching kernels in {afile}: it is not a folder; caching them in {default} instead" in err
    assert f"(cached in {default};" in err and f"cached in {afile}" not in err
    assert _kernel_cache.warm_marker().parent == default and _kernel_cache.warm_marker().exists()


def test_no_private_folder_means_no_cache_said_once(tmp_path, capsys):
    bad = tmp_path / "bad"
    bad.mkdir(mode=0o777)
    bad.chmod(0o777)
    assert _kernel_cache._choose(None, str(bad)).folder is None  # the default itself refused: nothing cached
    assert "compiling them in every process instead" in capsys.readouterr().err
    afile = tmp_path / "afile"
    afile.write_text("")
    assert _kernel_cache._choose(str(afile), str(bad)).folder is None
    assert capsys.readouterr().err == ""  # once per process


def test_off_caches_nothing(monkeypatch):
    monkeypatch.setenv(_kernel_cache.ENV, "off")
    assert _kernel_cache.cache_dir() is None and _kernel_cache.warm_marker() is None
    assert "turns the kernel cache off" in _kernel_cache.cache_note()


def _run(code: str, env: dict, timeout: int = 120) -> subprocess.CompletedProcess:
    full = dict(os.environ, PYTHONPATH=str(REPO), **env)
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=timeout, env=full)


@pytest.mark.slow
def test_the_kernels_are_not_cached_in_a_folder_others_can_write(tmp_path):
    shared = tmp_path / "shared"
    shared.mkdir()
    shared.chmod(0o777)
    code = ("from reeb_torch.stages import nms\n"
            "c = nms._sorted_boxes._cache\n"
            "print(c._cache_path, c._enabled)\n")
    r = _run(code, {_kernel_cache.ENV: str(shared), "XDG_CACHE_HOME": str(tmp_path / "xdg")})
    assert r.returncode == 0, r.stderr
    path, enabled = r.stdout.split()
    assert path.startswith(str(tmp_path / "xdg" / "reeb-torch" / "numba")) and enabled == "True"
    assert r.stderr.count("reeb-torch: not caching kernels in") == 1 and str(shared) in r.stderr
    assert not any(shared.iterdir())
    r = _run(code, {_kernel_cache.ENV: "off"})
    assert r.returncode == 0 and r.stdout.split()[1] == "False", r.stderr  # off: nothing loaded or saved


# -- the files: sealed, checked, dropped when damaged -------------------------------------------

def _file(tmp_path: Path) -> _kernel_cache._CheckedCacheFile:
    return _kernel_cache._CheckedCacheFile(str(tmp_path), "m.kernel-12.py311", source_stamp=b"stamp")


def _damage(kind: str, f: _kernel_cache._CheckedCacheFile, folder: Path) -> None:
    data = folder / "m.kernel-12.py311.1.nbc"
    index = folder / "m.kernel-12.py311.nbi"
    if kind == "truncated data":
        data.write_bytes(data.read_bytes()[:100])
    elif kind == "empty data":
        data.write_bytes(b"")
    elif kind == "data overwritten":
        data.write_bytes(os.urandom(300))
    elif kind == "one byte flipped":  # a valid pickle still: only the checksum tells
        b = bytearray(data.read_bytes())
        b[-20] ^= 0xFF
        data.write_bytes(bytes(b))
    elif kind == "truncated index":
        index.write_bytes(index.read_bytes()[:60])
    elif kind == "index overwritten":
        index.write_bytes(b"\x80\x05garbage" * 10)
    elif kind == "another kernel's data":
        f.save(("other key",), {"code": "another kernel"})  # data file 2
        shutil.copy(folder / "m.kernel-12.py311.2.nbc", data)
    elif kind == "another user's file":
        os.chown(data, 12345, -1)


DAMAGES = ["truncated data", "empty data", "data overwritten", "one byte flipped", "truncated index",
           "index overwritten", "another kernel's data",
           pytest.param("another user's file", marks=ROOT_ONLY)]


def test_a_cache_file_reads_back_what_was_saved(tmp_path):
    f = _file(tmp_path)
    key = (("int64", "float32"), ("cpu",), ("h1", "h2"))
    f.save(key, {"library": b"\x00" * 1000, "n": 3})
    assert _file(tmp_path).load(key) == {"library": b"\x00" * 1000, "n": 3}
    assert _file(tmp_path).load(("another key",)) is None
    other = _kernel_cache._CheckedCacheFile(str(tmp_path), "m.kernel-12.py311", source_stamp=b"changed")
    assert other.load(key) is None  # a stale index is a miss, as in numba


@pytest.mark.parametrize("kind", DAMAGES)
def test_a_damaged_file_is_a_miss_removed_with_one_line(tmp_path, capsys, kind):
    f = _file(tmp_path)
    key = (("int64",), ("cpu",), ("h",))
    f.save(key, {"library": b"\x01" * 5000})
    _damage(kind, f, tmp_path)
    assert _file(tmp_path).load(key) is None
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "reeb-torch: removed a damaged kernel cache entry (" in err, err
    assert str(tmp_path) in err and "compiling it again" in err
    assert not [p.name for p in tmp_path.iterdir() if p.name.startswith("m.kernel-12.py311.")]
    _file(tmp_path).save(key, {"library": b"\x02"})  # compiled again: saved and read back
    assert _file(tmp_path).load(key) == {"library": b"\x02"}
    _damage("empty data", f, tmp_path)
    assert _file(tmp_path).load(key) is None and capsys.readouterr().err == ""  # said once per process


def test_a_cache_that_cannot_be_written_is_said_once_not_raised(capsys, monkeypatch):
    from numba.core import caching

    from reeb_torch.stages import nms

    def full_disk(self, sig, data):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(caching.Cache, "save_overload", full_disk)  # what _KernelCache hands on to
    cache = nms._sorted_boxes._cache
    cache.save_overload(None, None)
    cache.save_overload(None, None)
    err = capsys.readouterr().err
    assert err.count("cannot write the kernel cache in") == 1 and "No space left on device" in err


# -- a real run on a damaged cache ---------------------------------------------------------------

RUN = ("import hashlib, torch\n"
       "from reeb_torch import ProposalGenerator, read_image\n"
       "x = read_image({sample!r})\n"
       "gen = ProposalGenerator()\n"
       "a, b = gen([x])[0], gen(x[None].float() / 255)[0]\n"
       "print(hashlib.sha256(b''.join(t.numpy().tobytes() for t in (a['boxes'], a['scores'], b['boxes']))).hexdigest())\n")


def _fill(cache: Path) -> None:
    """The kernels of this source in ``cache``: copied from this user's cache when that has
    them all (``warm-<hash>``), else compiled there by the run itself."""
    mine = _kernel_cache.cache_dir()
    marker = _kernel_cache.warm_marker()
    if mine is None or marker is None or not marker.exists():
        return
    for d in mine.glob(f"*-{_kernel_cache.kernels_hash()}"):
        if d.is_dir():
            shutil.copytree(d, cache / d.name)
    shutil.copy(marker, cache / marker.name)


@pytest.mark.slow
def test_a_damaged_cache_heals_itself_with_one_line_and_the_same_boxes(tmp_path):
    cache = tmp_path / "cache"
    cache.mkdir(mode=0o700)
    _fill(cache)
    env = {_kernel_cache.ENV: str(cache)}
    code = RUN.format(sample=str(SAMPLE))
    first = _run(code, env, timeout=900)
    assert first.returncode == 0, first.stderr[-3000:]
    boxes = first.stdout.split()[-1]
    # what a full disk, a copied home folder or a crash outside numba's atomic write leaves
    for p in sorted(cache.glob("nms-*/*.nbc")):
        p.write_bytes(p.read_bytes()[:1000])  # truncated
    for p in sorted(cache.glob("entropy-*/*.nbi")):
        p.write_bytes(hashlib.sha256(p.name.encode()).digest() * 8)  # overwritten
    for p in sorted(cache.glob("_radix-*/*.nbc"))[:1]:
        p.write_bytes(b"")
    healed = _run(code, env, timeout=900)
    assert healed.returncode == 0 and "Traceback" not in healed.stderr, healed.stderr[-3000:]
    assert healed.stdout.split()[-1] == boxes
    lines = [ln for ln in healed.stderr.splitlines() if "damaged kernel cache" in ln]
    assert len(lines) == 1 and str(cache) in lines[0], healed.stderr
    again = _run(code, env, timeout=900)  # healed: nothing said, the same boxes
    assert again.returncode == 0 and again.stdout.split()[-1] == boxes
    assert "damaged" not in again.stderr, again.stderr
