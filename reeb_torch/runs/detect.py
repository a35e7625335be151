"""``reeb detector fit`` and ``reeb detect``: train a detector on labelled frames, run it on images.

::

    reeb detector fit my_frames/ -o det.safetensors            # KITTI-format folders, labelled
    reeb detector fit a/ b/ -o det.safetensors --val held_out/ # and its AP on frames it never saw
    reeb detector show det.safetensors                         # what it was trained on, its scores
    reeb detect images/ --detector det.safetensors -o dets.jsonl --kitti-dir out/ --viz pics/

``reeb detect`` runs as ``reeb propose`` does (:mod:`.inputs`, :mod:`.decoding`, :mod:`.rows`,
:mod:`.output_files`, :mod:`.output_lock`): images found in files, folders and globs, decoded
in worker processes, one row per image in input order (a file that cannot be read becomes an ``error:`` row and the run goes on), the output written to a temporary
file and renamed into place, a lock against a second run on it, a progress bar; ``--resume``
keeps the rows the same detector wrote and detects only on the images missing. Rows have
``reeb propose``'s schema: ``boxes`` (the detections, xyxy pixels, best first), ``scores``,
``labels`` (the class names) and ``config`` (``det-`` and the detector file's SHA-256, first
16 digits). ``--kitti-dir`` writes one KITTI result file per image
(:func:`reeb_torch.detection.write_results`).

Exit codes: 0 success; 1 an image failed (named in its row and the summary) or the command
failed; 2 usage error (bad option, no images, an unusable detector file or output, all
checked before any work); 130 interrupted (the rows done are saved).
"""

from __future__ import annotations

import hashlib
import os
import shlex
import sys
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import click

from .common import Failure, FiniteFloat, UsageProblem, claim_output, resolve_device

__all__ = ["detector", "fit", "show", "detect", "draw_detections", "StageTimes"]

CONTEXT = dict(help_option_names=["-h", "--help"], max_content_width=100)
CLASS_COLOURS = ((255, 200, 0), (0, 200, 255), (255, 80, 200), (120, 255, 80), (255, 120, 60), (160, 120, 255))


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


# -- reeb detect ------------------------------------------------------------------------------

def draw_detections(image: Any, boxes: Any, labels: Sequence[str], scores: Any, title: str | None = None,
                    classes: Sequence[str] = ()) -> Any:
    """``image`` (``uint8 [3, H, W]``) with each detection's box (``[D, 4]`` xyxy), class name
    and score, one colour per class (the colours follow ``classes``' order, where given); an RGB
    ``uint8`` array ``(H', W, 3)`` (a title band on top)."""
    import cv2
    import numpy as np

    canvas = np.ascontiguousarray(image.permute(1, 2, 0).cpu().numpy())
    h, w = canvas.shape[:2]
    fs = max(0.35, min(w, 2 * h) / 1600)
    colours: dict[str, tuple[int, int, int]] = {n: CLASS_COLOURS[i % len(CLASS_COLOURS)] for i, n in enumerate(classes)}
    for (x1, y1, x2, y2), name, s in reversed(list(zip(boxes.tolist(), labels, scores.tolist()))):
        c = colours.setdefault(name, CLASS_COLOURS[len(colours) % len(CLASS_COLOURS)])
        p1, p2 = (int(round(x1)), int(round(y1))), (int(round(x2)), int(round(y2)))
        cv2.rectangle(canvas, p1, p2, c, 2, cv2.LINE_AA)
        cv2.putText(canvas, f"{name} {s:.2f}", (p1[0], max(p1[1] - 3, 10)), cv2.FONT_HERSHEY_SIMPLEX, fs, c, 1,
                    cv2.LINE_AA)
    if title:
        band = np.full((int(28 * fs / 0.5), w, 3), 30, np.uint8)
        cv2.putText(band, title, (6, band.shape[0] - 8), cv2.FONT_HERSHEY_SIMPLEX, fs, (255, 255, 255), 1, cv2.LINE_AA)
        canvas = np.concatenate([band, canvas])
    return canvas


def _unique_names(images: Sequence[Path]) -> dict[str, str]:
    """A distinct file stem per image: its own, ``<stem>-<n>`` where two share one."""
    from collections import Counter

    stems = Counter(Path(p).stem for p in images)
    out: dict[str, str] = {}
    for i, p in enumerate(images):
        stem = Path(p).stem
        out[str(p)] = stem if stems[stem] == 1 else f"{stem}-{i + 1}"
    return out


