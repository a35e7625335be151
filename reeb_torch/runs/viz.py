"""Pictures of proposals and of the algorithm's intermediate results.

Three pictures, for three uses:

- :func:`draw_proposals` — fast (OpenCV), one image with its top proposals ranked by
  colour; ``reeb propose --viz`` writes one per image (:func:`draw_detections`: a detector's
  boxes with their classes and scores, ``reeb detect --viz``).
- :func:`crop_sheet` — many objects at a glance: a crop around each with its ground truth
  and the proposal nearest to it, and a caption (``benchmarks/diagnose_recall.py --show``
  lays out every object the proposals miss).
- :func:`inspection_figure` — the explanatory picture of ``reeb show`` (matplotlib): three
  panels over the same image that follow the paper's pipeline, (1) edges and road mask
  (Sec. 3.4–3.5), (2) region strips with their entropy H and proposal share (Sec. 3.6,
  eqs. 2 and 9), (3) the top proposals with the ground-truth boxes (eqs. 1, 10–13).

The best boxes carry their rank; near-duplicate boxes (IoU 0.5 or more with a better one)
share one label listing their ranks (``1,2,4 Truck``), and labels are moved off each other
(:func:`rank_labels`), so a ranking whose best boxes are all one object stays legible. Text
drawn with OpenCV goes through :func:`cv_text` (its fonts draw ASCII; a file name that is
not UTF-8 would crash it).

Images are RGB ``uint8`` tensors ``(3, H, W)`` (as :func:`reeb_torch.read_image` returns)
or ``(H, W, 3)`` NumPy arrays; boxes are ``Tensor[N, 4]`` ``(x1, y1, x2, y2)`` in input
pixels, ranked best first. Ground truth is a sequence of ``(label, (x1, y1, x2, y2))``
pairs (or objects with ``.type`` and ``.box``, as :func:`reeb_torch.datasets.kitti.read_kitti_labels`
returns).
"""

from __future__ import annotations

import io
import os
from pathlib import Path
from typing import Any, Sequence

import cv2
import numpy as np
import torch

from ..io import replace_file
from .rows import text_path

__all__ = ["rank_colors", "draw_proposals", "draw_detections", "crop_sheet", "save_png", "inspection_figure",
           "save_figure", "gt_pairs", "cv_text", "rank_labels"]

GT_COLOR = (0, 255, 128)
"""Ground-truth boxes: spring green, unlike any colour of the proposal ranking."""
NEAREST_COLOR = (255, 96, 32)
"""The proposal nearest to a ground-truth box in :func:`crop_sheet`: orange."""
CLASS_COLOURS = ((255, 200, 0), (0, 200, 255), (255, 80, 200), (120, 255, 80), (255, 120, 60), (160, 120, 255))
"""The classes of :func:`draw_detections`, in the detector's order."""
DUPLICATE_IOU = 0.5
"""Boxes overlapping a better-ranked labelled box this much share its label (:func:`rank_labels`)."""


def cv_text(text: object) -> str:
    """``text`` as OpenCV's Hershey fonts can draw it: ASCII. A byte of a file name that is
    not UTF-8 (Python holds it as a lone surrogate, which crashes ``cv2.putText``) becomes
    ``\\xNN`` as in the rows (:func:`.rows.text_path`); any other non-ASCII character ``?``."""
    return text_path(str(text)).encode("ascii", "replace").decode("ascii")


def rank_labels(boxes: np.ndarray, n: int, hints: Sequence[str] | None = None) -> list[tuple[list[int], str]]:
    """The labels of the best ``n`` of ``boxes`` (``[N, 4]``, best first): ``(indices, text)``
    per label, best first. A box whose IoU with the first box of an earlier label is
    :data:`DUPLICATE_IOU` or more joins that label (``"1,2,4 Truck"``: the ranks, then the
    hint of each distinct class where ``hints`` are given)."""
    groups: list[list[int]] = []
    for i in range(min(n, len(boxes))):
        for g in groups:
            if _iou(boxes[g[0]], boxes[i]) >= DUPLICATE_IOU:
                g.append(i)
                break
        else:
            groups.append([i])
    out = []
    for g in groups:
        text = ",".join(str(i + 1) for i in g)
        if hints is not None:
            text += " " + "/".join(dict.fromkeys(str(hints[i]) for i in g))
        out.append((g, text))
    return out


