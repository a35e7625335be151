"""``reeb detector fit`` and ``reeb detector show``: train a detector on labelled frames,
and say what a detector file holds.

::

    reeb detector fit my_frames/ -o det.safetensors            # KITTI-format folders, labelled
    reeb detector fit a/ b/ -o det.safetensors --val held_out/ # and its AP on frames it never saw
    reeb detector show det.safetensors                         # what it was trained on, its scores
    reeb detector compress det.safetensors -o small.safetensors --int8  # its box head smaller

``reeb detect``, which runs a detector over images, is :mod:`.detect_run`.

Exit codes: 0 success; 1 the command failed; 2 usage error (bad option, an unusable detector
file or output, checked before any work).
"""

from __future__ import annotations

import hashlib
import shlex
import shutil
import sys
import warnings
from collections.abc import Sequence
from typing import Any

import click

from .common import CONTEXT, Failure, FloatOrAuto, UsageProblem, engine_options
from .detector_fit import (SettingRange, check_cache, check_frames, claim_weights_out, distinct, train, training_states,
                           warnings_as_lines)

__all__ = ["detector", "fit", "show", "compress", "SETTINGS_OPTIONS", "fit_settings", "proposal_changes"]


# -- reeb detector fit ---------------------------------------------------------------------

@click.group(context_settings=CONTEXT)
def detector() -> None:
    """Train an object detector on your labelled frames (the 'detect' extra).

    REEB's proposals, a frozen ImageNet EfficientNet-Lite0 and RoI heads trained on the CPU in
    minutes. Run it on images with reeb detect.
    """


SETTINGS_OPTIONS = {"min_size": "min_size", "max_size": "max_size", "top_k_train": "top_k_train",
                    "top_k_test": "top_k_test", "precision": "precision", "crop_top": "crop_top",
                    "neck_channels": "neck_channels", "head_width": "representation_size",
                    "box_passes": "box_passes", "box_head_rank": "box_head_rank", "int8_box_head": "box_head_int8"}
"""``reeb detector fit``'s options that set :class:`~reeb_torch.detection.DetectorSettings`
fields: option parameter -> field."""


def fit_settings(params: dict[str, Any]) -> Any:
    """The :class:`~reeb_torch.detection.DetectorSettings` of ``reeb detector fit``'s parsed
    parameters (``params``: the command's, as click parses them)."""
    from ..detection import DetectorSettings

    return DetectorSettings(**{field: params[name] for name, field in SETTINGS_OPTIONS.items()
                               if name in params and params[name] != "auto"})


def proposal_changes(proposals: str, sets: Sequence[str], settings: Any) -> dict[str, Any] | None:
    """``reeb detector fit --set``'s REEB fields (None without any), checked against
    ``proposals``' settings before any work: a usage error names what is wrong."""
    if not sets:
        return None
    from ..config_text import parse_sets
    from ..detection import proposal_settings

    try:
        changes = parse_sets(sets)
        proposal_settings(proposals, max(settings.top_k_train, settings.top_k_test), changes)
    except (TypeError, ValueError, ArithmeticError) as e:
        raise click.BadParameter(" ".join(str(e).split()) or type(e).__name__, param_hint="--set") from None
    return changes


def _changed_options(ctx: click.Context, names: dict[str, str]) -> list[str]:
    """``--option value`` for each of ``names`` (parameter names) whose value is not its default."""
    out = []
    for param in ctx.command.params:
        if param.name in names and ctx.params.get(param.name) != param.default:
            value = ctx.params[param.name]
            if getattr(param, "is_flag", False):
                out.append(param.opts[0] if value else param.secondary_opts[0])
            else:
                out += [param.opts[0], str(value)]
    return out


@detector.command("fit", context_settings=CONTEXT)
@click.argument("dirs", nargs=-1, required=True, type=click.Path(exists=True, file_okay=False))
@click.option("-o", "--out", type=click.Path(dir_okay=False), default="detector.safetensors", show_default=True,
              help="Detector file to write (safetensors, with its metadata).")
