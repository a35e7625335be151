"""The `reeb` command line, driven in a subprocess as a user would, checking what it writes.

Small images (160×48, cut from the bundled KITTI frame) and --top-k 100 keep this file
fast; one test runs the full-size bundled sample as the README does.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from tests.conftest import DATA

REPO = Path(__file__).resolve().parents[2]
SAMPLE = REPO / "examples" / "data" / "kitti_000001.png"
SAMPLE_LABEL = REPO / "examples" / "data" / "kitti_000001.txt"
FAST = ["--top-k", "100", "--device", "cpu"]


def reeb(*args, cwd, timeout=120, check_rc=None) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    r = subprocess.run([sys.executable, "-m", "reeb_torch.runs.cli", *map(str, args)], cwd=cwd,
                       capture_output=True, text=True, timeout=timeout, env=env)
    if check_rc is not None:
        assert r.returncode == check_rc, f"rc={r.returncode}\nstdout:\n{r.stdout}\nstderr:\n{r.stderr}"
    return r


def small_frame(scale: tuple[int, int] = (160, 48)) -> np.ndarray:
    img = cv2.imread(str(SAMPLE))
    return cv2.resize(img, scale, interpolation=cv2.INTER_AREA)


def good_folder(d: Path, n: int) -> list[Path]:
    d.mkdir(parents=True, exist_ok=True)
    base = small_frame()
    paths = []
    for i in range(n):
        p = d / f"frame_{i:03d}.png"
        cv2.imwrite(str(p), np.roll(base, 7 * i, axis=1))  # distinct images of one size
        paths.append(p)
    return paths


def read_jsonl(p: Path) -> list[dict]:
    return [json.loads(line) for line in p.read_text().splitlines() if line.strip()]


def no_temp_files(d: Path) -> bool:
    return not [p for p in d.iterdir() if p.name.startswith(".") and p.name.endswith(".tmp")]


def check_ok_row(row: dict, w: int, h: int, k: int = 100) -> None:
    assert row["status"] == "ok"
    assert (row["width"], row["height"]) == (w, h)
    boxes = np.asarray(row["boxes"], dtype=float).reshape(-1, 4)
    scores = np.asarray(row["scores"], dtype=float)
    assert 0 < len(boxes) <= k and len(scores) == len(boxes)
    assert (boxes[:, 0] < boxes[:, 2]).all() and (boxes[:, 1] < boxes[:, 3]).all()
    assert (boxes[:, :2] >= 0).all() and (boxes[:, 2] <= w).all() and (boxes[:, 3] <= h).all()
    assert (np.diff(scores) <= 1e-6).all()  # ranked best first
    assert isinstance(row["config"], str) and row["config"]


# -- the README's first command ----------------------------------------------------------

@pytest.mark.slow
def test_propose_without_arguments_uses_the_bundled_sample(tmp_path):
    r = reeb("propose", "--top-k", "100", cwd=tmp_path, check_rc=0)
    assert "kitti_000001.png" in r.stdout and "rank" in r.stdout and "hint" in r.stdout  # class hints column
    assert len([l for l in r.stdout.splitlines() if l.strip()[:1].isdigit()]) == 10  # top-10 table
    png = tmp_path / "reeb_proposals.png"
    img = cv2.imread(str(png))
    assert img is not None and img.shape[1] == 1242 and img.shape[0] > 375  # title band on top
    assert "1 ok, 0 failed" in r.stderr and "ms/img" in r.stderr


@pytest.mark.slow
def test_show_writes_the_explanatory_picture(tmp_path):
    # a half-size frame with its labels scaled to match: the show picture with ground truth
    img = cv2.resize(cv2.imread(str(SAMPLE)), (621, 187), interpolation=cv2.INTER_AREA)
    cv2.imwrite(str(tmp_path / "frame.png"), img)
    lines = []
    for line in SAMPLE_LABEL.read_text().splitlines():
        f = line.split()
        f[4:8] = [f"{float(v) / 2:.2f}" for v in f[4:8]]
        lines.append(" ".join(f))
    (tmp_path / "frame_label.txt").write_text("\n".join(lines) + "\n")
    r = reeb("show", "frame.png", "--label", "frame_label.txt", "--top", "15", "--out", "pic.png",
             *FAST, cwd=tmp_path, check_rc=0)
    pic = cv2.imread(str(tmp_path / "pic.png"))
    assert pic is not None and pic.shape[0] > 3 * 187 and pic.shape[1] >= 1000
    assert "regions: R1 H=" in r.stdout
    assert "Truck" in r.stdout and "Car" in r.stdout and "DontCare" not in r.stdout


# -- output formats ----------------------------------------------------------------------

@pytest.mark.slow
def test_jsonl_and_parquet_outputs(tmp_path):
    paths = good_folder(tmp_path / "imgs", 2)
    reeb("propose", "imgs", "--out", "p.jsonl", "--viz", "viz", *FAST, cwd=tmp_path, check_rc=0)
    rows = read_jsonl(tmp_path / "p.jsonl")
    assert sorted(r["image"] for r in rows) == sorted(str(p.relative_to(tmp_path)) for p in paths)
    assert set(rows[0]) == {"format_version", "image", "resolved", "width", "height", "boxes",
                            "scores", "labels", "status", "config"}
    for row in rows:
        check_ok_row(row, 160, 48)
    assert sorted(p.name for p in (tmp_path / "viz").iterdir()) == ["frame_000.png", "frame_001.png"]

    import pyarrow.parquet as pq

    reeb("propose", "imgs/*.png", "--out", "p.parquet", *FAST, cwd=tmp_path, check_rc=0)
    table = pq.read_table(tmp_path / "p.parquet")
    assert set(table.column_names) == set(rows[0])
    prow = {r["image"]: r for r in table.to_pylist()}
    for row in rows:  # same proposals and class hints in both formats (JSONL rounds to 0.01 px)
        check_ok_row(prow[row["image"]], 160, 48)
        assert prow[row["image"]]["labels"] == row["labels"] and len(row["labels"]) == len(row["boxes"])
        np.testing.assert_allclose(np.asarray(prow[row["image"]]["boxes"]), np.asarray(row["boxes"]),
                                   atol=0.006)
    assert no_temp_files(tmp_path)


# -- bad input ---------------------------------------------------------------------------

@pytest.mark.slow
def test_bad_files_are_reported_and_do_not_stop_the_run(tmp_path):
    d = tmp_path / "mixed"
    d.mkdir()
    base = small_frame()
    cv2.imwrite(str(d / "good.png"), base)
    cv2.imwrite(str(d / "grey.png"), cv2.cvtColor(base, cv2.COLOR_BGR2GRAY))
    cv2.imwrite(str(d / "rgba.png"), cv2.cvtColor(base, cv2.COLOR_BGR2BGRA))
    cv2.imwrite(str(d / "deep16.png"), base.astype(np.uint16) * 257)
    cv2.imwrite(str(d / "tiny.png"), base[:8, :8])
    data = (d / "good.png").read_bytes()
    (d / "truncated.png").write_bytes(data[: len(data) // 2])
    (d / "corrupt.png").write_bytes(data[:64] + bytes(range(256)) * 8)
    (d / "fake.jpg").write_text("not an image")
    (d / "notes.txt").write_text("labels are not images")  # in a folder: ignored
    (tmp_path / "readme.txt").write_text("named explicitly: reported")

    r = reeb("propose", "mixed", "readme.txt", "--out", "out.jsonl", *FAST, cwd=tmp_path, check_rc=1)
    rows = {Path(r["image"]).name: r for r in read_jsonl(tmp_path / "out.jsonl")}
    assert set(rows) == {"good.png", "grey.png", "rgba.png", "deep16.png", "tiny.png",
                         "truncated.png", "corrupt.png", "fake.jpg", "readme.txt"}
    for name in ("good.png", "grey.png", "rgba.png", "deep16.png"):
        check_ok_row(rows[name], 160, 48)
    expected = {"tiny.png": "8×8 px, smaller than the smallest window",
                "truncated.png": "corrupt or truncated PNG", "corrupt.png": "corrupt or truncated PNG",
                "fake.jpg": "not an image file", "readme.txt": "not an image file"}
    for name, reason in expected.items():
        status = rows[name]["status"]
        assert status.startswith("error: ") and name in status and reason in status, status
        assert rows[name]["boxes"] == []
        assert any(name in line and reason in line for line in r.stderr.splitlines()), r.stderr
    assert "4 ok, 5 failed" in r.stderr and "failed (5):" in r.stderr
    # grey and 16-bit copies of one image give the proposals of the colour original
    # (the grey one differs: the colour is gone, so only its sizes are checked above)
    assert rows["deep16.png"]["boxes"] == rows["good.png"]["boxes"]
    assert rows["rgba.png"]["boxes"] == rows["good.png"]["boxes"]


def test_empty_folder_is_a_usage_error(tmp_path):
    (tmp_path / "empty").mkdir()
    (tmp_path / "empty" / "labels.txt").write_text("x")
    r = reeb("propose", "empty", cwd=tmp_path, check_rc=2)
    assert "no images" in r.stderr and "empty" in r.stderr
    assert len(r.stderr.strip().splitlines()) <= 2


@pytest.mark.slow
def test_unwritable_output_fails_before_processing(tmp_path):
    good_folder(tmp_path / "imgs", 1)
    (tmp_path / "a_file").write_text("x")
    r = reeb("propose", "imgs", "--out", "a_file/out.jsonl", *FAST, cwd=tmp_path, check_rc=2)
    assert "a_file/out.jsonl" in r.stderr and "does not exist" in r.stderr, r.stderr
    assert len(r.stderr.strip().splitlines()) == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a_file", "imgs"]  # nothing written
    # (a folder as --out, an unknown extension: test_output_checks_and_atomic_writer)


# -- interruption, atomic writes, resume -------------------------------------------------

def _start(args, cwd) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "reeb_torch.runs.cli", *args], cwd=cwd,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _wait_for_rows(d: Path, name: str, proc: subprocess.Popen, rows: int = 1,
                   timeout: float = 90) -> Path:
    """The hidden temporary output once it holds at least ``rows`` rows."""
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        assert proc.poll() is None, proc.communicate()
        for p in d.iterdir():
            if p.name.startswith(f".{name}.") and p.name.endswith(".tmp"):
                try:
                    if p.read_bytes().count(b"\n") >= rows:
                        return p
                except FileNotFoundError:
                    pass
        time.sleep(0.02)
    raise AssertionError("no row was written in time")


def _assert_workers_hold_no_pipe(proc: subprocess.Popen) -> None:
    """The decoding workers (forked) hold neither of the run's output pipes: a caller
    that kills the run reads to their end at once, not when the orphaned workers exit (CI
    once waited more than 30 s for that)."""
    children = Path(f"/proc/{proc.pid}/task/{proc.pid}/children")
    if not children.exists():  # not Linux
        return
    ours = {os.readlink(f"/proc/{proc.pid}/fd/{fd}") for fd in (1, 2)}
    assert all(o.startswith("pipe:") for o in ours)
    kids = children.read_text().split()
    assert kids  # the run decodes in workers
    for k in kids:
        try:
            held = {os.readlink(f"/proc/{k}/fd/{fd}") for fd in (1, 2)}
        except FileNotFoundError:  # that worker has finished already
            continue
        assert not held & ours, (k, held)


@pytest.mark.slow
def test_interrupt_kill_and_resume(tmp_path):
    n = 60  # enough work (several seconds) that the signals land mid-run
    paths = good_folder(tmp_path / "imgs", n)
    args = ["propose", "imgs", "--out", "out.jsonl", "--batch-size", "1", *FAST]

    # Ctrl-C: what is done is saved (atomically), exit 130 with a hint to resume
    proc = _start(args, tmp_path)
    _wait_for_rows(tmp_path, "out.jsonl", proc)
    assert not (tmp_path / "out.jsonl").exists()  # nothing at the final path until done
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    assert "interrupted" in err and "--resume" in err
    saved_text = (tmp_path / "out.jsonl").read_text()
    saved = read_jsonl(tmp_path / "out.jsonl")
    assert 1 <= len(saved) < n
    assert no_temp_files(tmp_path)

    # an existing output is never replaced by accident, nor mixed with other settings
    r = reeb(*args, cwd=tmp_path, check_rc=2)
    assert "--resume" in r.stderr and "--overwrite" in r.stderr
    r = reeb(*args[:-len(FAST)], "--resume", "--top-k", "50", cwd=tmp_path, check_rc=2)
    assert "different settings" in r.stderr

    # kill -9 while resuming: no chance to clean up, the output is still the old one
    proc = _start([*args, "--resume"], tmp_path)
    tmp = _wait_for_rows(tmp_path, "out.jsonl", proc, rows=len(saved) + 1)
    _assert_workers_hold_no_pipe(proc)
    proc.kill()
    proc.communicate(timeout=30)
    assert (tmp_path / "out.jsonl").read_text() == saved_text
    tmp.unlink()  # the partial run is only in the hidden temporary file

    # --resume skips what is done and finishes
    r = reeb(*args, "--resume", cwd=tmp_path, check_rc=0)
    assert f"{n - len(saved)} to do" in r.stderr
    assert f": {n - len(saved)} ok, 0 failed" in r.stderr
    rows = read_jsonl(tmp_path / "out.jsonl")
    assert rows[: len(saved)] == saved  # earlier rows kept as they were
    assert sorted(r["image"] for r in rows) == sorted(str(p.relative_to(tmp_path)) for p in paths)
    assert all(r["status"] == "ok" for r in rows)
    assert no_temp_files(tmp_path)


# -- the pieces behind the commands, in process (fast) -----------------------------------

def test_find_images_rules(tmp_path):
    from reeb_torch.runs.inputs import NoImagesError, find_images

    for name in ("f10.png", "f2.png", "f1.jpg", "labels.txt"):
        (tmp_path / name).write_bytes(b"x")
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "f3.png").write_bytes(b"x")
    (tmp_path / "none").mkdir()
    images, notes = find_images([tmp_path, tmp_path / "f2.png", tmp_path / "none"])
    assert [p.name for p in images] == ["f1.jpg", "f2.png", "f10.png"]  # natural order, no dupes
    assert len(notes) == 2 and "none" in notes[0] and "--recursive" in notes[0]
    assert notes[1] == f"skipped 1 path, the same file as another: {tmp_path / 'f2.png'} (= {tmp_path / 'f2.png'})"
    images, _ = find_images([tmp_path], recursive=True)
    assert "f3.png" in [p.name for p in images]
    images, _ = find_images([str(tmp_path / "f1*")])
    assert [p.name for p in images] == ["f1.jpg", "f10.png"]
    with pytest.raises(NoImagesError, match="no such file"):
        find_images([tmp_path / "missing.png"])
    with pytest.raises(NoImagesError, match="matched no image"):
        find_images([str(tmp_path / "*.gif")])


def test_output_checks_and_atomic_writer(tmp_path):
    from reeb_torch.runs.output_files import OutputError, check_output, open_writer, read_results

    with pytest.raises(OutputError, match="unknown output format"):
        check_output(tmp_path / "out.csv")
    with pytest.raises(OutputError, match="does not exist"):
        check_output(tmp_path / "no" / "out.jsonl")
    with pytest.raises(OutputError, match="is a folder"):
        check_output(tmp_path)
    out = tmp_path / "out.jsonl"
    out.write_text('{"image": "old.png", "status": "ok"}\n')
    w = open_writer(out)
    w.write([{"image": "a.png", "status": "ok"}])
    w.discard()  # an aborted run: the old file stays
    assert read_results(out)[0] == [{"image": "old.png", "status": "ok"}]
    w = open_writer(out)
    w.write([{"image": "b.png", "status": "ok"}])
    assert read_results(out)[0][0]["image"] == "old.png"  # not replaced before commit
    w.commit()
    with open(out, "a") as f:
        f.write('{"image": "c.png"\n')  # a damaged line is skipped with a note, not fatal
    rows, problems = read_results(out)
    assert [r["image"] for r in rows] == ["b.png"] and len(problems) == 1
    assert no_temp_files(tmp_path)


def test_size_batches_groups_equal_sizes():
    import torch

    from reeb_torch.runs.decoding import Decoded, size_batches

    def item(i, h, w):
        return Decoded(i, f"{i}.png", image=torch.zeros(3, h, w, dtype=torch.uint8))

    items = [item(0, 20, 30), item(1, 40, 30), Decoded(2, "2.png", error="2.png: bad"),
             item(3, 20, 30), item(4, 20, 30), item(5, 40, 30)]
    batches = [[it.index for it in b] for b in size_batches(items, 2)]
    assert batches == [[2], [0, 3], [1, 5], [4]]


KITTI = DATA / "kitti"


@pytest.mark.slow
@pytest.mark.kitti
@pytest.mark.skipif(not (KITTI / "images").is_dir(), reason=f"needs {KITTI} (set $REEB_DATA)")
def test_eval_runs_table3(tmp_path):
    r = reeb("eval", KITTI, "--limit", "1", "--methods", "reeb-default", "--out", "t3",
             "--batch", "0", cwd=tmp_path, check_rc=0)  # --batch: passed on to table3.py
    assert "IoU 0.7" in r.stdout
    assert (tmp_path / "t3" / "table3.json").is_file()
    assert list((tmp_path / "t3").glob("*.png"))
