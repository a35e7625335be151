"""The field checks of the settings classes: a value checked against its annotation (a bool
is no number, floats finite, a ``Literal``'s words, tuples for lists) and its interval, with
one-line errors that name the field (``ReebConfig.kappa must be in (0, 8], got 200``); the
ranges that are not intervals, and the conditions between :class:`~reeb_torch.ReebConfig`'s
fields (:data:`JOINT`)."""

from __future__ import annotations

import dataclasses
import math
import numbers
import types
import typing
from typing import Any, Callable, Literal

__all__ = ["Check", "JOINT", "MAX_REGIONS", "check_fields", "conform", "describe", "field_plan", "interval_check",
           "quota_by_name", "quota_pairs", "show", "validate_config"]

_NUMBERS = {bool: bool, int: numbers.Integral, float: numbers.Real}


def conform(value: Any, hint: Any) -> Any:
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
                return conform(value, alt)
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
        items = [conform(v, a) for v, a in zip(value, args)]
        same = type(value) is tuple and all(a is b for a, b in zip(items, value))
        return value if same else tuple(items)
    if not isinstance(hint, type) or isinstance(value, hint):
        return value  # an annotation this checker does not know is left to the field's range
    raise TypeError


def describe(hint: Any, plural: bool = False) -> str:
    """What ``hint`` expects, in words (``"a tuple of 2 finite numbers"``)."""
    words = {bool: ("True or False (a bool)", "bools (True or False)"), int: ("an int (not a bool)", "ints"),
             float: ("a finite number", "finite numbers"), str: ("a string", "strings")}
    if hint in words:
        return words[hint][plural]
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin is Literal:
        return "one of " + ", ".join(repr(a) for a in args)
    if origin is typing.Union or origin is types.UnionType:
        alts = " or ".join(describe(a) for a in args if a is not type(None))
        return ("None or " if type(None) in args else "") + alts
    if origin is tuple:
        head = "tuples" if plural else "a tuple"
        if len(args) == 2 and args[1] is Ellipsis:
            return f"{head} of {describe(args[0], plural=True)}"
        if all(a == args[0] for a in args):
            return f"{head} of {len(args)} {describe(args[0], plural=True)}"
        return f"{head} ({', '.join(describe(a) for a in args)})"
    return getattr(hint, "__name__", repr(hint))


def show(value: Any, limit: int = 80) -> str:
    """``repr(value)``, shortened to ``limit`` characters for messages."""
    r = repr(value)
    return r if len(r) <= limit else r[: limit - 4] + " ..."


Check = tuple[Callable[[Any], bool], str]  # a range check and what it expects, in words


def interval_check(spec: str | Check) -> Check:
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


def check_fields(owner: str, values: typing.Mapping[str, Any], hints: typing.Mapping[str, Any],
                 ranges: typing.Mapping[str, str | Check | None]) -> dict[str, Any]:
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
            fixed = conform(value, hint)
        except (TypeError, ValueError) as e:
            raise type(e)(f"{owner}.{name} must be {describe(hint)}, got {show(value)}") from None
        interval = ranges.get(name)
        if interval is not None:
            ok, expected = interval_check(interval)
            if not ok(fixed):
                raise ValueError(f"{owner}.{name} must be {expected}, got {show(value)}")
        out[name] = fixed
    return out


# -- validation (ReebConfig.__post_init__) ---------------------------------------------------
# The type of every field is checked from its annotation, so a new field is checked as soon
# as it is declared; its range is declared with it (_knob), joint conditions go into JOINT.


def _quota_ok(t: tuple) -> bool:
    """``class_quota``: all shares or all ``(name, share)`` pairs (distinct names), each share
    >= 0, summing to at most 1."""
    named = [isinstance(x, tuple) for x in t]
    if any(named) and not all(named):
        return False
    shares = [x[1] for x in t] if any(named) else list(t)
    names = [x[0] for x in t] if any(named) else []
    return all(x >= 0 for x in shares) and sum(shares) <= 1 and len(set(names)) == len(names)


def quota_pairs(quota: Any) -> Any:
    """A ``class_quota`` given as a mapping (``{"Pedestrian": 0.2}``) as the ``(name, share)``
    pairs the field holds (hashable, in the mapping's order); any other value as it is."""
    return tuple(quota.items()) if isinstance(quota, typing.Mapping) else quota


def quota_by_name(quota: object) -> bool:
    """Whether a ``class_quota`` gives its shares by class name (``(name, share)`` pairs)."""
    return isinstance(quota, tuple) and bool(quota) and isinstance(quota[0], tuple)


MAX_REGIONS = 1024
"""Most region strips a camera setting may give (eq. 8); more is a setting error."""


def _region_count(c: Any) -> int:
    from .stages.regions import region_count, region_width_fraction

    frac = region_width_fraction(c.camera_height_m, c.vertical_fov_deg, c.horizontal_fov_deg,
                                 c.max_object_width_m, c.region_width_round)
    return region_count(frac, c.region_overlap) if frac > 0 else MAX_REGIONS + 1