@click.option("--overwrite", is_flag=True, help="Replace an existing --out file.")
@click.option("--proposals", default="default", show_default=True, metavar="default|training-free|FILE",
              help="REEB's settings: the learned ranking, the training-free preset, or ranker weights "
                   "that reeb fit wrote (FILE).")
@click.option("--set", "sets", multiple=True, metavar="FIELD=VALUE",
              help="A REEB setting of the proposals over --proposals' (repeatable; as reeb propose --set, e.g. "
                   "--set 'class_quota={\"Pedestrian\": 0.2}'); kept in the detector file.")
@click.option("--classes", default="Car,Pedestrian,Cyclist", show_default=True,
              help="Comma-separated class names, as the label files write them.")
@click.option("--epochs", type=click.IntRange(min=1), default=12, show_default=True, help="Passes over the frames.")
@click.option("--steps", type=click.IntRange(min=1),
              help="Train for this many steps (2 frames each) instead, the schedule spread over them: for data "
                   "sets where --epochs passes would take long.")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of the heads' weights and the frame order.")
@click.option("--val", multiple=True, type=click.Path(exists=True, file_okay=False), metavar="DIR",
              help="Labelled folder kept out of training: its KITTI AP|R40 is printed and stored (repeatable).")
@click.option("--hflip", is_flag=True, help="Train on each frame's mirror image half of the time.")
@click.option("--min-size", type=SettingRange("min_size"), default=576, show_default=True,
              help="Shorter side of the resized input, pixels; the backbone's time grows about with its square, "
                   "and small objects are lost as it shrinks.")
@click.option("--max-size", type=SettingRange("max_size"), default=2048, show_default=True,
              help="Bound on the longer side of the resized input.")
@click.option("--top-k-train", "--train-proposals", "top_k_train", type=SettingRange("top_k_train"), default=2000,
              show_default=True, help="REEB proposals per image in training.")
@click.option("--top-k-test", "--test-proposals", "top_k_test", type=SettingRange("top_k_test"), default=1000,
              show_default=True, help="REEB proposals per image in detection (the heads' time grows with it).")
@click.option("--precision", type=click.Choice(["bfloat16", "float32"]), default="bfloat16", show_default=True,
              help="The frozen backbone's precision; the heads train on its maps and detection uses the same "
                   "(bfloat16 where the CPU or GPU computes it natively, float32 elsewhere).")
@click.option("--crop-top", type=FloatOrAuto(0, 0.9), default="auto", show_default=True, metavar="SHARE|auto",
              help="Share of the image's height, from the top, the backbone skips (rows where no object lies); "
                   "auto: above the highest object of the training labels, less a margin.")
@click.option("--neck-channels", type=SettingRange("neck_channels"), default=128, show_default=True,
              help="Channels of the neck and of the pooled RoI features.")
@click.option("--head-width", type=SettingRange("representation_size"), default=1024, show_default=True,
              help="Units of each of the box head's two layers.")
@click.option("--box-head-rank", type=SettingRange("box_head_rank"), default=0, show_default=True,
              help="0: the box head's first layer in full; R: replaced once trained by its rank-R approximation "
                   "(a smaller file and a faster head; docs/results.md, \"A smaller box head\").")
@click.option("--int8-box-head/--float-box-head", default=True, show_default=True,
              help="The box head's layers in int8 once trained (a quarter of their size, faster on the CPU, the "
                   "same AP: docs/results.md, \"A smaller box head\"), or left in float.")
@click.option("--factorised-epochs", type=click.IntRange(min=0), default=0, show_default=True,
              help="With --box-head-rank: passes of further training once the layer is factorised (at a tenth of "
                   "the learning rate); 0: the approximation as it comes.")
@click.option("--box-passes", type=SettingRange("box_passes"), default=2, show_default=True,
              help="The box head's passes in detection: each after the first pools the boxes the last one "
                   "regressed and averages its class scores in.")
