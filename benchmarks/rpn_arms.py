"""REEB's proposals against a learned RPN in one MobileNetV3 Faster R-CNN trained from scratch,
on KITTI: the experiment behind docs/results.md's "A MobileNetV3 detector from scratch" (the
shipped detector is ``reeb detector fit``'s, on the public API).

The first ``--train-frames`` frames of a KITTI-format folder (sorted by id) are the
training set, the rest (or the next ``--val-frames``) the validation set. Every
``--eval-every`` iterations and at the end the script prints, for the validation set:

- detection AP per class at IoU 0.5 and mAP@[0.5:0.95] (torchmetrics'
  ``MeanAveragePrecision``, pycocotools backend), with ``--proposals-test`` proposals;
- the recall of the proposal stage at ``--recall-ks`` proposals and IoU 0.5 / 0.7
  (:func:`reeb_torch.metrics.recall.recall_table`), in the pixels of the input images.

REEB's proposals are computed once into ``--cache`` (default ``OUT/reeb_cache.pt``;
reused when still valid, see :mod:`reeb_torch.detection.proposal_cache`) and read from it during
training and evaluation. The learned arm (``--proposals learned``) is the same network
with torchvision's RPN. A checkpoint ``OUT/last.pt`` is written every
``--checkpoint-every`` iterations and at the end; ``--resume`` continues from it (data
order, learning rate and random state included). Runs on the GPU when there is one.

    python benchmarks/rpn_arms.py --data ../shared/data/kitti \\
        --train-frames 45 --proposals reeb --iterations 300 --out /tmp/rpn_arms/reeb

Nothing is downloaded: the backbone trains from scratch unless ``--backbone-weights``
names a local ``mobilenet_v3_large`` state dict.
"""

from __future__ import annotations

import argparse
import json
import math
import random
import time
from pathlib import Path
from typing import Any

import torch
from torchvision.models.detection.transform import resize_boxes
from tqdm import tqdm

from reeb_torch import ReebConfig, get_preset
from reeb_torch.datasets.kitti import KittiDataset
from reeb_torch.detection import ReebRPN, build_cache
from reeb_torch.metrics.recall import recall_table

from _mobilenet import reeb_fasterrcnn_mobilenet_v3  # noqa: E402  (this folder's)


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", default="../shared/data/kitti", help="KITTI-format folder")
    p.add_argument("--train-frames", type=int, default=45, help="first N frames train")
    p.add_argument("--val-frames", type=int, default=None, help="next N frames validate (default: all the rest)")
    p.add_argument("--classes", default="Car,Pedestrian,Cyclist,Truck")
    p.add_argument("--proposals", choices=("reeb", "learned"), default="reeb")
    p.add_argument("--preset", default="default", help="REEB preset (reeb_torch.get_preset)")
    p.add_argument("--cache", default=None, help="REEB proposal cache file (default OUT/reeb_cache.pt)")
    p.add_argument("--no-cache", action="store_true", help="run REEB on every forward pass instead")
    p.add_argument("--iterations", type=int, default=300, help="training budget, in batches")
    p.add_argument("--batch-size", type=int, default=2)
    p.add_argument("--optimizer", choices=("adamw", "sgd"), default="adamw")
    p.add_argument("--lr", type=float, default=None, help="default: 3e-4 (adamw), 0.02 (sgd)")
    p.add_argument("--momentum", type=float, default=0.9, help="sgd only")
    p.add_argument("--weight-decay", type=float, default=1e-4)
    p.add_argument("--warmup", type=int, default=20, help="linear warm-up iterations")
    p.add_argument("--min-size", type=int, default=320, help="model transform: shorter side")
    p.add_argument("--max-size", type=int, default=1088, help="model transform: longest side bound")
    p.add_argument("--box-batch-size", type=int, default=128,
                   help="RoIs sampled per image for the box head's loss (torchvision: 512)")
    p.add_argument("--proposals-train", type=int, default=1000, help="proposals per image in training")
    p.add_argument("--proposals-test", type=int, default=300, help="proposals per image for detection")
    p.add_argument("--recall-ks", default="300,1000", help="numbers of proposals for the recall table")
    p.add_argument("--backbone-weights", default=None, help="local mobilenet_v3_large state dict")
    p.add_argument("--eval-every", type=int, default=0, help="0: evaluate at the end only")
    p.add_argument("--checkpoint-every", type=int, default=100)
    p.add_argument("--out", required=True, help="folder for checkpoints and metrics")
    p.add_argument("--resume", action="store_true",
                   help="continue from OUT/last.pt (read with weights_only=True: tensors and plain values only)")
    p.add_argument("--device", default=None, help="default: cuda when available, else cpu")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=0, help="torch CPU threads (0: torch's default)")
    return p.parse_args(argv)


