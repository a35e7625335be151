"""``reeb calibrate``: fit the horizon and the camera height from a folder's labelled boxes
(:func:`reeb_torch.camera.fit_camera`), print the fit, write a config file and a picture."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any, Mapping, Sequence

from ..camera import CameraFit, fit_camera, read_kitti_calib

__all__ = ["read_boxes", "calibrate", "format_fit", "plot_fit"]


def read_boxes(roots: Sequence[str | os.PathLike]) -> dict[str, Any]:
    """Every labelled box of KITTI-format folders, without decoding the images: per frame the
    boxes, class names, image height, and (where a calib file has ``P2``) ``cy / H``.

    Raises:
        ValueError: a folder without a label folder or without images.
    """
    from PIL import Image

    from ..eval.data import KittiDataset, read_kitti_labels

    out: dict[str, Any] = {"boxes": [], "classes": [], "heights": [], "p2_horizon": []}
    for root in roots:
        ds = KittiDataset(root)
        if ds.label_dir is None:
            raise ValueError(f"{root}: no label folder (labels/ or label_2/ beside {ds.image_dir.name}/): "
                             "calibration needs labelled boxes")
        for i, image_id in enumerate(ds.ids):
            with Image.open(ds.image_paths[i]) as im:
                size = im.size
            height = size[1]
            objects = read_kitti_labels(ds.label_dir / f"{image_id}.txt", image_size=size)
            out["boxes"].append([o.box for o in objects])
            out["classes"].append([o.type for o in objects])
            out["heights"].append(height)
            if ds.calib_dir is not None:
                calib = read_kitti_calib(ds.calib_dir / f"{image_id}.txt")
                if "P2" in calib:
                    out["p2_horizon"].append(float(calib["P2"][1, 2]) / height)
    return out


def format_fit(fit: CameraFit, heights: Mapping[str, float], mean_height: float,
               p2: Sequence[float] = (), factor: float = 1.0) -> str:
    """The fit, its intervals, the residuals per class and (given) P2's horizon, as text."""
    lo, hi = fit.horizon_interval
    lines = [
        f"horizon          {fit.horizon:.4f} of the image height = {fit.horizon * mean_height:.1f} px of "
        f"{mean_height:.0f} ({100 * fit.level:g} % interval {lo:.4f}-{hi:.4f})",
        f"camera height    {fit.camera_height_m:.3f} m ({100 * fit.level:g} % interval "
        f"{fit.camera_height_interval[0]:.3f}-{fit.camera_height_interval[1]:.3f}; box height factor {factor:g})",
        f"boxes            {fit.num_boxes} in {fit.num_frames} frames, {fit.num_outliers} given no weight "
        f"(robust residual scale {fit.scale * mean_height:.1f} px)",
    ]
    if p2:
        lines.append(f"P2 horizon       cy/H = {sum(p2) / len(p2):.4f} (mean of {len(p2)} calib files, "
                     f"{min(p2):.4f}-{max(p2):.4f})")
    lines.append("class            boxes  outliers  median residual  MAD     height given  height implied")
    for name, r in fit.per_class.items():
        lines.append(f"{name:<16} {r.count:>5}  {r.outliers:>8}  {r.median_px:>+12.1f} px  {r.mad_px:>4.1f} px  "
                     f"{heights[name]:>9.2f} m  {r.implied_height_m:>11.2f} m")
    return "\n".join(lines)


def plot_fit(fit: CameraFit, out: Path) -> Path | None:
    """Boxes' bottom rows against their heights (both / image height; height / class height)
    with the fitted line; None without matplotlib."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return None
    import numpy as np

    fig, ax = plt.subplots(figsize=(7, 5))
    names = np.array(fit.classes)
    for name in fit.per_class:
        m = (names == name) & (fit.weight > 0)
        ax.scatter(fit.x[m], fit.y[m], s=12, label=name)
    m = fit.weight == 0
    if m.any():
        ax.scatter(fit.x[m], fit.y[m], s=16, marker="x", c="grey", label="no weight (outlier)")
    xs = np.linspace(0, fit.x.max() * 1.05, 50)
    ax.plot(xs, fit.horizon + fit.camera_height_m * xs, "k-",
            label=f"horizon {fit.horizon:.3f} + {fit.camera_height_m:.2f} m × x")
    ax.set_xlabel("box height / (image height × class height)  [1/m]")
    ax.set_ylabel("box bottom / image height")
    ax.invert_yaxis()
    ax.legend(fontsize=8)
    ax.set_title("reeb calibrate: bottom − horizon = box height × camera height / class height")
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out


def calibrate(roots: Sequence[str | os.PathLike], out: str | os.PathLike,
              class_heights: Mapping[str, float] | None = None, samples: int = 500,
              level: float = 0.95, seed: int = 0, box_height_factor: float | None = None) -> tuple[str, Path, Path | None]:
    """Fit, write the config JSON (``{"config": {"horizon", "camera_height_m"}, "fit": ...}``,
    which ``reeb propose --config`` reads) and the picture beside it (``<out stem>.png``).

    Returns ``(the printed text, the JSON path, the picture's path or None)``.
    """
    from ..camera import BOX_HEIGHT_FACTOR, KITTI_CLASS_HEIGHTS_M

    factor = BOX_HEIGHT_FACTOR if box_height_factor is None else box_height_factor
    heights = dict(KITTI_CLASS_HEIGHTS_M if class_heights is None else class_heights)
    data = read_boxes(roots)
    fit = fit_camera(data["boxes"], data["classes"], data["heights"], heights, level=level,
                     samples=samples, seed=seed, box_height_factor=factor)
    mean_h = sum(data["heights"]) / len(data["heights"])
    text = format_fit(fit, heights, mean_h, data["p2_horizon"], factor)
    out = Path(out)
    record = {
        "config": fit.config_changes(),
        "fit": {
            "horizon_interval": fit.horizon_interval, "camera_height_interval": fit.camera_height_interval,
            "level": fit.level, "num_boxes": fit.num_boxes, "num_frames": fit.num_frames,
            "num_outliers": fit.num_outliers, "class_heights_m": heights, "box_height_factor": factor,
            "per_class": {k: vars(v) for k, v in fit.per_class.items()},
            "p2_horizon_mean": (sum(data["p2_horizon"]) / len(data["p2_horizon"])) if data["p2_horizon"] else None,
            "data": [str(r) for r in roots],
        },
    }
    out.write_text(json.dumps(record, indent=2) + "\n", encoding="utf-8")
    picture = plot_fit(fit, out.with_suffix(".png"))
    return text, out, picture
