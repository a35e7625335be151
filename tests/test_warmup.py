"""The one-time compile: the kernels' cache folder, the notice, warmup()."""

from __future__ import annotations

import importlib
import pkgutil

import numba
import pytest
import torch

import reeb_torch
from reeb_torch import ProposalGenerator, ReebConfig, generator, warmup
from reeb_torch.config import TRAINING_FREE
from reeb_torch import _warm
from reeb_torch.stages import _kernel_cache


def _dispatchers() -> dict[str, object]:
    mods = ["reeb_torch._checks", "reeb_torch.ranker.features", "reeb_torch.ranker.prefilter"]
    mods += [f"reeb_torch.stages.{m.name}" for m in pkgutil.iter_modules(reeb_torch.stages.__path__)]
    out = {}
    for name in mods:
        mod = importlib.import_module(name)
        for attr, obj in vars(mod).items():
            if isinstance(obj, numba.core.registry.CPUDispatcher):
                out[f"{name}.{attr}"] = obj
    return out


def _signatures() -> dict[str, int]:
    return {k: len(d.signatures) for k, d in _dispatchers().items()}


def test_the_package_kernels_are_cached_in_the_per_user_folder_by_source_hash():
    # by the hash of every kernel source: a kernel's cache entry holds the kernels it calls
    # from other files, so a change to any of them must move every entry
    root = _kernel_cache.cache_dir()
    if root is None:
        pytest.skip("REEB_TORCH_CACHE_DIR turns the package cache off")
    found = 0
    for name, d in _dispatchers().items():
        if d._cache is None or not hasattr(d._cache, "_cache_path"):
            continue
        path = d._cache._cache_path
        assert path.startswith(str(root)), f"{name} is cached in {path}, not under {root}"
        assert path.endswith(f"-{_kernel_cache.kernels_hash()}"), f"{name} is cached in {path}"
        found += 1
    assert found >= 8


def test_warmup_compiles_what_the_default_runs_on_a_real_frame(sample_image):
    warmup(quiet=True)
    before = _signatures()
    ProposalGenerator()([sample_image])
    ProposalGenerator()(sample_image[None].float() / 255)
    after = _signatures()
    new = {k: after[k] - before.get(k, 0) for k in after if after[k] != before.get(k, 0)}
    assert not new, f"compiled after warmup(): {new}"


def test_first_call_reports_its_warm_up_apart(sample_image):
    cfg = ReebConfig(top_k=123)
    generator._WARM.discard(generator._kernel_key(cfg))  # as if this process had not run it yet
    gen = ProposalGenerator(cfg)
    gen([sample_image])
    assert gen.compile_s > 0
    again = ProposalGenerator(cfg)
    again([sample_image])
    assert again.compile_s == 0.0
    other = ProposalGenerator(cfg.replace(top_k=77, alpha=0.3))  # other numbers: the same kernels
    other([sample_image])
    assert other.compile_s == 0.0
    switched = ProposalGenerator(cfg.replace(**TRAINING_FREE, thin_edges=False))  # another switch: warms up
    generator._WARM.discard(generator._kernel_key(switched.config))
    switched([sample_image])
    assert switched.compile_s > 0


@pytest.mark.slow
def test_notice_only_while_not_cached(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv(_kernel_cache.ENV, str(tmp_path))
    assert _kernel_cache.cache_dir() == tmp_path
    warmup(quiet=False)
    err = capsys.readouterr().err
    assert "compiling kernels once for this install" in err and "kernels compiled in" in err
    assert _kernel_cache.warm_marker().exists()
    warmup(quiet=False)
    assert "compiling" not in capsys.readouterr().err


def test_cache_can_be_turned_off(monkeypatch):
    monkeypatch.setenv(_kernel_cache.ENV, "off")
    assert _kernel_cache.cache_dir() is None and _kernel_cache.warm_marker() is None


def test_warm_picture_is_deterministic_uint8():
    a, b = _warm.warm_picture(), _warm.warm_picture()
    assert a.dtype == torch.uint8 and a.shape == (3, 160, 480) and torch.equal(a, b)


def test_reeb_warmup_command(tmp_path, monkeypatch):
    from click.testing import CliRunner

    from reeb_torch.runs.cli import main

    res = CliRunner().invoke(main, ["warmup", "--preset", "nope"])
    assert res.exit_code == 2 and "unknown preset" in res.output
    res = CliRunner().invoke(main, ["warmup"])
    assert res.exit_code == 0 and "kernels ready in" in res.output


def test_the_helper_process_compiles_only_what_the_warm_up_runs(monkeypatch):
    # its kernels must be cached under the signatures the warm-up itself asks for, else the
    # warm-up would find nothing and compile them again
    from reeb_torch.stages import nms, scoring

    warmup(quiet=True)
    kernels = _dispatchers()
    before = {k: set(map(str, d.signatures)) for k, d in kernels.items()}
    called = set()
    for mod, name in ((scoring, "_score_grid_kernel"), (scoring, "_select_kernel"), (nms, "_grid_nms_sorted"),
                      (nms, "_sorted_boxes")):
        kernel = getattr(mod, name)
        monkeypatch.setattr(mod, name, lambda *a, _k=kernel, _n=name: (called.add(_n), _k(*a))[1])
    _warm.compile_helper_part()
    assert called == {"_score_grid_kernel", "_select_kernel", "_grid_nms_sorted", "_sorted_boxes"}
    after = {k: set(map(str, d.signatures)) for k, d in kernels.items()}
    assert {k: after[k] - before[k] for k in after if after[k] - before[k]} == {}


def test_the_helper_process_starts_and_is_stopped(monkeypatch):
    import subprocess

    monkeypatch.setenv(_warm.HELPER_ENV, "1")  # inside the helper (or turned off): none of its own
    assert _warm.start_helper() is None
    _warm.stop_helper(None)
    monkeypatch.delenv(_warm.HELPER_ENV)
    monkeypatch.setattr(_warm.os, "cpu_count", lambda: 1)
    assert _warm.start_helper() is None  # one core: nothing to run it on
    monkeypatch.setattr(_warm.os, "cpu_count", lambda: 2)
    helper = _warm.start_helper()
    assert isinstance(helper, subprocess.Popen)
    _warm.stop_helper(helper)  # the warm-up ended first: the helper is ended, not waited for
    assert helper.returncode is not None


def test_the_compiled_path_does_not_import_torchvision():
    # importing torchvision costs ~2.7 s (torch._dynamo) at every start; only the
    # torchvision NMS path (CUDA) needs it
    import os
    import subprocess
    import sys

    code = ("import sys, torch; from reeb_torch import ProposalGenerator; "
            "ProposalGenerator()([torch.zeros(3, 64, 200, dtype=torch.uint8)]); "
            "print('torchvision' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300,
                         env={**os.environ, _warm.HELPER_ENV: "1"})
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip().splitlines()[-1] == "False"


def test_gc_is_paused_while_compiling_and_restored_after():
    import gc

    assert gc.isenabled()
    with _warm.gc_paused():
        assert not gc.isenabled()
    assert gc.isenabled()
    gc.disable()  # a caller that keeps it off: left off
    try:
        with _warm.gc_paused():
            pass
        assert not gc.isenabled()
    finally:
        gc.enable()
    with pytest.raises(RuntimeError), _warm.gc_paused():
        raise RuntimeError("a failed warm-up")
    assert gc.isenabled()
