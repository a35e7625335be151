"""One dataclass that holds every constant of the REEB algorithm, and its presets.

Each field names the paper section or equation it comes from. Where the printed paper is
ambiguous or cannot run as printed (the readings, numbered, in ``docs/results.md``),
the field documents the choice and :meth:`ReebConfig.paper` keeps the printed reading.
"""

from __future__ import annotations

import dataclasses
import math
import typing
from dataclasses import dataclass
from typing import Any, Literal

from ._fields import (ASPECT_RANGE, CLASS_HEIGHTS_M, CLASS_QUOTA, CLASS_WEIGHTS, GROUND_BAND, GROUP_CELL, OBJECT_TEMPLATES,
                      RANKER, ROAD_BAND, ROAD_TOLERANCE, SEED, Check, check_fields, field_plan, interval_check,
                      quota_by_name, quota_pairs, validate_config)

__all__ = ["ReebConfig", "PRESETS", "get_preset", "TRAINING_FREE", "FRONT_END_FIELDS", "PARTS", "PART_FIELDS", "PART_OF",
           "FrontEndSettings", "CameraSettings", "RegionSettings", "WindowSettings", "ScoreSettings",
           "RankingSettings", "NmsSettings"]

ScoreNorm = Literal["perimeter", "area"]
RoadScore = Literal["reward", "none"]
LocationScore = Literal["paper", "classes", "none"]
WindowGeometry = Literal["camera", "grid"]
ShadowScore = Literal["underneath", "none"]
VegetationScore = Literal["green", "none"]
RefineOrder = Literal["interleave", "refined_first", "replace"]
if typing.TYPE_CHECKING:  # what a caller may give: shares in the head's order, or by class name
    ClassQuota = tuple[tuple[str, float], ...] | tuple[float, ...] | typing.Mapping[str, float]
else:  # what the field holds, and what the checks see (a mapping is made pairs first)
    ClassQuota = tuple[tuple[str, float], ...] | tuple[float, ...]


def _knob(default: Any, check: str | Check | None = None, *, front: bool = False) -> Any:
    """A field's default, with its range once its type is right (:func:`interval_check`: an interval
    such as ``"(0, 4]"``, or a ``(check, words)`` pair) and, with ``front``, a place in
    :data:`FRONT_END_FIELDS` (it changes the edges, groups, road mask or score maps)."""
    meta: dict[str, Any] = {}
    if check is not None:
        meta["range"] = interval_check(check)
    if front:
        meta["stage"] = "front"
    return dataclasses.field(default=default, metadata=meta)