class StageTimes:
    """Wall seconds spent in the backbone, the proposals and the heads of a torchvision
    detector (forward hooks on ``model.backbone``, ``model.rpn``, ``model.roi_heads``);
    ``seconds``: the running totals. On a CUDA ``device`` each stage's end waits for the GPU
    (``torch.cuda.synchronize``), so the seconds are the stage's, not its launch's."""

    def __init__(self, model: Any, device: Any = "cpu") -> None:
        import torch

        self.seconds = {"backbone": 0.0, "proposals": 0.0, "heads": 0.0}
        self._t: dict[str, float] = {}
        cuda = torch.device(device).type == "cuda"
        self._sync = (lambda: torch.cuda.synchronize(device)) if cuda else (lambda: None)
        for name, module in (("backbone", model.backbone), ("proposals", model.rpn), ("heads", model.roi_heads)):
            module.register_forward_pre_hook(lambda m, a, n=name: self._start(n))
            module.register_forward_hook(lambda m, a, o, n=name: self._add(n))

    def _start(self, name: str) -> None:
        self._sync()
        self._t[name] = time.perf_counter()

    def _add(self, name: str) -> None:
        self._sync()
        self.seconds[name] += time.perf_counter() - self._t.pop(name)


def _chunks(stream: Iterator[Any], size: int) -> Iterator[list[Any]]:
    chunk: list[Any] = []
    for item in stream:
        chunk.append(item)
        if len(chunk) == size:
            yield chunk
            chunk = []
    if chunk:
        yield chunk


class _DetectRun:
    """One ``reeb detect`` run: the state its steps share."""

    def __init__(self, det: Any, det_id: str, dev: Any, kitti_dir: Path | None, viz_dir: Path | None,
                 min_score: float, viz_min_score: float, quiet: bool) -> None:
        self.det, self.det_id, self.dev = det, det_id, dev
        self.kitti_dir, self.viz_dir, self.min_score, self.quiet = kitti_dir, viz_dir, min_score, quiet
        self.viz_min_score = viz_min_score
        self.warm: tuple[int, float, dict[str, float]] | None = None
        """(images, detector seconds, stage seconds) of the first batch, which pays the warm-up."""
        self.failures: list[str] = []
        self.ok = self.detections = 0
        self.detect_s = 0.0
        self.stages = StageTimes(det.model, dev)

    def run(self, images: Sequence[Path], workers: int, batch_size: int, writer: Any) -> bool:
        """Detect on every image, a row each in input order; False when interrupted."""
        from tqdm import tqdm

        from .decoding import decoded_images

        self.names = _unique_names(images)
        bar = tqdm(total=len(images), desc="detect", unit="img", disable=self.quiet)
        try:
            for chunk in _chunks(decoded_images(images, workers, quiet=self.quiet), batch_size):
                rows = self._chunk(chunk)
                if writer is not None:
                    writer.write(rows)
                bar.update(len(chunk))
                if self.warm is None and self.ok:
                    self.warm = (self.ok, self.detect_s, dict(self.stages.seconds))
        except KeyboardInterrupt:
            return False
        finally:
            bar.close()
        return True

    def _chunk(self, chunk: list[Any]) -> list[dict]:
        from .rows import error_row, file_error

        good = [it for it in chunk if it.ok]
        try:
            t0 = time.perf_counter()
            outs = self.det([it.image.to(self.dev) for it in good]) if good else []
            self.detect_s += time.perf_counter() - t0
            results: dict[int, Any] = {it.index: o for it, o in zip(good, outs)}
        except (RuntimeError, ValueError):  # one by one, to name the culprit
            results = {it.index: self._one(it) for it in good}
        rows = []
        for it in chunk:
            r = results.get(it.index, it.error)
            if isinstance(r, dict):
                rows.append(self._finish(it, r))
            else:
                message = r if isinstance(r, str) else file_error(it.path, r)
                self.failures.append(message)
                if not self.quiet:
                    click.echo(f"error: {message}", err=True)
                rows.append(error_row(it.path, message, self.det_id, it.size))
        return rows

    def _one(self, it: Any) -> Any:
        try:
            return self.det([it.image.to(self.dev)])[0]
        except (RuntimeError, ValueError) as e:
            return e

    def _finish(self, it: Any, out: dict) -> dict:
        from ..detection import write_results
        from .rows import result_row
        from .viz import save_png

        keep = out["scores"] >= self.min_score
        out = {k: v[keep].cpu() for k, v in out.items()}
        names = [self.det.categories[int(i)] for i in out["labels"]]
        self.ok += 1
        self.detections += len(names)
        stem = self.names[it.path]
        try:
            if self.kitti_dir is not None:
                write_results(self.kitti_dir / f"{stem}.txt", out, self.det.categories)
            if self.viz_dir is not None:
                shown = (out["scores"] >= self.viz_min_score).nonzero().flatten().tolist()
                title = f"{Path(it.path).name}: {len(shown)} detections scoring {self.viz_min_score:g} or more"
                save_png(self.viz_dir / f"{stem}.png", draw_detections(
                    it.image, out["boxes"][shown], [names[i] for i in shown], out["scores"][shown], title,
                    self.det.classes))
        except OSError as e:
            raise Failure(f"{e.filename or stem}: cannot write ({e.strerror or e})") from None
        h, w = it.image.shape[-2:]
        return result_row(it.path, w, h, out["boxes"], out["scores"], self.det_id, labels=names)

    def summary(self, n_images: int, wall: float) -> list[str]:
        done = self.ok + len(self.failures)
        lines = [f"{done} image{'s' if done != 1 else ''}: {self.ok} ok, {len(self.failures)} failed; "
                 f"{self.detections} detections"]
        if self.ok:
            n, det_s, stages, note = self.ok, self.detect_s, self.stages.seconds, ""
            if self.warm is not None and self.ok > self.warm[0]:  # after the first batch (warm-up)
                n, det_s = self.ok - self.warm[0], self.detect_s - self.warm[1]
                stages = {k: v - self.warm[2][k] for k, v in stages.items()}
                note = ", after the first batch"
            per = {k: f"{1000 * v / n:.0f}" for k, v in stages.items()}
            lines.append(f"time: {wall:.1f} s, {1000 * wall / max(1, done):.0f} ms/img end to end; in the detector "
                         f"{1000 * det_s / n:.0f} ms/img{note} (proposals {per['proposals']}, backbone "
                         f"{per['backbone']}, heads {per['heads']} ms; {self.dev})")
        if self.failures:
            lines.append(f"failed ({len(self.failures)}):")
            lines += [f"  {m}" for m in self.failures]
        if done < n_images:
            lines.append(f"interrupted after {done} of {n_images} images; the rows done are saved")
        return lines


