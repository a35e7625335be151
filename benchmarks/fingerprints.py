"""SHA-256 digests of the proposals (boxes and scores, bit for bit) of a few presets on a
few frames, for uint8 and float input, at batch 1 and batch 8: run it before and after a
speed change and compare (``--check FILE`` exits 1 on any difference).

The frames: the two bundled examples and, where the dev data is there (``$REEB_DATA``, else
``../shared/data``), the first of its KITTI frames of each other image size (KITTI's are
1242, 1241, 1238 and 1224 px wide, and 1241 resizes through longer filters), then its first
frames up to eight images in all. Float input is ``uint8 / 255`` (float32).

Rerun: ``python benchmarks/fingerprints.py [--out FILE] [--check FILE] [--presets default paper]``
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
from pathlib import Path

import torch

from reeb_torch import ProposalGenerator, get_preset
from reeb_torch.io import read_image

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import default_kitti_dir  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
EXAMPLES = sorted((REPO / "examples" / "data").glob("*.png"))
DEV = default_kitti_dir() / "images"


def frames(limit: int = 8) -> list[tuple[str, torch.Tensor]]:
    """``(name, uint8 (3, H, W))`` of the bundled examples, then a dev frame of each size
    not yet among them, then the first dev frames, ``limit`` in all."""
    out = [(p.name, read_image(p)) for p in EXAMPLES]
    dev = [(p.name, read_image(p)) for p in sorted(DEV.glob("*.png"))] if DEV.is_dir() else []
    for name, im in dev:  # one of each image size first
        if im.shape not in [x.shape for _, x in out]:
            out.append((name, im))
    taken = {n for n, _ in out}
    out += [(name, im) for name, im in dev if name not in taken]
    return out[:limit]


def digest(out: dict[str, torch.Tensor]) -> str:
    """SHA-256 of one image's boxes and scores (their bytes, shapes included)."""
    h = hashlib.sha256()
    for k in ("boxes", "scores"):
        t = out[k].contiguous().cpu()
        h.update(k.encode() + str(tuple(t.shape)).encode() + str(t.dtype).encode())
        h.update(t.numpy().tobytes())
    return h.hexdigest()


def fingerprints(presets: list[str], limit: int = 8) -> dict[str, str]:
    """``{"preset/input/batchN/frame": digest}`` for uint8 and float input at batch 1 and 8."""
    imgs = frames(limit)
    res: dict[str, str] = {}
    for preset in presets:
        gen = ProposalGenerator(get_preset(preset))
        for kind in ("uint8", "float"):
            xs = [im if kind == "uint8" else im.float() / 255 for _, im in imgs]
            for batch in (1, 8):
                outs = []
                for i in range(0, len(xs), batch):
                    outs += gen(xs[i: i + batch])
                for (name, _), o in zip(imgs, outs):
                    res[f"{preset}/{kind}/batch{batch}/{name}"] = digest(o)
    return res


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--presets", nargs="*", default=["default", "paper"])
    ap.add_argument("--limit", type=int, default=8)
    ap.add_argument("--out", type=Path, default=None, help="write the digests here (JSON)")
    ap.add_argument("--check", type=Path, default=None, help="compare with these digests (JSON)")
    args = ap.parse_args(argv)
    res = fingerprints(args.presets, args.limit)
    same_inputs = {}
    for key, d in res.items():  # float and uint8, batch 1 and 8 should all agree per frame
        preset, _, _, name = key.split("/")
        same_inputs.setdefault((preset, name), set()).add(d)
    split = [k for k, v in same_inputs.items() if len(v) > 1]
    print(f"{len(res)} digests; {len(split)} (preset, frame) pairs differ between input kinds/batches: {split}")
    if args.out:
        args.out.write_text(json.dumps(res, indent=1, sort_keys=True) + "\n")
        print(f"wrote {args.out}")
    if args.check:
        ref = json.loads(args.check.read_text())
        diff = sorted(k for k in set(ref) | set(res) if ref.get(k) != res.get(k))
        print(f"{len(diff)} differ from {args.check}" + (": " + ", ".join(diff[:10]) if diff else ""))
        return 1 if diff else 0
    return 0


if __name__ == "__main__":
    sys.exit(main())