@dataclass(frozen=True)
class ReebConfig:
    """Settings of :class:`reeb_torch.ProposalGenerator`.

    All lengths in pixels refer to the *input* image unless the name says otherwise;
    ``scale`` sets the working resolution at which edges, groups and windows are computed,
    and boxes are mapped back to input pixels at the end. Fields that change the front end
    are listed in :data:`FRONT_END_FIELDS`.
    """

    # -- working resolution --------------------------------------------------------------
    scale: float = _knob(0.5, "(0, 4]", front=True)
    """Resize factor applied before edge detection (1.0 = full resolution, as the paper)."""

    # -- Sec. 3.4: denoising and edges ---------------------------------------------------
    blur_sigma: float = _knob(1.0, "> 0", front=True)
    """Standard deviation of the Gaussian blur, in working pixels (kernel = 2*ceil(2σ)+1)."""
    edge_threshold: float = _knob(0.05, "[0, 1)", front=True)
    """Sobel magnitude (of a [0, 1] grey image, normalised to [0, 1]) below which a pixel
    is no edge. The paper gives no value (reading 4)."""
    thin_edges: bool = _knob(True, front=True)
    """Keep only the one-pixel ridge of each edge (non-maximum suppression across the
    edge, as the edge maps Edge Boxes scores). Not in the paper."""
    remove_isolated: bool = _knob(True, front=True)
    """Drop edge pixels with no edge pixel among their 8 neighbours (Sec. 3.4)."""

    # -- Sec. 3.7: edge groups -----------------------------------------------------------
    group_cell: int | None = _knob(8, GROUP_CELL, front=True)
    """The edge groups are the 8-connected components of edge pixels (as printed), cut at
    the borders of tiles of this side, in working pixels (reading 2: long chains are rarely
    enclosed); ``None`` = no bound, plain connected components as printed."""

    # -- Sec. 3.5, eqs. 3-4: road segmentation -------------------------------------------
    road_samples: int = _knob(300, "[1, 1000000]", front=True)
    """Random pixels sampled to estimate the road colour ("hundreds", Sec. 3.5)."""
    road_band: tuple[float, float, float, float] = _knob((0.3, 0.8, 0.7, 1.0), ROAD_BAND, front=True)
    """Where road is likely, as fractions of the image (x1, y1, x2, y2): bottom centre."""
    road_tolerance: tuple[float, float, float] = _knob((0.5, 0.12, 0.12), ROAD_TOLERANCE, front=True)
    """Half-width of the in-range test around the sampled median, per HSV channel
    (hue in radians, circular; saturation and value in [0, 1]). Not given in the paper."""
    seed: int = _knob(0, SEED, front=True)
    """Seed of the road pixel sampling; the same pixels are sampled for every image of a
    given size, so results do not depend on the batch."""

    # -- Sec. 3.6, eqs. 5-8: region division ---------------------------------------------
    use_regions: bool = True
    """Region enhancement. ``False`` = one region, the whole image ("Ours*")."""
    camera_height_m: float = _knob(1.65, "> 0")
    """Height of the camera above the road, in metres (eq. 5's h)."""
    vertical_fov_deg: float = _knob(35.0, "(0, 180)")
    """Vertical opening angle of the camera, in degrees (eq. 5's θv; :meth:`with_camera`)."""
    horizontal_fov_deg: float = _knob(90.0, "(0, 180)")
    """Horizontal opening angle of the camera, in degrees (eq. 6's θh; :meth:`with_camera`)."""
    max_object_width_m: float = _knob(2.55, "> 0")
    """Width of the widest object, in metres: it sets the region width (eq. 7's W)."""
    region_overlap: float = _knob(0.5, "(0, 1]")
    """Stride between regions as a fraction of their width (eq. 8's ``overlap``)."""
    region_assign: Literal["contained", "nearest"] = "nearest"
    """Which region's budget a window counts against. ``contained``: every region that wholly
    contains it (as printed; a window wider than the region stride can fall in none).
    ``nearest``: the region whose centre is nearest to the window's centre."""
    region_width_round: float | None = _knob(0.125, "None or (0, 1]")
    """Round the region width (fraction of image width) up to a multiple of this; the
    paper rounds 24.7 % to 25 %. ``None`` uses eq. 7 as computed."""

    # -- eqs. 2 and 9: entropy and proposal budget ---------------------------------------
    entropy_bins: int = _knob(256, "[2, 65536]")
    """Grey levels of the entropy histogram (eq. 2's M). 256 = 8-bit grey, H in [0, 8]."""
    entropy_sigma: float = _knob(4.0, "> 0")
    """σ of eq. 9 (the paper's KITTI value)."""
    candidates_per_region: int = _knob(30000, ">= 1")
    """Most windows a region may pass on to ranking (eq. 9's "maximum number of proposals
    that the user wants to generate in a region"); the region passes share × this. The
    default is the learned ranking's pool; :meth:`training_free` sets V's own budget."""
    candidates_without_regions: int = _knob(8000, ">= 1")
    """Windows passed on to ranking when ``use_regions=False`` (the whole image is one
    region with share 1)."""

    # -- Sec. 3.6: sliding windows (reading 13) ------------------------------------------
    min_window: int = _knob(16, ">= 4")
    """Smallest window side, in input pixels."""
    size_ratio: float = _knob(1.25, "(1, 16]")
    """Ratio between consecutive window widths (and heights)."""
    window_step: float = _knob(0.15, "(0, 1]")
    """Stride of the sliding windows as a fraction of the window's side."""
    aspect_range: tuple[float, float] = _knob((0.25, 4.0), ASPECT_RANGE)
    """Allowed width/height ratios of the windows."""
    ground_band: tuple[float, float] | None = _knob((0.45, 3.0), GROUND_BAND)
    """Keep only windows whose height h and bottom row y_b satisfy
    r_lo <= h / (y_b − horizon·H) <= r_hi: objects standing on the road (a flat-ground
    camera prior, in the spirit of eq. 11's "lower boxes are bigger"). ``None`` = all rows."""
    window_geometry: WindowGeometry = "camera"
    """``camera``: window sizes and rows from the ground plane and ``object_templates``.
    ``grid``: every size of the two geometric series within ``aspect_range``, no wider than
    a region, at the rows ``ground_band`` allows."""
    object_templates: tuple[tuple[float, float, float, float], ...] = _knob((
        (1.2, 2.6, 1.3, 6.5),   # car / van: height, width of its 2D box at any yaw
        (2.2, 4.5, 1.8, 16.0),  # truck
        (0.9, 2.2, 0.3, 1.4),   # pedestrian (children to adults, arms and legs swinging)
        (1.1, 2.2, 0.4, 2.4),   # cyclist (front to side view)
    ), OBJECT_TEMPLATES)
    """Real extents, in metres, of the 2D boxes of each object class standing on the road:
    ``(height_lo, height_hi, width_lo, width_hi)``. With ``window_geometry='camera'``, a window
    is kept at the rows where some template fits both its height and its width."""

    # -- eq. 1: edge score ---------------------------------------------------------------
    score_norm: ScoreNorm = "perimeter"
    """``area``: divide by 2·area^γ (as printed); ``perimeter``: by (2(w+h))^κ, as Edge
    Boxes, whose score REEB adopts (reading 1)."""
    gamma: float = _knob(0.75, "(0, 4]")
    """Exponent of the area normalisation (no value printed; 0.75 ≈ Edge Boxes' κ/2)."""
    kappa: float = _knob(1.6, "(0, 8]")
    """Exponent of the perimeter normalisation (Edge Boxes' value)."""
    center_fraction: float = _knob(0.5, "(0, 1)")
    """Side of the centre region c relative to the box (eq. 1: half)."""

    # -- eqs. 10-12: road, location and combined score -----------------------------------
    road_score: RoadScore = _knob("none", front=True)
    """``reward``: V adds β·R as printed (``paper``), R the road fraction of the box;
    ``none``: no road term (reading 10)."""
    shadow_score: ShadowScore = _knob("underneath", front=True)
    """``underneath``: V is multiplied by (``shadow_floor`` + U)^``shadow_power``, U in [0, 1] how
    much darker the box's bottom strip is than the road just below it on the grey image (the
    shadow a vehicle casts under itself; not in the paper). ``none``: no such term (as printed)."""
    shadow_strip: float = _knob(0.2, "(0, 1]")
    """With ``shadow_score='underneath'``: height of the two strips (the box's bottom rows
    and the rows just below it) as a fraction of the box height (at least one pixel)."""
    shadow_margin: float = _knob(0.15, "[0, 0.5)")
    """With ``shadow_score='underneath'``: fraction of the box width left out of both strips
    on each side (wheels and the background beside a vehicle)."""
    shadow_power: float = _knob(0.5, "(0, 8]")
    """Exponent of the shadow factor (0.5: a square root, so it re-ranks without dominating S)."""
    shadow_floor: float = _knob(0.001, "(0, 1]")
    """Added to U before the power, so a box without a shadow keeps a small score (> 0)."""
    vegetation_score: VegetationScore = _knob("green", front=True)
    """``green``: V is multiplied by (1 − G)^``vegetation_power``, G the fraction of green-dominant
    pixels (G > R and G > B) in the window's centre (``vegetation_box``): trees and verges rank
    below objects (not in the paper). ``none``: no such term (as printed)."""
    vegetation_box: float = _knob(0.7, "(0, 1]")
    """With ``vegetation_score='green'``: G is measured in the centred part of the window
    this fraction of its width and height (1: the whole window)."""
    vegetation_power: int = _knob(5, "[1, 16]")
    """With ``vegetation_score='green'``: the exponent, a whole number (the factor is a
    product, so every path computes the same numbers)."""
    location_score: LocationScore = "classes"
    """``paper``: L = b_y/(b_w·b_h)·W (eq. 11); ``classes``: how well the box fits a
    ground-plane object of one of the classes of ``class_heights_m`` standing at its bottom
    row, in [0, 1], at its best over the classes; ``none``: L = 1."""
    horizon: float = _knob(0.47, "(0, 1)")
    """Horizon row as a fraction of the image height, for ``location_score='classes'`` and ``window_geometry='camera'`` (KITTI: the principal point, cy/H ≈ 0.46–0.47)."""
    class_heights_m: tuple[float, ...] = _knob((1.5, 3.2, 1.72, 1.72), CLASS_HEIGHTS_M)
    """Typical real heights (metres) of car, truck, pedestrian and cyclist, for
    ``location_score='classes'``: L is the best fit over the classes of a Gaussian in
    log(b_h / (b_y − horizon·H) / (height / camera_height_m))."""
    class_weights: tuple[float, ...] = _knob((1.0, 0.7, 1.0, 1.0), CLASS_WEIGHTS)
    """Weight of each class's fit in ``location_score='classes'`` (same order as
    ``class_heights_m``): rarer classes weigh less, so their windows don't crowd the budget."""
    ground_log_sigma: float = _knob(0.3, "> 0")
    """Tolerance (in log units) of the class fits of ``location_score='classes'``: of the box
    height's ratio, and of its width outside the class's width range of ``object_templates``
    at the depth of its bottom row."""
    alpha: float = _knob(0.6, ">= 0")
    """Weight of the location score in V = S·(α·L + β·R) (eq. 12)."""
    beta: float = _knob(0.4, ">= 0")
    """Weight of the road score in V = S·(α·L + β·R) (eq. 12)."""
    min_edge_score: float = 0.0
    """Windows with S below this are dropped (Sec. 3.7 prints 0.01, kept by ``paper``; the
    scale of S depends on the edge map's, so the default only drops S < 0)."""

    # -- the learned ranking (not in the paper) --------------------------------------------
    ranker: str = _knob("kitti", RANKER)
    """Orders the region cut's candidates by a small learned model over per-box features in
    place of V, before eq. 13's NMS (not in the paper; scores are then its logits): ``kitti``,
    the shipped model; the path of a weights file ``reeb fit`` wrote for another camera; or
    ``none``: rank by V (as printed; :meth:`training_free` also sets V's own budget)."""
    ranker_keep: int = _knob(12000, ">= 1")
    """With ``ranker``: the candidates of each image that get the full features and the model;
    the others are dropped before NMS. ``ranker_v_share`` of them are the image's best by V,
    the rest the best by the model's prefilter (a tiny model over geometry, V and region)."""
    ranker_v_share: float = _knob(0.0, "[0, 1]")
    """The share of the ``ranker_keep`` candidates that are each image's best by V whatever
    the prefilter says (not in the paper). ``0``: the prefilter alone; ``1``: V alone."""
    rank_quality: float = _knob(0.0, "[0, 100]")
    """With a ranker whose weights hold a localisation-quality head (``FitOptions.quality_hidden``):
    each ranked candidate's score is the model's logit plus this times the head's sigmoid,
    how tight the box is on its object were it on one, so that of the boxes on one object the
    tight one goes first into the NMS. ``0``: the logit alone. Not in the paper."""
    class_quota: ClassQuota = _knob((), CLASS_QUOTA)
    """With a ranker that has a class head (``kitti``: Car, Pedestrian, Cyclist, Truck): the
    share of the ``top_k`` proposals a class gets first (the best boxes after NMS the head
    hints as that class), the rest going to the best of the others. By class name,
    ``{"Pedestrian": 0.2}`` (kept as pairs; ignored without a class head), or one share a
    class in the head's order, ``(0, 0.2, 0.05, 0)``. ``()``: one ranking. Not in the paper."""
    refine_top: int = _knob(0, "[0, 100000]")
    """With a ranker whose weights hold a box refiner (``reeb fit --refiner`` fits one): the best this
    many output boxes of each image are refined (each side moved by the refiner's offsets,
    :mod:`reeb_torch.ranker.refine`) and put beside their originals, or in their place, within
    ``top_k`` (``refine_order``); a refined box takes its original's score and class hints. ``0``: off.
    Not in the paper (its future work)."""
    refine_class: str = ""
    """With ``refine_top``: only the boxes whose class hint (the ranker's class head) is this
    class are refined, the best ``refine_top`` of them (e.g. ``"Car"``); ``""``: every box."""
    refine_order: RefineOrder = _knob("interleave")
    """Where the refined boxes go: ``interleave``, each right after its original (then the
    other originals); ``refined_first``, all of them before the originals; ``replace``, each
    in its original's place."""
    refine_steps: int = _knob(1, "[1, 4]")
    """How many times the refiner is applied (its features read again at each step)."""
    refine_nms: float = _knob(1.0, "(0, 1]")
    """Below 1: a greedy NMS at this IoU over the originals and refined boxes in their order
    (a refined box on top of its original makes room for the next); ``1``: none."""

    # -- eq. 13: NMS and output ----------------------------------------------------------
    nms_iou: float = _knob(0.75, "(0, 1]")
    """Eq. 13's IoU threshold. The paper prints 0.7 (kept by ``paper``); 0.75 is Edge Boxes'
    setting for recall at IoU 0.7 (β = 0.75)."""
    nms_iou_thin: float = _knob(0.0, "[0, 1]")
    """Above ``nms_iou``: the threshold for the boxes narrower than ``nms_thin_aspect`` times
    their height (a person's), whose loose and tight boxes overlap more than a wide box's
    (a tight box is kept beside a looser one that ranks first). ``0``: ``nms_iou`` for
    every box, as the paper. Not in the paper."""
    nms_thin_aspect: float = _knob(0.5, "(0, 4]")
    """The width / height under which ``nms_iou_thin`` applies to a box."""
    top_k: int = _knob(2000, ">= 1")
    """Proposals returned per image (at most)."""

    def __post_init__(self) -> None:
        """Check every field (:func:`validate_config`; TypeError, ValueError). Lists become tuples,
        ints in float fields floats and -0.0 0.0: equal settings give equal, hashable configs
        with equal fingerprints (JSON round trips included)."""
        validate_config(self)

    # -- presets -------------------------------------------------------------------------
    @classmethod
    def paper(cls, **overrides: object) -> "ReebConfig":
        """The printed text wherever it can run as printed (NOTES), with ``overrides``: V ranks
        (training-free budget); full resolution, Sobel edges as they are, plain connected
        components, area normalisation (eq. 1), S >= 0.01, the road score as a reward (eq. 12),
        L unnormalised (eq. 11), windows inside their regions, every row; eqs. 8 and 9 in their
        corrected forms (their printed forms give no regions / no proposals)."""
        return cls(**{**_PAPER, **overrides})  # type: ignore[arg-type]

    def training_free(self) -> "ReebConfig":
        """A copy without the learned ranking: ``ranker='none'``, V's own candidate budget
        and no class quota (:data:`TRAINING_FREE`)."""
        return self.replace(**TRAINING_FREE)

    def unranked(self) -> "ReebConfig":
        """A copy that ranks its candidates by V: ``ranker='none'``, and no ``class_quota``
        (which reads a ranker's class head); the candidates stay those of this config."""
        return self.replace(ranker="none", class_quota=())

    def class_shares(self, classes: typing.Sequence[str] | None) -> tuple[float, ...] | None:
        """``class_quota`` as one share per class of a ranker's class head
        (:meth:`RankingSettings.class_shares`)."""
        return self.ranking.class_shares(classes)

    # -- each part's settings (PARTS) -------------------------------------------------------
    @property
    def front_end(self) -> "FrontEndSettings":
        """The settings of the edges, edge groups and road mask."""
        return self._part("front_end")

    @property
    def camera(self) -> "CameraSettings":
        """The camera's height, opening angles and horizon row."""
        return self._part("camera")

    @property
    def regions(self) -> "RegionSettings":
        """The region strips, their entropy and the candidate budget (eqs. 2, 5-9)."""
        return self._part("regions")

    @property
    def windows(self) -> "WindowSettings":
        """The sliding windows' sizes, strides and rows (Sec. 3.6)."""
        return self._part("windows")

    @property
    def scores(self) -> "ScoreSettings":
        """The score V of a window and its terms (eqs. 1, 10-12)."""
        return self._part("scores")

    @property
    def ranking(self) -> "RankingSettings":
        """The learned ranking of the candidates, its class quota and box refiner."""
        return self._part("ranking")

    @property
    def nms(self) -> "NmsSettings":
        """Eq. 13's suppression and the number of proposals."""
        return self._part("nms")

    def _part(self, name: str) -> Any:
        """The settings of part ``name``, made once per config (every field checked once)."""
        key = "_part_" + name
        part = self.__dict__.get(key)
        if part is None:
            cls = PARTS[name]
            part = cls.__new__(cls)  # the fields are this config's, checked already
            for f in dataclasses.fields(cls):
                object.__setattr__(part, f.name, getattr(self, f.name))
            object.__setattr__(self, key, part)
        return part

    def replace(self, **changes: object) -> "ReebConfig":
        """A copy with ``changes`` applied (validated). A change may be a field
        (``top_k=1000``) or a part's settings as a whole (``nms=cfg.nms.replace(top_k=1000)``,
        :data:`PARTS`); a field named beside its part wins."""
        flat: dict[str, object] = {}
        for name, value in changes.items():
            if name in PARTS:
                if not isinstance(value, PARTS[name]):
                    raise TypeError(f"ReebConfig.replace({name}=...) takes a {PARTS[name].__name__}, "
                                    f"got {type(value).__name__}")
                flat.update({k: v for k, v in value.to_dict().items() if k not in changes})
            else:
                flat[name] = value
        return dataclasses.replace(self, **flat)  # type: ignore[arg-type]

    @classmethod
    def from_parts(cls, **parts: "_Part") -> "ReebConfig":
        """The config of part settings (``ReebConfig.from_parts(nms=NmsSettings(...))``), the
        default's for each part not given (:data:`PARTS`)."""
        return cls().replace(**parts)

    def to_dict(self) -> dict:
        """Every field by its flat name (what config files, weights' metadata and
        :meth:`fingerprint` read)."""
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "ReebConfig":
        """The config of a dict of fields (as :meth:`to_dict` writes it; lists for tuples), or of
        parts (``{"nms": {"top_k": 1000}}``, :data:`PARTS`), or both.

        Raises TypeError when ``d`` is not a mapping, ValueError naming unknown fields, and
        the field checks' TypeError / ValueError (:meth:`__post_init__`)."""
        if not isinstance(d, typing.Mapping):
            raise TypeError(f"ReebConfig.from_dict expects a dict of ReebConfig fields, got {type(d).__name__}")
        flat: dict[str, Any] = {}
        for k, v in d.items():
            if k in PARTS and isinstance(v, typing.Mapping):
                stray = sorted(set(v) - set(PART_FIELDS[k]))
                if stray:
                    raise ValueError(f"unknown {PARTS[k].__name__} field(s): {', '.join(map(str, stray))} "
                                     f"(it has {', '.join(PART_FIELDS[k])})")
                flat.update(v)
            else:
                flat[k] = v
        unknown = sorted(set(flat) - {f.name for f in dataclasses.fields(cls)})
        if unknown:
            raise ValueError(f"unknown ReebConfig field(s): {', '.join(unknown)}")
        fixed: dict[str, Any] = {k: tuple(v) if isinstance(v, list) else v for k, v in flat.items()}
        return cls(**fixed)

    def with_camera(self, fx: float, fy: float, width: int, height: int,
                    cy: float | None = None) -> "ReebConfig":
        """A copy whose opening angles (and, given the principal row ``cy``, the horizon)
        come from a pinhole camera (focal lengths and ``cy`` in pixels): θh = 2·atan(W / 2fx),
        θv = 2·atan(H / 2fy) (KITTI's P2: θh ≈ 81°, θv ≈ 29°), and, for a camera looking level
        along a flat road, ``horizon = cy / H`` (KITTI ≈ 0.46)."""
        if not (fx > 0 and fy > 0 and width > 0 and height > 0):
            raise ValueError(f"with_camera needs positive fx, fy, width, height; got {fx}, {fy}, {width}, {height}")
        changes: dict = dict(horizontal_fov_deg=math.degrees(2 * math.atan(width / (2 * fx))),
                             vertical_fov_deg=math.degrees(2 * math.atan(height / (2 * fy))))
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


