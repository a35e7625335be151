"""What ``reeb detector fit`` does around :meth:`ReebDetector.fit
<reeb_torch.detection.ReebDetector.fit>`: its inputs checked before any work, then the
training and the held-out scores.

Before any work (each problem a usage error, exit code 2, in one line): the output (a
``.safetensors`` name in a writable folder, not there unless ``--overwrite``, its lock held
so that a second fit on it exits at once), the folders (each once, however often named;
labelled KITTI-format frames; objects of the classes asked for; label files without an
image noted), ``--val`` (labelled folders of classes KITTI's AP scores) and ``--cache`` (a
folder that can be written). While it trains, the library's warnings (a cache that cannot
be written: the fit goes on without it) are one ``warning:`` line each.
"""

from __future__ import annotations

import os
import time
import warnings
from collections import Counter
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import click

from .common import UsageProblem, writable_folder

__all__ = ["claim_weights_out", "SettingRange", "distinct", "check_frames", "check_cache", "warnings_as_lines",
           "training_states", "train"]


def claim_weights_out(out: str, overwrite: bool, inputs: Mapping[str | os.PathLike, str] | None = None) -> Path:
    """``-o``: a ``.safetensors`` name in a writable folder, not there yet unless ``overwrite``,
    none of ``inputs`` (the files the command reads, by name: :func:`.claim.check_files`);
    claimed until the command ends (:func:`.claim.claim_files`: a second fit on it exits 2
    at once, and the temporary files a killed fit on it left are removed)."""
    from .claim import claim_files

    p = Path(os.path.expanduser(out))
    if p.suffix.lower() != ".safetensors":
        raise UsageProblem(f"{out}: a detector is written as safetensors; name it {p.with_suffix('.safetensors')}")
    return claim_files([p], overwrite, inputs=inputs, example="det.safetensors")[0][0]


class SettingRange(click.ParamType):
    """An int option within the range of the detector setting ``field``
    (:data:`~reeb_torch.detection.detector.SETTINGS_RANGES`, where a detector file's settings
    are checked), read when the option is (the command line loads without the detector)."""

    name = "integer"

    def __init__(self, field: str) -> None:
        self.field = field

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> Any:
        from ..detection.detector import SETTINGS_RANGES

        low, high = (int(float(x)) for x in str(SETTINGS_RANGES[self.field]).strip("[]").split(","))
        return click.IntRange(low, high).convert(value, param, ctx)


def distinct(folders: Sequence[str], option: str) -> list[str]:
    """``folders`` with each folder once (a note for each named again)."""
    from ..detection.kitti import distinct_folders

    kept, repeated = distinct_folders(folders)
    for f in repeated:
        click.echo(f"note: {option}{f} names a folder already given: its frames are used once", err=True)
    return [str(f) for f in kept]


def _survey(folders: Sequence[str], limit: int | None, what: str) -> Counter:
    """The label lines by type of ``folders``' frames; a usage error for a folder that is not
    labelled KITTI-format frames, a note for label files without an image."""
    from ..detection.kitti import survey_folder

    total: Counter = Counter()
    for folder in folders:
        try:
            s = survey_folder(folder, limit)
        except ValueError as e:
            raise UsageProblem(f"{what}{' '.join(str(e).split())}") from None
        if not s.labelled:
            raise UsageProblem(f"{what}{folder}: no label folder (labels/ or label_2/): "
                               + ("held-out scores need labels" if what else "a detector trains on labelled frames"))
        if s.orphans:
            click.echo(f"note: {folder}: {len(s.orphans)} label file{'s' if len(s.orphans) > 1 else ''} without an "
                       f"image ({', '.join(s.orphans[:3])}{', ...' if len(s.orphans) > 3 else ''}): not used", err=True)
        total += s.objects
    return total


def check_frames(dirs: Sequence[str], val: Sequence[str], names: tuple[str, ...], limit: int | None,
                  named: bool) -> None:
    """What ``reeb detector fit`` can check before any work: labelled folders, objects of the
    classes asked for (a class without any is a usage error where ``--classes`` names it, a
    note for the default classes), and ``--val`` folders KITTI's AP can score."""
    from ..metrics.kitti_ap import MIN_OVERLAP

    held = _survey(dirs, limit, "")
    shown = ", ".join(f"{n} {c}" for c, n in held.most_common() if c != "DontCare") or "no objects"
    absent = [c for c in names if not held[c]]
    if len(absent) == len(names) or (absent and named):
        raise click.BadParameter(f"no {' or '.join(absent)} object in the training frames' labels (they hold "
                                 f"{shown})", param_hint="--classes")
    for c in absent:
        click.echo(f"note: no {c} object in the training frames' labels: the detector will not find any "
                   f"(choose the classes with --classes; the labels hold {shown})", err=True)
    if val:
        unknown = [c for c in names if c not in MIN_OVERLAP]
        if unknown:
            raise UsageProblem(f"--val: KITTI's 2D AP has no overlap threshold for {', '.join(unknown)} (it scores "
                               f"{', '.join(MIN_OVERLAP)}); leave --val out, or train on those classes")
        _survey(val, None, "--val ")  # scored on all their frames


