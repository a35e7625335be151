"""``reeb detect``: a trained detector run over images, on the run engine.

::

    reeb detect images/ --detector det.safetensors -o dets.jsonl --kitti-dir out/ --viz pics/
    reeb detect images/ --detector det.safetensors -o dets.jsonl --resume   # after an interruption

The command (:mod:`.cli`) loads the detector (:func:`load_detector`) and hands the images to
:func:`run_detect`: :class:`DetectStep`, the detector, on :class:`.engine.ImageRun`; everything
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
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

from .common import UsageProblem, resolve_device
from .decoding import decoded_images, default_workers
from .engine import Found, ImageRun

__all__ = ["run_detect", "load_detector", "DetectStep"]


def _chunks(stream: Iterator[Any], size: int) -> Iterator[list[Any]]:
    chunk: list[Any] = []
    for item in stream:
        chunk.append(item)
        if len(chunk) == size:
            yield chunk
            chunk = []
    if chunk:
        yield chunk


class DetectStep:
    """A trained detector as a step of the run engine (:class:`~.engine.RunStep`): images in
    chunks of ``batch_size``, detections scoring ``min_score`` or more, the ``--viz``
    pictures of those scoring ``viz_min_score`` or more, a clock per stage."""

    noun = "detections"
    desc = "detect"

    def __init__(self, det: Any, det_id: str, dev: Any, *, batch_size: int, workers: int | None,
                 min_score: float, viz_min_score: float, quiet: bool) -> None:
        self.det, self.made_by, self.dev = det, det_id, dev
        self.batch_size, self.quiet = batch_size, quiet
        self.workers = default_workers() if workers is None else workers
        self.min_score, self.viz_min_score = min_score, viz_min_score
        self.warm: tuple[int, float, dict[str, float]] | None = None
        """(images, detector seconds, stage seconds) of the first batch, which pays the warm-up."""
        self.detect_s = 0.0
        from ..detection.inference import StageClock

        det.clock = StageClock(dev)
        self.stages = det.clock

    def mismatch(self, out: str, configs: list[str]) -> str:
        return (f"{out} holds detections of another detector ({', '.join(configs)}, this one is "
                f"{self.made_by}); use another --out, or --overwrite")

    def prepare(self, images: Sequence[Path]) -> None:
        """Nothing: the detector is loaded (:func:`load_detector`)."""

    def stream(self, images):
        return decoded_images(images, self.workers, quiet=self.quiet)

    def groups(self, stream):
        return _chunks(stream, self.batch_size)

    def run_batch(self, items: list) -> list:
        t0 = time.perf_counter()
        outs = self.det([it.image.to(self.dev) for it in items])
        self.detect_s += time.perf_counter() - t0
        return outs

    def after_group(self, done: int, ok: int, elapsed: float) -> None:
        if self.warm is None and ok:
            self.warm = (ok, self.detect_s, dict(self.stages.seconds))

    def found(self, item: Any, out: dict) -> Found:
        keep = out["scores"] >= self.min_score
        out = {k: v[keep].cpu() for k, v in out.items()}
        names = [self.det.categories[int(i)] for i in out["labels"]]
        return Found(out["boxes"], out["scores"], names, lambda: self._picture(item, out, names))

    def _picture(self, item: Any, out: dict, names: list[str]) -> Any:
        from .viz import draw_detections

        shown = (out["scores"] >= self.viz_min_score).nonzero().flatten().tolist()
        title = f"{Path(item.path).name}: {len(shown)} detections scoring {self.viz_min_score:g} or more"
        return draw_detections(item.image, out["boxes"][shown], [names[i] for i in shown], out["scores"][shown],
                               title, self.det.classes)

    def time_lines(self, done: int, ok: int, wall: float) -> list[str]:
        if not ok:
            return []
        n, det_s, stages, note = ok, self.detect_s, self.stages.seconds, ""
        if self.warm is not None and n > self.warm[0]:  # after the first batch (warm-up)
            n, det_s = n - self.warm[0], self.detect_s - self.warm[1]
            stages = {k: v - self.warm[2][k] for k, v in stages.items()}
            note = ", after the first batch"
        else:
            note = ", the warm-up included (one batch)"
        per = {k: 1000 * v / n for k, v in stages.items()}
        heads = sum(per[k] for k in ("neck", "roi_align", "box_head", "postprocess"))
        return [f"time: {wall:.1f} s, {1000 * wall / max(1, done):.0f} ms/img end to end; in the detector "
                f"{1000 * det_s / n:.0f} ms/img{note} (proposals {per['proposals']:.0f}, resize {per['resize']:.0f}, "
                f"backbone {per['backbone']:.0f}, heads {heads:.0f} ms; {self.dev}, backbone in "
                f"{self.det.precision})"]

    def record(self, done: int, ok: int, wall: float) -> dict:
        return {}

    def extra_lines(self, ok: int) -> list[str]:
        return []


def load_detector(path: str, device: str) -> tuple[Any, str, Any]:
    """The detector file at ``path`` loaded on ``device`` (``--device``), what its rows'
    ``config`` holds (``det-`` and the file's SHA-256, first 16 digits) and the device; a
    usage error when it cannot be loaded."""
    from ..detection import DetectorFileError, ReebDetector  # here: a usage error comes before the model loads
    from ..detection.detector import resolve_detector

    dev = resolve_device(device)
    try:
        det = ReebDetector.load(path, device=dev)
    except (DetectorFileError, ImportError) as e:
        raise UsageProblem(" ".join(str(e).split()))
    digest = hashlib.sha256(resolve_detector(path).read_bytes()).hexdigest()
    return det, f"det-{digest[:16]}", dev


def run_detect(paths: Sequence[str], det: Any, det_id: str, dev: Any, *, out: str | None, overwrite: bool,
               resume: bool, kitti_dir: str | None, viz_dir: str | None, min_score: float, viz_min_score: float,
               batch_size: int, workers: int | None, recursive: bool, quiet: bool) -> None:
    """``reeb detect``: ``det`` (a loaded detector, :func:`load_detector`; ``det_id`` what its
    rows' ``config`` holds) on the images of ``paths``, the options as the command takes them.

    Usage errors (exit 2) are raised as :class:`~.common.UsageProblem` before any work;
    the process exits 1 when an image failed or an output could not be written in full, 130
    when interrupted.
    """
    step = DetectStep(det, det_id, dev, batch_size=batch_size, workers=workers, min_score=min_score,
                      viz_min_score=viz_min_score, quiet=quiet)
    run = ImageRun(step, out=out, quiet=quiet)
    run.find_inputs(paths, recursive)  # 1. inputs
    work = run.plan_output(resume, overwrite)  # 2. the output, checked and locked before any work
    run.side_outputs(viz_dir, kitti_dir, det.categories, resume=resume, overwrite=overwrite)  # 3. its folders
    if not work:
        return run.nothing_to_do()
    run.run()  # 4. the run
    run.save_and_summarise()  # 5. save and summarise