# -- each part's settings -------------------------------------------------------------------
# Each part of the generator is built from its own settings and receives only those; the
# fields keep ReebConfig's names (one flat name each, PART_OF), types, ranges and docs.


@dataclass(frozen=True)
class _Part:
    """A part's settings: fields of :class:`ReebConfig` of the same names, checked as it checks
    them (type, then range; the joint checks need the whole config and run there)."""

    def __post_init__(self) -> None:
        values = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        if "class_quota" in values:
            values["class_quota"] = quota_pairs(values["class_quota"])
        fixed = check_fields(type(self).__name__, values, field_plan(type(self))[0],
                             {n: _RANGES[n] for n in values if n in _RANGES})
        for name, value in fixed.items():
            if value is not getattr(self, name):
                object.__setattr__(self, name, value)

    def replace(self, **changes: Any) -> Any:
        """A copy with ``changes`` applied (checked)."""
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict[str, Any]:
        """The fields, by their :class:`ReebConfig` names."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}


@dataclass(frozen=True)
class FrontEndSettings(_Part):
    """Edges (Sec. 3.4), edge groups (Sec. 3.7) and the road mask (eqs. 3-4) at the working
    resolution: :class:`ReebConfig`'s fields of these names."""

    scale: float
    blur_sigma: float
    edge_threshold: float
    thin_edges: bool
    remove_isolated: bool
    group_cell: int | None
    road_samples: int
    road_band: tuple[float, float, float, float]
    road_tolerance: tuple[float, float, float]
    seed: int


