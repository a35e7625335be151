"""Property tests (hypothesis) of the API contract and of ReebConfig.

* Any input — random sizes, dtypes, memory layouts, batch forms — gives valid boxes or a
  ValueError/TypeError, never another exception; valid inputs give the same boxes as the
  contiguous float32 batch (layout invariance), and a uint8 image the same as ``u / 255``.
* Batch ≡ single at random sizes (exact float64 sums, fixed-order blur).
* Any value for any ReebConfig field gives a valid (hashable, JSON round-tripping) config
  or a ValueError/TypeError whose message names the field; any valid config runs on any
  image or stops at the door with a ValueError.

Images are crops of the bundled KITTI frame (real edges, 8–160 px sides) and example
counts are small: the file runs in well under a minute on two CPU cores.
"""

from __future__ import annotations

import dataclasses
import json
import math
import re
import typing

import numpy as np
import pytest
import torch

hypothesis = pytest.importorskip("hypothesis")  # the dev extra; skipped in a bare install
from hypothesis import HealthCheck, event, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from reeb_torch import ProposalGenerator, ReebConfig  # noqa: E402
from reeb_torch._checks import check_images  # noqa: E402

FAST = dict(top_k=300, candidates_per_region=600, candidates_without_regions=600)
"""Smaller budgets than the defaults: the contract does not depend on them, speed does."""

SETTINGS = dict(deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow])
"""Derandomized: the same examples every run (a CI failure is reproducible as is)."""

FIELDS = [f.name for f in dataclasses.fields(ReebConfig)]


@pytest.fixture(scope="module")
def frame(sample_image: torch.Tensor) -> torch.Tensor:
    return sample_image  # the bundled KITTI frame, uint8 (3, 375, 1242)


@pytest.fixture(scope="module")
def gen() -> ProposalGenerator:
    return ProposalGenerator(**FAST)


def _crop(frame: torch.Tensor, h: int, w: int, y: int, x: int) -> torch.Tensor:
    """An ``h × w`` crop whose top-left corner is at fractions ``(y, x)`` (per mille) of the
    free range, so every draw is inside the frame."""
    H, W = frame.shape[-2:]
    y0, x0 = (H - h) * y // 1000, (W - w) * x // 1000
    return frame[:, y0:y0 + h, x0:x0 + w]


def _assert_valid(out: dict, h: int, w: int, top_k: int) -> None:
    """The output contract: float32 (x1, y1, x2, y2) inside the image, ranked scores."""
    boxes, scores = out["boxes"], out["scores"]
    assert boxes.dtype == torch.float32 and boxes.ndim == 2 and boxes.shape[1] == 4
    assert scores.dtype == torch.float32 and scores.shape == (boxes.shape[0],)
    assert boxes.shape[0] <= top_k
    assert bool(torch.isfinite(boxes).all() and torch.isfinite(scores).all())
    assert bool((boxes[:, 0] >= 0).all() and (boxes[:, 1] >= 0).all())
    assert bool((boxes[:, 2] <= w).all() and (boxes[:, 3] <= h).all())  # exactly: no rounding past the edge
    assert bool((boxes[:, 2] > boxes[:, 0]).all() and (boxes[:, 3] > boxes[:, 1]).all())
    assert bool((scores[1:] <= scores[:-1]).all())


def _same(a: list[dict], b: list[dict]) -> None:
    assert len(a) == len(b)
    for ra, rb in zip(a, b):
        assert torch.equal(ra["boxes"], rb["boxes"])
        assert torch.equal(ra["scores"], rb["scores"])


# -- the API contract ---------------------------------------------------------------------

GOOD_DTYPES = [torch.uint8, torch.float32, torch.float64, torch.float16, torch.bfloat16]
BAD_DTYPES = [torch.int64, torch.int8, torch.bool, torch.complex64]
DTYPES = st.sampled_from(GOOD_DTYPES * 3 + BAD_DTYPES)  # mostly usable: most examples run
LAYOUTS = ["contiguous", "channels_last", "transposed", "strided", "list", "expanded", "list_of_hwc"]


