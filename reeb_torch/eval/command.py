"""``reeb eval``: the click command that computes Table 3 (:mod:`.table3`) and writes its report
(:mod:`.report`).

::

    reeb eval data/kitti --limit 20                 # the first 20 frames
    reeb eval data/kitti data/kitti_tracking --cross-validate 10 --whole-drives --leave-folder-out
    reeb eval data/kitti --frames 0:39 --frames 40:59 --methods reeb-default,reeb-training-free

:mod:`.methods` holds the rows and checks the options (torch is imported only when the
table is computed). :func:`table3_parameters` declares the command's parameters and
:func:`run_command` runs it: ``reeb eval`` (:mod:`reeb_torch.runs.cli`) takes the folders as
arguments; :func:`table3_command` makes a command that takes them as ``--data DIR`` with
defaults of its own (``benchmarks/table3.py``). Bad options or unusable data exit with code 2 and a one-line
message, before any proposal is made.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import click

from ..datasets.folders import FrameRange, parse_frame_range
from .common import rerun_line
from .methods import DEFAULT_METHODS, KS, Table3Error, Table3Options

__all__ = ["FrameRanges", "Methods", "BadData", "QUICK_METHODS", "TABLE3_HELP", "TABLE3_SHORT_HELP",
           "table3_parameters", "run_command", "table3_command", "run_table3"]

CONTEXT = dict(help_option_names=["-h", "--help"], max_content_width=100)


class BadData(click.ClickException):
    """Options or data with which the table cannot be made: one line, exit code 2."""

    exit_code = 2


class FrameRanges(click.ParamType):
    """``A:B`` frame ranges (both ends included; ``A:``, ``:B`` and ``A`` too), several in one
    value separated by commas: a tuple of :class:`~reeb_torch.datasets.folders.FrameRange`."""

    name = "A:B"

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> tuple[FrameRange, ...]:
        if isinstance(value, tuple):
            return value
        try:
            return tuple(parse_frame_range(t) for t in str(value).split(","))
        except ValueError as e:
            self.fail(str(e), param, ctx)


class Methods(click.ParamType):
    """Method keys (:data:`~reeb_torch.eval.table3.DEFAULT_METHODS`), several in one value
    separated by commas."""

    name = "METHOD"

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> tuple[str, ...]:
        if isinstance(value, tuple):
            return value
        keys = tuple(k.strip() for k in str(value).split(",") if k.strip())
        if keys == ("all",):
            return DEFAULT_METHODS
        bad = [k for k in keys if k not in DEFAULT_METHODS]
        if bad or not keys:
            self.fail(f"{(bad or [value])[0]!r} is not a method; choose from all, {', '.join(DEFAULT_METHODS)}",
                      param, ctx)
        return keys


def _flatten(_ctx: click.Context, _param: click.Parameter, value: Sequence[tuple]) -> tuple:
    return tuple(v for group in value for v in group)


def _options(data_default: Sequence[str | os.PathLike] | None,
             bing_default: str | os.PathLike | None) -> list[click.Parameter]:
    """The command's parameters; the folders are an argument without ``data_default``, else a
    ``--data`` option with it."""
    folders_help = ("KITTI-format folders (images/ + labels/, or image_2/ + label_2/); with several, every "
                    "table is given for each folder and for all together")
    if data_default is None:
        data: click.Parameter = click.Argument(["data"], nargs=-1, required=True, metavar="KITTI_DIR...",
                                               type=click.Path(exists=True, file_okay=False, path_type=Path))
    else:
        data = click.Option(["--data"], multiple=True, default=[str(d) for d in data_default], show_default=True,
                            metavar="DIR", type=click.Path(file_okay=False, path_type=Path),
                            help=folders_help + " (repeatable).")
    bing_help = "Folder of BING's nine ObjNessB2W8*.yml.gz model files (opencv_contrib's saliency samples)"
    return [
        data,
        click.Option(["--limit"], type=click.IntRange(min=1), help="Use only the first N frames of each folder "
                     "(after --frames)."),
        click.Option(["--frames"], type=FrameRanges(), multiple=True, callback=_flatten,
                     help="Only frames whose numeric id is in these ranges (both ends included; A:, :B and A "
                          "also work; repeatable or comma-separated, e.g. --frames 0:39,40:59); with two or "
                          "more ranges every table is also given for each range."),
        click.Option(["-o", "--out"], type=click.Path(file_okay=False, path_type=Path), default="runs/table3",
                     show_default=True, help="Folder for table3.txt, table3.csv, table3.json and the plots."),
        click.Option(["--methods"], type=Methods(), multiple=True, callback=_flatten,
                     help=f"Rows to run, in table order (repeatable or comma-separated), or all: "
                          f"{', '.join(DEFAULT_METHODS)}. Default: "
                          + ("all." if data_default is not None else
                             f"{', '.join(QUICK_METHODS)}, and bing with --bing-model (selective-search, the "
                             f"slowest, only when asked).")),
        click.Option(["--top-k", "--max-proposals", "top_k"], type=int, default=max(KS), show_default=True,
                     help=f"Proposals kept per image (at least {max(KS)}; --max-proposals is another name)."),
        click.Option(["--batch"], type=click.IntRange(min=0), default=8, show_default=True,
                     help="Also time REEB in batches of this many images (0 or 1: not)."),
        click.Option(["--exclude-fitted"], is_flag=True,
                     help="Leave out the frames a learned ranking among the methods was fitted on (the same "
                          "pictures, whatever their names), so that every row is an estimate."),
        click.Option(["--cross-validate"], type=click.IntRange(min=0), default=0,
                     metavar="FOLDS",
                     help="Also the default ranked, on each of FOLDS blocks of frames, by a model fitted on the "
                          "other blocks (reeb fit's folds, options and seed); the rows are then paired with "
                          "training-free. Fits FOLDS models (about a minute for 100 frames)."),
        click.Option(["--whole-drives"], is_flag=True,
                     help="With --cross-validate: also the default ranked on each block by a model fitted on the "
                          "other blocks less every frame of the block's drives (reeb fit --whole-drives), in a row "
                          "before the cross-validated one: the estimate for drives no model saw, to read first."),
        click.Option(["--leave-folder-out"], is_flag=True,
                     help="Also the default ranked, on each folder, by a model fitted on the other folders."),
        click.Option(["--bing-model"], type=click.Path(file_okay=False, path_type=Path),
                     default=None if bing_default is None else str(bing_default), show_default=bing_default is not None,
                     metavar="DIR", help=bing_help + (": its row is added; without it there is no BING row."
                                                      if bing_default is None else ".")),
    ]


def _command_line(ctx: click.Context) -> str:
    """The command line that makes the same table: the command and the parameters given
    (not those left at their defaults)."""
    argv: list[str] = []
    for p in ctx.command.params:
        value = ctx.params.get(p.name or "")
        if isinstance(p, click.Argument):
            argv += [str(v) for v in value or ()]
            continue
        if not isinstance(p, click.Option) or ctx.get_parameter_source(p.name or "") != click.core.ParameterSource.COMMANDLINE:
            continue
        flag = max(p.opts, key=len)
        if p.is_flag:
            argv += [flag] if value else []
            continue
        texts = [v.text if isinstance(v, FrameRange) else str(v) for v in ((value or ()) if p.multiple else [value])]
        if isinstance(p.type, (FrameRanges, Methods)):
            texts = [",".join(texts)]
        for t in texts:
            argv += [flag, t]
    return rerun_line(ctx.command_path, argv)


def run_table3(options: Table3Options, out: str | os.PathLike, rerun: str = "") -> dict[str, Any]:
    """Compute the table (:func:`~reeb_torch.eval.table3.compute`), print it and write its
    files into ``out`` (:func:`~reeb_torch.eval.report.write_report`); return the JSON record.

    Raises:
        Table3Error: the data do not allow the table (nothing is written).
    """
    from .report import write_report
    from .table3 import compute

    if rerun:
        print(f"Rerun: {rerun}   (from {os.getcwd()})", flush=True)
    Path(out).mkdir(parents=True, exist_ok=True)
    return write_report(compute(options), out, rerun)


QUICK_METHODS: tuple[str, ...] = ("edgeboxes", "reeb-training-free", "reeb-default")
"""``reeb eval``'s rows without ``--methods``: the fast baseline and REEB's two presets (BING
joins them where ``--bing-model`` is given; Selective Search, the slowest by far, with
``--methods all`` or by name)."""


def table3_parameters(data_default: Sequence[str | os.PathLike] | None = None,
                      bing_default: str | os.PathLike | None = None):
    """A decorator that gives a click command function the table's parameters, in order (as
    ``@click.option`` does): the folders (an argument without ``data_default``, else ``--data``
    options with it), ``--limit``, ``--frames``, ``-o``, ``--methods``, ``--top-k``,
    ``--batch``, ``--exclude-fitted``, ``--cross-validate``, ``--whole-drives``,
    ``--leave-folder-out``, ``--bing-model`` (default ``bing_default``)."""

    def decorate(f: Any) -> Any:
        if not hasattr(f, "__click_params__"):
            f.__click_params__ = []
        f.__click_params__.extend(reversed(_options(data_default, bing_default)))  # click reverses them
        return f

    return decorate


TABLE3_SHORT_HELP = "Recall table (the paper's Table 3) and plots on KITTI-format folders."
TABLE3_HELP = (
    "Recall table (the paper's Table 3) and plots on KITTI-format folders: every table for each folder and for "
    "all of them together.\n\n"
    "Recall at IoU 0.3 / 0.5 / 0.7 of the top 100 / 300 / 500 / 1000 / 2000 proposals of REEB and of the "
    "classical baselines (BING, Selective Search, Edge Boxes), over all and over KITTI-moderate objects, per "
    "class, AR, the headline's 95 % interval and each row paired with the default; ms per image. Writes "
    "table3.txt (also printed), table3.csv, table3.json and two plots into --out.")
"""The table command's help (``reeb eval``'s)."""


def run_command(data: Sequence[Path], out: Path, methods: tuple[str, ...], config: Any = None,
                preset: str | None = None, quick: bool = False, **given: Any) -> dict[str, Any]:
    """The table command's work, in its click context (the rerun line is read from it): the
    JSON record. ``config``: the caller's settings (``reeb eval --config / --set``, a row of
    their own); then without ``methods`` the rows are the ``preset``'s and theirs. ``quick``:
    without ``methods``, :data:`QUICK_METHODS` (and BING given its model), else all;
    ``given``: the other parameters of :func:`table3_parameters` and ``device``.

    Raises:
        BadData: the data do not allow the table (exit code 2, one line).
    """
    ctx = click.get_current_context()
    if not methods:
        own = {"default": "reeb-default", "training-free": "reeb-training-free", "paper": "reeb-paper"}
        if config is not None:
            methods = (own.get(preset or "default", "reeb-default"),)
        elif quick:
            methods = (("bing",) if given.get("bing_model") else ()) + QUICK_METHODS
        else:
            methods = DEFAULT_METHODS
    try:
        options = Table3Options(data=data, methods=methods, config=config, **given)
        return run_table3(options, out, _command_line(ctx))
    except Table3Error as e:
        raise BadData(str(e)) from None


def table3_command(name: str = "eval", *, data_default: Sequence[str | os.PathLike] | None = None,
                   bing_default: str | os.PathLike | None = None) -> click.Command:
    """A click command that computes Table 3 and writes its report, returning the JSON record
    (``standalone_mode=False``), for scripts with defaults of their own (``reeb eval`` is
    :mod:`reeb_torch.runs.cli`'s).

    Args:
        name: the command's name.
        data_default: ``None``: the folders are arguments (``NAME KITTI_DIR...``); else they
            are ``--data DIR`` options, these by default.
        bing_default: the default of ``--bing-model`` (none: BING is skipped unless given).
    """

    @click.command(name, context_settings=CONTEXT, short_help=TABLE3_SHORT_HELP, help=TABLE3_HELP)
    @table3_parameters(data_default, bing_default)
    def command(**given: Any) -> dict[str, Any]:
        return run_command(quick=data_default is None, **given)

    return command