@dataclass(frozen=True)
class CameraSettings(_Part):
    """The camera: its height above the road, opening angles and horizon row (eqs. 5-6,
    :meth:`ReebConfig.with_camera`)."""

    camera_height_m: float
    vertical_fov_deg: float
    horizontal_fov_deg: float
    horizon: float


@dataclass(frozen=True)
class RegionSettings(_Part):
    """The region strips (eqs. 5-8), their entropy and each one's share of the candidate
    budget (eqs. 2 and 9)."""

    use_regions: bool
    max_object_width_m: float
    region_overlap: float
    region_width_round: float | None
    entropy_bins: int
    entropy_sigma: float
    candidates_per_region: int
    candidates_without_regions: int


@dataclass(frozen=True)
class WindowSettings(_Part):
    """The sliding windows (Sec. 3.6): their sizes, strides, shapes and rows, and which
    region each counts against."""

    min_window: int
    size_ratio: float
    window_step: float
    aspect_range: tuple[float, float]
    ground_band: tuple[float, float] | None
    window_geometry: WindowGeometry
    object_templates: tuple[tuple[float, float, float, float], ...]
    region_assign: Literal["contained", "nearest"]


@dataclass(frozen=True)
class ScoreSettings(_Part):
    """V of a window (eqs. 1, 10-12): the edge score, its road, shadow, vegetation and
    location terms, and their weights."""

    score_norm: ScoreNorm
    gamma: float
    kappa: float
    center_fraction: float
    road_score: RoadScore
    shadow_score: ShadowScore
    shadow_strip: float
    shadow_margin: float
    shadow_power: float
    shadow_floor: float
    vegetation_score: VegetationScore
    vegetation_box: float
    vegetation_power: int
    location_score: LocationScore
    class_heights_m: tuple[float, ...]
    class_weights: tuple[float, ...]
    ground_log_sigma: float
    alpha: float
    beta: float
    min_edge_score: float


