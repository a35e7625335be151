"""One dataclass that holds every constant of the REEB algorithm, and its presets.

Each field names the paper section or equation it comes from. Where the printed paper is
ambiguous or cannot run as printed (the readings, numbered, in ``docs/results.md``),
the field documents the choice and :meth:`ReebConfig.paper` keeps the printed reading.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
import types
import typing
from dataclasses import dataclass
from typing import Any, Callable, Literal

__all__ = ["ReebConfig", "PRESETS", "get_preset", "TRAINING_FREE", "FRONT_END_FIELDS", "check_fields"]

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


# -- validation (ReebConfig.__post_init__) ---------------------------------------------------
# The type of every field is checked from its annotation, so a new field is checked as soon
# as it is declared; its range is declared with it (_knob), joint conditions go into _JOINT.


_NUMBERS = {bool: bool, int: numbers.Integral, float: numbers.Real}


def _conform(value: Any, hint: Any) -> Any:
    """``value`` checked against the annotation ``hint`` (``bool``, ``int`` and ``float``, never
    a bool for a number; ``Literal``, unions, ``tuple[X, Y]``, ``tuple[X, ...]`` from a tuple or
    list, plain classes; other annotations pass) and normalised: floats finite, -0.0 as 0.0,
    tuples for lists. Raises a bare TypeError (wrong type) or ValueError (not finite, not a
    choice, wrong tuple length)."""
    if hint is bool or hint is int or hint is float:
        exact = type(value) is hint
        if not exact and (isinstance(value, bool) or not isinstance(value, _NUMBERS[hint])):
            raise TypeError
        if hint is not float:
            return value if exact else int(value)
        try:
            x = float(value)
        except OverflowError:  # an int beyond the float range
            raise ValueError from None
        if not math.isfinite(x):
            raise ValueError
        return 0.0 if x == 0.0 else value if type(value) is float else x  # -0.0 is 0.0: one fingerprint
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin is Literal:
        for c in args:
            if type(value) is type(c) and value == c:
                return value
        raise ValueError if any(type(value) is type(c) for c in args) else TypeError
    if origin is typing.Union or origin is types.UnionType:
        if value is None and type(None) in args:
            return None
        kinds = set()
        for alt in args:
            try:
                return _conform(value, alt)
            except (TypeError, ValueError) as e:
                kinds.add(type(e))
        raise ValueError if ValueError in kinds else TypeError
    if origin is tuple:
        if not isinstance(value, (tuple, list)):
            raise TypeError
        if len(args) == 2 and args[1] is Ellipsis:
            args = (args[0],) * len(value)
        elif len(value) != len(args):
            raise ValueError
        items = [_conform(v, a) for v, a in zip(value, args)]
        same = type(value) is tuple and all(a is b for a, b in zip(items, value))
        return value if same else tuple(items)
    if not isinstance(hint, type) or isinstance(value, hint):
        return value  # an annotation this checker does not know is left to the field's range
    raise TypeError


def _describe(hint: Any, plural: bool = False) -> str:
    """What ``hint`` expects, in words (``"a tuple of 2 finite numbers"``)."""
    words = {bool: ("True or False (a bool)", "bools (True or False)"), int: ("an int (not a bool)", "ints"),
             float: ("a finite number", "finite numbers"), str: ("a string", "strings")}
    if hint in words:
        return words[hint][plural]
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin is Literal:
        return "one of " + ", ".join(repr(a) for a in args)
    if origin is typing.Union or origin is types.UnionType:
        alts = " or ".join(_describe(a) for a in args if a is not type(None))
        return ("None or " if type(None) in args else "") + alts
    if origin is tuple:
        head = "tuples" if plural else "a tuple"
        if len(args) == 2 and args[1] is Ellipsis:
            return f"{head} of {_describe(args[0], plural=True)}"
        if all(a == args[0] for a in args):
            return f"{head} of {len(args)} {_describe(args[0], plural=True)}"
        return f"{head} ({', '.join(_describe(a) for a in args)})"
    return getattr(hint, "__name__", repr(hint))


def _show(value: Any, limit: int = 80) -> str:
    """``repr(value)``, shortened to ``limit`` characters for messages."""
    r = repr(value)
    return r if len(r) <= limit else r[: limit - 4] + " ..."


_Check = tuple[Callable[[Any], bool], str]  # a range check and what it expects, in words


def _range(spec: str | _Check) -> _Check:
    """A range check and its words: an interval as written in maths (``"(0, 4]"``, ``"> 0"``,
    ``">= 1"``, after ``"None or "`` where None passes), or a ``(check, words)`` pair as is."""
    if not isinstance(spec, str):
        return spec
    body = spec.removeprefix("None or ")
    if body[0] in "([":
        lo, hi = (float(x) for x in body[1:-1].split(","))
        lo_open, hi_open = body[0] == "(", body[-1] == ")"
        text = f"in {body[0]}{lo:g}, {hi:g}{body[-1]}"
        def ok(v: Any) -> bool:
            return (lo < v if lo_open else lo <= v) and (v < hi if hi_open else v <= hi)
    else:
        op, bound = body.split()[0], float(body.split()[1])
        text = f"{op} {bound:g}"
        def ok(v: Any) -> bool:
            return v > bound if op == ">" else v >= bound
    if body == spec:
        return ok, text
    return (lambda v: v is None or ok(v)), "None or " + text


def _quota_ok(t: tuple) -> bool:
    """``class_quota``: all shares or all ``(name, share)`` pairs (distinct names), each share
    >= 0, summing to at most 1."""
    named = [isinstance(x, tuple) for x in t]
    if any(named) and not all(named):
        return False
    shares = [x[1] for x in t] if any(named) else list(t)
    names = [x[0] for x in t] if any(named) else []
    return all(x >= 0 for x in shares) and sum(shares) <= 1 and len(set(names)) == len(names)


def _by_name(quota: object) -> bool:
    """Whether a ``class_quota`` gives its shares by class name (``(name, share)`` pairs)."""
    return isinstance(quota, tuple) and bool(quota) and isinstance(quota[0], tuple)


_MAX_REGIONS = 1024
"""Most region strips a camera setting may give (eq. 8); more is a setting error."""


def _region_count(c: "ReebConfig") -> int:
    from .stages.regions import region_count, region_width_fraction

    frac = region_width_fraction(c.camera_height_m, c.vertical_fov_deg, c.horizontal_fov_deg,
                                 c.max_object_width_m, c.region_width_round)
    return region_count(frac, c.region_overlap) if frac > 0 else _MAX_REGIONS + 1


# Checks that are not intervals, named by the fields that declare them (:func:`_knob`).
_GROUP_CELL = (lambda v: v is None or v >= 2), "None or an int >= 2"
_ROAD_BAND = ((lambda b: 0 <= b[0] < b[2] <= 1 and 0 <= b[1] < b[3] <= 1),
              "fractions (x1, y1, x2, y2) with 0 <= x1 < x2 <= 1 and 0 <= y1 < y2 <= 1")
_ROAD_TOLERANCE = (lambda t: all(x >= 0 for x in t)), "three non-negative numbers (hue, saturation, value)"
_SEED = (lambda v: -2**63 <= v < 2**64), "in [-2**63, 2**64) (what torch.Generator.manual_seed takes)"
_ASPECT_RANGE = (lambda a: 0 < a[0] <= a[1]), "(low, high) with 0 < low <= high"
_GROUND_BAND = (lambda g: g is None or 0 < g[0] < g[1]), "None or (r_lo, r_hi) with 0 < r_lo < r_hi"
_OBJECT_TEMPLATES = ((lambda ts: len(ts) > 0 and all(0 < hl <= hh and 0 < wl <= wh for hl, hh, wl, wh in ts)),
                     "a non-empty tuple of (height_lo, height_hi, width_lo, width_hi) "
                     "in metres with 0 < height_lo <= height_hi and 0 < width_lo <= width_hi")
_CLASS_HEIGHTS_M = (lambda t: len(t) > 0 and all(x > 0 for x in t)), "a non-empty tuple of heights > 0"
_CLASS_WEIGHTS = (lambda t: all(x >= 0 for x in t) and any(x > 0 for x in t)), "weights >= 0, not all 0"
_CLASS_QUOTA = (_quota_ok, "shares >= 0 that sum to at most 1: one a class in the ranker's order, or "
                           "(class name, share) pairs ({'Pedestrian': 0.2}) with distinct names")
_RANKER = (lambda v: v.strip() != ""), "'none', a shipped ranker name ('kitti') or the path of a weights file"

_JOINT: list[tuple[tuple[str, ...], Callable[["ReebConfig"], bool], str]] = [
    # Conditions between fields: (the fields, the check, what is expected).
    (("class_heights_m", "class_weights"), lambda c: len(c.class_weights) == len(c.class_heights_m),
     "of the same length (one weight per class)"),
    (("class_heights_m", "object_templates"), lambda c: len(c.object_templates) == len(c.class_heights_m),
     "of the same length (one template per class, in the same order)"),
    (("class_quota", "ranker"), lambda c: not c.class_quota or c.ranker != "none" or _by_name(c.class_quota),
     "a ranker (its class head hints each box's class) with class_quota given in the ranker's class order, "
     "class_quota by class name ({'Pedestrian': 0.2}: ignored without a class head), or class_quota=()"),
    (("camera_height_m", "vertical_fov_deg", "horizontal_fov_deg", "max_object_width_m",
      "region_width_round", "region_overlap"), lambda c: _region_count(c) <= _MAX_REGIONS,
     f"a camera and overlap giving at most {_MAX_REGIONS} regions (eqs. 5-8)"),
]

_PLANS: dict[type, tuple[dict[str, Any], dict[str, _Check]]] = {}


def _plan(cls: type) -> tuple[dict[str, Any], dict[str, _Check]]:
    """``cls``'s resolved field annotations (the module postpones them) and field ranges."""
    if cls not in _PLANS:
        _PLANS[cls] = (typing.get_type_hints(cls),
                       {f.name: f.metadata["range"] for f in dataclasses.fields(cls) if "range" in f.metadata})
    return _PLANS[cls]


