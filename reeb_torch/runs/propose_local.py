"""``reeb propose`` on this machine: images in, one row per image out, in input order.

:func:`propose_local` runs the command's local engine, :class:`.engine.ImageRun` (the
inputs, the output checked and locked before any work, ``--resume``, the ordered writer,
``--viz``, the closing summary and exit codes), on :class:`ProposeStep`, the proposal
generator: images decoded in DataLoader workers beside the algorithm (:mod:`.decoding`),
batches of equal-sized images, the kernels warmed up before the clock starts, the
``--print-top`` tables and the bundled sample's picture. The Ray engine is
:mod:`.propose_ray`.
"""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Any, Sequence

from .common import UsageProblem, box_table, bundled_sample, label_for, read_labels
from .decoding import decoded_images, default_workers, size_batches
from .engine import Found, ImageRun, mismatch_line, ms_per_img
from .rows import hint_names, text_path

__all__ = ["propose_local", "ProposeStep"]


def propose_local(paths: Sequence[str], cfg: Any, dev: Any, *, out: str | None, resume: bool, overwrite: bool,
                  batch_size: int, workers: int | None, viz_dir: str | None, viz_top: int, recursive: bool,
                  print_top: int | None, summary_json: str | None, quiet: bool) -> None:
    """``reeb propose`` with ``--engine local``: ``cfg`` (a ReebConfig) and ``dev`` (a
    ``torch.device``) as the command line built them, the other options as it takes them;
    the bundled sample without ``paths``.

    Usage errors (exit 2) are raised as :class:`~.common.UsageProblem` before any work;
    the process exits 1 when an image failed, 130 when interrupted.
    """
    sample_mode = not paths
    step = ProposeStep(cfg, dev, batch_size=batch_size, workers=workers, viz_top=viz_top, quiet=quiet)
    run = ImageRun(step, out=out, summary_json=summary_json, quiet=quiet)
    run.find_inputs([bundled_sample()] if sample_mode else paths, recursive)  # 1. inputs
    work = run.plan_output(resume, overwrite)  # 2. the output, checked and locked before any work
    run.side_outputs(viz_dir, resume=resume, overwrite=overwrite)  # 3. the pictures
    step.what_is_shown(run.out, viz_dir, print_top, sample_mode, run.echo_err)
    if not work:
        return run.nothing_to_do()
    run.run()  # 4. the run
    run.save_and_summarise()  # 5. save and summarise


