"""Changes to how the default picks its candidates, measured in the pipeline: rows of
recall at 2000 proposals / IoU 0.7 (per half and per class), each paired with the default.

The "measured and not taken" list of docs/results.md quotes this script. Families (``--family``):

- ``region-nms``: each region's budget (eq. 9) counts *distinct* boxes: greedy NMS at
  0.8 / 0.85 / 0.9 inside the region (over its best 8 × budget windows) before the cut.
- ``narrow-shadow``: boxes narrower than 0.6 / 0.8 × their height are not judged by the
  shadow-underneath term (a car's cue): their V without the term times a constant
  (0.2 / 0.35 / 0.5, the term's typical factor is 0.2-0.75), or times the term floored
  at that constant; the re-scored windows go through the region cut and NMS.
- ``ensemble``: the default's ranked proposals interleaved with those of a second setting
  (``min_window=12``, ``scale=1.0``, ``min_window=20``, ``blur_sigma=1.5``), the second
  taking every other place (share 0.5) or 3 of every 10 (0.3); NMS at the default's 0.75;
  top 2000.

Rerun: ``python benchmarks/selection_variants.py [--data DIR] [--frames 0:39 40:59]
[--family region-nms narrow-shadow ensemble] [--out DIR]`` (about a minute on 2 cores
for all three on the 60 frames).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Callable

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import default_kitti_dir, rerun_line, run_captured  # noqa: E402

from reeb_torch import ProposalGenerator, ReebConfig  # noqa: E402
from reeb_torch.config import CameraSettings, RegionSettings  # noqa: E402
from reeb_torch.selection import GridCache, RegionCut, WindowSelection  # noqa: E402
from _common import add_frames_option  # noqa: E402
from reeb_torch.datasets.folders import load_kitti  # noqa: E402
from reeb_torch.metrics.recall import compare_recall, object_hits  # noqa: E402
from reeb_torch.stages.nms import nms_top_k  # noqa: E402

TOP_K, IOU = 2000, 0.7
FAMILIES = ("region-nms", "narrow-shadow", "ensemble")


class RegionNMS(RegionCut):
    """The default's ranking, with greedy NMS at ``thr`` inside each region before eq. 9's cut."""

    def __init__(self, regions: RegionSettings, camera: CameraSettings, cache: GridCache, thr: float) -> None:
        super().__init__(regions, camera, cache)
        self.thr = thr

    def region_cut(self, scores, grid, share):
        budget = self.region_budget(share)
        chosen = torch.zeros_like(scores, dtype=torch.bool)
        for b in range(scores.shape[0]):
            for r, idx in enumerate(grid.region_windows):
                k = int(budget[b, r])
                s = scores[b, idx]
                idx = idx[torch.isfinite(s)]
                if k == 0 or len(idx) == 0:
                    continue
                best = idx[torch.sort(scores[b, idx], descending=True, stable=True).indices[: 8 * k]]
                chosen[b, best[nms_top_k(grid.boxes[best], scores[b, best], self.thr, k)]] = True
        return chosen


class NarrowShadow(RegionCut):
    """The default's ranking, with narrow boxes re-scored without the shadow term: ``plain`` (set per
    image: the scores of the same windows with ``shadow_score='none'``) times ``const``, or
    times the term floored at ``const`` (``floor=True``). The scores are changed in place,
    so the region cut and NMS both rank by them."""

    def __init__(self, regions: RegionSettings, camera: CameraSettings, cache: GridCache, aspect: float,
                 const: float, floor: bool) -> None:
        super().__init__(regions, camera, cache)
        self.aspect, self.const, self.floor = aspect, const, floor
        self.plain: torch.Tensor | None = None

    def region_cut(self, scores, grid, share):
        w = grid.boxes[:, 2] - grid.boxes[:, 0]
        h = grid.boxes[:, 3] - grid.boxes[:, 1]
        plain = self.plain
        factor = torch.where(plain > 0, scores / plain.clamp_min(1e-30), torch.zeros_like(scores))
        factor = factor.clamp_min(self.const) if self.floor else torch.full_like(factor, self.const)
        scores.copy_(torch.where((w < self.aspect * h)[None] & torch.isfinite(scores), plain * factor, scores))
        return super().region_cut(scores, grid, share)


def with_cut(config: ReebConfig, cut: type[RegionCut], *args: object) -> ProposalGenerator:
    """A generator of ``config`` whose region cut is ``cut(config.regions, config.camera, cache, *args)``."""
    gen = ProposalGenerator(config)
    gen.selection = WindowSelection.from_config(config, cut=lambda r, c, cache: cut(r, c, cache, *args))
    return gen


def interleave(a: torch.Tensor, b: torch.Tensor, share: float) -> torch.Tensor:
    """Ranked boxes ``a`` and ``b`` merged so that ``b`` takes about ``share`` of the places,
    then NMS at the default's IoU, top 2000."""
    ra = torch.arange(len(a), dtype=torch.float64) / (1 - share)
    rb = torch.arange(len(b), dtype=torch.float64) / share + 0.5
    boxes = torch.cat([a, b])
    return boxes[nms_top_k(boxes, -torch.cat([ra, rb]), ReebConfig().nms_iou, TOP_K)]


