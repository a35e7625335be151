"""``reeb propose`` on this machine: images in, one row per image out, in input order.

:func:`propose_local` runs the command's local engine on :class:`.engine.ImageRun` (the
inputs, the output checked and locked before any work, ``--resume``, the ordered writer,
``--viz``, the closing summary and exit codes); :class:`_LocalRun` gives it the proposal
generator: images decoded in DataLoader workers beside the algorithm (:mod:`.decoding`),
batches of equal-sized images, the kernels warmed up before the clock starts, the
``--print-top`` tables and the bundled sample's picture. The Ray engine is
:mod:`.propose_ray`.
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path
from typing import Any, Sequence

import torch

from ..generator import ProposalGenerator, _warm_for
from .common import UsageProblem, box_table, bundled_sample, label_for, read_labels
from .decoding import decoded_images, size_batches
from .engine import ImageRun, ms_per_img
from .rows import hint_names, result_row, text_path
from .viz import draw_proposals, save_png

__all__ = ["propose_local"]


def propose_local(paths: Sequence[str], cfg: Any, dev: Any, *, out: str | None, resume: bool, overwrite: bool,
                  batch_size: int, workers: int | None, viz_dir: str | None, viz_top: int, recursive: bool,
                  print_top: int | None, summary_json: str | None, quiet: bool) -> None:
    """``reeb propose`` with ``--engine local``: ``cfg`` (a ReebConfig) and ``dev`` (a
    ``torch.device``) as the command line built them, the other options as it takes them.

    Usage errors (exit 2) are raised as :class:`~.common.UsageProblem` before any work;
    the process exits 1 when an image failed, 130 when interrupted.
    """
    run = _LocalRun(cfg, dev, out=out, batch_size=batch_size, workers=workers, viz_top=viz_top,
                    summary_json=summary_json, quiet=quiet)
    run.find_inputs(paths, recursive)  # 1. inputs
    work = run.plan_output(resume, overwrite)  # 2. the output, checked and locked before any work
    run.check_pictures(viz_dir, print_top, resume=resume, overwrite=overwrite)  # 3. the pictures
    if not work:
        return run.nothing_to_do()
    run.run()  # 4. the run
    run.save_and_summarise()  # 5. save and summarise


class _LocalRun(ImageRun):
    """One local ``reeb propose`` run: the proposal generator on :class:`~.engine.ImageRun`."""

    desc = "reeb propose"

    def __init__(self, cfg: Any, dev: Any, *, out: str | None, batch_size: int, workers: int | None, viz_top: int,
                 summary_json: str | None, quiet: bool) -> None:
        super().__init__(made_by=cfg.fingerprint(), out=out, batch_size=batch_size, workers=workers, quiet=quiet,
                         summary_json=summary_json)
        self.cfg, self.dev, self.viz_top = cfg, dev, viz_top
        self.first_done: tuple[float, float, float] | None = None
        """(time, images done, algorithm seconds) after the first computed batch."""
        self.compile_s = self.size_warm_s = 0.0  # warm-up, kept out of the times (prepare)
        self.sized = False
        self.stats["algo_s"] = 0.0

    def find_inputs(self, paths: Sequence[str | Path], recursive: bool) -> None:
        """The images (the bundled sample without ``paths``)."""
        self.sample_mode = not paths
        super().find_inputs([bundled_sample()] if self.sample_mode else paths, recursive)

    def check_pictures(self, viz_dir: str | None, print_top: int | None, *, resume: bool = False,
                       overwrite: bool = False) -> None:
        """Where pictures go (``--viz``, or ``reeb_proposals.png`` for the sample) and how many
        boxes are printed per image."""
        self.side_outputs(viz_dir, resume=resume, overwrite=overwrite)
        sample_png = Path("reeb_proposals.png") if self.sample_mode and viz_dir is None else None
        if sample_png is not None and not os.access(sample_png.parent.resolve(), os.W_OK):
            raise UsageProblem(f"cannot write {sample_png.resolve()}: the current folder is not "
                               "writable (use --viz DIR)")
        self.sample_png = sample_png
        self.print_top = (0 if self.out else 10) if print_top is None else print_top
        if not self.out and not self.sample_mode and viz_dir is None:
            self.echo_err("note: no --out given: proposals are printed, not saved")

    # -- the generator ------------------------------------------------------------------------
    def prepare(self) -> None:
        """Build the generator and, before the clock starts, compile (or load) the CPU
        kernels; the summary gives that time apart (``compile_s``, with the first batch's
        warm-up: :meth:`run_batch`)."""

        try:
            self.gen = ProposalGenerator(self.cfg).to(self.dev).eval()
        except (TypeError, ValueError, ArithmeticError) as e:
            raise UsageProblem(f"the settings are not usable: {' '.join(str(e).split())}")
        self.compile_s = _warm_for(self.cfg) if self.dev.type == "cpu" else 0.0
        label = label_for(self.images[0]) if self.sample_mode else None
        self.gt = read_labels(label) if label else None

    def stream(self, images):
        return decoded_images(images, workers=self.workers, min_side=self.cfg.min_window, prefetch=self.batch_size,
                              pin_memory=self.dev.type == "cuda", quiet=self.quiet)

    def groups(self, stream):
        # max_lag: a group of a rare size waits at most this many inputs, which bounds the
        # rows held back to be written in input order
        return size_batches(stream, self.batch_size, max_lag=max(64, 4 * self.batch_size))

    def after_group(self) -> None:
        stats = self.stats
        if self.first_done is None and stats["ok"]:
            self.first_done = (time.perf_counter(), stats["ok"] + stats["failed"], stats["algo_s"])

    def run_batch(self, items: list) -> list:
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
        self.stats["algo_s"] += time.perf_counter() - t0
        return results

    def finish(self, item, result) -> None:
        h, w = item.image.shape[-2:]
        boxes, scores = result["boxes"].cpu(), result["scores"].cpu()
        hints = hint_names(self.gen.classes, result.get("labels"))
        self.emit(item, result_row(item.path, w, h, boxes, scores, self.made_by, labels=hints)
                  if self.rows.writer is not None else None, len(boxes))
        if self.print_top:
            self.bar.write(box_table(text_path(item.path), (w, h), boxes, scores, self.print_top, len(boxes),
                                     hints) + "\n", file=sys.stdout)
        self._pictures(item, boxes, scores, hints)

    def _pictures(self, item, boxes, scores, hints=None) -> None:
        """The ``--viz`` picture of an image (and ``reeb_proposals.png`` for the sample)."""

        viz_top = self.viz_top
        title = f"{Path(item.path).name}: top {min(viz_top, len(boxes))} of {len(boxes)} proposals"

        def picture(gt=None):
            return draw_proposals(item.image, boxes, scores, top=viz_top, gt=gt, title=title, hints=hints)

        if self.pictures is not None:
            self.pictures.save(self.stem(item), picture)
        if self.sample_png is not None:
            try:
                save_png(self.sample_png, picture(self.gt))
            except OSError as e:
                self.bar.write(f"warning: {self.sample_png}: cannot write picture ({e.strerror or e})",
                               file=sys.stderr)

    # -- the summary ----------------------------------------------------------------------------
    def time_lines(self, done: int) -> list[str]:
        stats, wall, workers = self.stats, self.wall - self.size_warm_s, self.workers
        return [f"time: {wall:.1f} s, {ms_per_img(wall, done)} end to end; "
                f"{ms_per_img(stats['algo_s'], stats['ok'])} "
                f"in the algorithm ({workers} decoding worker{'s' if workers != 1 else ''}, "
                f"batch {self.batch_size}, {self.dev})"
                + (f"; warm-up before (kernels compiled or loaded, tables for the image size) "
                   f"{self.compile_s:.1f} s, not counted" if self.compile_s >= 0.05 else "")]

    def record(self, done: int) -> dict:
        stats, wall = self.stats, self.wall - self.size_warm_s
        return dict(ms_per_image=1000 * wall / done if done else None,
                    algorithm_ms_per_image=1000 * stats["algo_s"] / stats["ok"] if stats["ok"] else None,
                    compile_s=self.compile_s, workers=self.workers, batch_size=self.batch_size, device=str(self.dev),
                    **_steady(self.first_done, self.t_start + self.wall, done, stats))

    def extra_lines(self) -> list[str]:
        if self.sample_png is not None and self.stats["ok"]:
            return [f"wrote {self.sample_png.resolve()} (top {self.viz_top} proposals"
                    + (", ground truth in green" if self.gt else "") + ")"]
        return []


def _steady(first_done, t_end: float, done: int, stats: dict) -> dict:
    """Throughput after the first computed batch (which pays the one-off warm-up)."""
    if first_done is None or done <= first_done[1]:
        return dict(steady_ms_per_image=None, steady_algorithm_ms_per_image=None)
    t1, n1, a1 = first_done
    n = done - n1
    return dict(steady_ms_per_image=1000 * (t_end - t1) / n,
                steady_algorithm_ms_per_image=1000 * (stats["algo_s"] - a1) / n)
