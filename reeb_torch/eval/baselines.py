"""Classical object-proposal baselines of the paper's Table 3, through OpenCV contrib.

The paper compares REEB with BING [14], Selective Search [16] and Edge Boxes [20]. This
module runs the OpenCV contrib implementations of the three and returns their proposals in
the same convention as :class:`reeb_torch.ProposalGenerator`, so one evaluation loop scores
all methods alike.

Contract (every baseline)::

    out = baseline(image)           # image: uint8 Tensor[3, H, W], RGB
    out["boxes"]                    # float32 Tensor[N, 4], (x1, y1, x2, y2), best first
    out["scores"]                   # float32 Tensor[N], non-increasing
    N <= baseline.top_k

Box convention (the one torchvision uses, and the one the KITTI labels are read in): boxes
are continuous pixel coordinates in which pixel ``(row r, column c)`` covers the square
``[c, c + 1) x [r, r + 1)``. A box that covers columns ``c0 .. c1`` and rows ``r0 .. r1``
(inclusive) is ``(c0, r0, c1 + 1, r1 + 1)``; hence ``0 <= x1 < x2 <= W`` and the box area
``(x2 - x1) * (y2 - y1)`` is its pixel count.

The +1 offsets of OpenCV's outputs, read in opencv_contrib's sources:

- Edge Boxes (``modules/ximgproc/src/edgeboxes.cpp``, ``scoreBox`` and
  ``getBoundingBoxes``): internally a box ``(x, y, w, h)`` covers the 0-based columns
  ``x .. x + w`` *inclusive* (``x1 = x + w``; the integral images are read at ``x0`` and
  ``x1 + 1``), i.e. ``w + 1`` columns. The output is ``Rect(x + 1, y + 1, w, h)``: the
  1-based convention of the MATLAB original. So an output ``(X, Y, w, h)`` is
  ``(X - 1, Y - 1, X + w, Y + h)`` here. See :func:`edge_boxes_to_xyxy`.
- BING (``modules/saliency/src/BING/objectnessBING.cpp``, ``predictBBoxSI``): ``box[0]``
  is the 0-based first column, ``box[2] = min(box[0] + width, imgW)`` the 0-based column
  *after* the last one, and then ``box[0]++; box[1]++``. So the output
  ``(minX, minY, maxX, maxY)`` is 1-based and inclusive, and is
  ``(minX - 1, minY - 1, maxX, maxY)`` here. See :func:`bing_to_xyxy`.
- Selective Search (``modules/ximgproc/src/selectivesearchsegmentation.cpp``): region
  boxes come from ``cv::boundingRect`` of the region's pixels and unions of such rects, an
  ordinary ``cv::Rect`` covering ``x .. x + w - 1``; so ``(x, y, w, h)`` is
  ``(x, y, x + w, y + h)`` here, no offset. See :func:`xywh_to_xyxy`.

Threads: OpenCV's global thread count (``cv2.setNumThreads``) is left as it is (OpenCV's
default is one thread per core). Edge Boxes, BING and Selective Search run their main loops
on one thread in any case; the count only affects the few parallel OpenCV filters they call.
"""

from __future__ import annotations

import contextlib
import math
import os
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterator

import cv2
import numpy as np
import torch
from torch import Tensor

__all__ = [
    "EdgeBoxesBaseline",
    "BingBaseline",
    "SelectiveSearchBaseline",
    "BASELINES",
    "sobel_edges",
    "edge_orientation",
    "edge_nms",
    "edge_boxes_to_xyxy",
    "bing_to_xyxy",
    "xywh_to_xyxy",
]


# -- input check and box conversions ------------------------------------------------------


def _check_image(image: Tensor) -> np.ndarray:
    """Check a ``uint8`` ``(3, H, W)`` RGB tensor and return it as an ``H x W x 3`` array."""
    if not isinstance(image, Tensor):
        raise TypeError(f"image must be a torch.Tensor, got {type(image).__name__}")
    if image.ndim != 3 or image.shape[0] != 3:
        raise ValueError(f"image must have shape (3, H, W), got {tuple(image.shape)}")
    if image.dtype != torch.uint8:
        raise ValueError(f"image must be uint8 RGB, got dtype {image.dtype}")
    if image.shape[1] < 2 or image.shape[2] < 2:
        raise ValueError(f"image must be at least 2x2 pixels, got {tuple(image.shape)}")
    return np.ascontiguousarray(image.detach().cpu().permute(1, 2, 0).numpy())