def variants(family: str, default_boxes: list[torch.Tensor]) -> list[tuple[str, Callable]]:
    """``(name, propose)`` rows of a family; ``propose(i, image)`` gives the ranked boxes of
    the ``i``-th frame (``default_boxes[i]``: the default's, computed once by the caller)."""
    cfg = ReebConfig()
    rows: list[tuple[str, Callable]] = []
    if family == "region-nms":
        for thr in (0.9, 0.85, 0.8):
            gen = with_cut(cfg, RegionNMS, thr)
            rows.append((f"NMS {thr} inside each region before the cut", lambda i, im, g=gen: g([im])[0]["boxes"]))
    elif family == "narrow-shadow":
        plain_gen = ProposalGenerator(cfg.replace(shadow_score="none"))
        for aspect in (0.6, 0.8):
            for floor in (True, False):
                for const in (0.2, 0.35, 0.5):
                    gen = with_cut(cfg, NarrowShadow, aspect, const, floor)

                    def run(i, im, g=gen):
                        g.selection.cut.plain = run_captured(plain_gen, im)[1]["scores"]
                        return g([im])[0]["boxes"]

                    how = f"term floored at {const}" if floor else f"x {const} instead of the term"
                    rows.append((f"w < {aspect} h: {how}", run))
    elif family == "ensemble":
        for change in ("min_window=12", "scale=1.0", "min_window=20", "blur_sigma=1.5"):
            field, value = change.split("=")
            other = ProposalGenerator(cfg.replace(**{field: type(getattr(cfg, field))(value)}))
            for share in (0.5, 0.3):
                rows.append((f"+ {change}, share {share}",
                             lambda i, im, o=other, s=share: interleave(default_boxes[i], o([im])[0]["boxes"], s)))
    else:
        raise ValueError(f"unknown family {family!r}; choose from {', '.join(FAMILIES)}")
    return rows


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=default_kitti_dir())
    add_frames_option(ap)
    ap.add_argument("--family", nargs="+", choices=FAMILIES, default=list(FAMILIES))
    ap.add_argument("--out", type=Path, default=None, help="write selection_variants.txt / .json here")
    args = ap.parse_args(argv)
    rerun = rerun_line("benchmarks/selection_variants.py", argv if argv is not None else sys.argv[1:])
    try:
        items, classes = load_kitti(args.data, frames=args.frames)
    except ValueError as e:
        ap.error(str(e))
    items = [it for it in items if len(it["boxes"])]
    gts = [it["boxes"] for it in items]
    labels = torch.cat([it["labels"] for it in items])
    ranges = args.frames if len(args.frames) > 1 else []
    in_range = [torch.cat([torch.full((len(it["boxes"]),), int(it["image_id"]) in r) for it in items])
                for r in ranges]
    lines = [f"# rerun: {rerun}",
             f"# {len(items)} frames with objects, {len(labels)} objects; recall (%) at {TOP_K} proposals, IoU {IOU}"]
    head = f"{'variant':48s} {'all':>6s}" + "".join(f" {r.text:>8s}" for r in ranges) + "".join(
        f" {c[:10]:>10s}" for c in classes) + "  vs default: +found / -lost, p"
    lines.append(head)
    print("\n".join(lines), flush=True)
    record: dict = {"rerun": rerun, "rows": []}

    def row(name: str, hits: list[torch.Tensor], ref: list[torch.Tensor] | None) -> None:
        h = torch.cat(hits)
        cells = f"{name:48s} {100 * h.float().mean():6.1f}" + "".join(
            f" {100 * h[m].float().mean():8.1f}" for m in in_range) + "".join(
            f" {int(h[labels == c].sum()):>4d} / {int((labels == c).sum()):<3d}" for c in range(len(classes)))
        entry: dict = {"variant": name, "recall": float(h.float().mean()),
                       "ranges": {r.text: float(h[m].float().mean()) for r, m in zip(ranges, in_range)}}
        if ref is not None:
            c = compare_recall(ref, hits)
            cells += f"  +{c.gained} / -{c.lost}, p {c.p_value:.2f}"
            entry.update(gained=c.gained, lost=c.lost, p_value=c.p_value)
        print(cells, flush=True)
        lines.append(cells)
        record["rows"].append(entry)

    base = ProposalGenerator(ReebConfig())
    default_boxes = [base([it["image"]])[0]["boxes"] for it in items]
    ref = object_hits(default_boxes, gts, TOP_K, IOU)
    row("default", ref, None)
    for family in args.family:
        for name, propose in variants(family, default_boxes):
            row(name, object_hits([propose(i, it["image"]) for i, it in enumerate(items)], gts, TOP_K, IOU), ref)
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "selection_variants.txt").write_text("\n".join(lines) + "\n")
        (args.out / "selection_variants.json").write_text(json.dumps(record, indent=1))
        print(f"wrote {args.out}/selection_variants.txt, .json")
    return record


if __name__ == "__main__":
    main()