def check_cache(cache_dir: str | None) -> str | None:
    """``--cache``: a folder that can be made and written (a usage error naming it, before any
    work); None (the default folder, where a failed write is a warning) stays None."""
    if cache_dir is None:
        return None
    p = Path(os.path.expanduser(cache_dir))
    writable_folder("--cache", p)
    return str(p)


@contextmanager
def warnings_as_lines() -> Iterator[None]:
    """The library's warnings while a command runs, each as one ``warning:`` line on stderr."""
    with warnings.catch_warnings():
        warnings.showwarning = lambda message, *args, **kwargs: click.echo(f"warning: {message}", err=True)
        yield


def training_states(out: Path) -> Path:
    """The folder beside ``out`` where ``reeb detector fit`` keeps its training state after
    each epoch (a killed fit, started again with the same command, goes on from it); removed
    once the detector is written."""
    from .output_files import hidden_stem

    return out.parent / f"{hidden_stem(out)}.train"


def _on_ray(engine: tuple[str | None, int, float | None], quiet: bool) -> Any:
    """The detector fit's per-frame pass on Ray (``--engine ray``): Ray started, or a
    one-line error."""
    from .common import Failure, ray_engine
    from .fit_ray import ray_frames

    actors, cpus = ray_engine(engine, quiet)

    def frames_by(det: Any, items: Sequence[dict], cache: Any) -> Any:
        try:
            yield from ray_frames(det, items, cache, actors, cpus)
        except Exception as e:  # noqa: BLE001 - a failed Ray job: the maps cached so far stay
            raise Failure(f"the Ray job failed: {' '.join(str(e).split())[:2000]}") from None

    return frames_by


def train(dirs: Sequence[str], val: Sequence[str], names: tuple[str, ...], proposals: str, epochs: int, seed: int,
          settings: Any, cache_dir: str | None, limit: int | None, hflip: bool, quiet: bool,
          command: str, auto_crop: bool = False, checkpoints: Path | None = None,
          steps: int | None = None, factorised_epochs: int = 0, proposal_changes: dict[str, Any] | None = None,
          engine: tuple[str | None, int, float | None] | None = None) -> tuple[Any, list[str]]:
    """``reeb detector fit``'s work once its inputs are checked: the trained detector (its
    ``--val`` scores in its provenance) and the lines that tell of it."""
    from ..detection import ReebDetector, TrainSettings, evaluate_detector, format_scores

    t0 = time.perf_counter()
    frames_by = _on_ray(engine, quiet) if engine is not None else None
    resumed = checkpoints is not None and checkpoints.is_dir()
    if resumed and not quiet:
        click.echo(f"note: going on from the training state in {checkpoints} (a fit on this output that was "
                   "stopped); a state of other settings or frames is not used", err=True)
    try:
        det: Any = ReebDetector.fit(dirs, classes=names, proposals=proposals, epochs=epochs, seed=seed,
                                    settings=settings, cache_dir=cache_dir, limit=limit, hflip=hflip,
                                    auto_crop=auto_crop, progress=not quiet, command=command,
                                    training=TrainSettings(max_steps=steps, factorised_epochs=factorised_epochs), checkpoints=checkpoints,
                                    frames_by=frames_by, proposal_changes=proposal_changes)
    except (ValueError, FileNotFoundError, ImportError) as e:
        raise UsageProblem(" ".join(str(e).split()))
    prov = det.meta["provenance"]
    lines = [f"trained on {len(prov['frames'])} frames ("
             + ", ".join(f"{n} {c}" for c, n in prov["objects"].items()) + f"): {det.history['steps']} steps, "
             f"{det.history['train_s']:.0f} s of head training, {time.perf_counter() - t0:.0f} s in all"]
    if auto_crop:
        lines.append(f"the backbone skips the top {det.settings.crop_top:g} of each image's height (above the "
                     "labels' highest object; --crop-top to choose)" if det.settings.crop_top else
                     "the backbone skips no rows: a training object reaches the top of its image")
    if val:
        try:
            scores = evaluate_detector(det, val, cache_dir=cache_dir, progress=not quiet, seed=seed)
        except (ValueError, OSError) as e:  # the detector is kept all the same
            return det, lines + [f"error: --val: cannot score the detector ({' '.join(str(e).split())}); it is "
                                 "written without held-out scores"]
        prov["val"] = {"folders": list(val), **scores}
        lines.append(f"KITTI 2D AP|R40 (moderate) on {scores['frames']} frames of {', '.join(val)}:\n"
                     + format_scores(scores))
        if scores["training_frames"]:
            lines.append(f"note: {scores['training_frames']} of these frames are training frames (the same "
                         "pictures): that part of the estimate is in-sample")
    return det, lines