def _iou(a: Sequence[float], b: Sequence[float]) -> float:
    ix = max(0.0, min(a[2], b[2]) - max(a[0], b[0]))
    iy = max(0.0, min(a[3], b[3]) - max(a[1], b[1]))
    inter = ix * iy
    union = (a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter
    return float(inter / union) if union > 0 else 0.0


def _free_spot(x: float, y: float, tw: float, th: float, placed: list[tuple[float, float, float, float]],
               width: float, height: float) -> tuple[float, float]:
    """Where a ``tw`` × ``th`` label wanted at top-left ``(x, y)`` overlaps none of ``placed``:
    there, else a line higher, then lower, a line at a time, within the picture (where none
    is free, where it was wanted); the spot is added to ``placed``."""
    x = min(max(0.0, x), max(0.0, width - tw))
    y = min(max(0.0, y), max(0.0, height - th))

    def free(ty: float) -> bool:
        return not any(x < px2 and px1 < x + tw and ty < py2 and py1 < ty + th for px1, py1, px2, py2 in placed)

    steps = int(height // max(th, 1.0)) + 1
    tries = [y] + [y - k * th for k in range(1, steps)] + [y + k * th for k in range(1, steps)]
    spot = next((t for t in tries if 0 <= t <= height - th and free(t)), y)
    placed.append((x, spot, x + tw, spot + th))
    return x, spot


def _hwc(image: torch.Tensor | np.ndarray) -> np.ndarray:
    """An RGB ``uint8`` ``(H, W, 3)`` contiguous array from a tensor ``(3, H, W)`` or array."""
    if isinstance(image, torch.Tensor):
        t = image.detach().cpu()
        if t.ndim != 3 or t.shape[0] != 3:
            raise ValueError(f"expected an image tensor of shape (3, H, W), got {tuple(t.shape)}")
        if t.dtype != torch.uint8:
            t = (t.float().clamp(0, 1) * 255 + 0.5).to(torch.uint8)
        return np.ascontiguousarray(t.permute(1, 2, 0).numpy())
    a = np.asarray(image)
    if a.ndim != 3 or a.shape[2] != 3 or a.dtype != np.uint8:
        raise ValueError(f"expected an RGB uint8 array of shape (H, W, 3), got {a.shape} {a.dtype}")
    return np.ascontiguousarray(a)


def _boxes(boxes: Any) -> np.ndarray:
    if boxes is None:
        return np.zeros((0, 4), np.float32)
    if isinstance(boxes, torch.Tensor):
        boxes = boxes.detach().cpu().float().numpy()
    a = np.asarray(boxes, dtype=np.float32).reshape(-1, 4)
    return a


def gt_pairs(objects: Sequence[Any] | None) -> list[tuple[str, tuple[float, float, float, float]]]:
    """Normalise ground truth to ``(label, (x1, y1, x2, y2))`` pairs.

    Accepts pairs already, or objects with ``.type`` and ``.box`` (KITTI labels).
    """
    out = []
    for o in objects or []:
        if hasattr(o, "box"):
            label, box = getattr(o, "type", "object"), o.box
        else:
            label, box = o
        x1, y1, x2, y2 = (float(v) for v in box)
        out.append((str(label), (x1, y1, x2, y2)))
    return out


def rank_colors(n: int, lo: float = 0.15) -> np.ndarray:
    """``n`` RGB ``uint8`` colours for ranks 1..n: bright yellow (best) to dim purple.

    Samples the *plasma* colour map from 1.0 (rank 1) down to ``lo`` (rank n).
    """

    if n <= 0:
        return np.zeros((0, 3), np.uint8)
    pos = np.linspace(1.0, lo, n) if n > 1 else np.array([1.0])
    lut = cv2.applyColorMap(np.arange(256, dtype=np.uint8)[:, None], cv2.COLORMAP_PLASMA)[:, 0, ::-1]
    return lut[np.round(pos * 255).astype(int)].copy()


def draw_proposals(
    image: torch.Tensor | np.ndarray,
    boxes: Any,
    scores: Any = None,
    top: int = 10,
    gt: Sequence[Any] | None = None,
    title: str | None = None,
    hints: Sequence[str] | None = None,
) -> np.ndarray:
    """Draw the ``top`` best proposals (and ground truth) over ``image`` with OpenCV.

    Proposals are coloured by rank (rank 1 bright yellow and thickest, the last dim purple,
    drawn first so that the best lie on top) and the best five carry their rank number, and
    their class hint where ``hints`` (one per box, e.g. ``"Car"``) are given; near-duplicates
    share one label and labels do not overlap (:func:`rank_labels`; the band says so). Ground
    truth boxes are green with their class name. ``title`` goes in a dark band above the
    image. Returns an RGB ``uint8`` array ``(H', W, 3)``.
    """

    canvas = _hwc(image).copy()
    h, w = canvas.shape[:2]
    b = _boxes(boxes)[: max(0, top)]
    colors = rank_colors(len(b))
    font = cv2.FONT_HERSHEY_SIMPLEX
    fs = max(0.35, min(w, 2 * h) / 1600)
    for i in range(len(b) - 1, -1, -1):
        x1, y1, x2, y2 = (int(round(v)) for v in b[i])
        cv2.rectangle(canvas, (x1, y1), (x2, y2), tuple(int(v) for v in colors[i]), 2 if i < 3 else 1, cv2.LINE_AA)
    labels = rank_labels(b, 5, hints)
    placed: list[tuple[float, float, float, float]] = []
    for group, text in labels:
        label = cv_text(text)
        (tw, th), _ = cv2.getTextSize(label, font, fs, 1)
        x1, y1 = (int(round(v)) for v in b[group[0]][:2])
        tx, ty = (int(v) for v in _free_spot(x1, y1 - th - 4, tw + 2, th + 3, placed, w, h))
        c = tuple(int(v) for v in colors[group[0]])
        cv2.rectangle(canvas, (tx, ty), (tx + tw + 2, ty + th + 3), c, -1)
        cv2.putText(canvas, label, (tx + 1, ty + th + 1), font, fs, (0, 0, 0), 1, cv2.LINE_AA)
    for label, (gx1, gy1, gx2, gy2) in gt_pairs(gt):
        p1, p2 = (int(round(gx1)), int(round(gy1))), (int(round(gx2)), int(round(gy2)))
        cv2.rectangle(canvas, p1, p2, GT_COLOR, 1, cv2.LINE_AA)
        cv2.putText(canvas, cv_text(label), (p1[0], min(h - 3, p2[1] + int(14 * fs / 0.5))), font, fs,
                    GT_COLOR, 1, cv2.LINE_AA)
    if any(len(g) > 1 for g, _ in labels):
        title = (f"{title}; " if title else "") + "ranks 1,2,..: near-duplicate boxes under one label"
    if title:
        band = max(18, int(round(30 * fs / 0.5)))
        head = np.full((band, w, 3), 24, np.uint8)
        cv2.putText(head, cv_text(title), (6, band - int(band * 0.3)), font, fs, (235, 235, 235), 1, cv2.LINE_AA)
        canvas = np.concatenate([head, canvas], axis=0)
    return canvas


def draw_detections(image: Any, boxes: Any, labels: Sequence[str], scores: Any, title: str | None = None,
                    classes: Sequence[str] = ()) -> np.ndarray:
    """``image`` (``uint8 [3, H, W]``) with each detection's box (``[D, 4]`` xyxy, best first),
    class name and score, one colour per class (the colours follow ``classes``' order, where
    given); labels are moved off each other, the best placed first; an RGB ``uint8`` array
    ``(H', W, 3)`` (a title band on top)."""

    canvas = _hwc(image).copy()
    h, w = canvas.shape[:2]
    fs = max(0.35, min(w, 2 * h) / 1600)
    colours: dict[str, tuple[int, int, int]] = {n: CLASS_COLOURS[i % len(CLASS_COLOURS)] for i, n in enumerate(classes)}
    dets = sorted(zip(_boxes(boxes).tolist(), labels, torch.as_tensor(scores).tolist()), key=lambda d: -d[2])
    font = cv2.FONT_HERSHEY_SIMPLEX
    for (x1, y1, x2, y2), name, _ in reversed(dets):  # the best drawn last, on top
        c = colours.setdefault(name, CLASS_COLOURS[len(colours) % len(CLASS_COLOURS)])
        cv2.rectangle(canvas, (int(round(x1)), int(round(y1))), (int(round(x2)), int(round(y2))), c, 2, cv2.LINE_AA)
    placed: list[tuple[float, float, float, float]] = []
    for (x1, y1, _, _), name, s in dets:  # labels best first, each moved off those placed before
        text = cv_text(f"{name} {s:.2f}")
        (tw, th), _ = cv2.getTextSize(text, font, fs, 1)
        tx, ty = (int(v) for v in _free_spot(round(x1), round(y1) - th - 4, tw + 2, th + 3, placed, w, h))
        cv2.rectangle(canvas, (tx, ty), (tx + tw + 2, ty + th + 3), colours[name], -1)
        cv2.putText(canvas, text, (tx + 1, ty + th + 1), font, fs, (0, 0, 0), 1, cv2.LINE_AA)
    if title:
        band = np.full((int(28 * fs / 0.5), w, 3), 30, np.uint8)
        cv2.putText(band, cv_text(title), (6, band.shape[0] - 8), cv2.FONT_HERSHEY_SIMPLEX, fs, (255, 255, 255), 1,
                    cv2.LINE_AA)
        canvas = np.concatenate([band, canvas])
    return canvas


def crop_sheet(
    crops: Sequence[tuple[Any, Sequence[float], Sequence[float] | None, str]],
    columns: int = 6,
    tile: tuple[int, int] = (200, 150),
    context: float = 0.6,
) -> np.ndarray:
    """A contact sheet of objects: one tile per ``(image, box, nearest, caption)``.

    Each tile is the part of ``image`` around ``box`` (``(x1, y1, x2, y2)``, input pixels;
    ``context`` × its width and height added on each side, at least 24 px), scaled to fit
    ``tile = (width, height)`` pixels without changing its aspect; ``box`` is drawn in
    green and ``nearest`` (another box, e.g. the proposal of best IoU; or None) in orange,
    and ``caption`` is written in a dark band under the crop. Tiles fill ``columns`` per
    row. Returns an RGB ``uint8`` array (an empty ``(0, 0, 3)`` one for no crops).
    """

    if columns < 1 or tile[0] < 16 or tile[1] < 16:
        raise ValueError(f"crop_sheet needs columns >= 1 and tiles of at least 16 px, got {columns}, {tile}")
    if not crops:
        return np.zeros((0, 0, 3), np.uint8)
    tw, th = tile
    band = 16
    font = cv2.FONT_HERSHEY_SIMPLEX
    tiles = []
    for image, box, nearest, caption in crops:
        img = _hwc(image)
        h, w = img.shape[:2]
        x1, y1, x2, y2 = (float(v) for v in box)
        mx, my = max(24.0, context * (x2 - x1)), max(24.0, context * (y2 - y1))
        cx1, cy1 = int(max(0, np.floor(x1 - mx))), int(max(0, np.floor(y1 - my)))
        cx2, cy2 = int(min(w, np.ceil(x2 + mx))), int(min(h, np.ceil(y2 + my)))
        crop = img[cy1:cy2, cx1:cx2]
        f = min(tw / max(1, crop.shape[1]), th / max(1, crop.shape[0]))
        crop = cv2.resize(crop, (max(1, int(crop.shape[1] * f)), max(1, int(crop.shape[0] * f))),
                          interpolation=cv2.INTER_AREA if f < 1 else cv2.INTER_LINEAR)
        cell = np.full((th + band, tw, 3), 24, np.uint8)
        oy, ox = (th - crop.shape[0]) // 2, (tw - crop.shape[1]) // 2
        cell[oy: oy + crop.shape[0], ox: ox + crop.shape[1]] = crop

        def draw(b: Sequence[float], color: tuple[int, int, int]) -> None:
            p = [(float(b[0]) - cx1) * f + ox, (float(b[1]) - cy1) * f + oy,
                 (float(b[2]) - cx1) * f + ox, (float(b[3]) - cy1) * f + oy]
            cv2.rectangle(cell, (int(round(p[0])), int(round(p[1]))), (int(round(p[2])), int(round(p[3]))),
                          color, 1, cv2.LINE_AA)

        if nearest is not None:
            draw(nearest, NEAREST_COLOR)
        draw(box, GT_COLOR)
        fs = 0.36
        text = cv_text(caption)
        while len(text) > 4 and cv2.getTextSize(text, font, fs, 1)[0][0] > tw - 4:
            text = text[:-2]
        cv2.putText(cell, text, (2, th + band - 4), font, fs, (235, 235, 235), 1, cv2.LINE_AA)
        tiles.append(cell)
    rows = []
    for r in range(0, len(tiles), columns):
        row = tiles[r: r + columns]
        row += [np.full_like(tiles[0], 0)] * (columns - len(row))
        rows.append(np.concatenate(row, axis=1))
    return np.concatenate(rows, axis=0)


def save_png(path: str | os.PathLike, rgb: np.ndarray) -> Path:
    """Write an RGB ``uint8`` array as PNG, atomically (temporary file, then rename)."""

    p = Path(path)
    ok, data = cv2.imencode(".png", np.ascontiguousarray(rgb[:, :, ::-1]))
    if not ok:  # pragma: no cover - encoding a uint8 array does not fail
        raise OSError(f"{p}: PNG encoding failed")
    replace_file(p, data.tobytes())
    return p


# -- the explanatory figure of `reeb show` -----------------------------------------------

def _best_match(gt_box: Sequence[float], boxes: np.ndarray) -> tuple[float, int]:
    """Best IoU of ``gt_box`` with any of ``boxes`` and the (1-based) rank of that box."""
    if len(boxes) == 0:
        return 0.0, 0
    gx1, gy1, gx2, gy2 = gt_box
    ix = np.clip(np.minimum(boxes[:, 2], gx2) - np.maximum(boxes[:, 0], gx1), 0, None)
    iy = np.clip(np.minimum(boxes[:, 3], gy2) - np.maximum(boxes[:, 1], gy1), 0, None)
    inter = ix * iy
    area = (boxes[:, 2] - boxes[:, 0]) * (boxes[:, 3] - boxes[:, 1])
    union = area + (gx2 - gx1) * (gy2 - gy1) - inter
    iou = np.where(union > 0, inter / np.maximum(union, 1e-9), 0.0)
    j = int(np.argmax(iou))
    return float(iou[j]), j + 1


def inspection_figure(
    image: torch.Tensor | np.ndarray,
    inspection: Any,
    gt: Sequence[Any] | None = None,
    top: int = 20,
    title: str | None = None,
    config: Any = None,
):
    """The three-panel picture of ``reeb show`` as a matplotlib Figure.

    ``inspection`` is a :class:`reeb_torch.generator.Inspection` (``boxes``, ``scores``,
    ``edges`` ``[H, W]`` in [0, 1], ``road_mask`` bool ``[H, W]``, ``regions`` ``[R, 4]``,
    ``entropy`` ``[R]``, ``share`` ``[R]`` in [0, 1]). ``config`` (a ReebConfig), if given,
    adds the road sampling band and σ of eq. 9 to the picture.

    1. *Edges and road*: the grey image, darkened, with the edge magnitude in white and the
       road mask in translucent green; the dashed box is where the road colour is sampled.
    2. *Regions*: the region strips as brackets over the image, and under it one bar per
       region whose height is its share of the candidate budget, labelled with its entropy.
    3. *Proposals*: the ``top`` best proposals coloured by rank (rank 1 bright yellow) and
       the ground truth in green, each labelled with its best IoU over *all* proposals and
       the rank of that proposal.
    """
    import matplotlib

    matplotlib.use("Agg", force=False)

    rgb = _hwc(image)
    h, w = rgb.shape[:2]
    regions = _boxes(inspection.regions)
    entropy = inspection.entropy.detach().cpu().float().numpy().reshape(-1)
    share = inspection.share.detach().cpu().float().numpy().reshape(-1)
    fig, axes, layout = _figure_axes(h, w)
    _edges_panel(axes["edge"], rgb, inspection, config)
    _regions_panel(axes["reg"], rgb, regions, entropy, share)
    _share_bars(axes["bar"], w, regions, entropy, share, config)
    _proposals_panel(axes["prop"], rgb, _boxes(inspection.boxes), gt_pairs(gt), top, layout, config)
    if title:
        fig.text(layout["left"] / layout["fig_w"], 1 - 0.3 / layout["fig_h"], title, ha="left", va="center",
                 fontsize=13, fontweight="bold")
    return fig


_SMALL = dict(fontsize=9)
_PALETTE = ["#4fc3f7", "#ff8a65"]  # the region strips, alternating


def _figure_axes(h: int, w: int):
    """The figure and its four axes (``edge``, ``reg``, ``bar``, ``prop``), and the layout
    (inches) the panels place their labels by.

    Top to bottom; images fill their axes exactly (no letterbox) at the image's own aspect
    ratio: a tall image is capped at 9 in high and made narrower, not stretched. The bars
    share the image's width so that they line up with its regions."""
    import matplotlib.pyplot as plt

    fig_w, left, right = 15.0, 0.75, 0.2
    img_h = min((fig_w - left - right) * h / w, 9.0)
    aw = img_h * w / h
    bar_h, title_h, gap = 1.5, 0.32, 0.3
    rows = [("title", 0.7), ("t", title_h), ("edge", img_h), ("g", gap), ("t", title_h),
            ("reg", img_h), ("g", 0.08), ("bar", bar_h), ("g", gap), ("t", title_h),
            ("prop", img_h), ("g", 0.15)]
    fig_h = sum(v for _, v in rows)
    fig = plt.figure(figsize=(fig_w, fig_h), dpi=100, facecolor="white")
    axes = {}
    y = fig_h
    for name, size in rows:
        y -= size
        if name in ("edge", "reg", "bar", "prop"):
            axes[name] = fig.add_axes((left / fig_w, y / fig_h, aw / fig_w, size / fig_h))
    for ax in (axes["edge"], axes["reg"], axes["prop"]):
        ax.set_xlim(0, w)
        ax.set_ylim(h, 0)
        ax.set_xticks([])
        ax.set_yticks([])
    return fig, axes, dict(fig_w=fig_w, fig_h=fig_h, left=left, aw=aw, img_h=img_h)


def _edges_panel(ax, rgb: np.ndarray, inspection: Any, config: Any) -> None:
    """Panel 1: the darkened grey image with the edge magnitude in white, the road mask in
    translucent green, and the band where the road colour is sampled."""
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch, Rectangle

    h, w = rgb.shape[:2]
    edges = inspection.edges.detach().cpu().float().clamp(0, 1).numpy()
    road = inspection.road_mask.detach().cpu().bool().numpy()
    grey = rgb.astype(np.float32) @ np.array([0.299, 0.587, 0.114], np.float32) / 255.0
    base = np.repeat((0.35 * grey)[:, :, None], 3, axis=2)
    e = edges[:, :, None] if edges.shape == (h, w) else np.zeros((h, w, 1), np.float32)
    e = np.clip(1.5 * e, 0, 1)
    layer = base * (1 - e) + e * np.array([1.0, 1.0, 1.0])
    road_rgb = np.array([0.1, 0.85, 0.3])
    if road.shape == (h, w):
        layer = np.where(road[:, :, None], 0.55 * layer + 0.45 * road_rgb, layer)
    ax.imshow(np.clip(layer, 0, 1), extent=(0, w, h, 0), interpolation="antialiased",
              aspect="auto")
    road_pct = 100.0 * float(road.mean()) if road.size else 0.0
    handles: list[Any] = [Patch(facecolor=tuple(road_rgb.tolist()), alpha=0.6,
                                label=f"road mask ({road_pct:.0f} % of pixels)"),
               Patch(facecolor="white", edgecolor="0.5", label="edge magnitude")]
    band = getattr(config, "road_band", None)
    if band is not None:
        bx1, by1, bx2, by2 = band[0] * w, band[1] * h, band[2] * w, band[3] * h
        ax.add_patch(Rectangle((bx1, by1), bx2 - bx1, by2 - by1, fill=False, ls="--",
                               lw=1.2, ec="#ffd54f"))
        handles.append(Line2D([], [], color="#ffd54f", ls="--", label="road colour sampled here"))
    ax.legend(handles=handles, loc="upper right", framealpha=0.85, **_SMALL)
    ax.set_title("1. Edges (Gaussian blur + Sobel, Sec. 3.4) and road segmentation "
                 "(HSV range around the sampled road colour, Sec. 3.5)", loc="left", fontsize=11)


def _regions_panel(ax, rgb: np.ndarray, regions: np.ndarray, entropy: np.ndarray, share: np.ndarray) -> None:
    """Panel 2: the region strips as brackets over the image, labelled with H and share."""
    from matplotlib import patheffects

    h, w = rgb.shape[:2]
    ax.imshow(rgb, extent=(0, w, h, 0), interpolation="antialiased", aspect="auto")
    ax.imshow(np.zeros((1, 1, 4)) + [0, 0, 0, 0.3], extent=(0, w, h, 0), aspect="auto")
    n_reg = len(regions)
    levels = 2 if n_reg > 1 else 1
    outline = [patheffects.withStroke(linewidth=3.5, foreground="black")]
    inset = 0.004 * w
    for i, (x1, y1, x2, y2) in enumerate(regions):
        c = _PALETTE[i % 2]
        lane = i % levels
        y = y1 + (0.1 + 0.13 * lane) * (y2 - y1)
        bx1, bx2 = x1 + inset, x2 - inset
        ax.plot([bx1, bx1, bx2, bx2], [y + 0.05 * h, y, y, y + 0.05 * h], color=c, lw=2.4,
                solid_capstyle="butt", path_effects=outline)
        for x in (bx1, bx2):
            ax.plot([x, x], [y + 0.05 * h, y2], color=c, lw=1.0, ls=":", alpha=0.9)
        hv = float(entropy[i]) if i < len(entropy) else float("nan")
        sv = float(share[i]) if i < len(share) else 0.0
        ax.text((x1 + x2) / 2, y - 0.015 * h, f"R{i + 1}  H={hv:.2f}  {100 * sv:.0f} %",
                color=c, ha="center", va="bottom", fontsize=9.5, fontweight="bold",
                path_effects=outline)
    ax.set_title(f"2. {n_reg} overlapping region strip{'s' if n_reg != 1 else ''} "
                 "(width from the camera geometry, eqs. 5–8)", loc="left", fontsize=11)


def _share_bars(ax, w: int, regions: np.ndarray, entropy: np.ndarray, share: np.ndarray, config: Any) -> None:
    """Under panel 2: one bar per region, its share of the window budget (eq. 9)."""
    n_reg = len(regions)
    ax.set_xlim(0, w)
    sigma = getattr(config, "entropy_sigma", None)
    if n_reg:
        stride = (np.min(np.diff(np.sort((regions[:, 0] + regions[:, 2]) / 2)))
                  if n_reg > 1 else (regions[0, 2] - regions[0, 0]))
        width = 0.8 * max(float(stride), 1.0)
        for i, (x1, _, x2, _) in enumerate(regions):
            cx = (x1 + x2) / 2
            s = float(share[i]) if i < len(share) else 0.0
            hv = float(entropy[i]) if i < len(entropy) else float("nan")
            ax.bar(cx, 100 * s, width=width, color=_PALETTE[i % 2], edgecolor="0.3", lw=0.6)
            ax.text(cx, 100 * s + 3, f"R{i + 1}: H={hv:.2f}\n{100 * s:.0f} %", ha="center",
                    va="bottom", fontsize=8.5)
    ax.set_ylim(0, 150)
    ax.set_yticks([0, 50, 100])
    ax.set_ylabel("share (%)", fontsize=9)
    ax.set_xticks([])
    ax.spines[["top", "right"]].set_visible(False)
    eq = (f"share = 1 − |σ − H| / σ, σ = {sigma:g}" if sigma is not None else "share from eq. 9")
    ax.text(0.005, 0.97, f"Entropy H of each strip (eq. 2, bits) sets its share of the "
            f"sliding-window budget (eq. 9: {eq})", transform=ax.transAxes, ha="left",
            va="top", fontsize=10)


def _proposals_panel(ax, rgb: np.ndarray, boxes: np.ndarray, gts: list, top: int, layout: dict,
                     config: Any) -> None:
    """Panel 3: the ``top`` proposals coloured by rank and the ground truth, each labelled
    with its best IoU over all proposals (:func:`_gt_labels`)."""
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch, Rectangle

    h, w = rgb.shape[:2]
    ax.imshow(rgb, extent=(0, w, h, 0), interpolation="antialiased", aspect="auto")
    shown = boxes[:top]
    colors = rank_colors(len(shown)) / 255.0
    for i in range(len(shown) - 1, -1, -1):
        x1, y1, x2, y2 = shown[i]
        lw = 2.6 if i < 3 else (1.6 if i < 10 else 1.0)
        ax.add_patch(Rectangle((x1, y1), x2 - x1, y2 - y1, fill=False, ec=colors[i], lw=lw,
                               alpha=1.0 if i < 10 else 0.85))
    labels = rank_labels(shown, 5)
    char_w, line_h = 0.62 * 8 / 72 * w / layout["aw"], 12 / 72 * h / layout["img_h"]  # data units, 8 pt bold
    placed: list[tuple[float, float, float, float]] = []
    for group, text in labels:
        x1, y1 = shown[group[0]][:2]
        tx, ty = _free_spot(x1 + 1, y1 + 1, char_w * len(text) + char_w, line_h, placed, w, h)
        ax.text(tx, ty, text, color="black", fontsize=8, va="top", ha="left", fontweight="bold",
                bbox=dict(boxstyle="square,pad=0.1", fc=colors[group[0]], ec="none"))
    gt_hex = "#%02x%02x%02x" % GT_COLOR
    _gt_labels(ax, boxes, gts, gt_hex, w, h, layout)
    handles: list[Any] = []
    if len(shown):
        handles.append(Patch(facecolor=colors[0], label="rank 1 (best)"))
        if len(shown) > 1:
            handles.append(Patch(facecolor=colors[-1], label=f"rank {len(shown)}"))
    if any(len(g) > 1 for g, _ in labels):
        handles.append(Patch(facecolor="none", edgecolor="none",
                             label=f"ranks 1,2,..: near-duplicate boxes (IoU ≥ {DUPLICATE_IOU:g}) under one label"))
    if gts:
        handles.append(Line2D([], [], color=gt_hex, ls="--", lw=1.8,
                              label="ground truth: best IoU over all proposals (#rank)"))
    if handles:
        ax.legend(handles=handles, loc="upper right", framealpha=0.85, **_SMALL)
    extra = " × shadow underneath" if getattr(config, "shadow_score", "none") != "none" else ""
    if getattr(config, "vegetation_score", "none") != "none":
        extra += " × (1 − green share)^p"
    ranker = getattr(config, "ranker", "none")
    if ranker != "none":
        name = Path(ranker).name  # "kitti", or a weights file's name
        title = (f"3. Top {len(shown)} of {len(boxes)} proposals: REEB's candidates (score V: eqs. 1, 10–12{extra}) "
                 f"ranked by the learned model '{name}', then NMS (eq. 13)")
    else:
        title = (f"3. Top {len(shown)} of {len(boxes)} proposals: edge score S (eq. 1) × "
                 f"(α·location L + β·road R) (eqs. 10–12){extra}, then NMS (eq. 13)")
    ax.set_title(title, loc="left", fontsize=11)


def _gt_labels(ax, boxes: np.ndarray, gts: list, gt_hex: str, w: int, h: int, layout: dict) -> None:
    """The ground-truth boxes, each with a label of its best IoU placed below it (moved down
    a line at a time until it overlaps no earlier label; above the box when there is no room)."""
    from matplotlib.patches import Rectangle

    char_w = 0.62 * 8 / 72 * w / layout["aw"]  # data units per character of an 8 pt label
    line_h = 12 / 72 * h / layout["img_h"]  # data units per line
    placed: list[tuple[float, float, float, float]] = []
    for label, (x1, y1, x2, y2) in sorted(gts, key=lambda g: (g[1][3], g[1][0])):
        iou, rank = _best_match((x1, y1, x2, y2), boxes)
        ax.add_patch(Rectangle((x1, y1), x2 - x1, y2 - y1, fill=False, ec=gt_hex, lw=1.8,
                               ls=(0, (4, 2))))
        note = f"{label}  IoU {iou:.2f} (#{rank})" if iou > 0 else f"{label}  no proposal overlaps"
        tw = char_w * len(note)
        tx = min(max(0.0, x1), max(0.0, w - tw))
        ty = y2 + 2
        while any(tx < px2 and px1 < tx + tw and ty < py2 and py1 < ty + line_h
                  for px1, py1, px2, py2 in placed) and ty < h - line_h:
            ty += line_h
        if ty > h - line_h:  # no room below: above the box
            ty = max(0.0, y1 - line_h - 2)
        placed.append((tx, ty, tx + tw, ty + line_h))
        ax.text(tx, ty, note, color="black", fontsize=8, va="top", ha="left",
                bbox=dict(boxstyle="square,pad=0.15", fc=gt_hex, ec="none", alpha=0.9))


def save_figure(fig, path: str | os.PathLike, dpi: int = 100) -> Path:
    """Save a matplotlib figure as PNG, atomically, and close it."""

    import matplotlib.pyplot as plt

    p = Path(path)
    buf = io.BytesIO()
    try:
        fig.savefig(buf, format="png", dpi=dpi, facecolor=fig.get_facecolor())
    finally:
        plt.close(fig)
    replace_file(p, buf.getvalue())
    return p