@click.option("--cache", "cache_dir", type=click.Path(file_okay=False),
              help="Where each frame's backbone maps and proposals are kept [default: ~/.cache/reeb-torch/detection].")
@click.option("--limit", type=click.IntRange(min=1), help="Use only the first N frames of each folder.")
@engine_options("Where each frame's proposals and backbone maps are computed: this process, or Ray Data actors "
                "(they write the maps to --cache, which every worker must reach; training runs here; "
                "pip install 'reeb-torch[ray]').", "--engine ray: actors, each holding one detector.")
@click.option("-q", "--quiet", is_flag=True, help="No progress bars.")
def fit(dirs, out, overwrite, proposals, sets, classes, epochs, steps, seed, val, hflip, min_size, max_size, top_k_train,
        top_k_test, precision, crop_top, neck_channels, head_width, box_head_rank, int8_box_head, factorised_epochs,
        box_passes, cache_dir, limit, engine, address, actors, cpus_per_actor, quiet):
    """Train a detector on labelled KITTI-format folders (DIRS: images/ and labels/, or image_2/ and
    label_2/) and write it to OUT. The backbone's maps and REEB's proposals of each frame are
    cached, so a second fit on the same frames trains at once. Deterministic for a seed.

    The frames are read one at a time and the maps read from the cache as training needs
    them: memory does not grow with the frames. The training state is kept beside OUT after
    each epoch until the detector is written, so a fit that was stopped, started again with
    the same command, goes on from its last finished epoch.
    """
    from click.core import ParameterSource

    if factorised_epochs and not box_head_rank:
        raise click.BadParameter("passes after factorising need a --box-head-rank", param_hint="--factorised-epochs")
    path = claim_weights_out(out, overwrite)
    names = tuple(c.strip() for c in classes.split(",") if c.strip())
    if not names or len(set(names)) != len(names):
        raise click.BadParameter(f"{classes!r}: expected distinct names such as Car,Pedestrian", param_hint="--classes")
    settings = fit_settings(click.get_current_context().params)
    changes = proposal_changes(proposals, sets, settings)
    dirs, val = distinct(dirs, ""), distinct(val, "--val ")
    named = click.get_current_context().get_parameter_source("classes") is not ParameterSource.DEFAULT
    check_frames(dirs, val, names, limit, named)
    cache_dir = check_cache(cache_dir)
    command = " ".join(["reeb detector fit", *map(shlex.quote, dirs), "-o", shlex.quote(out), "--proposals",
                        shlex.quote(proposals), *(a for kv in sets for a in ("--set", shlex.quote(kv))),
                        "--classes", shlex.quote(",".join(names)), "--epochs", str(epochs), "--seed", str(seed)] + (["--steps", str(steps)] if steps else []) + (["--hflip"] if hflip else [])
                       + (["--factorised-epochs", str(factorised_epochs)] if factorised_epochs else [])
                       + _changed_options(click.get_current_context(), SETTINGS_OPTIONS)
                       + (["--limit", str(limit)] if limit else []))
    states = training_states(path)
    with warnings_as_lines():
        det, lines = train(dirs, val, names, proposals, epochs, seed, settings, cache_dir, limit, hflip, quiet,
                           command, auto_crop=crop_top == "auto", checkpoints=states, steps=steps,
                           factorised_epochs=factorised_epochs, proposal_changes=changes,
                           engine=(address, actors, cpus_per_actor) if engine == "ray" else None)
    try:
        det.save(path)
    except OSError as e:
        raise Failure(f"{out}: cannot write the detector ({e.strerror or e})")
    shutil.rmtree(states, ignore_errors=True)  # written: nothing to go on from
    lines.append(f"wrote {path}; run it with: reeb detect IMAGES --detector {shlex.quote(str(path))} -o dets.jsonl")
    errors = [line for line in lines if line.startswith("error: ")]
    click.echo("\n".join(line for line in lines if line not in errors))
    if errors:
        click.echo("\n".join(errors), err=True)
        sys.exit(1)


