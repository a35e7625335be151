"""``reeb calibrate``: the camera's horizon (and height) by one of three routes, written as the
same config file (``{"config": {"horizon", "camera_height_m"}, "fit": {"route": ...}}``):

* ``labels``: fit the horizon and the camera height to a folder's labelled boxes
  (:func:`reeb_torch.camera.fit_camera`), with a picture of the fit;
* ``images``: the horizon from the frames alone, where the road's lines meet
  (:func:`reeb_torch.horizon.estimate_horizon`), the camera height given or the default;
* ``intrinsics``: the horizon of a level camera, ``cy / H``, from a KITTI calibration file's
  ``P2`` or from ``cy`` and the image height.
"""

from __future__ import annotations

import json
import math
import os
from collections import Counter
from pathlib import Path
from typing import Any, Mapping, Sequence

import click
import numpy as np
from PIL import Image
from tqdm import tqdm

from ..camera import BOX_HEIGHT_FACTOR, KITTI_CLASS_HEIGHTS_M, Camera, CameraFit, fit_camera, read_kitti_calib
from ..config import ReebConfig
from ..datasets.kitti import KittiDataset, find_layout, read_kitti_labels
from ..horizon import HorizonError, estimate_horizon, frame_vanishing_point
from ..io import ImageReadError, read_image, replace_file
from .claim import claim_files
from .common import UsageProblem
from .inputs import NoImagesError, scan_images

__all__ = ["check_out", "read_boxes", "calibrate", "format_fit", "plot_fit", "has_labels", "calibrate_images",
           "calibrate_intrinsics", "class_heights", "print_notes"]


def read_boxes(roots: Sequence[str | os.PathLike]) -> dict[str, Any]:
    """Every labelled box of KITTI-format folders, without decoding the images: per frame the
    boxes, class names, image height, and (where a calib file has ``P2``) ``cy / H``.

    Raises:
        ValueError: a folder without a label folder or without images.
    """

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
                path = ds.calib_dir / f"{image_id}.txt"
                calib = read_kitti_calib(path)
                if "P2" in calib:
                    cy = float(calib["P2"][1, 2])
                    if not math.isfinite(cy) or cy <= 0:
                        raise ValueError(f"{path}: P2's cy is {cy}: a calib file gives a positive, finite cy")
                    out["p2_horizon"].append(cy / height)
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
            "route": "labels",
            "horizon_interval": fit.horizon_interval, "camera_height_interval": fit.camera_height_interval,
            "level": fit.level, "num_boxes": fit.num_boxes, "num_frames": fit.num_frames,
            "num_outliers": fit.num_outliers, "class_heights_m": heights, "box_height_factor": factor,
            "per_class": {k: vars(v) for k, v in fit.per_class.items()},
            "p2_horizon_mean": (sum(data["p2_horizon"]) / len(data["p2_horizon"])) if data["p2_horizon"] else None,
            "data": [str(r) for r in roots],
        },
    }
    write_record(out, record)
    picture = plot_fit(fit, out.with_suffix(".png"))
    return "route            labelled boxes\n" + text, out, picture


# -- writing, and the routes without labels ------------------------------------------------------

def check_out(out: Path, picture: bool, overwrite: bool) -> None:
    """``-o`` before any work: a usage error (one line, exit 2) where it is a folder, its
    folder is a file, the picture beside it (``picture``: the labelled route's ``<stem>.png``)
    would be the config itself, or the config or the picture is there already without
    ``overwrite``; then both are claimed until the command ends (:func:`.claim.claim_files`)."""

    targets = [out]
    if picture:
        png = out.with_suffix(".png")
        if png == out:
            raise UsageProblem(f"-o {out}: the picture written beside the config is {png}, the same file; name the "
                               f"config {out.with_suffix('.json')}")
        targets.append(png)
    claim_files(targets, overwrite, example="camera.json")


def write_record(out: Path, record: dict) -> None:
    """Write the config file whole or not at all (:func:`reeb_torch.io.replace_file`): a failed
    write leaves the previous file as it was."""

    replace_file(out, (json.dumps(record, indent=2) + "\n").encode("utf-8"))


def has_labels(root: str | os.PathLike) -> bool:
    """Whether ``root`` is a KITTI-format folder with a label folder (by its layout alone: a
    frame without its label or calib file is the labelled route's error, named there)."""

    try:
        return find_layout(root)[1].is_dir()
    except ValueError:  # not a KITTI folder: a plain folder of images
        return False


def _image_folders(roots: Sequence[str | os.PathLike]) -> list[Path]:
    """The image folder of each root: ``images/`` or ``image_2/`` of a KITTI folder, else the root."""

    out = []
    for r in roots:
        try:
            out.append(find_layout(r)[0])
        except ValueError:
            out.append(Path(r))
    return out


def _camera_height(camera_height: float | None) -> float:
    return ReebConfig().camera_height_m if camera_height is None else float(camera_height)


