"""Make a test camera from a KITTI-format folder: zoom, crop and shift its frames, with their
labels and calibration moved, into a new KITTI-format folder.

A frame is scaled by ``--zoom`` (a longer focal length: objects ``zoom`` times larger), then a
window of ``--size W H`` (default: the frame's own size) is cut from it. The window's top is
set so that the row at ``--horizon-from`` of the source height (its horizon) lands at
``--horizon-to`` of the window's height (default: the same fraction, only a zoom); its left
edge is centred (``--shift-x`` moves it, in output pixels). Boxes move with the pixels and are
clipped to the window; an object with less than ``--min-visible`` of its box left becomes
``DontCare`` (not a target), one cut by the window gets its ``truncated`` raised. ``P2``
becomes ``A · P2`` with ``A = [[z, 0, -x0], [0, z, -y0], [0, 0, 1]]``: the same camera, its
principal point moved. A window that leaves the scaled frame is an error naming the frame.

    # a camera like the one the README's "Your own camera" reports on: horizon at 0.41 of the
    # height, objects a third larger
    python benchmarks/camera_transform.py ../shared/data/kitti -o /tmp/cam41/kitti \\
        --zoom 1.33 --horizon-from 0.4714 --horizon-to 0.41

The horizon of the made camera is ``horizon_to`` where ``horizon_from`` was the source's;
``transform.json`` in the output records the transform and that horizon.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import rerun_line  # noqa: E402

from reeb_torch.datasets.kitti import KittiDataset  # noqa: E402

__all__ = ["Transform", "window", "move_label_line", "move_calib", "transform_folder", "main"]


@dataclass(frozen=True)
class Transform:
    """What a frame undergoes: scale by ``zoom``, then a window of ``size`` (``None``: the
    frame's own size) placed so that ``horizon_from`` (a fraction of the source height) lands
    at ``horizon_to`` (``None``: the same fraction) of the window, centred left to right and
    moved right by ``shift_x`` output pixels; objects with less than ``min_visible`` of their
    box inside become DontCare."""

    zoom: float = 1.0
    size: tuple[int, int] | None = None
    horizon_from: float = 0.47
    horizon_to: float | None = None
    shift_x: float = 0.0
    min_visible: float = 0.5


def window(t: Transform, width: int, height: int) -> tuple[int, int, int, int, int, int]:
    """``(scaled W, scaled H, x0, y0, out W, out H)`` for a ``width × height`` source frame.

    Raises:
        ValueError: the window leaves the scaled frame.
    """
    sw, sh = round(width * t.zoom), round(height * t.zoom)
    ow, oh = t.size or (width, height)
    to = t.horizon_from if t.horizon_to is None else t.horizon_to
    y0 = round(t.horizon_from * height * t.zoom - to * oh)
    x0 = round((sw - ow) / 2 - t.shift_x)
    if x0 < 0 or y0 < 0 or x0 + ow > sw or y0 + oh > sh:
        raise ValueError(f"the {ow}x{oh} window at ({x0}, {y0}) leaves the {sw}x{sh} scaled frame "
                         f"(zoom {t.zoom:g}, horizon {t.horizon_from:g} -> {to:g})")
    return sw, sh, x0, y0, ow, oh


def move_label_line(line: str, t: Transform, x0: int, y0: int, ow: int, oh: int) -> str | None:
    """One KITTI label line with its box moved into the window (None: a blank line)."""
    f = line.split()
    if not f:
        return None
    x1, y1, x2, y2 = (float(v) * t.zoom for v in f[4:8])
    x1, x2, y1, y2 = x1 - x0, x2 - x0, y1 - y0, y2 - y0
    area = max(x2 - x1, 0.0) * max(y2 - y1, 0.0)
    cx1, cy1 = min(max(x1, 0.0), ow - 1.0), min(max(y1, 0.0), oh - 1.0)
    cx2, cy2 = min(max(x2, 0.0), ow - 1.0), min(max(y2, 0.0), oh - 1.0)
    visible = max(cx2 - cx1, 0.0) * max(cy2 - cy1, 0.0) / area if area > 0 else 0.0
    if f[0] != "DontCare" and visible < t.min_visible:
        f[0] = "DontCare"
    if visible <= 0:
        return None  # wholly outside: no line
    if visible < 1 and f[0] != "DontCare":
        old = float(f[1])
        cut = 1.0 - visible
        f[1] = f"{min(1.0, old + (1.0 - old) * cut):.2f}" if old <= 1 else f[1]
    f[4:8] = [f"{v:.2f}" for v in (cx1, cy1, cx2, cy2)]
    return " ".join(f)


def move_calib(text: str, t: Transform, x0: int, y0: int) -> str:
    """A KITTI calib file with ``P2`` moved: ``A · P2`` (the other matrices as they are)."""
    out = []
    for line in text.splitlines():
        key, sep, rest = line.partition(":")
        if key.strip() == "P2" and sep:
            p = np.array([float(v) for v in rest.split()], dtype=np.float64).reshape(3, 4)
            a = np.array([[t.zoom, 0, -x0], [0, t.zoom, -y0], [0, 0, 1]], dtype=np.float64)
            line = "P2: " + " ".join(f"{v:.12e}" for v in (a @ p).ravel())
        out.append(line)
    return "\n".join(out) + "\n"


def transform_folder(src: str | Path, dst: str | Path, t: Transform, limit: int | None = None) -> dict:
    """Write the transformed frames of ``src`` (a KITTI-format folder) into ``dst`` as
    ``images/``, ``labels/`` (where ``src`` has labels) and ``calib/`` (where it has calib);
    return the record also written to ``dst/transform.json``."""
    ds = KittiDataset(src)
    dst = Path(dst)
    for sub in ("images", "labels", "calib"):
        (dst / sub).mkdir(parents=True, exist_ok=True)
    frames = 0
    for i, image_id in enumerate(ds.ids[:limit]):
        bgr = cv2.imread(str(ds.image_paths[i]), cv2.IMREAD_COLOR)
        if bgr is None:
            raise ValueError(f"{ds.image_paths[i]}: cannot read the image")
        h, w = bgr.shape[:2]
        sw, sh, x0, y0, ow, oh = window(t, w, h)
        interp = cv2.INTER_AREA if t.zoom < 1 else cv2.INTER_LINEAR
        scaled = cv2.resize(bgr, (sw, sh), interpolation=interp)
        cv2.imwrite(str(dst / "images" / f"{image_id}.png"), scaled[y0:y0 + oh, x0:x0 + ow])
        if ds.label_dir is not None:
            lines = (ds.label_dir / f"{image_id}.txt").read_text(encoding="utf-8").splitlines()
            moved = [m for m in (move_label_line(x, t, x0, y0, ow, oh) for x in lines) if m is not None]
            (dst / "labels" / f"{image_id}.txt").write_text("".join(m + "\n" for m in moved), encoding="utf-8")
        if ds.calib_dir is not None and (ds.calib_dir / f"{image_id}.txt").exists():
            text = (ds.calib_dir / f"{image_id}.txt").read_text(encoding="utf-8")
            (dst / "calib" / f"{image_id}.txt").write_text(move_calib(text, t, x0, y0), encoding="utf-8")
        frames += 1
    if ds.label_dir is None:
        (dst / "labels").rmdir()
    to = t.horizon_from if t.horizon_to is None else t.horizon_to
    record = {"source": str(src), "frames": frames, "zoom": t.zoom, "size": t.size,
              "horizon_from": t.horizon_from, "horizon": to, "shift_x": t.shift_x,
              "min_visible": t.min_visible}
    (dst / "transform.json").write_text(json.dumps(record, indent=2) + "\n", encoding="utf-8")
    return record


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("src", help="a KITTI-format folder (images/ [+ labels/ + calib/])")
    ap.add_argument("-o", "--out", required=True, help="the folder to write (a KITTI-format folder)")
    ap.add_argument("--zoom", type=float, default=1.0, help="scale factor of the frames (objects this much larger)")
    ap.add_argument("--size", type=int, nargs=2, metavar=("W", "H"), help="output size [default: the frame's]")
    ap.add_argument("--horizon-from", type=float, default=0.47,
                    help="the source's horizon, a fraction of its height (reeb calibrate's)")
    ap.add_argument("--horizon-to", type=float, help="where it lands in the output [default: the same fraction]")
    ap.add_argument("--shift-x", type=float, default=0.0, help="move the window's content right by this many pixels")
    ap.add_argument("--min-visible", type=float, default=0.5,
                    help="objects with less of their box inside become DontCare")
    ap.add_argument("--limit", type=int, help="only the first N frames")
    args = ap.parse_args(argv)
    if not (args.zoom > 0 and 0 < args.horizon_from < 1 and (args.horizon_to is None or 0 < args.horizon_to < 1)
            and 0 <= args.min_visible <= 1 and math.isfinite(args.shift_x)):
        ap.error("need zoom > 0, horizons in (0, 1), 0 <= min-visible <= 1")
    t = Transform(args.zoom, tuple(args.size) if args.size else None, args.horizon_from, args.horizon_to,
                  args.shift_x, args.min_visible)
    try:
        record = transform_folder(args.src, args.out, t, args.limit)
    except ValueError as e:
        sys.exit(f"camera_transform: {e}")
    print(rerun_line("benchmarks/camera_transform.py", sys.argv[1:] if argv is None else argv))
    print(json.dumps(record))


if __name__ == "__main__":
    main()
