"""``reeb detector fit`` and ``reeb detector show``: train a detector on labelled frames,
and say what a detector file holds.

::

    reeb detector fit my_frames/ -o det.safetensors            # KITTI-format folders, labelled
    reeb detector fit a/ b/ -o det.safetensors --val held_out/ # and its AP on frames it never saw
    reeb detector show det.safetensors                         # what it was trained on, its scores

``reeb detect``, which runs a detector over images, is :mod:`.detect_run`.

Exit codes: 0 success; 1 the command failed; 2 usage error (bad option, an unusable detector
file or output, checked before any work).
"""

from __future__ import annotations

import hashlib
import os
import shlex
import time
from pathlib import Path

import click

from .common import CONTEXT, Failure, UsageProblem

__all__ = ["detector", "fit", "show"]


# -- reeb detector fit ---------------------------------------------------------------------

@click.group(context_settings=CONTEXT)
def detector() -> None:
    """Train an object detector on your labelled frames (the 'detect' extra).

    REEB's proposals, a frozen ImageNet EfficientNet-Lite0 and RoI heads trained on the CPU in
    minutes. Run it on images with reeb detect.
    """


def _check_weights_out(out: str, overwrite: bool) -> Path:
    p = Path(out)
    if p.suffix.lower() != ".safetensors":
        raise UsageProblem(f"{out}: a detector is written as safetensors; name it {p.with_suffix('.safetensors')}")
    if p.is_dir():
        raise UsageProblem(f"{out}: is a folder; give a file name such as {p / 'det.safetensors'}")
    parent = p.parent if str(p.parent) else Path(".")
    if not parent.is_dir() or not os.access(parent, os.W_OK):
        raise UsageProblem(f"{out}: cannot write there (folder {parent} missing or not writable)")
    if p.exists() and not overwrite:
        raise UsageProblem(f"{out} exists; add --overwrite to replace it")
    return p


@detector.command("fit", context_settings=CONTEXT)
@click.argument("dirs", nargs=-1, required=True, type=click.Path(exists=True, file_okay=False))
@click.option("-o", "--out", type=click.Path(dir_okay=False), default="detector.safetensors", show_default=True,
              help="Detector file to write (safetensors, with its metadata).")
@click.option("--overwrite", is_flag=True, help="Replace an existing --out file.")
@click.option("--proposals", default="default", show_default=True, metavar="default|training-free|FILE",
              help="REEB's settings: the learned ranking, the training-free preset, or ranker weights "
                   "that reeb fit wrote (FILE).")
@click.option("--classes", default="Car,Pedestrian,Cyclist", show_default=True,
              help="Comma-separated class names, as the label files write them.")
@click.option("--epochs", type=click.IntRange(min=1), default=12, show_default=True, help="Passes over the frames.")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of the heads' weights and the frame order.")
@click.option("--val", multiple=True, type=click.Path(exists=True, file_okay=False), metavar="DIR",
              help="Labelled folder kept out of training: its KITTI AP|R40 is printed and stored (repeatable).")
@click.option("--hflip", is_flag=True, help="Train on each frame's mirror image half of the time.")
@click.option("--min-size", type=click.IntRange(min=32), default=576, show_default=True,
              help="Shorter side of the resized input, pixels; the backbone's time grows about with its square "
                   "(KITTI frames: 375 runs about 2x faster on a CPU and finds fewer small pedestrians).")
@click.option("--max-size", type=click.IntRange(min=32), default=2048, show_default=True,
              help="Bound on the longer side of the resized input.")
@click.option("--train-proposals", type=click.IntRange(min=1), default=2000, show_default=True,
              help="REEB proposals per image in training.")
@click.option("--test-proposals", type=click.IntRange(min=1), default=1000, show_default=True,
              help="REEB proposals per image in detection (the heads' time grows with it).")
@click.option("--cache", "cache_dir", type=click.Path(file_okay=False),
              help="Where each frame's backbone maps and proposals are kept [default: ~/.cache/reeb-torch/detection].")