@dataclass(frozen=True)
class RankingSettings(_Part):
    """The learned ranking of the candidates (not in the paper): its weights, how many
    candidates it reads, the class quota and the box refiner."""

    ranker: str
    ranker_keep: int
    ranker_v_share: float
    rank_quality: float
    class_quota: ClassQuota
    refine_top: int
    refine_class: str
    refine_order: RefineOrder
    refine_steps: int
    refine_nms: float

    def class_shares(self, classes: typing.Sequence[str] | None) -> tuple[float, ...] | None:
        """``class_quota`` as one share per class of a ranker's class head (``classes``, in its
        order; None without a head), or None for no quota (``class_quota=()``, or by name
        without a head).

        Raises:
            ValueError: a share for each class in order, but no head or another number of
                classes; or a class name the head does not have (both name what it has).
        """
        quota = self.class_quota  # a mapping became (name, share) pairs when checked
        if not quota:
            return None
        named = quota_by_name(quota)
        if classes is None:
            if named:
                return None
            raise ValueError(f"ReebConfig.class_quota has {len(quota)} shares, one a class in order, but the "
                             f"ranker {self.ranker!r} has no class head: give the shares by class name "
                             "({'Pedestrian': 0.2}; ignored without a class head) or class_quota=()")
        classes = tuple(classes)
        if not named:
            shares = typing.cast("tuple[float, ...]", quota)
            if len(shares) != len(classes):
                raise ValueError(f"ReebConfig.class_quota has {len(shares)} shares, but the ranker {self.ranker!r} "
                                 f"has the classes {', '.join(classes)}: give one share a class, in its order, "
                                 "or the shares by class name")
            return tuple(float(x) for x in shares)
        by_name = dict(typing.cast("tuple[tuple[str, float], ...]", quota))
        unknown = [name for name in by_name if name not in classes]
        if unknown:
            raise ValueError(f"ReebConfig.class_quota names {', '.join(map(repr, unknown))}, but the ranker "
                             f"{self.ranker!r} hints the classes {', '.join(classes)}")
        return tuple(float(by_name.get(c, 0.0)) for c in classes)