class ProposeStep:
    """The proposal generator as a step of the run engine (:class:`~.engine.RunStep`):
    images decoded in workers, batches of equal-sized images, the kernels warmed up before
    the clock starts, the ``--print-top`` tables and the bundled sample's picture."""

    noun = "proposals"
    desc = "reeb propose"

    def __init__(self, cfg: Any, dev: Any, *, batch_size: int, workers: int | None, viz_top: int,
                 quiet: bool) -> None:
        self.cfg, self.dev, self.viz_top, self.batch_size, self.quiet = cfg, dev, viz_top, batch_size, quiet
        self.made_by = cfg.fingerprint()
        self.workers = default_workers() if workers is None else workers
        self.first_done: tuple[float, int, float] | None = None
        """(seconds into the run, images done, algorithm seconds) after the first computed batch."""
        self.compile_s = self.size_warm_s = self.algo_s = 0.0  # warm-up, kept out of the times (prepare)
        self.sized = False
        self.sample_mode = False
        self.sample_png: Path | None = None
        self.print_top = 0
        self.gt: list | None = None

    def mismatch(self, out: str, configs: list[str]) -> str:
        return mismatch_line(out, configs, self.made_by)

    def what_is_shown(self, out: str | None, viz_dir: str | None, print_top: int | None, sample_mode: bool,
                      echo_err: Any) -> None:
        """How many boxes are printed per image, and the sample's picture
        (``reeb_proposals.png`` in the current folder, unless ``--viz``)."""
        sample_png = Path("reeb_proposals.png") if sample_mode and viz_dir is None else None
        if sample_png is not None and not os.access(sample_png.parent.resolve(), os.W_OK):
            raise UsageProblem(f"cannot write {sample_png.resolve()}: the current folder is not "
                               "writable (use --viz DIR)")
        self.sample_png = sample_png
        self.sample_mode = sample_mode
        self.print_top = (0 if out else 10) if print_top is None else print_top
        if not out and not sample_mode and viz_dir is None:
            echo_err("note: no --out given: proposals are printed, not saved")

    # -- the generator ------------------------------------------------------------------------
    def prepare(self, images: Sequence[Path]) -> None:
        """Build the generator and, before the clock starts, compile (or load) the CPU
        kernels; the summary gives that time apart (``compile_s``, with the first batch's
        warm-up: :meth:`run_batch`)."""
        from ..generator import ProposalGenerator, _warm_for  # here: a usage error comes before the model loads

        try:
            self.gen = ProposalGenerator(self.cfg).to(self.dev).eval()
        except (TypeError, ValueError, ArithmeticError) as e:
            raise UsageProblem(f"the settings are not usable: {' '.join(str(e).split())}")
        self.compile_s = _warm_for(self.cfg) if self.dev.type == "cpu" else 0.0
        label = label_for(images[0]) if self.sample_mode else None
        self.gt = read_labels(label) if label else None

    def stream(self, images):
        return decoded_images(images, workers=self.workers, min_side=self.cfg.min_window, prefetch=self.batch_size,
                              pin_memory=self.dev.type == "cuda", quiet=self.quiet)

    def groups(self, stream):
        # max_lag: a group of a rare size waits at most this many inputs, which bounds the
        # rows held back to be written in input order
        return size_batches(stream, self.batch_size, max_lag=max(64, 4 * self.batch_size))

    def after_group(self, done: int, ok: int, elapsed: float) -> None:
        if self.first_done is None and ok:
            self.first_done = (elapsed, done, self.algo_s)

    def run_batch(self, items: list) -> list:
        import torch

        x = torch.stack([it.image for it in items]).to(self.dev, non_blocking=True)
        if not self.sized:  # the tables of the first image size (window grid, score plan), untimed
            t0 = time.perf_counter()
            self.gen(x[:1])
            self.size_warm_s = time.perf_counter() - t0  # in the wall time: taken out of it
            self.compile_s += self.size_warm_s
            self.sized = True
        t0 = time.perf_counter()
        results = self.gen(x)
        results = [{k: v.cpu() for k, v in r.items()} for r in results]
        self.algo_s += time.perf_counter() - t0
        return results

    def found(self, item, result) -> Found:
        from .viz import draw_proposals, save_png

        h, w = item.image.shape[-2:]
        boxes, scores = result["boxes"].cpu(), result["scores"].cpu()
        hints = hint_names(self.gen.classes, result.get("labels"))
        text = None
        if self.print_top:
            text = box_table(text_path(item.path), (w, h), boxes, scores, self.print_top, len(boxes), hints) + "\n"
        title = f"{Path(item.path).name}: top {min(self.viz_top, len(boxes))} of {len(boxes)} proposals"

        def picture(gt=None):
            return draw_proposals(item.image, boxes, scores, top=self.viz_top, gt=gt, title=title, hints=hints)

        warning = None
        if self.sample_png is not None:
            try:
                save_png(self.sample_png, picture(self.gt))
            except OSError as e:
                warning = f"warning: {self.sample_png}: cannot write picture ({e.strerror or e})"
        return Found(boxes, scores, hints, picture, text, warning)

    # -- the summary ----------------------------------------------------------------------------
    def time_lines(self, done: int, ok: int, wall: float) -> list[str]:
        wall, workers = wall - self.size_warm_s, self.workers
        return [f"time: {wall:.1f} s, {ms_per_img(wall, done)} end to end; "
                f"{ms_per_img(self.algo_s, ok)} "
                f"in the algorithm ({workers} decoding worker{'s' if workers != 1 else ''}, "
                f"batch {self.batch_size}, {self.dev})"
                + (f"; warm-up before (kernels compiled or loaded, tables for the image size) "
                   f"{self.compile_s:.1f} s, not counted" if self.compile_s >= 0.05 else "")]

    def record(self, done: int, ok: int, wall: float) -> dict:
        steady = _steady(self.first_done, wall, done, self.algo_s)
        wall = wall - self.size_warm_s
        return dict(ms_per_image=1000 * wall / done if done else None,
                    algorithm_ms_per_image=1000 * self.algo_s / ok if ok else None,
                    compile_s=self.compile_s, workers=self.workers, batch_size=self.batch_size, device=str(self.dev),
                    **steady)

    def extra_lines(self, ok: int) -> list[str]:
        if self.sample_png is not None and ok:
            return [f"wrote {self.sample_png.resolve()} (top {self.viz_top} proposals"
                    + (", ground truth in green" if self.gt else "") + ")"]
        return []


def _steady(first_done, wall: float, done: int, algo_s: float) -> dict:
    """Throughput after the first computed batch (which pays the one-off warm-up)."""
    if first_done is None or done <= first_done[1]:
        return dict(steady_ms_per_image=None, steady_algorithm_ms_per_image=None)
    t1, n1, a1 = first_done
    n = done - n1
    return dict(steady_ms_per_image=1000 * (wall - t1) / n,
                steady_algorithm_ms_per_image=1000 * (algo_s - a1) / n)
