"""``reeb detect``: a trained detector run over images, on the run engine.

::

    reeb detect images/ --detector det.safetensors -o dets.jsonl --kitti-dir out/ --viz pics/
    reeb detect images/ --detector det.safetensors -o dets.jsonl --resume   # after an interruption

The command loads the detector (:class:`reeb_torch.detection.ReebDetector`) and hands the
images to :class:`_DetectRun`, the detector on :class:`.engine.ImageRun`: everything
``reeb propose`` promises about inputs, outputs, ``--resume`` (a killed run's ``.tmp`` rows
included), Ctrl-C and exit codes holds here too. Rows have ``reeb propose``'s schema:
``boxes`` (the detections, xyxy pixels, best first), ``scores``, ``labels`` (the class
names) and ``config`` (``det-`` and the detector file's SHA-256, first 16 digits);
``--resume`` keeps only the rows of the same detector file. ``--kitti-dir`` writes one
KITTI result file per image (:class:`.side_outputs.KittiFolder`), ``--viz`` a picture per
image (:func:`.viz.draw_detections`); both are named by the whole input list.

Exit codes: 0 success; 1 an image failed (named in its row and the summary) or the command
failed (an output that could not be written: one line naming it); 2 usage error (bad
option, no images, an unusable detector file or output, all checked before any work); 130
interrupted (the rows done are saved).
"""

from __future__ import annotations

import hashlib
import os
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import click

from .common import CONTEXT, FiniteFloat, UsageProblem, device_option, resolve_device
from .engine import ImageRun

__all__ = ["detect", "StageTimes"]


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


class _DetectRun(ImageRun):
    """One ``reeb detect`` run: the detector on :class:`~.engine.ImageRun`."""

    noun = "detections"
    desc = "detect"

    def __init__(self, det: Any, det_id: str, dev: Any, *, out: str | None, batch_size: int, workers: int | None,
                 min_score: float, viz_min_score: float, quiet: bool) -> None:
        super().__init__(made_by=det_id, out=out, batch_size=batch_size, workers=workers, quiet=quiet)
        self.det, self.dev = det, dev
        self.min_score, self.viz_min_score = min_score, viz_min_score
        self.warm: tuple[int, float, dict[str, float]] | None = None
        """(images, detector seconds, stage seconds) of the first batch, which pays the warm-up."""
        self.detect_s = 0.0
        self.stages = StageTimes(det.model, dev)

    def mismatch(self, out: str, configs: list[str]) -> str:
        return (f"{out} holds detections of another detector ({', '.join(configs)}, this one is "
                f"{self.made_by}); use another --out, or --overwrite")

    def stream(self, images):
        from .decoding import decoded_images

        return decoded_images(images, self.workers, quiet=self.quiet)

    def groups(self, stream):
        return _chunks(stream, self.batch_size)

    def run_batch(self, items: list) -> list:
        t0 = time.perf_counter()
        outs = self.det([it.image.to(self.dev) for it in items])
        self.detect_s += time.perf_counter() - t0
        return outs

    def after_group(self) -> None:
        if self.warm is None and self.stats["ok"]:
            self.warm = (self.stats["ok"], self.detect_s, dict(self.stages.seconds))

    def finish(self, item: Any, out: dict) -> None:
        from .rows import result_row

        keep = out["scores"] >= self.min_score
        out = {k: v[keep].cpu() for k, v in out.items()}
        names = [self.det.categories[int(i)] for i in out["labels"]]
        h, w = item.image.shape[-2:]
        row = result_row(item.path, w, h, out["boxes"], out["scores"], self.made_by, labels=names)
        self.emit(item, row, len(names))
        stem = self.stem(item)
        if self.kitti is not None and row["status"] == "ok":
            self.kitti.write(stem, row)
        if self.pictures is not None:
            self.pictures.save(stem, lambda: self._picture(item, out, names))

    def _picture(self, item: Any, out: dict, names: list[str]) -> Any:
        from .viz import draw_detections

        shown = (out["scores"] >= self.viz_min_score).nonzero().flatten().tolist()
        title = f"{Path(item.path).name}: {len(shown)} detections scoring {self.viz_min_score:g} or more"
        return draw_detections(item.image, out["boxes"][shown], [names[i] for i in shown], out["scores"][shown],
                               title, self.det.classes)

    def time_lines(self, done: int) -> list[str]:
        if not self.stats["ok"]:
            return []
        n, det_s, stages, note = self.stats["ok"], self.detect_s, self.stages.seconds, ""
        if self.warm is not None and n > self.warm[0]:  # after the first batch (warm-up)
            n, det_s = n - self.warm[0], self.detect_s - self.warm[1]
            stages = {k: v - self.warm[2][k] for k, v in stages.items()}
            note = ", after the first batch"
        per = {k: f"{1000 * v / n:.0f}" for k, v in stages.items()}
        return [f"time: {self.wall:.1f} s, {1000 * self.wall / max(1, done):.0f} ms/img end to end; in the detector "
                f"{1000 * det_s / n:.0f} ms/img{note} (proposals {per['proposals']}, backbone "
                f"{per['backbone']}, heads {per['heads']} ms; {self.dev})"]