@dataclass(frozen=True)
class NmsSettings(_Part):
    """Eq. 13's greedy NMS and the number of proposals it returns (``top_k``)."""

    nms_iou: float
    nms_iou_thin: float
    nms_thin_aspect: float
    top_k: int


PARTS: dict[str, type[_Part]] = {
    "front_end": FrontEndSettings, "camera": CameraSettings, "regions": RegionSettings,
    "windows": WindowSettings, "scores": ScoreSettings, "ranking": RankingSettings, "nms": NmsSettings,
}
"""Each part's settings, by the :class:`ReebConfig` property that gives them."""

PART_FIELDS: dict[str, tuple[str, ...]] = {name: tuple(f.name for f in dataclasses.fields(cls))
                                           for name, cls in PARTS.items()}
"""The flat names of each part's fields."""

PART_OF: dict[str, str] = {field: part for part, names in PART_FIELDS.items() for field in names}
"""The one mapping of flat names to parts: ``PART_OF["top_k"] == "nms"``. Every
:class:`ReebConfig` field is in exactly one part (a test checks it), so ``--set FIELD=VALUE``,
config files, weights' metadata and presets keep their flat names."""


TRAINING_FREE: dict[str, object] = {"ranker": "none", "candidates_per_region": 12000, "class_quota": ()}
"""The fields :meth:`ReebConfig.training_free` sets: no learned ranking, and the candidate budget
with which V alone ranks (``benchmarks/ablations.py``)."""