def _clip(boxes: np.ndarray, width: int, height: int) -> np.ndarray:
    boxes = boxes.astype(np.float32, copy=True).reshape(-1, 4)
    boxes[:, 0::2] = boxes[:, 0::2].clip(0, width)
    boxes[:, 1::2] = boxes[:, 1::2].clip(0, height)
    return boxes


def edge_boxes_to_xyxy(rects: np.ndarray, width: int, height: int) -> np.ndarray:
    """OpenCV Edge Boxes ``(X, Y, w, h)`` (1-based, ``w + 1`` columns) to ``(x1, y1, x2, y2)``.

    ``(X, Y, w, h) -> (X - 1, Y - 1, X + w, Y + h)``, clipped to ``[0, W] x [0, H]``.
    """
    r = np.asarray(rects, dtype=np.float64).reshape(-1, 4)
    out = np.stack([r[:, 0] - 1, r[:, 1] - 1, r[:, 0] + r[:, 2], r[:, 1] + r[:, 3]], axis=1)
    return _clip(out, width, height)


def bing_to_xyxy(boxes: np.ndarray, width: int, height: int) -> np.ndarray:
    """OpenCV BING ``(minX, minY, maxX, maxY)`` (1-based, inclusive) to ``(x1, y1, x2, y2)``.

    ``(minX, minY, maxX, maxY) -> (minX - 1, minY - 1, maxX, maxY)``, clipped to the image.
    """
    b = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    out = np.stack([b[:, 0] - 1, b[:, 1] - 1, b[:, 2], b[:, 3]], axis=1)
    return _clip(out, width, height)


def xywh_to_xyxy(rects: np.ndarray, width: int, height: int) -> np.ndarray:
    """An ordinary ``cv::Rect`` ``(x, y, w, h)`` (0-based, ``w`` columns) to ``(x1, y1, x2, y2)``."""
    r = np.asarray(rects, dtype=np.float64).reshape(-1, 4)
    out = np.stack([r[:, 0], r[:, 1], r[:, 0] + r[:, 2], r[:, 1] + r[:, 3]], axis=1)
    return _clip(out, width, height)


def _result(boxes: np.ndarray, scores: np.ndarray) -> dict[str, Tensor]:
    """Drop empty boxes (``x2 <= x1`` or ``y2 <= y1``) and wrap as tensors."""
    boxes = boxes.reshape(-1, 4).astype(np.float32)
    scores = np.asarray(scores, dtype=np.float32).reshape(-1)
    keep = (boxes[:, 2] > boxes[:, 0]) & (boxes[:, 3] > boxes[:, 1])
    return {"boxes": torch.from_numpy(boxes[keep].copy()), "scores": torch.from_numpy(scores[keep].copy())}


# -- Edge Boxes: edges from Sobel, since the structured-edge model is not available -------


