"""The horizon without labels: candidate methods measured on the dev folders and on test cameras
made from them, against the horizon ``reeb calibrate`` fits from their labelled boxes.

Test cameras (:data:`CAMERAS`, made with ``benchmarks/camera_transform.py`` into ``--work``,
each applied alike to every dev folder, so that one camera holds the frames of both): KITTI's
own, a zoom of 1.33 with the horizon moved to 0.41 (the README's camera), a crop to 0.55, a
zoom out, a zoom of 1.6 to 0.50, and a zoom of 1.2 to 0.35 moved sideways. Per folder the
truth is the labelled fit (:func:`reeb_torch.camera.fit_camera`, its 95 % interval) and, for a
level camera, the calibration's ``cy / H`` (mean over the frames' ``P2``).

Methods (per frame, then over the frames of a folder):

* ``lsd-vp``: the vanishing point of LSD's line segments (:mod:`reeb_torch.horizon`); over
  frames the mode (``kde``) or the median of the frames in which a road was seen, or the mode
  of all frames (``all``); ``+offset``: with :data:`reeb_torch.horizon.BOX_BOTTOM_OFFSET`;
* ``hough-edges-vp``: the same vote over OpenCV's probabilistic Hough segments of REEB's edge map;
* ``lsd-road-vp``: the vote over LSD's segments on or beside REEB's road mask (road edges, lane
  markings);
* ``road-top``: the top of REEB's road mask in the middle columns (the road's far end);
* ``edge-row``: the row where REEB's edge map is densest in the middle columns;
* ``reeb-boxes``: ``reeb calibrate``'s fit to REEB's own best car boxes (the default preset at
  its horizon 0.47) in place of labels.

Also, for the chosen method, how the estimate holds with fewer frames: random subsets of n
frames of each folder, the share within 0.01 of the truth and the median interval width.

    python benchmarks/horizon_methods.py --out docs/results/horizon
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import default_dev_dirs, environment, rerun_line, write_outputs  # noqa: E402
from camera_transform import Transform, transform_folder  # noqa: E402

from reeb_torch import horizon as H  # noqa: E402
from reeb_torch.camera import fit_camera  # noqa: E402

CAMERAS: dict[str, Transform | None] = {
    "kitti": None,
    "zoom1.33-h0.41": Transform(1.33, None, 0.4714, 0.41),
    "crop-h0.55": Transform(1.0, (1100, 300), 0.4714, 0.55),
    "zoom0.8": Transform(0.8, (960, 290), 0.4714, None),
    "zoom1.6-h0.50": Transform(1.6, None, 0.4714, 0.50),
    "zoom1.2-h0.35-side": Transform(1.2, (1000, 340), 0.4714, 0.35, 120.0),
}
"""The test cameras: a transform of the dev frames (None: the frames as they are)."""


def camera_folders(dev: list[Path], work: Path) -> dict[str, list[Path]]:
    """Each camera's folders (one per dev folder), made into ``work`` where not there yet."""
    out: dict[str, list[Path]] = {}
    for name, t in CAMERAS.items():
        out[name] = []
        for d in dev:
            if t is None:
                out[name].append(d)
                continue
            dst = work / name / d.name
            if not (dst / "transform.json").exists():
                transform_folder(d, dst, t)
            out[name].append(dst)
    return out


def truth(folder: Path) -> dict:
    """The labelled fit's horizon and interval, and the mean ``cy / H`` of the frames' ``P2``."""
    from reeb_torch.runs.calibrate import read_boxes

    data = read_boxes([folder])
    fit = fit_camera(data["boxes"], data["classes"], data["heights"], samples=300)
    p2 = data["p2_horizon"]
    return {"labelled": fit.horizon, "interval": list(fit.horizon_interval),
            "p2": float(np.mean(p2)) if p2 else None}


