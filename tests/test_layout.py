"""The package's layout keeps its design (docs/architecture.md): no import circles, the
stages import only stages, the algorithm imports none of the runs, the evaluation or the
detectors, the libraries of runs/ do not import the command, and there is one import path
per name (no compatibility modules).

Imports are read from the source (``ast``), module-level and inside functions alike."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "reeb_torch"

SELECTION = {"reeb_torch.selection", "reeb_torch.selection.cache", "reeb_torch.selection.cut",
             "reeb_torch.selection.maps",
             "reeb_torch.selection.score", "reeb_torch.selection.suppress"}
RANKER = {"reeb_torch.ranker", "reeb_torch.ranker.features", "reeb_torch.ranker.model", "reeb_torch.ranker.prefilter",
          "reeb_torch.ranker.step", "reeb_torch.ranker.weights"}
ALGORITHM = {"reeb_torch.config", "reeb_torch.generator", "reeb_torch._checks", "reeb_torch.camera",
             "reeb_torch.io"} | SELECTION | RANKER
RUNS_LIBRARIES = {"reeb_torch.runs.inputs", "reeb_torch.runs.decoding", "reeb_torch.runs.rows",
                  "reeb_torch.runs.output_files", "reeb_torch.runs.output_lock", "reeb_torch.runs.ctrl_c",
                  "reeb_torch.runs.distributed", "reeb_torch.runs.export", "reeb_torch.runs.viz"}
COMMAND = {"reeb_torch.runs.cli", "reeb_torch.runs.common", "reeb_torch.runs.propose_local",
           "reeb_torch.runs.propose_ray"}
MAX_FUNCTION_LINES = 100
LONG_FUNCTIONS: set[str] = set()
"""Functions allowed past :data:`MAX_FUNCTION_LINES`, each with its reason (none)."""


def _modules() -> dict[str, tuple[Path, bool]]:
    out = {}
    for p in PACKAGE.rglob("*.py"):
        parts = list(p.relative_to(PACKAGE.parent).with_suffix("").parts)
        is_pkg = parts[-1] == "__init__"
        out[".".join(parts[:-1] if is_pkg else parts)] = (p, is_pkg)
    return out


def _imports(name: str, is_pkg: bool, tree: ast.AST, modules: dict) -> set[str]:
    """The package's modules that ``name`` imports (``from .x import y`` resolved to the
    module ``x.y`` where that is one, else ``x``)."""
    found = set()
    for node in ast.walk(tree):
        targets = []
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = name.split(".") if is_pkg else name.split(".")[:-1]
                base = base[: len(base) - (node.level - 1)]
                module = ".".join(base + ([node.module] if node.module else []))
            else:
                module = node.module or ""
            targets = [f"{module}.{a.name}" if f"{module}.{a.name}" in modules else module for a in node.names]
        for t in targets:
            while t and t not in modules:
                t = t.rpartition(".")[0]
            if t and t != name:
                found.add(t)
    return found


@pytest.fixture(scope="module")
def graph() -> dict[str, set[str]]:
    modules = _modules()
    return {m: _imports(m, is_pkg, ast.parse(p.read_text(encoding="utf-8")), modules)
            for m, (p, is_pkg) in modules.items()}


def _reach(graph: dict[str, set[str]], start: str) -> set[str]:
    seen, todo = set(), [start]
    while todo:
        for d in graph[todo.pop()]:
            if d not in seen:
                seen.add(d)
                todo.append(d)
    return seen


def test_the_graph_is_read(graph):
    assert "reeb_torch.selection" in graph["reeb_torch.generator"]
    assert ALGORITHM <= set(graph)
    assert "reeb_torch.stages.windows" in graph["reeb_torch.stages.scoring"]
    assert "reeb_torch.runs.propose_ray" in graph["reeb_torch.runs.cli"]  # an import inside a function


def test_no_import_circles(graph):
    circles = sorted(m for m in graph if m in _reach(graph, m))
    assert not circles, f"modules on an import circle: {circles}"


def test_stages_import_only_stages(graph):
    for m, deps in graph.items():
        if m.startswith("reeb_torch.stages."):
            outside = {d for d in deps if not d.startswith("reeb_torch.stages")}
            assert not outside, f"{m} imports {outside}"


def test_the_algorithm_imports_no_runs_evaluation_or_detectors(graph):
    for m in ALGORITHM | {m for m in graph if m.startswith("reeb_torch.stages")}:
        wrong = {d for d in _reach(graph, m) if d.startswith(("reeb_torch.runs", "reeb_torch.eval",
                                                               "reeb_torch.detection"))}
        assert not wrong, f"{m} reaches {wrong}"


def test_run_libraries_do_not_import_the_command(graph):
    for m in RUNS_LIBRARIES:
        assert not (_reach(graph, m) & COMMAND), f"{m} reaches {_reach(graph, m) & COMMAND}"


def test_the_evaluation_imports_no_runs(graph):
    for m in graph:
        if m.startswith("reeb_torch.eval"):
            wrong = {d for d in _reach(graph, m) if d.startswith("reeb_torch.runs")}
            assert not wrong, f"{m} reaches {wrong}"


def test_functions_are_short():
    """No function over :data:`MAX_FUNCTION_LINES` lines (def to end) but the ones named, with their reasons."""
    long = set()
    for p in PACKAGE.rglob("*.py"):
        for node in ast.walk(ast.parse(p.read_text(encoding="utf-8"))):
            if (isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef))
                    and node.end_lineno - node.lineno >= MAX_FUNCTION_LINES):
                long.add(f"{p.relative_to(PACKAGE).as_posix()}:{node.name}")
    assert long <= LONG_FUNCTIONS, f"over {MAX_FUNCTION_LINES} lines: {sorted(long - LONG_FUNCTIONS)}"


def test_no_compatibility_shims():
    """One import path per name: the old top-level modules are gone, the public names of
    ``reeb_torch`` are there, and the ``reeb`` script points at the command itself."""
    import reeb_torch

    for shim in ("cli", "data", "distributed", "metrics"):
        assert not (PACKAGE / f"{shim}.py").exists(), f"reeb_torch/{shim}.py is back"
    from reeb_torch.eval import data as eval_data

    assert not {"read_kitti_calib", "camera_intrinsics"} & set(eval_data.__all__)
    for name in reeb_torch.__all__:
        assert getattr(reeb_torch, name) is not None, name
    for name in ("ProposalGenerator", "ReebConfig", "propose", "get_preset", "PRESETS", "read_image",
                 "ImageReadError", "Inspection"):
        assert name in reeb_torch.__all__, name
    pyproject = (PACKAGE.parent / "pyproject.toml").read_text(encoding="utf-8")
    assert 'reeb = "reeb_torch.runs.cli:main"' in pyproject
    from reeb_torch.detection import ReebRPN, build_cache  # noqa: F401
    from reeb_torch.eval import main, table3  # noqa: F401
    from reeb_torch.runs.cli import main as cli_main  # noqa: F401
    from reeb_torch.runs.distributed import propose_dataset, write_results  # noqa: F401
