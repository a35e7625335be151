"""Helpers shared by the benchmark scripts: default paths, their ``--data`` and ``--frames``
options, the rerun line, the machine."""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any, Callable, Sequence

from reeb_torch.datasets.folders import parse_frame_range
from reeb_torch.eval.common import rerun_line

__all__ = ["REPO_ROOT", "DATA_ENV", "data_root", "default_kitti_dir", "default_dev_dirs", "add_data_option", "add_frames_option", "rerun_line",
           "environment", "timed", "run_captured", "paired_ratios", "setting_pairs", "settings_config",
           "write_outputs"]

REPO_ROOT = Path(__file__).resolve().parents[1]
"""The repository root (the folder holding ``benchmarks/``)."""


DATA_ENV = "REEB_DATA"
"""The variable naming the dev data folder (:func:`data_root`)."""


def data_root() -> Path:
    """The dev data folder: ``$REEB_DATA`` where it is set, else ``shared/data`` beside the
    repository; it holds ``kitti/`` and ``kitti_tracking/`` (KITTI-format folders) and
    ``bing_model/``."""
    import os

    return Path(os.path.expanduser(os.environ.get(DATA_ENV) or REPO_ROOT.parent / "shared" / "data"))


def default_kitti_dir() -> Path:
    """``kitti/`` of the dev data (:func:`data_root`): the 60 KITTI frames of the project."""
    return data_root() / "kitti"


def default_dev_dirs() -> list[Path]:
    """The dev folders of :func:`data_root` that exist: ``kitti`` (60 KITTI object frames)
    and ``kitti_tracking`` (46 frames of two tracking sequences); both when neither exists
    (so the error names them)."""
    root = data_root()
    dirs = [root / "kitti", root / "kitti_tracking"]
    return [d for d in dirs if d.is_dir()] or dirs


def add_data_option(parser: argparse.ArgumentParser, default: Sequence[str | Path] | None = None) -> None:
    """Add ``--data DIR [DIR ...]`` (KITTI-format folders, reported each and together) to
    ``parser``; without a ``default`` it is required."""
    shown = " ".join(str(d) for d in default) if default else ""
    parser.add_argument(
        "--data", type=Path, nargs="+", default=list(default) if default else None, required=not default,
        metavar="DIR",
        help="KITTI-format folders (images/ + labels/, or image_2/ + label_2/); with several, every table "
             "is given for each folder and for all together" + (f"; default: {shown}" if shown else ""),
    )


def _frame_range(text: str) -> Any:
    """``type=`` of ``--frames``: :func:`reeb_torch.datasets.folders.parse_frame_range`."""
    try:
        return parse_frame_range(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def add_frames_option(parser: argparse.ArgumentParser) -> None:
    """Add ``--frames A:B [A:B ...]`` (:class:`reeb_torch.datasets.folders.FrameRange` each) to ``parser``."""
    parser.add_argument(
        "--frames", nargs="+", type=_frame_range, default=[], metavar="A:B",
        help="only frames whose numeric id is in these ranges (both ends included; "
             "A:, :B and A also work), e.g. --frames 0:39 40:59; with two or more ranges "
             "the recall is also reported for each range",
    )


def environment() -> dict[str, Any]:
    """Versions, thread counts and CPU of this run, for the JSON record
    (:func:`reeb_torch.eval.common.environment`)."""
    from reeb_torch.eval.common import environment as _environment

    return _environment()


def setting_pairs(text: str) -> list[str]:
    """A ``--variant``'s ``FIELD=VALUE;...`` as the pairs ``reeb propose --set`` takes."""
    return [p.strip() for p in text.split(";") if p.strip()]


def settings_config(text: str) -> Any:
    """The package default with ``FIELD=VALUE;...`` applied, as ``reeb propose --set`` applies
    them (a :class:`~reeb_torch.ReebConfig`; :class:`~reeb_torch.config_text.SettingError` for a bad field or value)."""
    from reeb_torch.config_text import config_from

    return config_from("default", None, setting_pairs(text), None)


def run_captured(gen: Any, image: Any) -> tuple[dict, dict]:
    """Run ``gen`` (a :class:`~reeb_torch.ProposalGenerator`) on one image and return its
    output and what its per-region cut saw (:meth:`~reeb_torch.ProposalGenerator.trace`):
    ``scores`` (``[1, N]``, every window), ``grid`` (the
    :class:`~reeb_torch.stages.windows.WindowGrid`), ``chosen`` (``bool [1, N]``, the
    candidates) and ``share`` (eq. 9's region shares); with a learned ranking also ``ranked``
    (its logits, ``[1, N]``) and ``kept`` (the candidates it ranked)."""
    out, trace = gen.trace(image)
    captured = dict(scores=trace.scores, grid=trace.grid, chosen=trace.chosen, share=trace.share)
    if trace.ranked is not None:
        captured.update(ranked=trace.ranked, kept=trace.kept)
    return out, captured


def timed(fn: Callable[[], Any]) -> tuple[Any, float]:
    """Call ``fn()`` and return ``(result, wall seconds)`` (``time.perf_counter``)."""
    t0 = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - t0


def paired_ratios(base: Sequence[float], this: Sequence[float]) -> tuple[list[float], int, int, float]:
    """Each pair's ratio ``this / base``, the pairs where ``this`` is faster and slower, and
    the exact sign-test p of those counts (:func:`reeb_torch.metrics.recall.sign_test`)."""
    from reeb_torch.metrics.recall import sign_test

    ratios = [t / b for b, t in zip(base, this)]
    faster, slower = sum(r < 1 for r in ratios), sum(r > 1 for r in ratios)
    return ratios, faster, slower, sign_test(faster, slower)


def write_outputs(out: Path, stem: str, text: list[str], record: dict) -> Path:
    """Write ``out/<stem>.txt`` (the lines of ``text``) and ``out/<stem>.json`` (``record``),
    making ``out``; print and return the text file's path."""
    import json

    out.mkdir(parents=True, exist_ok=True)
    (out / f"{stem}.txt").write_text("\n".join(text) + "\n", encoding="utf-8")
    (out / f"{stem}.json").write_text(json.dumps(record, indent=1) + "\n", encoding="utf-8")
    print(f"wrote {out / f'{stem}.txt'}")
    return out / f"{stem}.txt"