def _load_detector(path: str, device: str) -> tuple[Any, str, Any]:
    from ..detection import DetectorFileError, ReebDetector

    dev = resolve_device(device)
    try:
        det = ReebDetector.load(path, device=dev)
    except (DetectorFileError, ImportError) as e:
        raise UsageProblem(" ".join(str(e).split()))
    digest = hashlib.sha256(Path(os.path.expanduser(path)).read_bytes()).hexdigest()
    return det, f"det-{digest[:16]}", dev


@click.command("detect", context_settings=CONTEXT)
@click.argument("paths", nargs=-1, required=True, type=click.Path(readable=False))
@click.option("--detector", "detector_path", required=True, type=click.Path(dir_okay=False),
              help="The detector file reeb detector fit wrote.")
@click.option("-o", "--out", type=click.Path(dir_okay=False),
              help="Write one row per image here: .jsonl (JSON Lines) or .parquet.")
@click.option("--overwrite", is_flag=True, help="Replace an existing --out file (and the files in --kitti-dir).")
@click.option("--resume", is_flag=True,
              help="Keep the rows this detector already wrote to --out; detect only on the images missing there "
                   "(or that failed).")
@click.option("--kitti-dir", type=click.Path(file_okay=False),
              help="Write one KITTI result file per image here (<image stem>.txt), as KITTI's devkit scores them; "
                   "an empty folder, or one of this output's results with --resume.")
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
@device_option
@click.option("-r", "--recursive", is_flag=True, help="Look for images in sub-folders too.")
@click.option("-q", "--quiet", is_flag=True, help="No progress bar, no per-file messages.")
def detect(paths, detector_path, out, overwrite, resume, kitti_dir, viz_dir, min_score, viz_min_score, batch_size,
           workers, device, recursive, quiet):
    """Run a trained detector on images (PATHS: files, folders or globs) and write its
    detections: rows to OUT, KITTI result files to --kitti-dir, pictures to --viz.

    A file that cannot be processed never stops the run: it gets an "error: ..." row, is
    named in the summary, and the exit code is 1. The output is written atomically; after
    Ctrl-C what is done is saved, and --resume continues (also from the rows a killed run
    left in a hidden .NAME.*.tmp file).
    """
    if not (out or kitti_dir or viz_dir):
        raise UsageProblem("nothing to write: give -o/--out, --kitti-dir or --viz")
    det, det_id, dev = _load_detector(detector_path, device)
    run = _DetectRun(det, det_id, dev, out=out, batch_size=batch_size, workers=workers, min_score=min_score,
                     viz_min_score=viz_min_score, quiet=quiet)
    run.find_inputs(paths, recursive)  # 1. inputs
    work = run.plan_output(resume, overwrite)  # 2. the output, checked and locked before any work
    run.side_outputs(viz_dir, kitti_dir, det.categories, resume=resume, overwrite=overwrite)  # 3. its folders
    if not work:
        return run.nothing_to_do()
    run.run()  # 4. the run
    run.save_and_summarise()  # 5. save and summarise