def _as_dtype(u8: torch.Tensor, dtype: torch.dtype, spoil: str) -> torch.Tensor:
    """The uint8 batch in ``dtype`` (floats scaled to [0, 1]), optionally spoiled."""
    if dtype == torch.uint8 or not (dtype.is_floating_point or dtype.is_complex):
        return u8.to(dtype)
    x = u8.to(dtype) / 255
    if spoil == "range":  # every value above 1, as data not divided by 255
        x = x + 1.5
    elif spoil == "nan":
        x = x.clone()
        x.view(-1)[0] = float("nan")
    return x


def _in_layout(x: torch.Tensor, layout: str) -> torch.Tensor | list[torch.Tensor]:
    """The same values (B, 3, H, W) in another memory layout or batch form."""
    if layout == "channels_last":
        return x.contiguous(memory_format=torch.channels_last)
    if layout == "transposed":  # stored (B, 3, W, H), viewed as (B, 3, H, W)
        return x.transpose(2, 3).contiguous().transpose(2, 3)
    if layout == "strided":  # every other column of a wider tensor
        wide = torch.zeros(*x.shape[:3], 2 * x.shape[3], dtype=x.dtype)
        wide[..., ::2] = x
        return wide[..., ::2]
    if layout == "list":
        return list(x.unbind(0))
    if layout == "expanded":  # one row repeated with stride 0
        return x[:, :, :1].expand(-1, -1, x.shape[2], -1)
    if layout == "list_of_hwc":  # a common mistake: (H, W, 3) images
        return [im.permute(1, 2, 0) for im in x]
    return x.contiguous()


@settings(max_examples=16, **SETTINGS)
@given(h=st.integers(16, 150), w=st.integers(16, 160), b=st.integers(1, 2), dtype=DTYPES,
       layout=st.sampled_from(LAYOUTS), spoil=st.sampled_from(["none"] * 4 + ["range", "nan"]),
       tiny=st.sampled_from(["no"] * 5 + ["h", "w"]), y=st.integers(0, 1000), x=st.integers(0, 1000))
