"""One dataclass that holds every constant of the REEB algorithm.

Each field names the paper section or equation it comes from. Where the printed paper is
ambiguous or cannot run as printed (``../shared/paper/NOTES.md``), the field documents the
choice and :meth:`ReebConfig.paper` keeps the printed reading. The package default
(``ReebConfig()``) is the variant with the best recall measured by
``benchmarks/ablations.py`` on the 60 KITTI frames in ``../shared/data/kitti``.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Literal

__all__ = ["ReebConfig", "PRESETS", "get_preset"]

Grouping = Literal["connected", "cell"]
ScoreNorm = Literal["perimeter", "area"]
RoadScore = Literal["reward", "penalize", "none", "flat", "stand"]
LocationScore = Literal["paper", "ground", "classes", "none"]
EntropyForm = Literal["printed", "abs-diff"]
WindowGeometry = Literal["camera", "grid"]


@dataclass(frozen=True)
class ReebConfig:
    """Settings of :class:`reeb_torch.ProposalGenerator`.

    All lengths in pixels refer to the *input* image unless the name says otherwise;
    ``scale`` sets the working resolution at which edges, groups and windows are computed,
    and boxes are mapped back to input pixels at the end.
    """

    # -- working resolution --------------------------------------------------------------
    scale: float = 0.5
    """Resize factor applied before edge detection (1.0 = full resolution, as the paper)."""

    # -- Sec. 3.4: denoising and edges ---------------------------------------------------
    blur_sigma: float = 1.0
    """Standard deviation of the Gaussian blur, in working pixels (kernel = 2*ceil(2σ)+1)."""
    edge_threshold: float = 0.05
    """Sobel magnitude (of a [0, 1] grey image, normalised to [0, 1]) below which a pixel
    is no edge. The paper gives no value (NOTES #4)."""
    edge_channels: Literal["gray", "rgb"] = "gray"
    """Sobel on the grey image (as printed) or on each RGB channel, keeping the strongest."""
    thin_edges: bool = True
    """Keep only the one-pixel ridge of each edge (non-maximum suppression across the
    edge, as the edge maps Edge Boxes scores). Not in the paper; measured."""
    remove_isolated: bool = True
    """Drop edge pixels with no edge pixel among their 8 neighbours (Sec. 3.4)."""

    # -- Sec. 3.7: edge groups -----------------------------------------------------------
    grouping: Grouping = "connected"
    """``connected``: 8-connected components of edge pixels, as printed. ``cell``: all
    edge pixels of one ``group_cell``×``group_cell`` tile form one group (fastest)."""
    group_cell: int | None = 8
    """Side, in working pixels, of the tiles that bound a group. With ``connected``,
    components are cut at tile borders (NOTES #2: long chains are rarely enclosed);
    ``None`` = no bound, plain connected components as printed."""

    # -- Sec. 3.5, eqs. 3-4: road segmentation -------------------------------------------
    road_samples: int = 300
    """Random pixels sampled to estimate the road colour ("hundreds", Sec. 3.5)."""
    road_band: tuple[float, float, float, float] = (0.3, 0.8, 0.7, 1.0)
    """Where road is likely, as fractions of the image (x1, y1, x2, y2): bottom centre."""
    road_tolerance: tuple[float, float, float] = (0.5, 0.12, 0.12)
    """Half-width of the in-range test around the sampled median, per HSV channel
    (hue in radians, circular; saturation and value in [0, 1]). Not given in the paper."""
    road_combine: Literal["and", "or"] = "and"
    """How the three channel masks are combined (eq. 4 prints AND, the text says OR)."""
    seed: int = 0
    """Seed of the road pixel sampling; the same pixels are sampled for every image of a
    given size, so results do not depend on the batch."""

    # -- Sec. 3.6, eqs. 5-8: region division ---------------------------------------------
    use_regions: bool = True
    """Region enhancement. ``False`` = one region, the whole image ("Ours*")."""
    camera_height_m: float = 1.65
    vertical_fov_deg: float = 35.0
    horizontal_fov_deg: float = 90.0
    max_object_width_m: float = 2.55
    region_overlap: float = 0.5
    """Stride between regions as a fraction of their width (eq. 8's ``overlap``)."""
    region_assign: Literal["contained", "nearest"] = "nearest"
    """Which region's budget a window counts against. ``contained``: every region that
    wholly contains it (as printed: windows are generated inside regions; a window wider
    than the region stride can then fall in none). ``nearest``: the region whose centre
    is nearest to the window's centre (every window no wider than a region has one)."""
    region_width_round: float | None = 0.125
    """Round the region width (fraction of image width) up to a multiple of this; the
    paper rounds 24.7 % to 25 %. ``None`` uses eq. 7 as computed."""

    # -- eqs. 2 and 9: entropy and proposal budget ---------------------------------------
    entropy_bins: int = 256
    """Grey levels of the entropy histogram (eq. 2's M). 256 = 8-bit grey, H in [0, 8]."""
    entropy_sigma: float = 4.0
    """σ of eq. 9 (the paper's KITTI value)."""
    entropy_form: EntropyForm = "abs-diff"
    """``abs-diff``: %P = 1 − |σ − H|/σ (NOTES #9). ``printed``: |σ + H|, which gives
    no proposals for any H > 0 and is kept only to show that it cannot run."""
    region_quota: bool = False
    """Also split the ``top_k`` output among the regions by their shares (eq. 9 applied to
    the final proposals, not only to the candidates)."""
    candidates_per_region: int = 6000
    candidates_without_regions: int = 8000
    """Windows passed on to ranking when ``use_regions=False`` (the whole image is one
    region with share 1); about ``top_k`` of them survive NMS on KITTI."""
    """Most windows a region may pass on to ranking (eq. 9's "maximum number of proposals
    that the user wants to generate in a region"); the region passes share × this."""

    # -- Sec. 3.6: sliding windows (NOTES #13) -------------------------------------------
    min_window: int = 16
    """Smallest window side, in input pixels."""
    size_ratio: float = 1.25
    """Ratio between consecutive window widths (and heights)."""
    window_step: float = 0.15
    """Stride of the sliding windows as a fraction of the window's side."""
    aspect_range: tuple[float, float] = (0.25, 4.0)
    """Allowed width/height ratios of the windows."""
    ground_band: tuple[float, float] | None = (0.45, 3.0)
    """Keep only windows whose height h and bottom row y_b satisfy
    r_lo <= h / (y_b − horizon·H) <= r_hi: objects standing on the road (a flat-ground
    camera prior, in the spirit of eq. 11's "lower boxes are bigger"). ``None`` = all rows."""
    window_geometry: WindowGeometry = "camera"
    """``camera``: window sizes and rows from the ground plane and ``object_templates``
    (:func:`reeb_torch.windows.camera_window_sizes`; regions set budgets, not the largest
    window). ``grid``: every size of the two geometric series within ``aspect_range``, no
    wider than a region, at the rows ``ground_band`` allows (the first release's grid)."""
    object_templates: tuple[tuple[float, float, float, float], ...] = (
        (1.2, 2.6, 1.3, 6.5),   # car / van: height, width of its 2D box at any yaw
        (2.2, 4.5, 1.8, 16.0),  # truck
        (0.9, 2.2, 0.3, 1.4),   # pedestrian (children to adults, arms and legs swinging)
        (1.1, 2.2, 0.4, 2.4),   # cyclist (front to side view)
    )
    """Real extents, in metres, of the 2D boxes of each object class standing on the road:
    ``(height_lo, height_hi, width_lo, width_hi)`` (the box width spans the object's width
    to its length, by its yaw). With ``window_geometry='camera'``, a window is kept at the
    rows where some template fits both its height and its width (camera at
    ``camera_height_m``, horizon at ``horizon``)."""
    horizon_slack: float = 0.0
    """With ``window_geometry='camera'``: how far (fraction of the image height) the horizon
    may stray from ``horizon`` (camera pitch, road slope); widens each template's rows."""
    border_windows: bool = True
    """With ``window_geometry='camera'``: also windows flush with the left/right image
    border at any width (objects cut by the border keep only their height)."""
    local_max: bool = False
    """Keep only windows whose score is a local maximum among the 8 neighbouring
    positions of the same size before NMS (a cheap pre-NMS; costs recall at IoU 0.7)."""

    # -- eq. 1: edge score ---------------------------------------------------------------
    score_norm: ScoreNorm = "perimeter"
    """``area``: divide by 2·area^γ (as printed); ``perimeter``: by (2(w+h))^κ, as Edge
    Boxes, whose score REEB adopts (NOTES #1)."""
    gamma: float = 0.75
    """Exponent of the area normalisation (no value printed; 0.75 ≈ Edge Boxes' κ/2)."""
    kappa: float = 1.6
    """Exponent of the perimeter normalisation (Edge Boxes' value)."""
    straddle_weight: float = 0.0
    """Weight λ of a straddling term in eq. 1: S = (Σ wₙmₙ − Σ_c m_c − λ·Σ_cut m) / norm,
    where Σ_cut m is the edge mass that crosses the box's sides (within ``straddle_band``
    working pixels of each side, weighted by how much the contour runs across that side).
    A cheap, exact-on-a-grid stand-in for Edge Boxes' affinity-weighted wₙ: a contour that
    continues out of the box counts against it. 0 = off (as printed)."""
    straddle_band: int = 1
    """Half-width, in working pixels, of the band around each box side for ``straddle_weight``."""
    refine: bool = False
    """Edge Boxes' refinement: before NMS, move each side of every candidate by halving
    steps while its score V improves (:mod:`reeb_torch.refinement`). Not in the paper."""
    center_fraction: float = 0.5
    """Side of the centre region c relative to the box (eq. 1: half)."""

    # -- eqs. 10-12: road, location and combined score -----------------------------------
    road_score: RoadScore = "none"
    """``reward``: V adds β·R as printed (``paper``); ``penalize``: β·(1 − R) (NOTES #10);
    ``none``: no road term; ``flat``: R = 1, a constant β; ``stand``: objects stand *on* the
    road: R = (road fraction of the strip just below the box) · (1 − road fraction inside)."""
    road_strip: float = 0.15
    """With ``road_score='stand'``: height of the strip just below a box, as a fraction of the
    box height, whose road fraction says the box stands on the road."""
    location_score: LocationScore = "classes"
    """``paper``: L = b_y/(b_w·b_h)·W (eq. 11); ``ground``: how well the box height fits
    a ground-plane object standing at its bottom row, in [0, 1]; ``none``: L = 1."""
    horizon: float = 0.47
    """Horizon row as a fraction of the image height, for ``location_score='ground'`` /
    ``'classes'`` and ``window_geometry='camera'`` (KITTI: the principal point, cy/H ≈ 0.46–0.47)."""
    ground_ratio: float = 1.0
    """Expected box height / (bottom row − horizon) of an object on the ground; about
    object height / camera height (cars ≈ 0.9, pedestrians ≈ 1.05 on KITTI)."""
    class_heights_m: tuple[float, ...] = (1.5, 3.2, 1.72, 1.72)
    """Typical real heights (metres) of car, truck, pedestrian and cyclist, for
    ``location_score='classes'``: L is the best fit over the classes of a Gaussian in
    log(b_h / (b_y − horizon·H) / (height / camera_height_m))."""
    class_weights: tuple[float, ...] = (1.0, 0.7, 1.0, 1.0)
    """Weight of each class's fit in ``location_score='classes'`` (same order as
    ``class_heights_m``): rarer classes weigh less, so their windows don't crowd the budget."""
    ground_log_sigma: float = 0.3
    """Tolerance (in log units) of that ratio for ``location_score='ground'`` or ``'classes'``."""
    alpha: float = 0.6
    beta: float = 0.4
    min_edge_score: float = 0.0
    """Windows with S below this are dropped (Sec. 3.7 prints 0.01, kept by ``paper``; the
    scale of S depends on the edge map's, so the default only drops S <= 0, measured)."""

    # -- eq. 13: NMS and output ----------------------------------------------------------
    nms_iou: float = 0.7
    top_k: int = 2000
    """Proposals returned per image (at most)."""

    def __post_init__(self) -> None:
        def check(ok: bool, name: str, expected: str) -> None:
            if not ok:
                raise ValueError(
                    f"ReebConfig.{name} must be {expected}, got {getattr(self, name)!r}"
                )

        def pos(name: str) -> None:
            v = getattr(self, name)
            check(isinstance(v, (int, float)) and math.isfinite(v) and v > 0, name, "> 0")

        for name in ("scale", "blur_sigma", "camera_height_m", "vertical_fov_deg",
                     "horizontal_fov_deg", "max_object_width_m", "entropy_sigma",
                     "size_ratio", "window_step", "kappa", "gamma"):
            pos(name)
        check(self.scale <= 4, "scale", "in (0, 4]")
        check(0 <= self.edge_threshold < 1, "edge_threshold", "in [0, 1)")
        check(self.edge_channels in ("gray", "rgb"), "edge_channels", "'gray' or 'rgb'")
        check(self.grouping in ("connected", "cell"), "grouping", "'connected' or 'cell'")
        check(self.group_cell is None or (isinstance(self.group_cell, int) and self.group_cell >= 2),
              "group_cell", "None or an int >= 2")
        check(self.grouping != "cell" or self.group_cell is not None, "group_cell",
              "set (an int >= 2) when grouping='cell'")
        check(isinstance(self.road_samples, int) and self.road_samples >= 1, "road_samples", "an int >= 1")
        x1, y1, x2, y2 = self.road_band
        check(0 <= x1 < x2 <= 1 and 0 <= y1 < y2 <= 1, "road_band",
              "fractions (x1, y1, x2, y2) with 0 <= x1 < x2 <= 1 and 0 <= y1 < y2 <= 1")
        check(len(self.road_tolerance) == 3 and all(t >= 0 for t in self.road_tolerance),
              "road_tolerance", "three non-negative numbers (hue, saturation, value)")
        check(self.road_combine in ("and", "or"), "road_combine", "'and' or 'or'")
        check(self.vertical_fov_deg < 180 and self.horizontal_fov_deg < 180,
              "vertical_fov_deg", "an angle below 180 degrees (both opening angles)")
        check(0 < self.region_overlap <= 1, "region_overlap", "in (0, 1]")
        check(self.region_width_round is None or 0 < self.region_width_round <= 1,
              "region_width_round", "None or in (0, 1]")
        check(isinstance(self.entropy_bins, int) and 2 <= self.entropy_bins <= 65536,
              "entropy_bins", "an int in [2, 65536]")
        check(self.entropy_form in ("printed", "abs-diff"), "entropy_form", "'printed' or 'abs-diff'")
        check(isinstance(self.candidates_per_region, int) and self.candidates_per_region >= 1,
              "candidates_per_region", "an int >= 1")
        check(isinstance(self.candidates_without_regions, int) and self.candidates_without_regions >= 1,
              "candidates_without_regions", "an int >= 1")
        check(isinstance(self.min_window, int) and self.min_window >= 4, "min_window", "an int >= 4")
        check(self.size_ratio > 1, "size_ratio", "> 1")
        check(self.window_step <= 1, "window_step", "in (0, 1]")
        lo, hi = self.aspect_range
        check(0 < lo <= hi, "aspect_range", "(low, high) with 0 < low <= high")
        check(self.score_norm in ("perimeter", "area"), "score_norm", "'perimeter' or 'area'")
        check(0 < self.center_fraction < 1, "center_fraction", "in (0, 1)")
        check(self.road_score in ("reward", "penalize", "none", "flat", "stand"), "road_score",
              "'reward', 'penalize', 'none', 'flat' or 'stand'")
        check(self.region_assign in ("contained", "nearest"), "region_assign", "'contained' or 'nearest'")
        pos("ground_ratio")
        pos("ground_log_sigma")
        check(self.location_score in ("paper", "ground", "classes", "none"), "location_score",
              "'paper', 'ground', 'classes' or 'none'")
        check(0 < self.horizon < 1, "horizon", "in (0, 1)")
        check(self.ground_band is None or (len(self.ground_band) == 2 and 0 < self.ground_band[0] < self.ground_band[1]),
              "ground_band", "None or (r_lo, r_hi) with 0 < r_lo < r_hi")
        check(self.alpha >= 0 and self.beta >= 0, "alpha", "non-negative (alpha and beta)")
        check(0 < self.nms_iou <= 1, "nms_iou", "in (0, 1]")
        check(isinstance(self.top_k, int) and self.top_k >= 1, "top_k", "an int >= 1")

    # -- presets -------------------------------------------------------------------------
    @classmethod
    def paper(cls, **overrides: object) -> "ReebConfig":
        """The printed text wherever it can run as printed (see NOTES.md).

        Full resolution, Sobel edges as they are (no thinning), plain connected components,
        area normalisation (eq. 1), S >= 0.01, the road score as a reward (eq. 12), L
        unnormalised (eq. 11), windows inside their regions, every row; eq. 8 and eq. 9 in
        their corrected forms (their printed forms give no regions / no proposals).
        """
        base = dict(
            scale=1.0,
            grouping="connected",
            group_cell=None,
            score_norm="area",
            road_score="reward",
            location_score="paper",
            road_combine="and",
            entropy_form="abs-diff",
            local_max=False,
            region_assign="contained",
            thin_edges=False,
            ground_band=None,
            window_geometry="grid",
            min_edge_score=0.01,
        )
        base.update(overrides)
        return cls(**base)  # type: ignore[arg-type]

    def replace(self, **changes: object) -> "ReebConfig":
        """A copy with ``changes`` applied (validated)."""
        return dataclasses.replace(self, **changes)  # type: ignore[arg-type]

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "ReebConfig":
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - names)
        if unknown:
            raise ValueError(f"unknown ReebConfig field(s): {', '.join(unknown)}")
        fixed = {k: tuple(v) if isinstance(v, list) else v for k, v in d.items()}
        return cls(**fixed)

    def with_camera(self, fx: float, fy: float, width: int, height: int,
                    cy: float | None = None) -> "ReebConfig":
        """A copy whose opening angles (and, given the principal row ``cy``, the horizon)
        come from a pinhole camera (focal lengths and ``cy`` in pixels).

        θh = 2·atan(W / 2fx), θv = 2·atan(H / 2fy). For KITTI's P2 (fx = fy ≈ 721 px,
        1242 × 375 px) this gives θh ≈ 81°, θv ≈ 29°. A camera looking level along a flat
        road sees the horizon at its principal row: ``horizon = cy / H`` (KITTI ≈ 0.46).
        """
        if not (fx > 0 and fy > 0 and width > 0 and height > 0):
            raise ValueError(f"with_camera needs positive fx, fy, width, height; got {fx}, {fy}, {width}, {height}")
        changes: dict = dict(
            horizontal_fov_deg=math.degrees(2 * math.atan(width / (2 * fx))),
            vertical_fov_deg=math.degrees(2 * math.atan(height / (2 * fy))),
        )
        if cy is not None:
            if not 0 < cy < height:
                raise ValueError(f"with_camera: the principal row cy={cy} must lie inside the image height {height}")
            changes["horizon"] = cy / height
        return self.replace(**changes)

    def with_kitti_calib(self, path: str, width: int, height: int) -> "ReebConfig":
        """A copy whose opening angles and horizon row come from the ``P2`` matrix of a
        KITTI ``calib`` file (the left colour camera) for images of ``width × height`` pixels
        (:meth:`with_camera`; the camera height stays ``camera_height_m``)."""
        from .camera import Camera

        cam = Camera.from_kitti_calib(path)  # ValueError naming the file without P2
        return self.with_camera(cam.fx, cam.fy, width, height, cy=cam.cy)

    def fingerprint(self) -> str:
        """A short stable hash of all fields (used to detect stale proposal caches)."""
        import hashlib
        import json

        blob = json.dumps(self.to_dict(), sort_keys=True, default=str).encode()
        return hashlib.sha256(blob).hexdigest()[:16]


def _no_regions(cfg: ReebConfig) -> ReebConfig:
    return cfg.replace(use_regions=False)


PRESETS: dict[str, ReebConfig] = {}


def _build_presets() -> None:
    PRESETS["default"] = ReebConfig()
    PRESETS["default-no-regions"] = _no_regions(ReebConfig())
    PRESETS["paper"] = ReebConfig.paper()
    PRESETS["paper-no-regions"] = _no_regions(ReebConfig.paper())


_build_presets()


def get_preset(name: str) -> ReebConfig:
    """Look up a named preset: ``default``, ``default-no-regions``, ``paper``,
    ``paper-no-regions``."""
    try:
        return PRESETS[name]
    except KeyError:
        raise ValueError(f"unknown preset {name!r}; choose one of {', '.join(sorted(PRESETS))}") from None