class _InOrder:
    """Writes this run's rows with the rows kept from an earlier run (``--resume``), in input
    order: ``kept`` has one entry per input, its kept row or ``None`` (computed now)."""

    def __init__(self, writer: Any, first: list[dict], kept: list[dict | None]) -> None:
        self.writer, self.kept, self.pos = writer, kept, 0
        writer.write(first)  # kept rows of files that are not among the inputs
        self._kept_run([])

    def _kept_run(self, out: list[dict]) -> None:
        while self.pos < len(self.kept) and self.kept[self.pos] is not None:
            out.append(self.kept[self.pos])  # type: ignore[arg-type]
            self.pos += 1
        self.writer.write(out)

    def write(self, rows: list[dict]) -> None:
        for row in rows:
            self.pos += 1
            self._kept_run([row])

    def rest(self) -> None:
        """The kept rows after the last computed one (after an interrupt too)."""
        self.writer.write([r for r in self.kept[self.pos:] if r is not None])
        self.pos = len(self.kept)


def _resume_rows(out: str, det_id: str, images: Sequence[Path]) -> tuple[list[dict], list[dict | None]]:
    """The ``ok`` rows of ``out`` made by this detector: those of files not among ``images``,
    and per input its row or ``None`` (to compute)."""
    from .output_files import OutputError, read_results
    from .rows import row_key

    try:
        rows, problems = read_results(out)
    except OutputError as e:
        raise UsageProblem(str(e))
    for p in problems:
        click.echo(f"warning: {p}", err=True)
    ok = [r for r in rows if r.get("status") == "ok"]
    other = {str(r.get("config")) for r in ok} - {det_id}
    if other:
        raise UsageProblem(f"{out} holds detections of another detector ({', '.join(sorted(other))}, this one is "
                           f"{det_id}); use another --out, or --overwrite")
    by_key: dict[str, dict] = {}
    for r in ok:
        by_key.setdefault(str(r.get("resolved") or row_key(str(r["image"]))), r)
    keys = [row_key(p) for p in images]
    inputs = set(keys)
    first = [r for k, r in by_key.items() if k not in inputs]
    return first, [by_key.get(k) for k in keys]


def _load_detector(path: str, device: str) -> tuple[Any, str, Any]:
    from ..detection import DetectorFileError, ReebDetector

    dev = resolve_device(device)
    try:
        det = ReebDetector.load(path, device=dev)
    except (DetectorFileError, ImportError) as e:
        raise UsageProblem(" ".join(str(e).split()))
    digest = hashlib.sha256(Path(os.path.expanduser(path)).read_bytes()).hexdigest()
    return det, f"det-{digest[:16]}", dev


