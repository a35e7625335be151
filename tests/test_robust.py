"""Second break-it round (issue 23): nothing lost, no tracebacks.

Each test reproduces a fault as a user hit it: file names that are not UTF-8, the output
lock taken before anything is deleted, boxes past the image edge, a full disk, configs
that cannot be read, devices that cannot run, export rows that break the schema.
Subprocess tests use small 160×48 images and --top-k 100.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import cv2
import numpy as np
import pytest

from test_cli import FAST, good_folder, no_temp_files, read_jsonl, reeb


def _non_utf8_folder(d: Path, n: int) -> list[str]:
    """``n`` images, the middle one under a name with the byte 0xff (not UTF-8)."""
    paths = good_folder(d, n)
    bad = os.path.join(os.fsencode(d), b"frame_x\xff.png")
    os.rename(os.fsencode(paths[n // 2]), bad)
    return sorted(os.listdir(d))


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