# -- data ---------------------------------------------------------------------------------


def load_split(args: argparse.Namespace) -> tuple[list[dict], list[dict], tuple[str, ...]]:
    """Decode every frame once (the sets are small): (train items, val items, classes)."""
    classes = tuple(c.strip() for c in args.classes.split(",") if c.strip())
    try:
        ds = KittiDataset(args.data, classes=classes)
    except (ValueError, OSError) as e:
        raise SystemExit(f"--data {args.data}: {e}") from None
    n_val = len(ds) - args.train_frames if args.val_frames is None else args.val_frames
    if args.train_frames < 1 or n_val < 1 or args.train_frames + n_val > len(ds):
        raise SystemExit(f"{args.data}: {len(ds)} frames, cannot take {args.train_frames} "
                         f"for training and {n_val} for validation")
    items = [ds[i] for i in tqdm(range(args.train_frames + n_val), desc="reading frames", unit="img")]
    return items[: args.train_frames], items[args.train_frames:], classes


def to_model_inputs(batch: list[dict], device: torch.device) -> tuple[list, list]:
    """Float images in [0, 1] and targets with labels 1..C (0 is the background)."""
    images = [b["image"].to(device).float().div_(255.0) for b in batch]
    targets = [{"boxes": b["boxes"].to(device), "labels": (b["labels"] + 1).to(device)} for b in batch]
    return images, targets