def _validate(cfg: "ReebConfig") -> None:
    """Check every field of ``cfg`` in place: its type from its annotation (:func:`_conform`,
    so new fields are checked too), then its declared range (:func:`_knob`), then :data:`_JOINT`.

    Raises TypeError for a value of the wrong type (``top_k=True``, ``seed="a"``) and
    ValueError for one of the right type out of range (``kappa=200``), both as
    ``ReebConfig.<name> must be <expected>, got <value>``.
    """
    hints, ranges = _plan(type(cfg))
    if isinstance(cfg.class_quota, typing.Mapping):  # {"Pedestrian": 0.2}: kept as pairs, hashable
        object.__setattr__(cfg, "class_quota", tuple(cfg.class_quota.items()))
    for name, hint in hints.items():
        value = getattr(cfg, name)
        try:
            fixed = _conform(value, hint)
        except (TypeError, ValueError) as e:
            raise type(e)(f"ReebConfig.{name} must be {_describe(hint)}, got {_show(value)}") from None
        if fixed is not value:
            object.__setattr__(cfg, name, fixed)
    for name, (ok, expected) in ranges.items():
        if not ok(getattr(cfg, name)):
            raise ValueError(f"ReebConfig.{name} must be {expected}, got {_show(getattr(cfg, name))}")
    for names, ok, expected in _JOINT:
        if all(n in hints for n in names) and not ok(cfg):
            got = ", ".join(f"{n}={_show(getattr(cfg, n))}" for n in names)
            fields = ", ".join(f"ReebConfig.{n}" for n in names[:-1]) + f" and ReebConfig.{names[-1]}"
            raise ValueError(f"{fields} must be {expected}, got {got}")