@detector.command("show", context_settings=CONTEXT)
@click.argument("path", type=click.Path(dir_okay=False))
def show(path):
    """What a detector file (PATH, or a shipped name such as kitti) holds: its classes,
    settings, proposals, the frames it was trained on, its held-out scores and the command
    that trains it again; a warning where reeb detect would refuse it."""
    from ..detection import DetectorFileError, ReebDetector
    from ..detection.detector import resolve_detector
    from ..detection.detector_file import read_detector_file

    try:
        tensors, meta, ranker = read_detector_file(resolve_detector(path))
    except DetectorFileError as e:
        raise UsageProblem(str(e))
    prov, backbone, proposals = (_part(meta, k) for k in ("provenance", "backbone", "proposals"))
    params = sum(t.numel() for t in tensors.values())
    lines = [f"{path}: a detector of {', '.join(meta['classes'])} ({params / 1e6:.1f} M trained parameters)",
             f"backbone: {backbone.get('name')} (weights {str(backbone.get('sha256'))[:16]}...)",
             "settings: " + ", ".join(f"{k}={v}" for k, v in _part(meta, "settings").items()),
             f"proposals: {proposals.get('spec')}{_changes_note(proposals)} (REEB config "
             f"{proposals.get('fingerprint')}); ranker: {_ranker_note(proposals, ranker)}"]
    frames, objects = prov.get("frames"), _part(prov, "objects")
    if isinstance(frames, list) and frames:
        folders = prov.get("folders") if isinstance(prov.get("folders"), list) else []
        lines.append(f"trained on {len(frames)} frames of {', '.join(map(str, folders))}: "
                     + ", ".join(f"{n} {c}" for c, n in objects.items()))
    lines += _val_lines(_part(prov, "val"))
    if prov.get("command"):
        lines.append(f"command: {prov['command']}")
    click.echo("\n".join(lines))
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ReebDetector.load(path)
    except (DetectorFileError, ImportError) as e:
        click.echo(f"warning: reeb detect refuses this file: {' '.join(str(e).split())}", err=True)


@detector.command("compress", context_settings=CONTEXT)
@click.argument("path", type=click.Path(dir_okay=False))
@click.option("-o", "--out", required=True, type=click.Path(dir_okay=False), help="The detector file to write.")
@click.option("--rank", type=SettingRange("box_head_rank"), default=0, show_default=True,
              help="Replace the box head's first layer by its approximation of this rank (0: keep it whole).")
@click.option("--int8", "int8", is_flag=True, help="The box head's layers in int8 (after --rank).")
@click.option("--overwrite", is_flag=True, help="Replace an existing --out file.")
def compress(path, out, rank, int8, overwrite):
    """Write PATH (a detector file, or a shipped name such as kitti) with a smaller box head:
    its first layer factorised (--rank) and/or its layers in int8 (--int8), as reeb detector
    fit --box-head-rank and --int8-box-head make them once trained. A smaller file and a
    faster head; check its detections on frames it was not trained on."""
    from ..detection import DetectorFileError, ReebDetector

    from ..detection.detector import resolve_detector

    if not rank and not int8:
        raise click.UsageError("nothing to do: give --rank R, --int8 or both")
    target = claim_weights_out(out, overwrite, inputs={resolve_detector(path): "PATH"})
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the float32 notice of a CPU without native bfloat16
            det = ReebDetector.load(path)
        if rank:
            det.factorise_box_head(rank)
            if not det.settings.box_head_rank:
                raise ValueError(f"--rank {rank}: not below the box head's smaller side, nothing to factorise")
        if int8:
            if det.settings.box_head_int8:
                raise ValueError("the box head is in int8 already")
            det.quantise_box_head()
    except (DetectorFileError, ValueError) as e:
        raise UsageProblem(" ".join(str(e).split())) from None
    prov = det.meta.setdefault("provenance", {})
    step = " ".join(["reeb detector compress", shlex.quote(str(path)), "-o", shlex.quote(str(out))]
                    + (["--rank", str(rank)] if rank else []) + (["--int8"] if int8 else []))
    prov["command"] = f"{prov['command']} && {step}" if prov.get("command") else step
    try:
        det.save(target)
    except OSError as e:
        raise Failure(f"{out}: cannot write the detector ({e.strerror or e})") from None
    s = det.settings
    click.echo(f"wrote {target}: box head rank {s.box_head_rank or 'full'}{', int8' if s.box_head_int8 else ''}, "
               f"{target.stat().st_size / 1e6:.1f} MB")


