"""What the ``reeb`` command's runs share: errors with their exit codes, the finite-float
option type, the settings from the command line, the device, the bundled sample, the output's
claim (checked and locked) and the printed table of boxes.

The command (:mod:`.cli`) and its runs (:mod:`.engine` and the commands on it) import this
module; the libraries they call (:mod:`.rows`, :mod:`.output_files`, :mod:`.distributed`,
:mod:`.export`, :mod:`.viz`, ...) import none of them. The closing summary's lines are the
engine's (:mod:`.engine`).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Sequence

import click

__all__ = [
    "CONTEXT",
    "UsageProblem",
    "Failure",
    "writable_folder",
    "OUTPUT_RULE",
    "FiniteFloat",
    "engine_options",
    "ray_engine",
    "settings_options",
    "config_options",
    "device_option",
    "SAMPLE_NAME",
    "repo_root",
    "bundled_sample",
    "build_config",
    "resolve_device",
    "label_for",
    "read_labels",
    "box_table",
]

SAMPLE_NAME = "kitti_000001.png"

CONTEXT = dict(help_option_names=["-h", "--help"], max_content_width=100)
"""click's context settings of every ``reeb`` command: ``-h`` for help, 100 columns."""


class UsageProblem(click.ClickException):
    """A one-line error with exit code 2 (bad input given on the command line)."""

    exit_code = 2


class Failure(click.ClickException):
    """A one-line error with exit code 1 (the command could not do its work)."""

    exit_code = 1


def writable_folder(option: str, folder: Path) -> None:
    """Make ``folder`` if needed and check that a file can be written there; a usage error
    naming ``option`` and the folder when not (before any work)."""
    import os
    import tempfile

    try:
        folder.mkdir(parents=True, exist_ok=True)
        fd, probe = tempfile.mkstemp(prefix=".reeb-probe.", dir=folder)
        os.close(fd)
        os.unlink(probe)
    except OSError as e:
        raise UsageProblem(f"{option} {folder}: cannot write there ({e.strerror or e})") from None


OUTPUT_RULE = ("A command never replaces a file that is there already unless given --overwrite, never writes "
               "into a folder it reads, and writes each file whole or not at all.")
"""The rule every ``reeb`` command that writes a file keeps (``propose``, ``detect``, ``fit``,
``tune``, ``calibrate``, ``export``, ``detector fit``); the views made only for looking
(``reeb show``'s picture, the bare ``reeb propose`` sample's, ``reeb eval``'s report folder)
are redrawn in place."""


class FiniteFloat(click.FloatRange):
    """A float option that must be a finite number within its range: ``nan``, ``inf`` and
    ``-inf`` are usage errors naming the option (click's ``FloatRange`` lets ``nan`` through,
    since every comparison with it is false, and ``inf`` where the range has no bound on
    that side). Takes ``FloatRange``'s arguments: ``FiniteFloat(0, 1)``,
    ``FiniteFloat(min=0, min_open=True)``."""

    name = "float"

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> Any:

        rv = super().convert(value, param, ctx)
        if not math.isfinite(rv):
            self.fail(f"{value!r} is not a finite number.", param, ctx)
        return rv


class FloatOrAuto(FiniteFloat):
    """:class:`FiniteFloat`, or the word ``auto`` (kept as the string ``"auto"``)."""

    name = "float|auto"

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> Any:
        if isinstance(value, str) and value.strip().lower() == "auto":
            return "auto"
        return super().convert(value, param, ctx)


# -- options shared by the commands -----------------------------------------------------

device_option = click.option("--device", default="auto", show_default=True,
                             help="cpu, cuda, cuda:N, or auto (CUDA when available).")
"""``--device`` of every command that runs a model (:func:`resolve_device` reads it)."""