def test_any_input_gives_valid_boxes_or_a_value_or_type_error(frame, gen, h, w, b, dtype, layout, spoil, tiny, y, x):
    h, w = (h // 10 if tiny == "h" else h), (w // 10 if tiny == "w" else w)  # 1-16 px: below the smallest window
    u8 = torch.stack([_crop(frame, h, w, y, (x + 500 * i) % 1001) for i in range(b)])
    images = _in_layout(_as_dtype(u8, dtype, spoil), layout)
    floaty = dtype == torch.uint8 or dtype.is_floating_point
    spoiled = dtype.is_floating_point and spoil != "none"
    fits = min(h, w) >= gen.min_side
    valid = floaty and not spoiled and fits and layout != "list_of_hwc"
    try:
        out = gen(images)
    except (ValueError, TypeError) as e:
        event(f"refused: {type(e).__name__}")
        assert not valid, f"a valid input was refused: {e}"
        if not floaty and layout != "list_of_hwc":
            assert isinstance(e, TypeError) and "dtype" in str(e), str(e)
        return
    assert valid, "an invalid input was accepted"
    event("ran")
    assert len(out) == b
    for r in out:
        _assert_valid(r, h, w, gen.config.top_k)
    # the same values as one contiguous float32 batch: layout, batch form, uint8 ≡ float / 255
    ref = torch.stack([im.float() / 255 if dtype == torch.uint8 else im.float() for im in images])
    _same(out, gen(ref))


def test_boxes_stay_inside_an_odd_sized_image():
    """Windows on the last working column map back inside the image (not 99.0000076 for W = 99)."""
    torch.manual_seed(35)
    _assert_valid(ProposalGenerator()(torch.rand(1, 3, 157, 99))[0], 157, 99, 2000)


@settings(max_examples=12, **SETTINGS)
@given(h=st.integers(40, 200), w=st.integers(40, 200), odd=st.sampled_from(["h", "w", "both", "none"]),
       seed=st.integers(0, 2**16), scale=st.sampled_from([0.5, 0.5, 1.0, 0.37]))
def test_boxes_stay_inside_the_image_at_any_size(h, w, odd, seed, scale):
    """The box contract 0 <= x1 < x2 <= W, 0 <= y1 < y2 <= H over random sizes, odd ones
    included, and working scales that do not divide them."""
    h = h | 1 if odd in ("h", "both") else h
    w = w | 1 if odd in ("w", "both") else w
    torch.manual_seed(seed)
    gen = ProposalGenerator(**FAST, scale=scale)
    if min(h, w) < gen.min_side:
        return
    (out,) = gen(torch.rand(1, 3, h, w))
    _assert_valid(out, h, w, gen.config.top_k)


@settings(max_examples=6, **SETTINGS)
@given(h=st.integers(16, 150), w=st.integers(16, 160), b=st.integers(1, 2), dtype=st.sampled_from(GOOD_DTYPES),
       layout=st.sampled_from([lay for lay in LAYOUTS if lay != "list_of_hwc"]),
       y=st.integers(0, 1000), x=st.integers(0, 1000))
def test_usable_inputs_give_the_same_boxes_in_any_layout_and_dtype(frame, gen, h, w, b, dtype, layout, y, x):
    """Every usable input runs (no example is refused), as the contiguous float32 batch."""
    u8 = torch.stack([_crop(frame, h, w, y, (x + 500 * i) % 1001) for i in range(b)])
    images = _in_layout(_as_dtype(u8, dtype, "none"), layout)
    out = gen(images)
    for r in out:
        _assert_valid(r, h, w, gen.config.top_k)
    ref = torch.stack([im.float() / 255 if dtype == torch.uint8 else im.float() for im in images])
    _same(out, gen(ref))


@settings(max_examples=4, **SETTINGS)
@given(h=st.integers(60, 150), w=st.integers(60, 200), y=st.integers(0, 1000), x=st.integers(0, 1000))
def test_uint8_is_the_same_as_float_over_255(frame, gen, h, w, y, x):
    u = _crop(frame, h, w, y, x)
    _same(gen([u]), gen([u.float() / 255]))


@pytest.mark.parametrize("make, error, words", [
    (lambda: torch.rand(1, 3, 64, 64, device="meta"), TypeError, "meta"),
    (lambda: [torch.rand(3, 64, 64, device="meta")], TypeError, "meta"),
    (lambda: torch.rand(1, 3, 64, 64).to_sparse(), TypeError, "dense"),
    (lambda: [torch.rand(3, 64, 64).to_sparse()], TypeError, "dense"),
    (lambda: "image.png", TypeError, "Tensor"),
    (lambda: [np.zeros((3, 64, 64), np.float32)], TypeError, "torch.Tensor"),
    (lambda: [], ValueError, "empty"),
    (lambda: torch.rand(3, 64, 64), ValueError, "images[None]"),
    (lambda: torch.rand(1, 4, 64, 64), ValueError, "3 (RGB) channels"),
])
def test_unusable_tensors_are_refused_at_the_door(make, error, words):
    with pytest.raises(error, match=re.escape(words)):
        ProposalGenerator()(make())
    with pytest.raises(error, match=re.escape(words)):
        check_images(make(), 16)


@settings(max_examples=5, **SETTINGS)
@given(h=st.integers(60, 150), w=st.integers(60, 200), y=st.integers(0, 1000), x=st.integers(0, 1000),
       dx=st.integers(1, 1000))
def test_batch_is_the_same_as_single(frame, gen, h, w, y, x, dx):
    """Two different crops as one batch give, per image, what each gives alone."""
    a, b = _crop(frame, h, w, y, x), _crop(frame, h, w, 1000 - y, (x + dx) % 1001)
    together = gen(torch.stack([a, b]))
    _same(together, gen(a[None]) + gen(b[None]))


# -- ReebConfig fuzzing ------------------------------------------------------------------

_finite = st.floats(allow_nan=False, allow_infinity=False)
_scalars = st.one_of(
    st.none(), st.booleans(), st.integers(), st.integers(-3, 300), st.floats(),
    _finite.filter(lambda v: -5 <= v <= 5), st.text(max_size=8),
    st.sampled_from(["connected", "cell", "gray", "rgb", "and", "or", "camera", "grid", "paper", "none",
                     "classes", "stand", "nearest", "contained", "abs-diff", "true", "off", "1"]),
    st.builds(np.float32, st.floats(-10, 10, width=32)), st.builds(np.int64, st.integers(-10, 10**6)),
    st.just(b"bytes"), st.just(object()), st.just(1 + 2j),
)
_values = st.one_of(
    _scalars,
    st.lists(_scalars, max_size=5), st.lists(_scalars, max_size=5).map(tuple),
    st.lists(st.floats(0, 1), min_size=2, max_size=4).map(tuple),
    st.lists(st.lists(st.floats(0.1, 5), min_size=3, max_size=5), min_size=0, max_size=3),
    st.dictionaries(st.text(max_size=3), st.integers(), max_size=2),
)


def _check_valid(cfg: ReebConfig) -> None:
    """A valid config is hashable, survives JSON, and re-validates to itself."""
    hash(cfg)
    back = ReebConfig.from_dict(json.loads(json.dumps(cfg.to_dict())))
    assert back == cfg and back.fingerprint() == cfg.fingerprint()
    assert cfg.replace() == cfg
    for f in dataclasses.fields(cfg):
        v = getattr(cfg, f.name)
        assert not isinstance(v, (list, np.generic)), f"{f.name} kept a {type(v).__name__}"
        if isinstance(v, float):
            assert math.isfinite(v)


@settings(max_examples=400, **SETTINGS)
@given(name=st.sampled_from(FIELDS), value=_values)
def test_any_value_for_any_field_is_valid_or_an_error_naming_it(name, value):
    try:
        cfg = ReebConfig(**{name: value})
    except (ValueError, TypeError) as e:
        assert f"ReebConfig.{name}" in str(e), str(e)
        event(type(e).__name__)
        return
    event("valid")
    _check_valid(cfg)
    hint = typing.get_type_hints(ReebConfig)[name]
    if hint is bool:
        assert value is True or value is False
    if hint is int:
        assert not isinstance(value, bool)


@settings(max_examples=150, **SETTINGS)
@given(changes=st.dictionaries(st.sampled_from(FIELDS), _values, min_size=1, max_size=4))
def test_several_bad_fields_name_one_of_them(changes):
    try:
        cfg = ReebConfig(**changes)
    except (ValueError, TypeError) as e:
        assert any(f"ReebConfig.{n}" in str(e) for n in changes), str(e)
        return
    _check_valid(cfg)


# Settings within each field's range, a few per field, so that a valid config runs fast enough
# to run: the point is that every combination that validates also runs (or stops at the door).
_RUNNABLE = dict(
    scale=st.sampled_from([0.05, 0.25, 0.5, 1.0]),
    blur_sigma=st.sampled_from([0.3, 1.0, 4.0]),
    edge_threshold=st.sampled_from([0.0, 0.05, 0.9]),
    thin_edges=st.booleans(), remove_isolated=st.booleans(),
    group_cell=st.sampled_from([2, 8, 64, None]),
    road_samples=st.sampled_from([1, 300]), road_band=st.sampled_from([(0.3, 0.8, 0.7, 1.0), (0.0, 0.0, 0.01, 0.01)]),
    seed=st.integers(-2**63, 2**64 - 1),
    use_regions=st.booleans(), max_object_width_m=st.sampled_from([0.3, 2.55, 50.0]),
    region_overlap=st.sampled_from([0.05, 0.5, 1.0]), region_assign=st.sampled_from(["contained", "nearest"]),
    region_width_round=st.sampled_from([None, 0.125, 1.0]), entropy_bins=st.sampled_from([2, 65536]),
    entropy_sigma=st.sampled_from([0.1, 4.0]),
    candidates_per_region=st.sampled_from([1, 600]),
    candidates_without_regions=st.sampled_from([1, 600]), min_window=st.sampled_from([4, 16, 40]),
    size_ratio=st.sampled_from([1.2, 2.0, 16.0]), window_step=st.sampled_from([0.1, 0.5, 1.0]),
    aspect_range=st.sampled_from([(0.25, 4.0), (1.0, 1.0), (0.01, 100.0)]),
    ground_band=st.sampled_from([None, (0.45, 3.0), (0.001, 0.002)]),
    window_geometry=st.sampled_from(["camera", "grid"]), horizon=st.sampled_from([0.01, 0.47, 0.99]),
    score_norm=st.sampled_from(["perimeter", "area"]), gamma=st.sampled_from([0.01, 4.0]),
    kappa=st.sampled_from([0.01, 8.0]),
    center_fraction=st.sampled_from([0.01, 0.99]),
    road_score=st.sampled_from(["reward", "none"]),
    location_score=st.sampled_from(["paper", "classes", "none"]),
    ground_log_sigma=st.sampled_from([0.01, 3.0]), alpha=st.sampled_from([0.0, 1.0]), beta=st.sampled_from([0.0, 1.0]),
    min_edge_score=st.sampled_from([-1.0, 0.0, 1e6]), nms_iou=st.sampled_from([0.01, 1.0]),
    top_k=st.sampled_from([1, 50]),
)


def _equal_spelling(value, how: int):
    """The same setting written another way: -0.0 for 0.0, an int for a whole float, a list
    for a tuple (``how`` picks which, per value)."""
    if isinstance(value, float) and not isinstance(value, bool):
        if value == 0.0 and how % 2:
            return -0.0
        if value.is_integer() and how % 3 == 0 and abs(value) < 2**53:
            return int(value)
        return value
    if isinstance(value, tuple):
        items = [_equal_spelling(v, how + i) for i, v in enumerate(value)]
        return items if how % 2 else tuple(items)
    return value


@settings(max_examples=40, **SETTINGS)
@given(changes=st.fixed_dictionaries({}, optional=_RUNNABLE), how=st.integers(0, 5))
def test_equal_configs_give_equal_fingerprints(changes, how):
    """Equal settings spelled differently (min_edge_score=-0.0 and 0.0, 1 and 1.0, a list and a
    tuple) give equal configs with equal fingerprints."""
    try:
        cfg = ReebConfig(**changes)
    except ValueError:
        return
    spelled = {k: _equal_spelling(v, how + i) for i, (k, v) in enumerate(cfg.to_dict().items())}
    other = ReebConfig.from_dict(spelled)
    assert other == cfg
    assert other.fingerprint() == cfg.fingerprint()
    back = ReebConfig.from_dict(json.loads(json.dumps(spelled)))
    assert back.fingerprint() == cfg.fingerprint()


def test_signed_zero_and_from_dict_of_a_list():
    assert ReebConfig(min_edge_score=-0.0).fingerprint() == ReebConfig(min_edge_score=0.0).fingerprint()
    with pytest.raises(TypeError, match="dict"):
        ReebConfig.from_dict([])


@pytest.mark.slow
@settings(max_examples=10, **SETTINGS)
@given(changes=st.fixed_dictionaries({}, optional=_RUNNABLE), h=st.integers(6, 120), w=st.integers(6, 160),
       y=st.integers(0, 1000), x=st.integers(0, 1000))
def test_any_valid_config_runs_or_stops_at_the_door(frame, changes, h, w, y, x):
    try:
        cfg = ReebConfig(**changes)
    except ValueError as e:  # a joint condition (e.g. one template per class)
        assert str(e).startswith("ReebConfig.") and any(n in str(e) for n in changes), str(e)
        event("invalid config")
        return
    g = ProposalGenerator(cfg)
    img = _crop(frame, h, w, y, x)
    try:
        out = g([img])
    except ValueError as e:  # too small for the smallest window or for the blur
        assert f"{w}x{h}" in str(e), str(e)
        event("image too small")
        return
    event("ran")
    _assert_valid(out[0], h, w, cfg.top_k)


# -- output rows: the vectorised rounding is Python's --------------------------------------

_decimal_ties = st.builds(lambda n, d, e: n / 10.0 ** d + e, st.integers(-10**7, 10**7), st.integers(0, 6),
                          st.sampled_from([0.0, 1e-13, -1e-13, 4e-7, -4e-7]))


@settings(max_examples=300, **SETTINGS)
@given(values=st.lists(st.floats(allow_nan=False, allow_infinity=False) | _decimal_ties, min_size=1, max_size=64),
       decimals=st.integers(0, 4), digits=st.integers(1, 9))
def test_row_rounding_is_pythons_for_any_floats(values, decimals, digits):
    from reeb_torch.runs.rows import round_like_python, significant_like_python

    v = np.array(values, np.float64)
    want = np.array([round(x, decimals) for x in values], np.float64)
    assert np.array_equal(round_like_python(v, decimals).view(np.int64), want.view(np.int64))
    want = np.array([float(f"{x:.{digits}g}") for x in values], np.float64)
    assert np.array_equal(significant_like_python(v, digits).view(np.int64), want.view(np.int64))