_PAPER: dict[str, object] = dict(
    **TRAINING_FREE,  # REEB ranks by V (eq. 12), with the training-free region budget
    scale=1.0, group_cell=None, score_norm="area", road_score="reward",
    shadow_score="none", vegetation_score="none", nms_iou=0.7, location_score="paper",
    region_assign="contained", thin_edges=False, ground_band=None,
    window_geometry="grid", min_edge_score=0.01,
)
"""The fields :meth:`ReebConfig.paper` sets: the printed reading of each."""

FRONT_END_FIELDS: tuple[str, ...] = tuple(f.name for f in dataclasses.fields(ReebConfig)
                                          if f.metadata.get("stage") == "front")
"""The fields that change the generator's front end (edges, groups, road mask, score maps): two
configs equal in these share that work (``reeb tune`` computes it once per frame). A field
joins by its declaration (``_knob(..., front=True)``)."""

_RANGES: dict[str, Check] = field_plan(ReebConfig)[1]
"""The range of each field that declares one (:func:`_knob`), once its type is right."""

PRESETS: dict[str, ReebConfig] = {
    "default": ReebConfig(),
    "training-free": ReebConfig().training_free(),
    "paper": ReebConfig.paper(),
}


def get_preset(name: str) -> ReebConfig:
    """Look up a named preset.

    * ``default``: REEB's windows ranked by the shipped learned model (``ranker='kitti'``).
    * ``training-free``: no learned part: the windows ranked by V (eq. 12), with V's own
      candidate budget (:meth:`ReebConfig.training_free`).
    * ``paper``: the printed text wherever it can run (:meth:`ReebConfig.paper`).

    Any of them without the region enhancement (the paper's Ours*) is
    ``get_preset(name).replace(use_regions=False)``.

    Raises:
        ValueError: naming the unknown preset and the known ones.
    """
    try:
        return PRESETS[name]
    except KeyError:
        raise ValueError(f"unknown preset {name!r}; choose one of {', '.join(sorted(PRESETS))}") from None