def check_fields(owner: str, values: typing.Mapping[str, Any], hints: typing.Mapping[str, Any],
                 ranges: typing.Mapping[str, str | None]) -> dict[str, Any]:
    """``values`` of the fields of another settings class checked as ReebConfig's are: each by
    its annotation in ``hints`` (a bool is no number, floats finite, a ``Literal``'s words)
    then by its interval in ``ranges`` (``"[32, 4096]"``, ``"(0, 1]"``, ``">= 1"``; None or
    absent: none), normalised (ints for integral numbers, tuples for lists).

    Raises:
        TypeError: a value of the wrong type; ValueError: one out of its range. Both as
        ``<owner>.<name> must be <expected>, got <value>``.
    """
    out = {}
    for name, value in values.items():
        hint = hints.get(name, Any)
        try:
            fixed = _conform(value, hint)
        except (TypeError, ValueError) as e:
            raise type(e)(f"{owner}.{name} must be {_describe(hint)}, got {_show(value)}") from None
        interval = ranges.get(name)
        if interval is not None:
            ok, expected = _range(interval)
            if not ok(fixed):
                raise ValueError(f"{owner}.{name} must be {expected}, got {_show(value)}")
        out[name] = fixed
    return out


def _knob(default: Any, check: str | _Check | None = None, *, front: bool = False) -> Any:
    """A field's default, with its range once its type is right (:func:`_range`: an interval
    such as ``"(0, 4]"``, or a ``(check, words)`` pair) and, with ``front``, a place in
    :data:`FRONT_END_FIELDS` (it changes the edges, groups, road mask or score maps)."""
    meta: dict[str, Any] = {}
    if check is not None:
        meta["range"] = _range(check)
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
    group_cell: int | None = _knob(8, _GROUP_CELL, front=True)
    """The edge groups are the 8-connected components of edge pixels (as printed), cut at
    the borders of tiles of this side, in working pixels (reading 2: long chains are rarely
    enclosed); ``None`` = no bound, plain connected components as printed."""

    # -- Sec. 3.5, eqs. 3-4: road segmentation -------------------------------------------
    road_samples: int = _knob(300, "[1, 1000000]", front=True)
    """Random pixels sampled to estimate the road colour ("hundreds", Sec. 3.5)."""
    road_band: tuple[float, float, float, float] = _knob((0.3, 0.8, 0.7, 1.0), _ROAD_BAND, front=True)
    """Where road is likely, as fractions of the image (x1, y1, x2, y2): bottom centre."""
    road_tolerance: tuple[float, float, float] = _knob((0.5, 0.12, 0.12), _ROAD_TOLERANCE, front=True)
    """Half-width of the in-range test around the sampled median, per HSV channel
    (hue in radians, circular; saturation and value in [0, 1]). Not given in the paper."""
    seed: int = _knob(0, _SEED, front=True)
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
    aspect_range: tuple[float, float] = _knob((0.25, 4.0), _ASPECT_RANGE)
    """Allowed width/height ratios of the windows."""
    ground_band: tuple[float, float] | None = _knob((0.45, 3.0), _GROUND_BAND)
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
    ), _OBJECT_TEMPLATES)
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
    class_heights_m: tuple[float, ...] = _knob((1.5, 3.2, 1.72, 1.72), _CLASS_HEIGHTS_M)
    """Typical real heights (metres) of car, truck, pedestrian and cyclist, for
    ``location_score='classes'``: L is the best fit over the classes of a Gaussian in
    log(b_h / (b_y − horizon·H) / (height / camera_height_m))."""
    class_weights: tuple[float, ...] = _knob((1.0, 0.7, 1.0, 1.0), _CLASS_WEIGHTS)
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
    ranker: str = _knob("kitti", _RANKER)
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
    class_quota: ClassQuota = _knob((), _CLASS_QUOTA)
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
        """Check every field (:func:`_validate`; TypeError, ValueError). Lists become tuples,
        ints in float fields floats and -0.0 0.0: equal settings give equal, hashable configs
        with equal fingerprints (JSON round trips included)."""
        _validate(self)

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
        """``class_quota`` as one share per class of a ranker's class head (``classes``, in its
        order; None without a head), or None for no quota (``class_quota=()``, or by name
        without a head).

        Raises:
            ValueError: a share for each class in order, but no head or another number of
                classes; or a class name the head does not have (both name what it has).
        """
        quota = self.class_quota  # a mapping became (name, share) pairs in __post_init__
        if not quota:
            return None
        named = _by_name(quota)
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

    def replace(self, **changes: object) -> "ReebConfig":
        """A copy with ``changes`` applied (validated)."""
        return dataclasses.replace(self, **changes)  # type: ignore[arg-type]

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "ReebConfig":
        """The config of a dict of fields (as :meth:`to_dict` writes it; lists for tuples).

        Raises TypeError when ``d`` is not a mapping, ValueError naming unknown fields, and
        the field checks' TypeError / ValueError (:meth:`__post_init__`)."""
        if not isinstance(d, typing.Mapping):
            raise TypeError(f"ReebConfig.from_dict expects a dict of ReebConfig fields, got {type(d).__name__}")
        unknown = sorted(set(d) - {f.name for f in dataclasses.fields(cls)})
        if unknown:
            raise ValueError(f"unknown ReebConfig field(s): {', '.join(unknown)}")
        fixed: dict[str, Any] = {k: tuple(v) if isinstance(v, list) else v for k, v in d.items()}
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

_RANGES: dict[str, _Check] = _plan(ReebConfig)[1]
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
