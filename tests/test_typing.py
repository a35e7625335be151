"""The annotations users' type checkers read (``reeb_torch/py.typed``): the README's code
type-checks with the types it says (``tests/typing/user_code.py``), and mistakes are
caught (``tests/typing/misuse.py``), as mypy sees the installed package (its own modules
followed silently: a user sees only their own code's errors); the package itself checks
clean. The lazily imported top-level names are declared for type checkers too."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

HERE = Path(__file__).resolve().parent
PACKAGE = HERE.parent / "reeb_torch"


def _mypy(path: Path, cache: Path) -> subprocess.CompletedProcess:
    pytest.importorskip("mypy", reason="mypy (in the dev extra) checks the public annotations")
    return subprocess.run([sys.executable, "-m", "mypy", "--follow-imports=silent", "--ignore-missing-imports",
                           "--no-color-output", "--cache-dir", str(cache), str(path)],
                          capture_output=True, text=True, cwd=HERE.parent, timeout=600)


@pytest.fixture(scope="module")
def cache(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("mypy_cache")


@pytest.mark.slow
def test_the_readme_code_type_checks_with_the_types_it_says(cache):
    r = _mypy(HERE / "typing" / "user_code.py", cache)
    assert r.returncode == 0, r.stdout + r.stderr


def test_mistakes_are_caught_where_they_are(cache):
    path = HERE / "typing" / "misuse.py"
    marked = {i for i, line in enumerate(path.read_text().splitlines(), 1) if line.endswith("# error")}
    r = _mypy(path, cache)
    flagged = {int(line.split(":")[1]) for line in r.stdout.splitlines() if ": error:" in line}
    assert marked and flagged == marked, r.stdout


@pytest.mark.slow
def test_the_package_type_checks(cache):
    """mypy over the whole package, with the settings in pyproject.toml ([tool.mypy]: numba
    and OpenCV read as Any): no finding."""
    pytest.importorskip("mypy", reason="mypy (in the dev extra) checks the package's annotations")
    r = subprocess.run([sys.executable, "-m", "mypy", "--no-color-output", "--cache-dir", str(cache), "reeb_torch"],
                       capture_output=True, text=True, cwd=HERE.parent, timeout=900)
    assert r.returncode == 0, r.stdout[-4000:] + r.stderr[-2000:]


def test_lazy_names_are_declared_for_type_checkers():
    """``reeb_torch/__init__.py`` imports its names on first use (``_LAZY``); the same names,
    from the same modules, are imported under ``TYPE_CHECKING`` and listed in ``__all__``."""
    import reeb_torch

    tree = ast.parse((PACKAGE / "__init__.py").read_text())
    guarded = next(n for n in tree.body if isinstance(n, ast.If) and getattr(n.test, "id", "") == "TYPE_CHECKING")
    declared = {a.name: node.module for node in guarded.body if isinstance(node, ast.ImportFrom) for a in node.names}
    assert declared == reeb_torch._LAZY
    assert set(reeb_torch.__all__) == set(declared)
    assert (PACKAGE / "py.typed").is_file()