@click.option("--limit", type=click.IntRange(min=1), help="Use only the first N frames of each folder.")
@click.option("-q", "--quiet", is_flag=True, help="No progress bars.")
def fit(dirs, out, overwrite, proposals, classes, epochs, seed, val, hflip, min_size, max_size, train_proposals,
        test_proposals, cache_dir, limit, quiet):
    """Train a detector on labelled KITTI-format folders (DIRS: images/ and labels/, or image_2/ and
    label_2/) and write it to OUT. The backbone's maps and REEB's proposals of each frame are
    cached, so a second fit on the same frames trains at once. Deterministic for a seed.
    """
    from ..detection import DetectorSettings, ReebDetector, evaluate_detector, format_scores

    path = _check_weights_out(out, overwrite)
    names = tuple(c.strip() for c in classes.split(",") if c.strip())
    if not names or len(set(names)) != len(names):
        raise click.BadParameter(f"{classes!r}: expected distinct names such as Car,Pedestrian", param_hint="--classes")
    settings = DetectorSettings(min_size=min_size, max_size=max_size, proposals_train=train_proposals,
                                proposals_test=test_proposals)
    command = " ".join(["reeb detector fit", *map(shlex.quote, dirs), "-o", shlex.quote(out), "--proposals",
                        shlex.quote(proposals), "--classes", shlex.quote(",".join(names)), "--epochs", str(epochs),
                        "--seed", str(seed)] + (["--hflip"] if hflip else [])
                       + (["--min-size", str(min_size)] if min_size != 576 else [])
                       + (["--max-size", str(max_size)] if max_size != 2048 else [])
                       + (["--train-proposals", str(train_proposals)] if train_proposals != 2000 else [])
                       + (["--test-proposals", str(test_proposals)] if test_proposals != 1000 else [])
                       + (["--limit", str(limit)] if limit else []))
    t0 = time.perf_counter()
    try:
        det = ReebDetector.fit(dirs, classes=names, proposals=proposals, epochs=epochs, seed=seed, settings=settings,
                               cache_dir=cache_dir, limit=limit, hflip=hflip, progress=not quiet, command=command)
    except (ValueError, FileNotFoundError, ImportError) as e:
        raise UsageProblem(" ".join(str(e).split()))
    prov = det.meta["provenance"]
    lines = [f"trained on {len(prov['frames'])} frames ("
             + ", ".join(f"{n} {c}" for c, n in prov["objects"].items()) + f"): {det.history['steps']} steps, "
             f"{det.history['train_s']:.0f} s of head training, {time.perf_counter() - t0:.0f} s in all"]
    if val:
        try:
            scores = evaluate_detector(det, val, cache_dir=cache_dir, progress=not quiet, seed=seed)
        except ValueError as e:
            raise UsageProblem(" ".join(str(e).split()))
        prov["val"] = {"folders": list(val), **scores}
        lines.append(f"KITTI 2D AP|R40 (moderate) on {scores['frames']} frames of {', '.join(val)}:\n"
                     + format_scores(scores))
        if scores["training_frames"]:
            lines.append(f"note: {scores['training_frames']} of these frames are training frames (the same "
                         "pictures): that part of the estimate is in-sample")
    try:
        det.save(path)
    except OSError as e:
        raise Failure(f"{out}: cannot write the detector ({e.strerror or e})")
    lines.append(f"wrote {path}; run it with: reeb detect IMAGES --detector {shlex.quote(str(path))} -o dets.jsonl")
    click.echo("\n".join(lines))


@detector.command("show", context_settings=CONTEXT)
@click.argument("path", type=click.Path(dir_okay=False))
def show(path):
    """What a detector file (PATH) holds: its classes, settings, proposals, the frames it was
    trained on, its held-out scores and the command that trains it again."""
    from ..detection import DetectorFileError
    from ..detection.detector_file import read_detector_file
    from ..detection.fitting import format_scores

    try:
        tensors, meta, ranker = read_detector_file(path)
    except DetectorFileError as e:
        raise UsageProblem(str(e))
    prov = meta.get("provenance") or {}
    params = sum(t.numel() for t in tensors.values())
    lines = [f"{path}: a detector of {', '.join(meta['classes'])} ({params / 1e6:.1f} M trained parameters)",
             f"backbone: {meta['backbone'].get('name')} (weights {str(meta['backbone'].get('sha256'))[:16]}...)",
             "settings: " + ", ".join(f"{k}={v}" for k, v in meta["settings"].items()),
             f"proposals: {meta['proposals'].get('spec')} (REEB config {meta['proposals'].get('fingerprint')}); "
             f"ranker: {_ranker_note(meta['proposals'], ranker)}"]
    if prov.get("frames"):
        lines.append(f"trained on {len(prov['frames'])} frames of {', '.join(prov.get('folders', []))}: "
                     + ", ".join(f"{n} {c}" for c, n in (prov.get("objects") or {}).items()))
    if isinstance(prov.get("val"), dict) and "ap" in prov["val"]:
        seen = prov["val"].get("training_frames") or 0
        lines.append(f"KITTI 2D AP|R40 (moderate) on {', '.join(prov['val'].get('folders', []))}"
                     + (f" ({seen} of its frames are training frames)" if seen else "") + ":\n"
                     + format_scores(prov["val"]))
    if prov.get("command"):
        lines.append(f"command: {prov['command']}")
    click.echo("\n".join(lines))


def _ranker_note(info: dict, ranker: bytes | None) -> str:
    """Where a detector file's proposals find their ranker: embedded in it (and whether that
    copy is the one recorded), shipped with reeb-torch, a file named by its path, or none."""
    from ..ranker import SHIPPED

    name = str((info.get("config") or {}).get("ranker", "none"))
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