def _reeb_maps(image) -> tuple[np.ndarray, np.ndarray]:
    """REEB's edge map and road mask (the default settings, working resolution)."""
    from reeb_torch import ReebConfig
    from reeb_torch.stages.edges import edge_map, to_gray, working_images
    from reeb_torch.stages.road import road_mask

    c = ReebConfig()
    x = working_images([image], c.scale)
    edges = edge_map(to_gray(x), c.blur_sigma, c.edge_threshold, c.remove_isolated, c.thin_edges)[0].numpy()
    road = road_mask(x, c.road_samples, c.road_band, c.road_tolerance, c.seed)[0].numpy()
    return edges, road


def _point(p: H.FrameVanishingPoint) -> dict:
    return {"row": p.row, "support": p.support, "left": p.left, "right": p.right, "road": p.road}


def frame_features(image) -> dict:
    """Every method's per-frame numbers for one uint8 ``(3, H, W)`` image."""
    import cv2

    h, w = image.shape[-2:]
    grey = H._grey(image)
    lsd = H.line_segments(grey)
    edges, road = _reeb_maps(image)
    s = edges.shape[1] / w
    found = cv2.HoughLinesP((edges > 0).astype(np.uint8) * 255, 1, np.pi / 180, 20,
                            minLineLength=max(2, int(H._MIN_LENGTH * edges.shape[1])), maxLineGap=3)
    hough = H.steep_segments(found.reshape(-1, 4) / s, w) if found is not None else np.zeros((0, 4))
    near = cv2.dilate(road.astype(np.uint8), np.ones((9, 9), np.uint8)) > 0
    mid = np.round((lsd[:, :2] + lsd[:, 2:]) / 2 * s).astype(int)
    mid[:, 0] = mid[:, 0].clip(0, near.shape[1] - 1)
    mid[:, 1] = mid[:, 1].clip(0, near.shape[0] - 1)
    on_road = lsd[near[mid[:, 1], mid[:, 0]]] if len(lsd) else lsd
    rh, rw = road.shape
    cover = road[:, int(0.3 * rw):int(0.7 * rw)].mean(1)
    empty = np.flatnonzero(cover[:-1] < 0.05)
    density = np.convolve((edges[:, int(0.25 * rw):int(0.75 * rw)] > 0).mean(1), np.ones(5) / 5, "same")
    return {
        "lsd": _point(H.vanishing_point(lsd, h, w)),
        "hough": _point(H.vanishing_point(hough, h, w)),
        "road_lsd": _point(H.vanishing_point(on_road, h, w)),
        "road_top": float((empty.max() + 1) / rh if len(empty) else 0.0),
        "edge_row": float(density.argmax() / rh),
    }


def reeb_boxes(images) -> float:
    """``fit_camera`` on REEB's own best boxes hinted as cars (the default preset) in place of labels."""
    import warnings

    from reeb_torch import ProposalGenerator, ReebConfig

    gen = ProposalGenerator(ReebConfig(), top_k=30).eval()
    boxes, classes, heights = [], [], []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for im in images:
            out = gen([im])[0]
            keep = (out["labels"] == 0) & (out["class_probs"][:, 0] > 0.5)
            b = out["boxes"][keep][:10].numpy()
            boxes.append(b)
            classes.append(["Car"] * len(b))
            heights.append(int(im.shape[-2]))
    return fit_camera(boxes, classes, heights, samples=1).horizon


def folder_features(folder: Path, cache: Path) -> dict:
    """Per-frame features of a folder (cached in ``cache``) and the REEB-boxes fit."""
    if cache.exists():
        return json.loads(cache.read_text(encoding="utf-8"))
    from reeb_torch import read_image
    from reeb_torch.datasets.kitti import KittiDataset

    ds = KittiDataset(folder)
    t0 = time.perf_counter()
    images = [read_image(p) for p in ds.image_paths]
    frames, seconds = [], []
    for im in images:
        t = time.perf_counter()
        H.frame_vanishing_point(im)
        seconds.append(time.perf_counter() - t)
        frames.append(frame_features(im))
    record = {"frames": frames, "ids": list(ds.ids), "lsd_seconds": seconds, "reeb_boxes": reeb_boxes(images),
              "seconds": time.perf_counter() - t0}
    cache.parent.mkdir(parents=True, exist_ok=True)
    cache.write_text(json.dumps(record) + "\n", encoding="utf-8")
    return record