def _part(meta: Any, key: str) -> dict:
    """``meta[key]`` where it is a JSON object, else an empty one (a file's metadata as found)."""
    value = meta.get(key) if isinstance(meta, dict) else None
    return value if isinstance(value, dict) else {}


def _val_lines(val: dict) -> list[str]:
    """The held-out scores a detector file records (``provenance.val``), as far as they go."""
    from ..detection.fitting import format_scores

    ap = _part(val, "ap")
    if not ap:
        return []
    given = val.get("folders")
    folders = ", ".join(map(str, given)) if isinstance(given, list) else "?"
    seen = val.get("training_frames") or 0
    head = (f"KITTI 2D AP|R40 (moderate) on {folders}"
            + (f" ({seen} of its frames are training frames)" if seen else "") + ":")
    spans = _part(val, "interval_95")
    scores = {"ap": ap, "objects": _part(val, "objects"),
              "interval_95": {k: spans[k] if _is_span(spans.get(k)) else [None, None] for k in ap}}
    try:
        return [head + "\n" + format_scores(scores)]
    except (TypeError, ValueError):  # values of other types than a fit writes
        return [head + " " + ", ".join(f"{k} {v}" for k, v in ap.items())]


def _is_span(v: Any) -> bool:
    return isinstance(v, list) and len(v) == 2 and all(x is None or isinstance(x, (int, float)) for x in v)


def _changes_note(info: dict) -> str:
    """``", with FIELD=VALUE, ..."``: the REEB fields of a detector file's proposals that
    differ from its named settings' (``reeb detector fit --set``); empty where none do."""
    from ..config import get_preset
    from ..detection import PROPOSALS

    spec = info.get("spec")
    base = get_preset(spec if spec in PROPOSALS else "default").to_dict()
    stored = _part(info, "config")
    changed = [f"{k}={stored[k]}" for k in sorted(stored)
               if k not in ("ranker", "top_k") and k in base and _plain(stored[k]) != _plain(base[k])]
    return ", with " + ", ".join(changed) if changed else ""


def _plain(value: Any) -> Any:
    """A config value as JSON writes it (tuples as lists), for comparing a file's with a preset's."""
    return [_plain(v) for v in value] if isinstance(value, (list, tuple)) else value


def _ranker_note(info: dict, ranker: bytes | None) -> str:
    """Where a detector file's proposals find their ranker: embedded in it (and whether that
    copy is the one recorded), shipped with reeb-torch, a file named by its path, or none."""
    from ..ranker import SHIPPED

    name = str(_part(info, "config").get("ranker", "none"))
    sha = str(info.get("ranker_sha256"))
    if ranker is not None:
        same = hashlib.sha256(ranker).hexdigest() == sha
        return (f"embedded ({len(ranker) / 1e3:.0f} kB, SHA-256 {sha[:16]}..., "
                + ("as recorded" if same else "NOT the one recorded: damaged") + f"; fitted as {name})")
    if name == "none":
        return "none (ranked by V alone)"
    if name in SHIPPED:
        return f"shipped ({name!r}, with reeb-torch)"
    return f"the file {name} (not embedded: it must stay there; saving the loaded detector again embeds it)"