# Checks that are not intervals, named by the fields that declare them (:func:`_knob`).
GROUP_CELL = (lambda v: v is None or v >= 2), "None or an int >= 2"
ROAD_BAND = ((lambda b: 0 <= b[0] < b[2] <= 1 and 0 <= b[1] < b[3] <= 1),
              "fractions (x1, y1, x2, y2) with 0 <= x1 < x2 <= 1 and 0 <= y1 < y2 <= 1")
ROAD_TOLERANCE = (lambda t: all(x >= 0 for x in t)), "three non-negative numbers (hue, saturation, value)"
SEED = (lambda v: -2**63 <= v < 2**64), "in [-2**63, 2**64) (what torch.Generator.manual_seed takes)"
ASPECT_RANGE = (lambda a: 0 < a[0] <= a[1]), "(low, high) with 0 < low <= high"
GROUND_BAND = (lambda g: g is None or 0 < g[0] < g[1]), "None or (r_lo, r_hi) with 0 < r_lo < r_hi"
OBJECT_TEMPLATES = ((lambda ts: len(ts) > 0 and all(0 < hl <= hh and 0 < wl <= wh for hl, hh, wl, wh in ts)),
                     "a non-empty tuple of (height_lo, height_hi, width_lo, width_hi) "
                     "in metres with 0 < height_lo <= height_hi and 0 < width_lo <= width_hi")
CLASS_HEIGHTS_M = (lambda t: len(t) > 0 and all(x > 0 for x in t)), "a non-empty tuple of heights > 0"
CLASS_WEIGHTS = (lambda t: all(x >= 0 for x in t) and any(x > 0 for x in t)), "weights >= 0, not all 0"
CLASS_QUOTA = (_quota_ok, "shares >= 0 that sum to at most 1: one a class in the ranker's order, or "
                           "(class name, share) pairs ({'Pedestrian': 0.2}) with distinct names")
RANKER = (lambda v: v.strip() != ""), "'none', a shipped ranker name ('kitti') or the path of a weights file"

JOINT: list[tuple[tuple[str, ...], Callable[[Any], bool], str]] = [
    # Conditions between fields: (the fields, the check, what is expected).
    (("class_heights_m", "class_weights"), lambda c: len(c.class_weights) == len(c.class_heights_m),
     "of the same length (one weight per class)"),
    (("class_heights_m", "object_templates"), lambda c: len(c.object_templates) == len(c.class_heights_m),
     "of the same length (one template per class, in the same order)"),
    (("class_quota", "ranker"), lambda c: not c.class_quota or c.ranker != "none" or quota_by_name(c.class_quota),
     "a ranker (its class head hints each box's class) with class_quota given in the ranker's class order, "
     "class_quota by class name ({'Pedestrian': 0.2}: ignored without a class head), or class_quota=()"),
    (("camera_height_m", "vertical_fov_deg", "horizontal_fov_deg", "max_object_width_m",
      "region_width_round", "region_overlap"), lambda c: _region_count(c) <= MAX_REGIONS,
     f"a camera and overlap giving at most {MAX_REGIONS} regions (eqs. 5-8)"),
]

_PLANS: dict[type, tuple[dict[str, Any], dict[str, Check]]] = {}


def field_plan(cls: type) -> tuple[dict[str, Any], dict[str, Check]]:
    """``cls``'s resolved field annotations (the module postpones them) and field ranges."""
    if cls not in _PLANS:
        _PLANS[cls] = (typing.get_type_hints(cls),
                       {f.name: f.metadata["range"] for f in dataclasses.fields(cls) if "range" in f.metadata})
    return _PLANS[cls]


def validate_config(cfg: Any) -> None:
    """Check every field of ``cfg`` in place: its type from its annotation (:func:`conform`,
    so new fields are checked too), then its declared range (:func:`_knob`), then :data:`JOINT`.

    Raises TypeError for a value of the wrong type (``top_k=True``, ``seed="a"``) and
    ValueError for one of the right type out of range (``kappa=200``), both as
    ``ReebConfig.<name> must be <expected>, got <value>``.
    """
    hints, ranges = field_plan(type(cfg))
    object.__setattr__(cfg, "class_quota", quota_pairs(cfg.class_quota))
    for name, hint in hints.items():
        value = getattr(cfg, name)
        try:
            fixed = conform(value, hint)
        except (TypeError, ValueError) as e:
            raise type(e)(f"ReebConfig.{name} must be {describe(hint)}, got {show(value)}") from None
        if fixed is not value:
            object.__setattr__(cfg, name, fixed)
    for name, (ok, expected) in ranges.items():
        if not ok(getattr(cfg, name)):
            raise ValueError(f"ReebConfig.{name} must be {expected}, got {show(getattr(cfg, name))}")
    for names, ok, expected in JOINT:
        if all(n in hints for n in names) and not ok(cfg):
            got = ", ".join(f"{n}={show(getattr(cfg, n))}" for n in names)
            fields = ", ".join(f"ReebConfig.{n}" for n in names[:-1]) + f" and ReebConfig.{names[-1]}"
            raise ValueError(f"{fields} must be {expected}, got {got}")