def sobel_edges(rgb: np.ndarray, blur_sigma: float = 1.0) -> np.ndarray:
    """Sobel gradient magnitude of a ``H x W x 3`` uint8 RGB image, ``float32`` in ``[0, 1]``.

    Grey in ``[0, 1]`` (``cv2.COLOR_RGB2GRAY``), Gaussian blur with ``blur_sigma`` (kernel
    ``2 * ceil(3 sigma) + 1``; no blur if ``blur_sigma <= 0``), 3x3 Sobel in x and y
    (``BORDER_REFLECT_101``), magnitude ``sqrt(gx^2 + gy^2)`` divided by its maximum over
    the image (an all-flat image gives all zeros).
    """

    grey = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY).astype(np.float32) / 255.0
    if blur_sigma > 0:
        k = 2 * math.ceil(3 * blur_sigma) + 1
        grey = cv2.GaussianBlur(grey, (k, k), blur_sigma)
    gx = cv2.Sobel(grey, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(grey, cv2.CV_32F, 0, 1, ksize=3)
    mag = cv2.magnitude(gx, gy)
    peak = float(mag.max())
    return mag / peak if peak > 0 else mag


def _conv_tri(image: np.ndarray, r: int) -> np.ndarray:
    """Separable triangle filter of radius ``r`` (kernel ``[1 .. r+1 .. 1] / (r+1)^2``)."""

    if r <= 0:
        return image
    f = np.concatenate([np.arange(1, r + 2), np.arange(r, 0, -1)]).astype(np.float32) / (r + 1) ** 2
    return cv2.sepFilter2D(image, cv2.CV_32F, f, f, borderType=cv2.BORDER_REFLECT)


def _gradient2(image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Central differences in x and y (one-sided at the border), like MATLAB's ``gradient``."""
    gy, gx = np.gradient(image)
    return gx.astype(np.float32), gy.astype(np.float32)


def edge_orientation(edges: np.ndarray, r: int = 4) -> np.ndarray:
    """Edge normal orientation in ``[0, pi)`` from an edge map, as OpenCV/Dollár compute it.

    The same formula as ``StructuredEdgeDetection::computeOrientation`` in opencv_contrib
    and ``edgesDetect.m`` in Dollár's toolbox: smooth ``E`` with a triangle filter of
    radius ``r``, take first differences ``Ox, Oy``, second differences ``Oxx, Oxy, Oyy``,
    and ``O = mod(atan(Oyy * sign(-Oxy) / (Oxx + 1e-5)), pi)``. ``O`` points across the
    edge (a vertical edge gives ``O ~ 0``, a horizontal one ``O ~ pi/2``). One deviation:
    ``sign(0)`` is taken as +1, not 0, so that exactly axis-aligned edges (``Oxy == 0``,
    common in synthetic images) get ``pi/2`` rather than 0; elsewhere it changes nothing.
    """
    e = _conv_tri(edges.astype(np.float32), r)
    ox, oy = _gradient2(e)
    oxx, _ = _gradient2(ox)
    oxy, oyy = _gradient2(oy)
    sign = np.where(oxy > 0, -1.0, 1.0).astype(np.float32)  # sign(-Oxy), with sign(0) := +1
    o = np.arctan(oyy * sign / (oxx + 1e-5))
    return np.mod(o, np.pi).astype(np.float32)


def edge_nms(edges: np.ndarray, orientation: np.ndarray, r: int = 1, m: float = 1.01) -> np.ndarray:
    """Thin an edge map: keep a pixel only where it is a maximum across the edge.

    The rule of Dollár's ``edgesNmsMex`` (the ``edgesNms`` of OpenCV's structured edge
    detector, which needs the model): a pixel of magnitude ``e`` is zeroed if any sample at
    distance ``d in {-r..r} \\ {0}`` along the orientation ``(cos O, sin O)``, bilinearly
    interpolated (border replicated), exceeds ``m * e``.
    """

    e = edges.astype(np.float32)
    h, w = e.shape
    xs, ys = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    cos, sin = np.cos(orientation).astype(np.float32), np.sin(orientation).astype(np.float32)
    keep = np.ones_like(e, dtype=bool)
    for d in range(-r, r + 1):
        if d == 0:
            continue
        e_d = cv2.remap(e, xs + d * cos, ys + d * sin, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        keep &= m * e >= e_d
    return np.where(keep, e, 0.0).astype(np.float32)


@dataclass
class EdgeBoxesBaseline:
    """Edge Boxes (Zitnick & Dollár, ECCV 2014) via ``cv2.ximgproc.createEdgeBoxes``.

    Edges. Edge Boxes is meant to run on structured-forest edges, but the SE model file
    (``model.yml.gz``) is not available offline, so the edge map is built from Sobel
    (:func:`sobel_edges`: grey in [0, 1], Gaussian blur ``blur_sigma``, 3x3 Sobel magnitude
    normalised by its maximum), its orientation computed as OpenCV's
    ``computeOrientation`` does (:func:`edge_orientation`, triangle radius
    ``orientation_radius``) and the map thinned by non-maximum suppression across the edge
    (:func:`edge_nms`, radius 1, multiplier 1.01), as SE edges are before Edge Boxes. The
    paper's own Table 2 uses Sobel edges for REEB, so this is also the like-for-like
    comparison.

    Settings (OpenCV's ``createEdgeBoxes`` arguments; defaults are OpenCV's and the Edge
    Boxes paper's "IoU 0.7" setting):

    - ``top_k`` (2000) -> ``maxBoxes``: at most this many boxes are kept by the
      Edge Boxes NMS.
    - ``alpha`` (0.65): step size of the sliding-window search (IoU of neighbouring windows).
    - ``beta`` (0.75): NMS IoU threshold between proposals.
    - ``eta`` (1.0): adaptation rate of ``beta`` (1 = fixed).
    - ``min_score`` (0.01): boxes scoring below are dropped.
    - ``edge_min_mag`` (0.1): edge pixels of magnitude <= this are ignored. With the
      max-normalised Sobel map this is 10 % of the image's strongest gradient.
    - ``edge_merge_thr`` (0.5), ``cluster_min_mag`` (0.5): edge grouping.
    - ``max_aspect_ratio`` (3.0), ``min_box_area`` (1000.0 px): the window family.
    - ``gamma`` (2.0): affinity sensitivity; ``kappa`` (1.5): scale normalisation exponent.
    - ``blur_sigma`` (1.0), ``orientation_radius`` (4): edge map, see above.

    Output boxes follow the module's convention (``(X, Y, w, h) -> (X-1, Y-1, X+w, Y+h)``,
    see :func:`edge_boxes_to_xyxy`); scores are Edge Boxes' scores, already sorted
    descending by OpenCV.
    """

    top_k: int = 2000
    alpha: float = 0.65
    beta: float = 0.75
    eta: float = 1.0
    min_score: float = 0.01
    edge_min_mag: float = 0.1
    edge_merge_thr: float = 0.5
    cluster_min_mag: float = 0.5
    max_aspect_ratio: float = 3.0
    min_box_area: float = 1000.0
    gamma: float = 2.0
    kappa: float = 1.5
    blur_sigma: float = 1.0
    orientation_radius: int = 4
    name: str = "Edge Boxes"

    def __post_init__(self) -> None:
        if not hasattr(cv2, "ximgproc"):
            raise ImportError("cv2.ximgproc is missing: install opencv-contrib-python(-headless)")
        self._eb = cv2.ximgproc.createEdgeBoxes(
            alpha=self.alpha,
            beta=self.beta,
            eta=self.eta,
            minScore=self.min_score,
            maxBoxes=int(self.top_k),
            edgeMinMag=self.edge_min_mag,
            edgeMergeThr=self.edge_merge_thr,
            clusterMinMag=self.cluster_min_mag,
            maxAspectRatio=self.max_aspect_ratio,
            minBoxArea=self.min_box_area,
            gamma=self.gamma,
            kappa=self.kappa,
        )

    def edges(self, rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Thinned edge map and orientation (both ``float32 H x W``) of an RGB uint8 array."""
        e = sobel_edges(rgb, self.blur_sigma)
        o = edge_orientation(e, self.orientation_radius)
        return edge_nms(e, o), o

    def __call__(self, image: Tensor) -> dict[str, Tensor]:
        rgb = _check_image(image)
        h, w = rgb.shape[:2]
        e, o = self.edges(rgb)
        rects, scores = self._eb.getBoundingBoxes(e, o)
        if rects is None or len(rects) == 0:
            return _result(np.zeros((0, 4)), np.zeros(0))
        scores = np.asarray(scores, dtype=np.float32).reshape(-1)
        boxes = edge_boxes_to_xyxy(np.asarray(rects), w, h)
        order = np.argsort(-scores, kind="stable")[: self.top_k]
        return _result(boxes[order], scores[order])


# -- BING ----------------------------------------------------------------------------------


_BING_FILES = ("ObjNessB2W8MAXBGR.idx.yml.gz", "ObjNessB2W8MAXBGR.wS1.yml.gz", "ObjNessB2W8MAXBGR.wS2.yml.gz")


@contextlib.contextmanager
def _quiet_stdout(enabled: bool = True) -> Iterator[None]:
    """Silence C-level stdout (BING ``printf``s a timing line per colour space and call)."""
    if not enabled:
        yield
        return
    try:
        fd = sys.stdout.fileno()
    except (AttributeError, OSError, ValueError):
        yield
        return
    sys.stdout.flush()
    saved = os.dup(fd)
    try:
        with open(os.devnull, "wb") as null:
            os.dup2(null.fileno(), fd)
        yield
    finally:
        os.dup2(saved, fd)
        os.close(saved)


class BingBaseline:
    """BING objectness (Cheng et al., CVPR 2014) via ``cv2.saliency.ObjectnessBING``.

    Settings:

    - ``model_dir`` (required): folder holding the nine trained model files
      (``ObjNessB2W8{MAXBGR,HSV,I}.{idx,wS1,wS2}.yml.gz``, trained on PASCAL VOC 2007; from
      opencv_contrib's ``modules/saliency/samples/ObjectnessTrainedModel``); a missing
      folder or file raises :class:`FileNotFoundError`.
    - ``top_k`` (2000): the first ``top_k`` boxes of BING's ranking are
      returned. OpenCV proposes up to 250 boxes per window size and colour space
      (``numDetPerSize = 250``, fixed in ``computeSaliencyImpl``), typically ~10 000 in all.
    - ``ranking`` (``"opencv"``): order of the boxes, see *Ranking* below.
    - ``quiet`` (True): silence the timing lines OpenCV ``printf``s on every call.
    - The window base 2, feature size W = 8 and NMS size NSS = 2 are OpenCV's defaults
      (the BING paper's), left unchanged.

    OpenCV runs all three colour-space models it finds (MAXBGR, HSV, I: "BING-diversified")
    and writes ``bb.txt`` into a results folder on every call; that folder is a private
    temporary directory, removed when the object is garbage-collected. Input is converted
    to BGR, as OpenCV expects.

    Ranking (``ranking``): ``computeSaliency`` returns the three colour spaces' lists one
    after the other (MAXBGR, then HSV, then I), each sorted by descending SVM score. The
    values of ``getobjectnessValues()`` are not SVM scores but rank keys ``(i + 300) * s``,
    ``s = 1, 3, 5`` for MAXBGR, HSV, I (``ValStructVec::append`` in ``objectnessBING.cpp``),
    so sorting them *descending* would put the worst boxes first. Two orders make sense:

    - ``"opencv"`` (default): the order ``computeSaliency`` returns. ``scores = -rank``.
    - ``"interleaved"``: ascending rank key (stable), which interleaves the three lists as
      Cheng's "BING-diversified" code does; ``scores = -key``.

    OpenCV's order recalled the most on KITTI frames (docs/results.md, "Recall of the
    presets"), hence the default. Box conversion: see :func:`bing_to_xyxy`.
    """

    name = "BING"

    def __init__(
        self,
        model_dir: str | os.PathLike,
        top_k: int = 2000,
        ranking: str = "opencv",
        quiet: bool = True,
    ):
        if not hasattr(cv2, "saliency"):
            raise ImportError("cv2.saliency is missing: install opencv-contrib-python(-headless)")
        self.top_k = int(top_k)
        self.model_dir = Path(model_dir)
        self.quiet = quiet
        if ranking not in ("opencv", "interleaved"):
            raise ValueError(f"ranking must be 'opencv' or 'interleaved', got {ranking!r}")
        self.ranking = ranking
        if not self.model_dir.is_dir():
            raise FileNotFoundError(
                f"BING model folder not found: {self.model_dir} (expected the nine "
                "ObjNessB2W8*.yml.gz files from opencv_contrib modules/saliency/samples/ObjectnessTrainedModel)"
            )
        missing = [f for f in _BING_FILES if not (self.model_dir / f).is_file()]
        if missing:
            raise FileNotFoundError(f"BING model folder {self.model_dir} lacks {', '.join(missing)}")
        self._tmp = tempfile.TemporaryDirectory(prefix="reeb-bing-")
        self._bing = cv2.saliency.ObjectnessBING_create()  # type: ignore[attr-defined]  # contrib, not in cv2's stubs
        self._bing.setTrainingPath(str(self.model_dir))
        self._bing.setBBResDir(self._tmp.name)

    def __repr__(self) -> str:
        return (
            f"BingBaseline(top_k={self.top_k}, model_dir={str(self.model_dir)!r}, "
            f"ranking={self.ranking!r})"
        )

    def __call__(self, image: Tensor) -> dict[str, Tensor]:
        rgb = _check_image(image)
        h, w = rgb.shape[:2]
        bgr = cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)
        with _quiet_stdout(self.quiet):
            ok, boxes = self._bing.computeSaliency(bgr)
        if not ok or boxes is None or len(boxes) == 0:
            return _result(np.zeros((0, 4)), np.zeros(0))
        boxes = np.asarray(boxes).reshape(-1, 4)
        keys = np.arange(boxes.shape[0], dtype=np.float32)
        if self.ranking == "interleaved":
            values = np.asarray(self._bing.getobjectnessValues(), dtype=np.float32).reshape(-1)
            if values.shape[0] == boxes.shape[0]:
                keys = values
        order = np.argsort(keys, kind="stable")[: self.top_k]
        return _result(bing_to_xyxy(boxes[order], w, h), -keys[order])


# -- Selective Search ----------------------------------------------------------------------


@dataclass
class SelectiveSearchBaseline:
    """Selective Search (Uijlings et al., IJCV 2013), OpenCV's "fast" mode.

    ``cv2.ximgproc.segmentation.createSelectiveSearchSegmentation`` with
    ``switchToSelectiveSearchFast(base_k, inc_k, sigma)``: HSV and Lab images, Felzenszwalb
    segmentations with k = 150, 300, 450, and the colour+fill+texture+size and
    fill+texture+size strategies (the paper's "fast" setting).

    Settings:

    - ``top_k`` (2000): the first boxes of OpenCV's order are kept. OpenCV orders
      the regions by its pseudo-random rank (hierarchy level times a random number, as in
      the original) and removes duplicate boxes; the order is taken as the ranking.
      ``scores`` are ``1 - i / N`` (rank-derived, non-increasing), not a real objectness.
    - ``base_k`` (150), ``inc_k`` (150), ``sigma`` (0.8): OpenCV's fast-mode defaults.
    - ``scale`` (1.0): resize factor applied before segmenting (``INTER_AREA``); boxes are
      mapped back by dividing by the factor. 1.0 = full resolution (slow: Table 3's time
      column, docs/results.md).
    - ``seed`` (0): ``cv2.setRNGSeed`` before each call, so the ranking is reproducible
      (the global OpenCV RNG is reseeded; nothing else here uses it).

    Box conversion: plain ``cv::Rect``, see :func:`xywh_to_xyxy`.
    """

    top_k: int = 2000
    base_k: int = 150
    inc_k: int = 150
    sigma: float = 0.8
    scale: float = 1.0
    seed: int | None = 0
    name: str = "Selective Search"

    def __post_init__(self) -> None:
        if not hasattr(cv2, "ximgproc"):
            raise ImportError("cv2.ximgproc is missing: install opencv-contrib-python(-headless)")
        if not self.scale > 0:
            raise ValueError(f"scale must be > 0, got {self.scale}")
        self._ss = cv2.ximgproc.segmentation.createSelectiveSearchSegmentation()

    def __call__(self, image: Tensor) -> dict[str, Tensor]:
        rgb = _check_image(image)
        h, w = rgb.shape[:2]
        bgr = cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)
        if self.scale != 1.0:
            size = (max(2, round(w * self.scale)), max(2, round(h * self.scale)))
            bgr = cv2.resize(bgr, size, interpolation=cv2.INTER_AREA)
        if self.seed is not None:
            cv2.setRNGSeed(int(self.seed))
        self._ss.setBaseImage(bgr)
        self._ss.switchToSelectiveSearchFast(self.base_k, self.inc_k, self.sigma)
        rects = self._ss.process()
        if rects is None or len(rects) == 0:
            return _result(np.zeros((0, 4)), np.zeros(0))
        xywh = np.asarray(rects, dtype=np.float64).reshape(-1, 4)[: self.top_k]
        sh, sw = bgr.shape[:2]
        boxes = xywh_to_xyxy(xywh, sw, sh)
        if self.scale != 1.0:
            boxes = _clip(boxes * np.array([w / sw, h / sh, w / sw, h / sh], dtype=np.float32), w, h)
        n = len(xywh)
        return _result(boxes, 1.0 - np.arange(n, dtype=np.float32) / n)


BASELINES: dict[str, Callable[..., Callable[..., Any]]] = {
    "edgeboxes": EdgeBoxesBaseline,
    "bing": BingBaseline,
    "selective-search": SelectiveSearchBaseline,
}
"""Registry: baseline name -> class; each class takes ``top_k=`` (BING also its
``model_dir``) and is called on one ``uint8 (3, H, W)`` RGB tensor."""