def batch_order(n: int, batch_size: int, iteration: int, seed: int) -> list[int]:
    """Indices of the batch at ``iteration``: epochs are seeded permutations, so the order
    is the same whether or not the run was resumed."""
    per_epoch = max(1, n // batch_size)
    epoch, pos = divmod(iteration, per_epoch)
    perm = torch.randperm(n, generator=torch.Generator().manual_seed(seed * 100003 + epoch))
    return perm[pos * batch_size:(pos + 1) * batch_size].tolist()


# -- model --------------------------------------------------------------------------------


def reeb_config(args: argparse.Namespace, ks: tuple[int, ...]) -> ReebConfig:
    return get_preset(args.preset).replace(top_k=max(args.proposals_train, args.proposals_test, *ks))


def build_model(args: argparse.Namespace, num_classes: int, ks: tuple[int, ...],
                items: list[dict], device: torch.device):
    kwargs: dict[str, Any] = {}
    if args.proposals == "reeb":
        config = reeb_config(args, ks)
        kwargs["config"] = config
        if not args.no_cache:
            cache_path = Path(args.cache or Path(args.out) / "reeb_cache.pt")
            t0 = time.perf_counter()
            cache = build_cache(items, cache_path, config, device=device)
            print(f"REEB cache {cache_path}: {len(cache)} frames, config {config.fingerprint()} "
                  f"({time.perf_counter() - t0:.1f} s)")
            kwargs["cache"] = cache
    torch.manual_seed(args.seed)  # same initial weights for both arms
    model = reeb_fasterrcnn_mobilenet_v3(
        num_classes + 1,
        proposals=args.proposals,
        backbone_weights=args.backbone_weights,
        min_size=args.min_size,
        max_size=args.max_size,
        top_k_train=args.proposals_train,
        top_k_test=max(args.proposals_test, *ks),
        box_batch_size_per_image=args.box_batch_size,
        **kwargs,
    )
    return model.to(device)


def set_test_proposals(model, n: int) -> None:
    """Proposals per image in evaluation, for either kind of proposal stage."""
    model.rpn._top_k["testing"] = n
    if not isinstance(model.rpn, ReebRPN):
        model.rpn._pre_nms_top_n["testing"] = max(n, model.rpn._pre_nms_top_n["testing"])


# -- evaluation ---------------------------------------------------------------------------


@torch.no_grad()
def evaluate(model, items: list[dict], classes: tuple[str, ...], args: argparse.Namespace,
             ks: tuple[int, ...], device: torch.device) -> dict[str, Any]:
    """Detection AP (``--proposals-test`` proposals) and proposal recall (``ks``)."""
    from torchmetrics.detection import MeanAveragePrecision

    model.eval()
    captured: list[tuple[torch.Tensor, tuple[int, int]]] = []  # (proposals, resized size)
    hook = model.rpn.register_forward_hook(
        lambda m, inp, out: captured.extend(zip(out[0], inp[0].image_sizes)))
    proposals: list[torch.Tensor] = []
    map_coco = MeanAveragePrecision(iou_type="bbox", class_metrics=True, backend="pycocotools")
    map_50 = MeanAveragePrecision(iou_type="bbox", iou_thresholds=[0.5], class_metrics=True,
                                  backend="pycocotools")
    try:
        for n_props, pass_name in ((max(ks), "recall"), (args.proposals_test, "detection")):
            set_test_proposals(model, n_props)
            for i in tqdm(range(0, len(items), args.batch_size), desc=f"eval ({pass_name})",
                          unit="batch", leave=False):
                batch = items[i:i + args.batch_size]
                images, targets = to_model_inputs(batch, device)
                captured.clear()
                detections = model(images)
                if pass_name == "recall":
                    # the RPN's boxes are in the resized frame; map them back like postprocess
                    for (b, size), img in zip(captured, images):
                        proposals.append(resize_boxes(b, list(size), list(img.shape[-2:])).cpu())
                    continue
                preds = [{k: d[k].cpu() for k in ("boxes", "scores", "labels")} for d in detections]
                gts = [{k: t[k].cpu() for k in ("boxes", "labels")} for t in targets]
                map_coco.update(preds, gts)
                map_50.update(preds, gts)
    finally:
        hook.remove()
        set_test_proposals(model, max(args.proposals_test, *ks))
    rec = recall_table(proposals, [it["boxes"] for it in items], [it["labels"] for it in items],
                       classes, ks=ks, ious=(0.5, 0.7))
    coco, at50 = map_coco.compute(), map_50.compute()
    present = [int(c) for c in at50["classes"].reshape(-1).tolist()]

    def per_class(values: torch.Tensor) -> dict[str, float | None]:
        vals = values.reshape(-1).tolist()
        out: dict[str, float | None] = {c: None for c in classes}
        for label, v in zip(present, vals):
            out[classes[label - 1]] = None if v < 0 else float(v)
        return out

    return {
        "mAP": float(coco["map"]),
        "mAP50": float(coco["map_50"]),
        "AP50_per_class": per_class(at50["map_per_class"]),
        "AP_per_class": per_class(coco["map_per_class"]),
        "recall": rec.to_dict(),
        "recall_table": rec.format_table(),
    }


def format_metrics(m: dict[str, Any], classes: tuple[str, ...]) -> str:
    def pct(v: float | None) -> str:
        return "   -" if v is None or v < 0 else f"{100 * v:5.1f}"

    lines = [f"detection: mAP@[.5:.95] {pct(m['mAP'])}   mAP@.5 {pct(m['mAP50'])}",
             "AP@.5 per class: " + "  ".join(f"{c} {pct(m['AP50_per_class'][c])}" for c in classes),
             m["recall_table"]]
    return "\n".join(lines)


# -- training -----------------------------------------------------------------------------


def lr_at(iteration: int, args: argparse.Namespace) -> float:
    """Linear warm-up, then cosine decay to 1 % of ``--lr``."""
    if iteration < args.warmup:
        return args.lr * (0.001 + 0.999 * iteration / max(1, args.warmup))
    t = (iteration - args.warmup) / max(1, args.iterations - args.warmup)
    return args.lr * (0.01 + 0.99 * 0.5 * (1 + math.cos(math.pi * min(1.0, t))))


def save_checkpoint(path: Path, model, optimizer, iteration: int, args, history: list) -> None:
    """Tensors and plain values only (dicts, lists, tuples, numbers, strings): what
    :func:`load_checkpoint` reads with ``weights_only=True``."""
    tmp = path.with_name(path.name + ".tmp")
    torch.save({
        "model": model.state_dict(),
        "optimizer": optimizer.state_dict(),
        "iteration": iteration,
        "args": vars(args),
        "history": history,
        "rng": {"torch": torch.get_rng_state(), "python": random.getstate()},
    }, tmp)
    tmp.replace(path)


def load_checkpoint(path: Path, device: torch.device) -> dict[str, Any]:
    """A checkpoint of :func:`save_checkpoint`, read with ``weights_only=True``: a file that
    holds anything else (pickled code: a checkpoint from elsewhere can run code when loaded
    in full) is refused with a message, never run."""
    if not path.exists():
        raise SystemExit(f"--resume: no checkpoint {path}")
    try:
        return torch.load(path, map_location=device, weights_only=True)
    except Exception as e:  # noqa: BLE001 - UnpicklingError, RuntimeError: each names what it met
        first = " ".join(str(e).split())[:300]
        raise SystemExit(f"--resume: {path} is not a checkpoint of this script (it holds more than tensors "
                         f"and plain values, or is damaged); not loaded: {first}") from None


def main(argv: list[str] | None = None) -> dict[str, Any]:
    args = parse_args(argv)
    if args.lr is None:
        args.lr = 3e-4 if args.optimizer == "adamw" else 0.02
    if args.threads:
        torch.set_num_threads(args.threads)
    device = torch.device(args.device or ("cuda" if torch.cuda.is_available() else "cpu"))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    ks = tuple(int(k) for k in args.recall_ks.split(","))
    random.seed(args.seed)

    train, val, classes = load_split(args)
    print(f"{len(train)} training frames ({sum(len(t['boxes']) for t in train)} objects), "
          f"{len(val)} validation frames ({sum(len(t['boxes']) for t in val)} objects), "
          f"device {device}, proposals {args.proposals}")
    model = build_model(args, len(classes), ks, train + val, device)
    params = [p for p in model.parameters() if p.requires_grad]
    if args.optimizer == "sgd":
        optimizer = torch.optim.SGD(params, lr=args.lr, momentum=args.momentum,
                                    weight_decay=args.weight_decay)
    else:
        optimizer = torch.optim.AdamW(params, lr=args.lr, weight_decay=args.weight_decay)

    start, history = 0, []
    ckpt_path = out / "last.pt"
    if args.resume:
        ckpt = load_checkpoint(ckpt_path, device)
        model.load_state_dict(ckpt["model"])
        optimizer.load_state_dict(ckpt["optimizer"])
        start, history = ckpt["iteration"], ckpt["history"]
        torch.set_rng_state(ckpt["rng"]["torch"])
        random.setstate(ckpt["rng"]["python"])
        print(f"resumed from {ckpt_path} at iteration {start}")

    model.train()
    t_train = 0.0
    bar = tqdm(range(start, args.iterations), desc=f"train ({args.proposals})", unit="it",
               initial=start, total=args.iterations)
    for it in bar:
        for group in optimizer.param_groups:
            group["lr"] = lr_at(it, args)
        images, targets = to_model_inputs([train[i] for i in batch_order(len(train), args.batch_size, it, args.seed)], device)
        t0 = time.perf_counter()
        losses = model(images, targets)
        loss = sum(losses.values())
        if not torch.isfinite(loss):
            raise SystemExit(f"iteration {it}: non-finite loss {({k: v.item() for k, v in losses.items()})}")
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        t_train += time.perf_counter() - t0
        record = {"iteration": it + 1, "loss": loss.item(), **{k: v.item() for k, v in losses.items()}}
        history.append(record)
        bar.set_postfix(loss=f"{loss.item():.3f}", lr=f"{lr_at(it, args):.1e}")
        done = it + 1
        if done % args.checkpoint_every == 0 or done == args.iterations:
            save_checkpoint(ckpt_path, model, optimizer, done, args, history)
        if args.eval_every and done % args.eval_every == 0 and done != args.iterations:
            metrics = evaluate(model, val, classes, args, ks, device)
            bar.write(f"iteration {done}\n" + format_metrics(metrics, classes))
            model.train()
    if start >= args.iterations and not ckpt_path.exists():
        save_checkpoint(ckpt_path, model, optimizer, start, args, history)

    t0 = time.perf_counter()
    metrics = evaluate(model, val, classes, args, ks, device)
    t_eval = time.perf_counter() - t0
    window = history[-20:]
    summary = {
        "proposals": args.proposals,
        "iterations": args.iterations,
        "train_frames": len(train),
        "val_frames": len(val),
        "train_seconds_this_run": round(t_train, 1),
        "eval_seconds": round(t_eval, 1),
        "final_loss_mean20": sum(h["loss"] for h in window) / max(1, len(window)),
        "args": vars(args),
        **{k: v for k, v in metrics.items() if k != "recall_table"},
    }
    (out / "metrics.json").write_text(json.dumps(summary, indent=2))
    print(f"\nafter {args.iterations} iterations ({args.proposals} proposals), {len(val)} validation frames:")
    print(format_metrics(metrics, classes))
    print(f"metrics written to {out / 'metrics.json'}, checkpoint {ckpt_path}")
    return summary


if __name__ == "__main__":
    main()