def settings_options(purpose: str = "Named settings to start from.", run: bool = True):
    """The options that make a ReebConfig (``--preset``, ``--config``, ``--set``; with ``run``,
    also a run's ``--top-k`` and ``--device``), declared once for every command that takes
    them; ``purpose``: what the settings are for (``--preset``'s help). The command builds
    the config from them once (:func:`build_config`)."""
    from ..config import PRESETS

    options = [
        click.option("--preset", type=click.Choice(sorted(PRESETS)), default="default",
                     show_default=True, help=purpose),
        click.option("--config", "config_file", type=click.Path(exists=True, dir_okay=False),
                     help="JSON file of ReebConfig fields applied over the preset (e.g. reeb calibrate's "
                          "camera.json)."),
        click.option("--set", "sets", multiple=True, metavar="FIELD=VALUE",
                     help="Change one ReebConfig field (repeatable), e.g. --set scale=1.0 or, named with its "
                          "part, --set nms.top_k=500."),
    ]
    if run:
        options += [
            click.option("--top-k", type=click.IntRange(min=1), default=None,
                         help="Proposals kept per image (default: the config's top_k, 2000)."),
            device_option,
        ]

    def decorate(f):
        for opt in reversed(options):
            f = opt(f)
        return f

    return decorate


config_options = settings_options()
"""``--preset``, ``--config``, ``--set``, ``--top-k``, ``--device``: the options of a command
that runs the generator (``propose``, ``show``)."""


# -- settings, device, sample ---------------------------------------------------------

def engine_options(engine_help: str, actor_help: str):
    """``--engine``, ``--address``, ``--actors``, ``--cpus-per-actor``: where a command's
    per-image work runs (this process, or Ray Data actors)."""
    options = [
        click.option("--engine", type=click.Choice(["local", "ray"]), default="local", show_default=True,
                     help=engine_help),
        click.option("--address", default=None,
                     help="--engine ray: the Ray cluster (auto, ray://HOST:PORT) [default: a local Ray "
                          "instance sized to this machine]."),
        click.option("--actors", type=click.IntRange(min=1), default=1, show_default=True, help=actor_help),
        click.option("--cpus-per-actor", type=FiniteFloat(min=0, min_open=True), default=None,
                     help="--engine ray: CPUs each actor reserves (and its torch threads) "
                          "[default: leaves one CPU to Ray's read/write tasks]."),
    ]

    def decorate(f):
        for option in reversed(options):
            f = option(f)
        return f

    return decorate


def ray_engine(engine: tuple[str | None, int, float | None], quiet: bool) -> tuple[int, float]:
    """Ray started for ``--engine ray`` (``engine``: ``(address, actors, cpus_per_actor)``,
    :func:`reeb_torch.runs.fit_ray.start_ray`): the actors and the CPUs each reserves, or a
    one-line error (Ray cannot be reached: exit 1; more CPUs asked for than it has: exit 2)."""
    from .fit_ray import start_ray

    address, actors, cpus_per_actor = engine
    try:
        return actors, start_ray(address, actors, cpus_per_actor, quiet)
    except RuntimeError as e:
        raise Failure(str(e)) from None
    except ValueError as e:
        raise UsageProblem(str(e)) from None


def repo_root() -> Path:
    """The source checkout the package is installed from (editable install)."""
    # this file's package folder, not reeb_torch.__file__: that is None when the package is
    # imported as a namespace package (an editable install made before __init__.py existed)
    return Path(__file__).resolve().parents[2]


def bundled_sample() -> Path:
    """The sample KITTI frame that ``reeb propose`` / ``reeb show`` use without arguments."""
    p = repo_root() / "examples" / "data" / SAMPLE_NAME
    if not p.is_file():
        raise UsageProblem(
            f"the bundled sample image is missing (expected {p}; it ships with the source "
            "checkout, not with an installed wheel); give an image path instead")
    return p