def _points(frames: list[dict], key: str) -> list[H.FrameVanishingPoint]:
    return [H.FrameVanishingPoint(f[key]["row"], 0.0, f[key]["support"], f[key]["left"], f[key]["right"], 3)
            for f in frames]


def _estimate(frames: list[dict], key: str, how: str, offset: float) -> float:
    """A folder's estimate from its frames' vanishing points ``key``: ``kde``: the package's
    :func:`~reeb_torch.horizon.estimate_horizon` (the mode of the road frames, by support);
    ``median``: the median of the road frames; ``all``: the mode of every frame, unweighted."""
    pts = _points(frames, key)
    if how == "kde":
        try:
            return H.estimate_horizon((), points=pts, samples=1, offset=offset).horizon
        except H.HorizonError:
            return math.nan
    rows = np.array([p.row for p in pts if (p.road if how == "median" else math.isfinite(p.row))])
    if not len(rows):
        return math.nan
    return (float(np.median(rows)) if how == "median" else H._mode(rows, np.ones(len(rows)))) + offset


METHODS = {
    "lsd-vp mode +offset (chosen)": lambda r: _estimate(r["frames"], "lsd", "kde", H.BOX_BOTTOM_OFFSET),
    "lsd-vp mode": lambda r: _estimate(r["frames"], "lsd", "kde", 0.0),
    "lsd-vp median +offset": lambda r: _estimate(r["frames"], "lsd", "median", H.BOX_BOTTOM_OFFSET),
    "lsd-vp all frames mode +offset": lambda r: _estimate(r["frames"], "lsd", "all", H.BOX_BOTTOM_OFFSET),
    "hough-edges-vp all frames mode +offset": lambda r: _estimate(r["frames"], "hough", "all", H.BOX_BOTTOM_OFFSET),
    "lsd-road-vp all frames mode +offset": lambda r: _estimate(r["frames"], "road_lsd", "all", H.BOX_BOTTOM_OFFSET),
    "road-top median": lambda r: float(np.median([f["road_top"] for f in r["frames"]])),
    "edge-row median": lambda r: float(np.median([f["edge_row"] for f in r["frames"]])),
    "reeb-boxes (default at 0.47)": lambda r: r["reeb_boxes"],
}


