"""Settings that act after the learned ranking, cross-validated and paired with the default on the same folds.

``reeb fit --folds`` estimates one setting against training-free. A setting that changes
only what comes after the model (``class_quota``, ``top_k``, ``nms_iou``, ...: the fields
the model does not see) can be paired with the default exactly: each fold's model is
fitted once (on the default's candidates, as ``reeb fit`` does) and every setting runs with
it on the held-out block. Per fit seed: recall at 2000 proposals / IoU 0.7 with its
frame-bootstrap interval, per class and per folder, and the sign test against the default;
beside it recall at 500 proposals / IoU 0.7 (its interval, per class, its sign test), at
2000 / IoU 0.5, and AR@2000 (the mean recall over IoU 0.5:0.95).
With several seeds, also over all of them: each object counts once, as gained when the
setting finds it with more fit seeds than the default does, as lost with fewer (the sign
test on those: the seeds' noise averaged within each object, the objects the unit).

    python benchmarks/cv_paired.py --variant "class_quota=[0,0.3,0.1,0.05]" --seeds 0 1 2 \\
        --out docs/results/ranker/class_quota

``--variant`` takes ``FIELD=VALUE`` pairs separated by ``;`` (as ``reeb propose --set``) or
a preset name; a field the model reads (the candidates, the features), or the ranker
itself, is refused.

``--refit`` takes the same pairs, and also :class:`~reeb_torch.ranker.fit.FitOptions` fields
(``hidden=32,32``, ``members=2``, ``mirror=1``, ``jitter=0.2``, ...: ``reeb fit``'s options)
and the fields the model reads: each fold's model is fitted again with them (same seed, same folds), so the pairing
is of two fits, not of one model under two settings:

    python benchmarks/cv_paired.py --refit "hidden=32,32" --seeds 0 1 2 3 4 --out docs/results/ranker/h32

``--whole-drives`` holds out, with each block, every frame of its drives (as ``reeb fit
--whole-drives``): the estimate for drives the model never saw.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import click
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import (default_dev_dirs, environment, rerun_line, setting_pairs, settings_config,  # noqa: E402
                     write_outputs)

from reeb_torch import ReebConfig, get_preset  # noqa: E402
from reeb_torch.ranker import frames as F  # noqa: E402
from reeb_torch.ranker import fit as RF  # noqa: E402
from reeb_torch.ranker import cv as fit_cv  # noqa: E402
from reeb_torch.metrics.recall import compare_recall, sign_test  # noqa: E402
from reeb_torch.tuning import FrameCache, bootstrap_interval  # noqa: E402
from reeb_torch.ranker import NOT_SEEN_BY_RANKER  # noqa: E402
from reeb_torch.config_text import config_from  # noqa: E402


def parse_variant(text: str) -> ReebConfig:
    """A preset name, or ``FIELD=VALUE;...`` on the default; ValueError for a field the
    ranking model reads, or ``ranker`` (the fold models would be another setting's)."""
    try:
        cfg = get_preset(text)
    except ValueError:
        cfg = settings_config(text)
    base = ReebConfig().to_dict()
    seen = sorted(k for k, v in cfg.to_dict().items()
                  if base[k] != v and (k not in NOT_SEEN_BY_RANKER or k == "ranker"))
    if seen:
        raise ValueError(f"{text!r} changes {', '.join(seen)}, which the ranking model reads or is: "
                         "estimate it with reeb fit --set instead")
    return cfg


_FIT_FIELDS = {f.name for f in dataclasses.fields(RF.FitOptions)} - {"seed"}


def _fit_value(name: str, text: str) -> object:
    """A :class:`~reeb_torch.ranker.fit.FitOptions` value from text: widths as ``32,32``
    (``none`` for no layer where the field allows it), numbers as numbers, switches
    (``mirror``) as ``1`` / ``0``."""
    default = getattr(RF.FitOptions(), name)
    text = text.strip()
    if name == "init":  # a model to fine-tune: a shipped name or a weights file
        return None if text.lower() in ("none", "null") else text
    if name == "drop_features":  # names or groups: place,log_v
        return tuple(x.strip() for x in text.split(",") if x.strip())
    if name == "quality_iou":  # two IoUs: 0.5,0.9
        return tuple(float(x) for x in text.split(","))
    if name in ("hidden", "prefilter", "class_hidden", "refine_hidden", "quality_hidden"):
        if text.lower() in ("none", "null") and name != "hidden":
            return None
        return tuple(int(x) for x in text.split(",") if x.strip())
    if isinstance(default, bool):  # mirror: 1 / 0, true / false, yes / no, on / off
        flags = {"1": True, "true": True, "yes": True, "on": True, "0": False, "false": False, "no": False,
                 "off": False}
        if text.lower() not in flags:
            raise ValueError(f"{text!r}: expected 1 or 0")
        return flags[text.lower()]
    if default is None or isinstance(default, float):  # prefilter_balance: a number, or none
        return None if text.lower() in ("none", "null") and default is None else float(text)
    return type(default)(text)


def parse_refit(text: str) -> tuple[ReebConfig, dict]:
    """``FIELD=VALUE;...`` of ``--refit``: the config (fields of :class:`~reeb_torch.ReebConfig`
    on the default, as ``reeb propose --set``) and the fit options (fields of
    :class:`~reeb_torch.ranker.fit.FitOptions` but the seed) the fold models are fitted with.
    ValueError for a bad value or a ``ranker`` (the fit makes the model)."""
    opts, pairs = {}, []
    for pair in setting_pairs(text):
        name, _, value = pair.partition("=")
        if name.strip() in _FIT_FIELDS:
            try:
                opts[name.strip()] = _fit_value(name.strip(), value)
            except ValueError as e:
                raise ValueError(f"--refit {pair!r}: {e}") from None
        elif name.strip() == "ranker":
            raise ValueError("--refit fits the fold models itself: no ranker=")
        else:
            pairs.append(pair)
    return config_from("default", None, pairs, None), opts


KS = (2000, 500)
"""The proposal counts whose best IoU per object is kept (:func:`cross_validated_best`)."""
CUTS = {"@2000 IoU .7": (0, 0.7), "@500 IoU .7": (1, 0.7), "@2000 IoU .5": (0, 0.5)}
"""Recall cuts: name to (column of :data:`KS`, IoU)."""
AR_IOUS = tuple(round(0.5 + 0.05 * i, 2) for i in range(10))


def cross_validated_best(cache: FrameCache, configs: list[ReebConfig], seed: int, folds: int,
                         ks: tuple[int, ...] = KS, refits: list[tuple[ReebConfig, dict]] = (),
                         whole_drives: bool = False) -> list[list]:
    """Per frame, ``float32 [N_i, len(ks)]``: each object's best IoU with the top ``k`` held-out
    proposals of the default, then of each of ``configs``, all run with the same fold models
    (:func:`reeb_torch.ranker.cv.cross_validate`, fitted as ``reeb fit`` fits, on the default's
    candidates); then of each ``(config, fit options)`` of ``refits``, with fold models fitted
    on the same folds with those options, for that config. ``whole_drives``: a held-out
    block's training frames hold no frame of its drives (``reeb fit --whole-drives``), not
    only none within 2 frames of it. Where one of ``configs`` refines boxes
    (``refine_top``), the fold models also get a box refiner (``refine_hidden`` 64, 64: fitted
    after the ranking, which it leaves as it is); where one ranks by the quality head
    (``rank_quality``), a quality head (``quality_hidden`` 32, the same way)."""
    opts = RF.FitOptions(seed=seed, refine_hidden=(64, 64) if any(c.refine_top for c in configs) else None,
                        quality_hidden=(32,) if any(c.rank_quality for c in configs) else None)
    base = ReebConfig()
    samples = F.frame_samples(cache, base, opts)
    gap = len(cache.frames) if whole_drives else 2
    cv = fit_cv.cross_validate(cache, base, base.training_free(), samples, opts, folds, ks[0], gap=gap, also=configs,
                          best_ks=ks)
    out = [cv.ranked_best, *cv.also_best]
    for cfg, changes in refits:
        o = dataclasses.replace(opts, **{"refine_hidden": (64, 64) if cfg.refine_top else None, **changes})
        s = F.frame_samples(cache, cfg, o)
        out.append(fit_cv.cross_validate(cache, cfg, cfg.training_free(), s, o, folds, ks[0], gap=gap,
                                    best_ks=ks).ranked_best)
    return out


def cross_validated_hits(cache: FrameCache, configs: list[ReebConfig], seed: int, folds: int,
                         k: int = 2000, iou: float = 0.7,
                         refits: list[tuple[ReebConfig, dict]] = (), whole_drives: bool = False) -> list[list]:
    """Per frame, the held-out hits (``bool [N_i]``) at ``k`` proposals / ``iou`` of the
    default, then of each of ``configs``, then of each of ``refits``
    (:func:`cross_validated_best`)."""
    best = cross_validated_best(cache, configs, seed, folds, (k,), refits, whole_drives)
    return [[b[:, 0] >= iou for b in frames] for frames in best]


def hits_at(best: list, cut: str) -> list:
    """Per frame, ``bool [N_i]``: the objects found at the recall cut ``cut`` (:data:`CUTS`)."""
    col, iou = CUTS[cut]
    return [b[:, col] >= iou for b in best]


def average_recall(best: list, idx: list[int]) -> float:
    """AR at the first of :data:`KS` on the frames ``idx``: recall averaged over IoU 0.5:0.95, in %."""
    b = torch.cat([best[i][:, 0] for i in idx])
    return 100 * float(torch.stack([(b >= t).float().mean() for t in AR_IOUS]).mean()) if len(b) else float("nan")


def describe(frames, hits: list, ref: list | None, idx: list[int]) -> dict:
    """Recall with its interval, per class, and the pairing with ``ref`` on the frames ``idx``."""
    h, lab = [hits[i] for i in idx], [frames.labels[i] for i in idx]
    est = bootstrap_interval(h, lab)
    row = {"recall": 100 * est.recall, "low": 100 * est.low, "high": 100 * est.high, "per_class": {}}
    for c, name in enumerate(frames.classes):
        n = sum(int((x == c).sum()) for x in lab)
        if n:
            found = sum(int(y[x == c].sum()) for y, x in zip(h, lab))
            row["per_class"][name] = {"found": found, "objects": n}
    if ref is not None:
        p = compare_recall([ref[i] for i in idx], h)
        row["paired"] = {"gained": p.gained, "lost": p.lost, "p_value": p.p_value}
    return row


def over_seeds(per_seed: list[list], variant: int, idx: list[int]) -> dict:
    """Objects of the frames ``idx`` found with more / fewer fit seeds by ``variant`` (the
    index into each seed's hits; 0 is the default) than by the default, and the sign test."""
    diff = torch.cat([sum(h[variant][i].int() - h[0][i].int() for h in per_seed) for i in idx])
    gained, lost = int((diff > 0).sum()), int((diff < 0).sum())
    return {"gained": gained, "lost": lost, "p_value": sign_test(gained, lost)}


def describe_all(frames, best: list, ref: list | None, idx: list[int]) -> dict:
    """:func:`describe` at each of :data:`CUTS` (the first one's keys at the top level, the
    others under ``cuts``) and AR@2000 (``ar``), on the frames ``idx``."""
    row = describe(frames, hits_at(best, "@2000 IoU .7"), None if ref is None else hits_at(ref, "@2000 IoU .7"), idx)
    row["cuts"] = {c: describe(frames, hits_at(best, c), None if ref is None else hits_at(ref, c), idx)
                   for c in list(CUTS)[1:]}
    row["ar"] = average_recall(best, idx)
    return row


def cut_line(row: dict) -> str:
    """The second line of a row: the other cuts and AR."""
    parts = []
    for c, r in row["cuts"].items():
        paired = f", +{r['paired']['gained']} / -{r['paired']['lost']} p {r['paired']['p_value']:.2g}" \
            if "paired" in r else ""
        classes = ", ".join(f"{n} {v['found']}" for n, v in r["per_class"].items())
        parts.append(f"{c} {r['recall']:.1f} % ({r['low']:.1f}-{r['high']:.1f}; {classes}{paired})")
    return f"  {'':<36} " + "; ".join(parts) + f"; AR@2000 {row['ar']:.1f} %"


def line(name: str, row: dict) -> str:
    classes = ", ".join(f"{c} {v['found']}/{v['objects']}" for c, v in row["per_class"].items())
    paired = ""
    if "paired" in row:
        p = row["paired"]
        paired = f"; against the default +{p['gained']} / -{p['lost']}, p {p['p_value']:.2g}"
    return f"  {name:<36} {row['recall']:5.1f} % ({row['low']:.1f}-{row['high']:.1f}; {classes}){paired}"


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, nargs="+", default=default_dev_dirs())
    ap.add_argument("--variant", action="append", default=[], metavar="SETTINGS",
                    help="a setting run with the default's fold models (fields after the model)")
    ap.add_argument("--refit", action="append", default=[], metavar="SETTINGS",
                    help="a setting whose fold models are fitted again (fit options, fields the model reads)")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0])
    ap.add_argument("--folds", type=int, default=10)
    ap.add_argument("--whole-drives", action="store_true",
                    help="no frame of a held-out block's drives on the training side (reeb fit --whole-drives)")
    ap.add_argument("--limit", type=int, default=None, help="the first N frames of each folder (a smoke run)")
    ap.add_argument("--out", type=Path, default=Path("runs/cv_paired"))
    args = ap.parse_args(argv)
    if not args.variant and not args.refit:
        ap.error("give at least one --variant or --refit")
    try:
        variants = {v: parse_variant(v) for v in args.variant}
        refits = {f"refit {r}": parse_refit(r) for r in args.refit}
    except (ValueError, click.ClickException) as e:
        ap.error(str(getattr(e, "message", e)))
    t0 = time.monotonic()
    frames = F.load_fit_frames([str(d) for d in args.data], limit=args.limit)
    cache = FrameCache(frames)
    groups = [("all frames", list(range(len(frames))))]
    folders = list(dict.fromkeys(frames.folders))
    if len(folders) > 1:
        groups += [(n, [i for i, f in enumerate(frames.folders) if f == n]) for n in folders]
    text = [f"# rerun: {rerun_line('benchmarks/cv_paired.py', argv if argv is not None else sys.argv[1:])}"]
    record: dict = {"seeds": {}, "environment": environment()}
    per_seed: list[list] = []
    for seed in args.seeds:
        best = cross_validated_best(cache, list(variants.values()), seed, args.folds, refits=list(refits.values()),
                                    whole_drives=args.whole_drives)
        per_seed.append(best)
        apart = "; no frame of a held-out block's drives on the training side" if args.whole_drives else ""
        text.append(f"fit seed {seed}: {len(frames)} frames, {args.folds} folds of blocks of frames{apart}; recall at "
                    "2000 proposals, IoU 0.7, 95 % frame-bootstrap intervals; below each, @500 / IoU 0.7 and "
                    "@2000 / IoU 0.5 (objects found per class; paired), AR@2000 (IoU 0.5:0.95)")
        record["seeds"][seed] = {}
        for title, idx in groups:
            text.append(f" {title} ({len(idx)} frames):")
            rows = {"default": describe_all(frames, best[0], None, idx)}
            rows.update({v: describe_all(frames, h, best[0], idx) for v, h in zip([*variants, *refits], best[1:])})
            for name, row in rows.items():
                text += [line(name, row), cut_line(row)]
            record["seeds"][seed][title] = rows
        print("\n".join(text[-(1 + len(groups) * (1 + 2 * (1 + len(variants) + len(refits)))):]), flush=True)
    if len(args.seeds) > 1:
        text.append(f"over the {len(args.seeds)} fit seeds: objects found with more / fewer seeds than by the "
                    "default, sign test")
        record["over_seeds"] = {}
        for cut in CUTS:
            hits = [[hits_at(b, cut) for b in seed_best] for seed_best in per_seed]
            for title, idx in groups:
                rows = {v: over_seeds(hits, j + 1, idx) for j, v in enumerate([*variants, *refits])}
                text += [f" {cut}, {title}: " + "; ".join(f"{v} +{r['gained']} / -{r['lost']}, p {r['p_value']:.2g}"
                                                          for v, r in rows.items())]
                record["over_seeds"].setdefault(cut, {})[title] = rows
        ar = {v: [sum(average_recall(b[j], idx) for b in per_seed) / len(per_seed) for _, idx in groups]
              for j, v in enumerate(["default", *variants, *refits])}
        text += [" AR@2000 averaged over the seeds (" + ", ".join(t for t, _ in groups) + "): "
                 + "; ".join(f"{v} " + " / ".join(f"{a:.1f}" for a in vals) for v, vals in ar.items())]
        record["over_seeds"]["ar"] = ar
        print("\n".join(text[-(2 + len(groups) * len(CUTS)):]), flush=True)
    text.append(f"({time.monotonic() - t0:.0f} s)")
    write_outputs(args.out, "cv_paired", text, record)
    return record


if __name__ == "__main__":
    main()