def build_config(preset: str, config_file: str | None, sets: Sequence[str], top_k: int | None):
    """The ReebConfig from a preset, then a JSON file of fields, then ``--set`` pairs, then
    ``--top-k`` (:func:`reeb_torch.config_text.config_from`: each later source overrides the
    earlier ones); any refusal is a usage error naming the option, exit code 2."""
    from ..config_text import SettingError, config_from

    try:
        return config_from(preset, config_file, sets, top_k)
    except SettingError as e:
        raise click.BadParameter(str(e), param_hint=e.option) from None


def resolve_device(name: str):
    """``--device``: ``auto`` (CUDA when available), ``cpu``, ``cuda`` or ``cuda:N``, as a
    ``torch.device``; a usage error (before any work) when it is not one, cannot compute
    (``meta``, ``cpu:5``) or is not here (``cuda`` without a GPU, ``mps`` without support)."""
    import torch

    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        dev = torch.device(name)
    except (RuntimeError, ValueError):
        raise click.BadParameter(f"{name!r} is not a device (try cpu, cuda, cuda:1 or auto)",
                                 param_hint="--device")
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise click.BadParameter("CUDA was asked for but is not available here (use --device cpu)",
                                 param_hint="--device")
    if dev.type == "cuda" and dev.index is not None and dev.index >= torch.cuda.device_count():
        raise click.BadParameter(f"{name}: only {torch.cuda.device_count()} CUDA device(s)",
                                 param_hint="--device")
    if dev.type == "meta":
        raise click.BadParameter("meta is not a device that computes (its tensors hold no values); "
                                 "use cpu, cuda or auto", param_hint="--device")
    if dev.type == "cpu" and dev.index not in (None, 0):
        raise click.BadParameter(f"{name}: there is one CPU device; use cpu", param_hint="--device")
    if dev.type not in ("cpu", "cuda"):  # mps, xpu, ...: refused unless it can hold a tensor here
        try:
            torch.zeros(1, device=dev).add_(1).cpu()
        except Exception as e:  # noqa: BLE001 - each backend raises its own kind
            raise click.BadParameter(f"{name}: not available here ({' '.join(str(e).split())[:200]}); "
                                     "use cpu, cuda or auto", param_hint="--device") from None
    return dev


def label_for(image: Path) -> Path | None:
    """A KITTI label file for ``image``: beside it, or in ../labels or ../label_2."""
    for cand in (image.with_suffix(".txt"),
                 image.parent.parent / "labels" / f"{image.stem}.txt",
                 image.parent.parent / "label_2" / f"{image.stem}.txt"):
        if cand.is_file():
            return cand
    return None


def read_labels(path: Path) -> list:
    from ..datasets.kitti import read_kitti_labels

    try:
        objs = read_kitti_labels(path)
    except (OSError, ValueError) as e:
        raise Failure(f"{path}: cannot read the label file ({' '.join(str(e).split())})")
    return [o for o in objs if o.type != "DontCare"]


def box_table(name: str, size: tuple[int, int], boxes, scores, n: int, total: int,
              labels: Sequence[str] | None = None) -> str:
    """The top ``n`` of ``total`` boxes of one image as a printed table (``reeb propose``, ``reeb show``),
    with a column of each box's class hint where ``labels`` (one per box) are given."""
    w, h = size
    lines = [f"{name}  {w}×{h} px  {total} proposals" + (f" (top {min(n, total)})" if total else "")]
    if total:
        lines.append(f"{'rank':>5} {'x1':>8} {'y1':>8} {'x2':>8} {'y2':>8} {'score':>10}"
                     + ("  hint" if labels is not None else ""))
        hints = list(labels[:n]) if labels is not None else None
        for i, (b, s) in enumerate(zip(boxes[:n].tolist(), scores[:n].tolist()), 1):
            lines.append(f"{i:>5} {b[0]:8.1f} {b[1]:8.1f} {b[2]:8.1f} {b[3]:8.1f} {s:10.4f}"
                         + (f"  {hints[i - 1]}" if hints is not None else ""))
    return "\n".join(lines)