def calibrate_images(roots: Sequence[str | os.PathLike], out: str | os.PathLike, camera_height: float | None = None,
                     samples: int = 500, level: float = 0.95, seed: int = 0,
                     progress: bool = True) -> tuple[str, Path, list[str]]:
    """The ``images`` route: the horizon from the frames of ``roots`` (KITTI folders or plain
    folders of images) without labels; write the config. A frame that cannot be read is left
    out with a note.

    Returns ``(the printed text, the JSON path, the notes)``.

    Raises:
        reeb_torch.horizon.HorizonError: too few frames, or no road seen in them (its
            ``notes``: the frames left out, and why).
        ValueError: no image in the folders.
    """

    try:
        found = scan_images(_image_folders(roots))
    except NoImagesError as e:
        raise ValueError(str(e)) from None
    notes, points = list(found.notes), []
    for path in tqdm(found.images, desc="vanishing points", unit="frame", disable=not progress, leave=False):
        try:
            points.append(frame_vanishing_point(read_image(path)))
        except (ImageReadError, ValueError) as e:
            reason = " ".join(str(e).split()).removeprefix(f"{path}: ")
            notes.append(f"{path}: left out ({reason})")
    try:
        est = estimate_horizon((), level=level, samples=samples, seed=seed, points=points)
    except HorizonError as e:
        e.notes = notes  # the frames left out say why there were too few
        raise
    cam_h = _camera_height(camera_height)
    lo, hi = est.interval
    sure = "within ±0.01 of the height" if hi - lo <= 0.02 else "wider than ±0.01 of the height: give more frames"
    text = "\n".join([
        "route            images without labels (where the road's lines meet)",
        f"horizon          {est.horizon:.4f} of the image height ({100 * level:g} % interval {lo:.4f}-{hi:.4f}: {sure})",
        f"frames           {est.num_frames}, a road seen in {est.num_road}; {est.agree} of them meet within 0.02 of it",
        f"                 (vanishing point {est.vanishing_row:.4f}, + {est.offset:g} to the boxes' bottoms)",
        f"camera height    {cam_h:.3f} m ({'given' if camera_height is not None else 'the default; --camera-height sets it'})",
    ])
    record = {"config": {"horizon": est.horizon, "camera_height_m": cam_h},
              "fit": {"route": "images", "horizon_interval": list(est.interval), "level": level,
                      "vanishing_row": est.vanishing_row, "offset": est.offset, "num_frames": est.num_frames,
                      "num_road": est.num_road, "agree": est.agree, "camera_height_given": camera_height is not None,
                      "data": [str(r) for r in roots]}}
    out = Path(out)
    write_record(out, record)
    return text, out, notes


def _heights(roots: Sequence[str | os.PathLike]) -> list[int]:
    """The height in pixels of every image in ``roots`` (read from the files' headers)."""

    try:
        found = scan_images(_image_folders(roots))
    except NoImagesError as e:
        raise ValueError(str(e)) from None
    heights = []
    for p in found.images:
        try:
            with Image.open(p) as im:
                heights.append(im.size[1])
        except OSError:
            continue
    if not heights:
        raise ValueError(f"{', '.join(map(str, roots))}: no readable image to take the image height from")
    return heights


def calibrate_intrinsics(out: str | os.PathLike, calib: str | os.PathLike | None = None, cy: float | None = None,
                         height: int | None = None, roots: Sequence[str | os.PathLike] = (),
                         camera_height: float | None = None) -> tuple[str, Path]:
    """The ``intrinsics`` route: the horizon of a level camera, ``cy / H``, with ``cy`` from
    ``calib``'s ``P2`` (a KITTI calibration file) or given, and ``H`` given or the images' in
    ``roots`` (their most common height); write the config.

    Raises:
        ValueError: no ``P2`` in ``calib``, no height to divide by, or ``cy`` outside the image.
    """

    cam = Camera.from_kitti_calib(calib) if calib is not None else None
    row = cam.cy if cam is not None else cy
    if row is None:
        raise ValueError("the intrinsics route needs --calib FILE or --cy PIXELS")
    if height is None:
        if not roots:
            raise ValueError("the image height is needed: give --height PIXELS or folders of the camera's frames")
        height = Counter(_heights(roots)).most_common(1)[0][0]
    if not 0 < row < height:
        raise ValueError(f"the principal row cy = {row:g} px lies outside the image height {height} px")
    cam_h = _camera_height(camera_height)
    source = f"P2 of {calib}" if cam is not None else "--cy"
    lines = [
        "route            intrinsics (the horizon of a level camera: cy / image height)",
        f"horizon          {row / height:.4f} of the image height = cy {row:.1f} px / {height} px ({source}); exact "
        "for a level camera, off by the camera's pitch otherwise",
        f"camera height    {cam_h:.3f} m ({'given' if camera_height is not None else 'the default; --camera-height sets it'})",
    ]
    fit: dict = {"route": "intrinsics", "cy_px": row, "image_height_px": height, "source": source,
                 "camera_height_given": camera_height is not None}
    if cam is not None:
        fit.update(fx_px=cam.fx, fy_px=cam.fy, vertical_fov_deg=math.degrees(2 * math.atan(height / (2 * cam.fy))))
    out = Path(out)
    write_record(out, {"config": {"horizon": row / height, "camera_height_m": cam_h}, "fit": fit})
    return "\n".join(lines), out


def class_heights(items: tuple[str, ...]) -> dict[str, float] | None:
    """``--class-height CLASS=METRES`` items over KITTI's class heights (None without any);
    a usage error naming the item that is not CLASS=METRES with metres > 0."""

    if not items:
        return None
    heights = dict(KITTI_CLASS_HEIGHTS_M)
    for item in items:
        name, sep, value = item.partition("=")
        try:
            h = float(value)
        except ValueError:
            h = float("nan")
        if not sep or not name.strip() or not h > 0:
            raise click.BadParameter(f"{item!r}: expected CLASS=METRES with metres > 0, e.g. Car=1.53",
                                     param_hint="--class-height")
        heights[name.strip()] = h
    return heights


def print_notes(notes: list[str], most: int = 10) -> None:
    """The frames left out, one ``note:`` line each on stderr (the first ``most``, then a count)."""

    for note in notes[:most]:
        click.echo(f"note: {note}", err=True)
    if len(notes) > most:
        click.echo(f"note: ... and {len(notes) - most} more frames left out", err=True)
