"""Faults as users meet them: nothing lost, no tracebacks.

Each test reproduces a fault as a user hit it: file names that are not UTF-8, the output
lock taken before anything is deleted, boxes past the image edge, a full disk, configs
that cannot be read, devices that cannot run, export rows that break the schema.
Subprocess tests use small 160×48 images and --top-k 100.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.runs.test_cli import FAST, good_folder, no_temp_files, read_jsonl, reeb


def _non_utf8_folder(d: Path, n: int) -> list[str]:
    """``n`` images, the middle one under a name with the byte 0xff (not UTF-8)."""
    paths = good_folder(d, n)
    bad = os.path.join(os.fsencode(d), b"frame_x\xff.png")
    os.rename(os.fsencode(paths[n // 2]), bad)
    return sorted(os.listdir(d))


@pytest.mark.slow
@pytest.mark.parametrize("ext", ["jsonl", "parquet"])
def test_a_file_name_that_is_not_utf8_gets_one_row_and_resumes(tmp_path, ext):
    if ext == "parquet":
        pytest.importorskip("pyarrow")
    n = 9
    _non_utf8_folder(tmp_path / "d", n)
    out = f"o.{ext}"
    r = reeb("propose", "d", "-o", out, "-b", "4", "-j", "0", *FAST, cwd=tmp_path, check_rc=0)
    assert "Traceback" not in r.stderr
    if ext == "jsonl":
        rows = read_jsonl(tmp_path / out)
        raw = (tmp_path / out).read_bytes()
        raw.decode("utf-8")  # the file is valid UTF-8
    else:
        import pyarrow.parquet as pq

        rows = pq.read_table(tmp_path / out).to_pylist()
    assert len(rows) == n, [r["image"] for r in rows]
    assert len({r["resolved"] for r in rows}) == n  # none dropped, none twice
    assert all(r["status"] == "ok" for r in rows)
    assert "d/frame_x\\xff.png" in {r["image"] for r in rows}  # the documented escaped form
    assert f"({n} rows)" in r.stderr
    r = reeb("propose", "d", "-o", out, "--resume", *FAST, cwd=tmp_path, check_rc=0)
    assert "Nothing to do" in r.stderr, r.stderr
    assert no_temp_files(tmp_path)


# -- Ray output folder: the lock before anything is deleted; unfinished files ----------------

def _parquet_result(path: Path, image: str) -> None:
    import pyarrow as pa
    import pyarrow.parquet as pq

    from reeb_torch.runs.output_files import ParquetWriter
    from reeb_torch.runs.rows import error_row

    pq.write_table(pa.Table.from_pylist([error_row(image, f"{image}: x", "cfg")],
                                        schema=ParquetWriter.schema()), path)


@pytest.mark.slow
def test_ray_overwrite_takes_the_lock_before_deleting(tmp_path):
    pytest.importorskip("ray")
    pytest.importorskip("pyarrow")
    from reeb_torch.runs.output_lock import lock_output

    good_folder(tmp_path / "imgs", 1)
    out = tmp_path / "out.parquet"
    out.mkdir()
    _parquet_result(out / "part-0.parquet", "old.png")
    with lock_output(out):  # another run holds the output
        r = reeb("propose", "imgs", "--engine", "ray", "-o", "out.parquet", "--overwrite", *FAST,
                 cwd=tmp_path, check_rc=2)
    assert "another reeb run" in r.stderr, r.stderr
    assert (out / "part-0.parquet").is_file()  # nothing deleted


def test_ray_resume_sets_aside_a_file_cut_short(tmp_path):
    pytest.importorskip("pyarrow")
    from reeb_torch.runs import distributed as D
    from reeb_torch.runs.output_files import read_result_dir

    out = tmp_path / "out.parquet"
    out.mkdir()
    _parquet_result(out / "a.parquet", "a.png")
    _parquet_result(out / "b.parquet", "b.png")
    data = (out / "b.parquet").read_bytes()
    (out / "b.parquet").write_bytes(data[: len(data) // 2])  # killed while Ray wrote it
    moved = D.set_aside_unfinished(out)
    assert [p.name for p in moved] == [".b.parquet.unfinished"]
    assert [r["image"] for r in read_result_dir(out)] == ["a.png"]  # readable for --resume again


# -- Ctrl-C in the first seconds -------------------------------------------------------------

def test_the_command_starts_without_importing_torch():
    import subprocess
    import sys

    code = "import sys, reeb_torch.runs.cli; print('torch' in sys.modules)"
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                       env=dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[2])))
    assert r.stdout.strip() == "False", r.stderr


@pytest.mark.parametrize("command", ["propose", "detect", "eval"])
def test_a_usage_error_comes_before_the_model_loads(command, tmp_path):
    """An empty input folder is refused before the generator, the detector or torchvision
    is imported (seconds a mistyped path should not cost)."""
    import subprocess
    import sys

    code = ("import sys\n"
            "from reeb_torch.runs.cli import main\n"
            "try:\n"
            f"    main([{command!r}, {str(tmp_path)!r}], standalone_mode=False)\n"
            "except Exception as e:\n"
            "    print(type(e).__name__)\n"
            "print(sorted(m for m in ('reeb_torch.generator', 'reeb_torch.detection', 'torchvision') "
            "if m in sys.modules))\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.stdout.splitlines()[-1] == "[]", r.stdout + r.stderr
    assert r.stdout.splitlines()[-2] in ("UsageProblem", "BadData"), r.stdout


def test_ctrl_c_while_torch_imports_exits_130_quietly(tmp_path):
    """SIGINT at the first thing the command does (where torch is imported)."""
    import subprocess
    import sys

    code = ("import os, signal, sys\n"
            "import reeb_torch.runs.common as c\n"
            "def hit(*a, **k):\n"
            "    os.kill(os.getpid(), signal.SIGINT)\n"
            "    import torch\n"
            "c.build_config = hit\n"
            "from reeb_torch.runs.cli import main\n"
            "main(['propose', 'x.png', '-o', 'o.jsonl'])\n")
    r = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True,
                       timeout=120, env=dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[2])))
    assert r.returncode == 130, r.stderr
    assert "Traceback" not in r.stderr and "Aborted" not in r.stderr, r.stderr


def _as_the_console_script(code: str, args: list[str], cwd: Path) -> subprocess.CompletedProcess:
    """Run ``code`` and then what the ``reeb`` console script runs (``main()`` reading
    ``sys.argv``), with ``args`` on the command line."""
    script = code + "from reeb_torch.runs.cli import main\nsys.exit(main())\n"
    return subprocess.run([sys.executable, "-c", script, *args], cwd=cwd, capture_output=True, text=True,
                          timeout=300, env=dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[2])))


@pytest.mark.parametrize("module", ["click", "numba"])
def test_ctrl_c_while_the_command_is_imported_exits_130_with_one_line(tmp_path, module):
    """SIGINT while Python imports the command (click, the settings' numba), the
    first ~0.5 s after reeb's own code starts."""
    hook = ("import os, signal, sys\n"
            "class Hit:\n"
            "    def find_spec(self, name, path=None, target=None):\n"
            f"        if name == {module!r}:\n"
            "            os.kill(os.getpid(), signal.SIGINT)\n"
            "sys.meta_path.insert(0, Hit())\n")
    r = _as_the_console_script(hook, ["propose", "x.png", "-o", "o.jsonl"], tmp_path)
    assert r.returncode == 130 and r.stderr == "interrupted\n", (r.returncode, r.stderr)


@pytest.mark.slow
@pytest.mark.parametrize("when", ["right after the command", "in the exit functions", "as Python shuts down"])
@pytest.mark.parametrize("rc", [0, 1])
def test_ctrl_c_after_the_run_has_finished_keeps_its_exit_code(tmp_path, when, rc):
    """SIGINT once the output is written (Python shutting down) keeps the run's exit code,
    never -2 (killed by the signal)."""
    good_folder(tmp_path / "d", 1)
    if rc:
        (tmp_path / "d" / "bad.png").write_bytes(b"not an image")
    if when == "right after the command":
        hook = ("import os, signal, sys\n"
                "from reeb_torch.runs import cli\n"
                "real = cli._Reeb.invoke\n"
                "def invoke(self, ctx):\n"
                "    try:\n"
                "        return real(self, ctx)\n"
                "    finally:\n"
                "        os.kill(os.getpid(), signal.SIGINT)\n"
                "cli._Reeb.invoke = invoke\n")
    elif when == "in the exit functions":  # the last one (registered first)
        hook = "import atexit, os, signal, sys\natexit.register(os.kill, os.getpid(), signal.SIGINT)\n"
    else:  # as the modules are torn down, after the exit functions: Python runs no handler then
        hook = ("import os, signal, sys\n"
                "class Late:\n"
                "    def __del__(self, kill=os.kill, pid=os.getpid(), sig=signal.SIGINT):\n"
                "        kill(pid, sig)\n"
                "late = Late()\n")
    r = _as_the_console_script(hook, ["propose", "d", "-o", "o.jsonl", "-q", *FAST], tmp_path)
    assert r.returncode == rc, (r.returncode, r.stderr)
    assert "Traceback" not in r.stderr and "KeyboardInterrupt" not in r.stderr and "Aborted" not in r.stderr, r.stderr
    assert len(read_jsonl(tmp_path / "o.jsonl")) == 1 + rc


# -- a full disk, a config nested too deeply -------------------------------------------------

@pytest.mark.parametrize("where", ["_write", "fsync"])
def test_a_full_disk_is_one_line_naming_the_output(tmp_path, monkeypatch, where):
    import errno

    from click.testing import CliRunner

    from reeb_torch.runs import output_files
    from reeb_torch.runs.cli import main

    good_folder(tmp_path / "imgs", 2)
    out = tmp_path / "o.jsonl"
    out.write_text("old\n")

    def full(self, *a):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    if where == "fsync":  # the disk fills as the file is closed: the file is closed all the same
        opened = []
        real_open = open
        monkeypatch.setattr(output_files, "open", lambda *a, **k: opened.append(real_open(*a, **k)) or opened[-1], raising=False)
        monkeypatch.setattr(output_files.os, "fsync", lambda fd: full(None))
    else:
        monkeypatch.setattr(output_files.JsonlWriter, where, full)
    monkeypatch.chdir(tmp_path)
    res = CliRunner().invoke(main, ["propose", "imgs", "-o", "o.jsonl", "--overwrite", "-j", "0", "-q", *FAST])
    assert res.exit_code == 1, res.output
    assert res.exception is None or isinstance(res.exception, SystemExit), repr(res.exception)
    lines = res.output.strip().splitlines()
    assert len(lines) == 1 and "o.jsonl: cannot" in lines[0], res.output
    assert "the results (No space left on device)" in lines[0], res.output
    assert out.read_text() == "old\n"  # the atomic write held
    assert no_temp_files(tmp_path)
    if where == "fsync":
        assert opened and all(f.closed for f in opened)


@pytest.mark.parametrize("where", ["config", "set"])
def test_a_deeply_nested_config_is_a_usage_error(tmp_path, where):
    deep = "[" * 200_000 + "]" * 200_000
    if where == "config":
        (tmp_path / "c.json").write_text(deep)
        args = ["--config", "c.json"]
    else:
        args = ["--set", f"object_templates={'[' * 5000 + ']' * 5000}"]
    good_folder(tmp_path / "imgs", 1)
    r = reeb("propose", "imgs", *args, *FAST, cwd=tmp_path, check_rc=2)
    assert "Traceback" not in r.stderr and "nested too deeply" in r.stderr, r.stderr


# -- devices that cannot run -------------------------------------------------------------------

@pytest.mark.parametrize("name", ["meta", "cpu:5", "mps", "cuda:99"])
def test_a_device_that_cannot_run_is_refused_before_work(name):
    import click
    import torch

    from reeb_torch.runs.common import resolve_device

    if name == "mps" and getattr(torch.backends, "mps", None) and torch.backends.mps.is_available():
        pytest.skip("this machine has MPS")
    with pytest.raises(click.BadParameter):
        resolve_device(name)


def test_a_bad_device_on_the_command_line_is_exit_2(tmp_path):
    good_folder(tmp_path / "imgs", 1)
    r = reeb("propose", "imgs", "-o", "o.jsonl", "--top-k", "100", "--device", "meta", cwd=tmp_path, check_rc=2)
    assert "meta" in r.stderr and not (tmp_path / "o.jsonl").exists()


# -- what a folder scan skips is named; a file named on the command line gets its row ---------

@pytest.mark.slow
def test_skipped_entries_are_named_and_named_files_get_error_rows(tmp_path):
    good_folder(tmp_path / "d", 1)
    (tmp_path / "d" / "broken.png").symlink_to(tmp_path / "nowhere.png")
    (tmp_path / "d" / "x.png").mkdir()
    (tmp_path / "gone.png").symlink_to(tmp_path / "nowhere.png")
    r = reeb("propose", "d", "gone.png", "-o", "o.jsonl", "-q", *FAST, cwd=tmp_path, check_rc=1)
    summary = r.stderr
    assert "broken.png: skipped, a broken symbolic link" in summary, summary
    assert "x.png: skipped, a folder named like an image" in summary, summary
    rows = read_jsonl(tmp_path / "o.jsonl")
    assert [row["image"] for row in rows] == ["d/frame_000.png", "gone.png"]
    assert rows[1]["status"].startswith("error: gone.png"), rows[1]


# -- reeb export checks rows against the schema ------------------------------------------------

@pytest.mark.parametrize("change, words", [
    (dict(boxes=[[1.0, 2.0, 3.0]], scores=[0.5]), "box 0"),
    (dict(boxes=None), "'boxes' is null"),
    (dict(scores=[0.5, 0.4]), "1 boxes but 2 scores"),
])
def test_export_names_the_row_that_breaks_the_schema(tmp_path, change, words):
    from click.testing import CliRunner

    from reeb_torch.runs.cli import main
    from reeb_torch.runs.rows import FORMAT_VERSION

    good = dict(format_version=FORMAT_VERSION, image="a.png", resolved="/a.png", width=10, height=10,
                boxes=[[0.0, 0.0, 5.0, 5.0]], scores=[0.9], status="ok", config="c")
    bad = dict(good, image="b.png", resolved="/b.png", **change)
    (tmp_path / "r.jsonl").write_text(json.dumps(good) + "\n" + json.dumps(bad) + "\n")
    res = CliRunner().invoke(main, ["export", str(tmp_path / "r.jsonl"), "-o", str(tmp_path / "p.pkl")])
    assert res.exit_code == 2, res.output
    assert "row 2 (b.png)" in res.output and words in res.output, res.output
    assert not (tmp_path / "p.pkl").exists()


def test_export_of_a_broken_parquet_file_does_not_speak_of_resume(tmp_path):
    pytest.importorskip("pyarrow")
    from click.testing import CliRunner

    from reeb_torch.runs.cli import main

    (tmp_path / "r.parquet").write_bytes(b"PAR1 not really")
    res = CliRunner().invoke(main, ["export", str(tmp_path / "r.parquet"), "-o", str(tmp_path / "p.pkl")])
    assert res.exit_code == 2 and "cannot read the results" in res.output, res.output
    assert "--resume" not in res.output


# -- output names: any legal name; a symbolic link writes its target ---------------------------

@pytest.mark.slow
def test_a_long_legal_output_name_works(tmp_path):
    good_folder(tmp_path / "d", 1)
    name = "p" * 240 + ".jsonl"  # 246 characters: legal, but .NAME.XXXXXXXX.tmp is not
    reeb("propose", "d", "-o", name, "-q", *FAST, cwd=tmp_path, check_rc=0)
    assert len(read_jsonl(tmp_path / name)) == 1
    assert no_temp_files(tmp_path) and not [p for p in tmp_path.iterdir() if p.name.endswith(".reeb-lock")]


@pytest.mark.slow
def test_an_output_symlink_writes_its_target_and_stays_a_link(tmp_path):
    from reeb_torch.runs.output_lock import lock_output

    good_folder(tmp_path / "d", 1)
    (tmp_path / "real").mkdir()
    target = tmp_path / "real" / "t.jsonl"
    (tmp_path / "link.jsonl").symlink_to(target)
    with lock_output(target):  # the lock protects the target, also through the link
        r = reeb("propose", "d", "-o", "link.jsonl", *FAST, cwd=tmp_path, check_rc=2)
        assert "another reeb run" in r.stderr, r.stderr
    reeb("propose", "d", "-o", "link.jsonl", "-q", *FAST, cwd=tmp_path, check_rc=0)
    assert (tmp_path / "link.jsonl").is_symlink()
    assert len(read_jsonl(target)) == 1


# -- settings that give no proposals are warned about once -------------------------------------

def test_a_config_that_gives_no_proposals_warns_once():
    import warnings

    import torch

    from reeb_torch import ProposalGenerator

    gen = ProposalGenerator(entropy_bins=65536, top_k=100, candidates_per_region=600)
    torch.manual_seed(0)
    x = torch.rand(2, 3, 64, 160)
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        out = gen(x)
        gen(x)
    assert all(len(r["boxes"]) == 0 for r in out)
    msgs = [str(w.message) for w in seen if issubclass(w.category, RuntimeWarning)]
    assert len(msgs) == 1 and "no proposals" in msgs[0] and "share" in msgs[0], msgs


def test_the_two_halves_of_a_cpu_batch_warn_once_between_them():
    """Both halves of a CPU batch may find an empty image at the same moment: one warns."""
    import threading
    import warnings

    import torch

    from reeb_torch import ProposalGenerator

    gen = ProposalGenerator(top_k=100)
    share, edges = torch.zeros(1, 4), torch.ones(1, 8, 8)
    start = threading.Barrier(8)

    def half() -> None:
        start.wait()
        gen._warn_empty((64, 160), 10, share, edges, [0])

    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        threads = [threading.Thread(target=half) for _ in range(8)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    msgs = [str(w.message) for w in seen if issubclass(w.category, RuntimeWarning)]
    assert len(msgs) == 1 and "share of the budget is 0" in msgs[0], msgs


# -- -q is quiet --------------------------------------------------------------------------------

@pytest.mark.slow
def test_quiet_drops_the_decoders_own_error_lines(tmp_path):
    good_folder(tmp_path / "d", 1)
    data = (tmp_path / "d" / "frame_000.png").read_bytes()
    (tmp_path / "d" / "cut.png").write_bytes(data[:20] + b"\0" * 10 + data[30:])  # a bad IHDR CRC
    (tmp_path / "d" / "half.png").write_bytes(data[: len(data) // 2])  # cut short
    r = reeb("propose", "d", "-o", "o.jsonl", "-q", "-j", "0", *FAST, cwd=tmp_path, check_rc=1)
    assert "libpng" not in r.stderr and "WARN" not in r.stderr, r.stderr
    assert "cut.png" in r.stderr  # still named in the summary