def fewer_frames(records: dict, truths: dict, ns: list[int], draws: int, seed: int) -> list[dict]:
    """The chosen method on random subsets of ``n`` frames of each folder: the share of subsets
    whose estimate lies within 0.01 of the estimate from all the folder's frames, and within
    0.01 of the labelled fit; the share refused (:class:`~reeb_torch.horizon.HorizonError`);
    the median interval width."""
    rng = np.random.default_rng(seed)
    out = []
    for n in ns:
        same = near = refused = total = 0
        widths = []
        for key, rec in records.items():
            pts = _points(rec["frames"], "lsd")
            if n > len(pts):
                continue
            full = H.estimate_horizon((), points=pts, samples=1).horizon
            for _ in range(draws):
                pick = [pts[i] for i in rng.choice(len(pts), n, replace=False)]
                total += 1
                try:
                    est = H.estimate_horizon((), points=pick, samples=100, min_frames=min(n, H.MIN_FRAMES))
                except H.HorizonError:
                    refused += 1
                    continue
                same += abs(est.horizon - full) <= 0.01
                near += abs(est.horizon - truths[key]["labelled"]) <= 0.01
                widths.append(est.interval[1] - est.interval[0])
        out.append({"frames": n, "within_0.01_of_all": same / max(total, 1), "within_0.01": near / max(total, 1),
                    "refused": refused / max(total, 1), "subsets": total,
                    "median_interval_width": float(np.median(widths)) if widths else None})
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, nargs="+", default=default_dev_dirs(), help="dev folders (KITTI format)")
    ap.add_argument("--work", type=Path, default=Path("runs/horizon"), help="where the test cameras and caches go")
    ap.add_argument("--out", type=Path, default=Path("docs/results/horizon"))
    ap.add_argument("--draws", type=int, default=200, help="random subsets per folder and size")
    args = ap.parse_args()
    cams = camera_folders(args.data, args.work)
    records, truths = {}, {}
    for cam, folders in cams.items():
        for f in folders:
            key = f"{cam}/{f.name}"
            print(f"{key}: ...", flush=True)
            truths[key] = truth(f)
            records[key] = folder_features(f, args.work / "cache" / cam / f"{f.name}.json")
    text = [rerun_line("benchmarks/horizon_methods.py", sys.argv[1:]), ""]
    keys = list(records)
    text.append("| folder | frames | labelled fit (95 % interval) | P2 cy/H | "
                + " | ".join(METHODS) + " |")
    text.append("|---" * (4 + len(METHODS)) + "|")
    table: dict[str, dict] = {m: {} for m in METHODS}
    for key in keys:
        t = truths[key]
        cells = []
        for m, fn in METHODS.items():
            v = fn(records[key])
            table[m][key] = v
            cells.append(f"{v:.4f}")
        text.append(f"| {key} | {len(records[key]['frames'])} | {t['labelled']:.4f} ({t['interval'][0]:.4f}-"
                    f"{t['interval'][1]:.4f}) | {t['p2']:.4f} | " + " | ".join(cells) + " |")
    text += ["", "| method | mean abs. error vs labelled | max | inside the labelled interval | "
                 "mean abs. error vs P2 cy/H | kitti |", "|---|---|---|---|---|---|"]
    summary = {}
    for m in METHODS:
        e = np.array([table[m][k] - truths[k]["labelled"] for k in keys])
        inside = sum(truths[k]["interval"][0] <= table[m][k] <= truths[k]["interval"][1] for k in keys)
        ep = np.array([table[m][k] - truths[k]["p2"] for k in keys])
        summary[m] = {"mean_abs": float(np.nanmean(np.abs(e))), "max_abs": float(np.nanmax(np.abs(e))),
                      "inside": int(inside), "mean_abs_p2": float(np.nanmean(np.abs(ep)))}
        text.append(f"| {m} | {summary[m]['mean_abs']:.4f} | {summary[m]['max_abs']:.4f} | {inside} of {len(keys)} | "
                    f"{summary[m]['mean_abs_p2']:.4f} | {table[m][keys[0]]:.4f} |")
    few = fewer_frames(records, truths, [3, 5, 8, 12, 20, 40], args.draws, 0)
    text += ["", "| frames | within 0.01 of the estimate from all frames | within 0.01 of the labelled fit | refused | "
                 "median interval width |", "|---|---|---|---|---|"]
    for r in few:
        w = "-" if r["median_interval_width"] is None else f"{r['median_interval_width']:.4f}"
        text.append(f"| {r['frames']} | {100 * r['within_0.01_of_all']:.0f} % | {100 * r['within_0.01']:.0f} % | "
                    f"{100 * r['refused']:.0f} % | {w} |")
    ms = [1000 * s for rec in records.values() for s in rec["lsd_seconds"]]
    text.append(f"\nlsd-vp: {np.median(ms):.0f} ms a frame (median; decoded images, one process)")
    print("\n".join(text))
    write_outputs(args.out, "methods", text, {"truth": truths, "estimates": table, "summary": summary,
                                             "fewer_frames": few, "environment": environment()})


if __name__ == "__main__":
    main()