def _out_folder(path: str | None, option: str) -> Path | None:
    if path is None:
        return None
    p = Path(path)
    try:
        p.mkdir(parents=True, exist_ok=True)
        if not os.access(p, os.W_OK):
            raise PermissionError(13, "not writable")
    except OSError as e:
        raise UsageProblem(f"{option} {p}: cannot write there ({e.strerror or e})")
    return p


@click.command("detect", context_settings=CONTEXT)
@click.argument("paths", nargs=-1, required=True, type=click.Path())
@click.option("--detector", "detector_path", required=True, type=click.Path(dir_okay=False),
              help="The detector file reeb detector fit wrote.")
@click.option("-o", "--out", type=click.Path(dir_okay=False),
              help="Write one row per image here: .jsonl (JSON Lines) or .parquet.")
@click.option("--overwrite", is_flag=True, help="Replace an existing --out file.")
@click.option("--resume", is_flag=True,
              help="Keep the rows this detector already wrote to --out; detect only on the images missing there "
                   "(or that failed).")
@click.option("--kitti-dir", type=click.Path(file_okay=False),
              help="Write one KITTI result file per image here (<image stem>.txt), as KITTI's devkit scores them.")
@click.option("--viz", "viz_dir", type=click.Path(file_okay=False),
              help="Save a picture per image here, with each detection's class and score.")
@click.option("--min-score", type=FiniteFloat(0, 1), default=0.0, show_default=True,
              help="Keep detections scoring at least this (in every output).")
@click.option("--viz-min-score", type=FiniteFloat(0, 1), default=0.3, show_default=True,
              help="Draw detections scoring at least this in the --viz pictures.")
@click.option("-b", "--batch-size", type=click.IntRange(min=1), default=1, show_default=True,
              help="Images run through the detector together.")
@click.option("-j", "--workers", type=click.IntRange(min=0), default=None,
              help="Decoding processes beside the detector (0 = decode inline). [default: min(2, CPUs)]")
@click.option("--device", default="auto", show_default=True, help="cpu, cuda, cuda:N, or auto (CUDA when available).")
@click.option("-r", "--recursive", is_flag=True, help="Look for images in sub-folders too.")
@click.option("-q", "--quiet", is_flag=True, help="No progress bar, no per-file messages.")
def detect(paths, detector_path, out, overwrite, resume, kitti_dir, viz_dir, min_score, viz_min_score, batch_size, workers,
           device, recursive, quiet):
    """Run a trained detector on images (PATHS: files, folders or globs) and write its
    detections: rows to OUT, KITTI result files to --kitti-dir, pictures to --viz.
    """
    from .decoding import default_workers
    from .inputs import NoImagesError, scan_images
    from .output_files import open_writer

    if not (out or kitti_dir or viz_dir):
        raise UsageProblem("nothing to write: give -o/--out, --kitti-dir or --viz")
    det, det_id, dev = _load_detector(detector_path, device)
    try:
        found = scan_images(paths, recursive)
    except NoImagesError as e:
        raise UsageProblem(str(e))
    for n in found.notes if not quiet else ():
        click.echo(f"note: {n}", err=True)
    images, first, kept = found.images, [], [None] * len(found.images)
    if resume and not out:
        raise UsageProblem("--resume needs --out (the file to continue)")
    if out:
        claim_output(out)
        if Path(out).exists() and resume and not overwrite:
            first, kept = _resume_rows(out, det_id, images)
            images = [p for p, r in zip(images, kept) if r is None]
            click.echo(f"resume: {len(kept) - len(images)} images already in {out}; {len(images)} to do", err=True)
        elif Path(out).exists() and not overwrite:
            raise UsageProblem(f"{out} exists; add --resume to continue it or --overwrite to replace it")
    kitti, viz = _out_folder(kitti_dir, "--kitti-dir"), _out_folder(viz_dir, "--viz")
    run = _DetectRun(det, det_id, dev, kitti, viz, min_score, viz_min_score, quiet)
    t0 = time.perf_counter()
    writer = open_writer(out) if out else None
    try:
        ordered = _InOrder(writer, first, kept) if writer is not None else None
        finished = run.run(images, default_workers() if workers is None else workers, batch_size, ordered)
        if ordered is not None:
            ordered.rest()
        saved = writer.commit() if writer is not None else None
    except BaseException:
        if writer is not None:
            writer.discard()
        raise
    lines = run.summary(len(images), time.perf_counter() - t0)
    if saved is not None and writer is not None:
        lines.append(f"wrote {saved} ({writer.rows_written} rows)")
    if kitti is not None:
        lines.append(f"KITTI result files in {kitti}/")
    if viz is not None:
        lines.append(f"pictures in {viz}/")
    click.echo("\n".join(lines), err=True)
    if not finished:
        sys.exit(130)
    if run.failures:
        sys.exit(1)
