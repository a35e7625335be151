"""The whole pipeline: shapes, ranking, batching, determinism, input checks, devices."""

from __future__ import annotations

import pytest
import torch

from reeb_torch import Inspection, ProposalGenerator, ReebConfig, get_preset, propose

SMALL = dict(top_k=300, candidates_per_region=600)


@pytest.fixture(scope="module")
def crop(sample_image):
    # a 192 x 512 crop of the sample keeps the tests fast
    return sample_image[:, 160:352, 300:812].contiguous()


def _check(out, h, w, top_k):
    boxes, scores = out["boxes"], out["scores"]
    assert boxes.dtype == torch.float32 and boxes.ndim == 2 and boxes.shape[1] == 4
    assert scores.shape == (boxes.shape[0],) and 0 < boxes.shape[0] <= top_k
    assert bool((boxes[:, 0] >= 0).all() and (boxes[:, 1] >= 0).all())
    assert bool((boxes[:, 2] <= w + 1e-3).all() and (boxes[:, 3] <= h + 1e-3).all())
    assert bool((boxes[:, 2] > boxes[:, 0]).all() and (boxes[:, 3] > boxes[:, 1]).all())
    assert bool((scores[1:] <= scores[:-1]).all())


def test_full_frame_default(sample_image):
    out = ProposalGenerator(top_k=500)([sample_image])
    _check(out[0], 375, 1242, 500)
    assert out[0]["boxes"].shape[0] == 500


def test_uint8_float_and_batch_forms_agree(crop):
    gen = ProposalGenerator(**SMALL)
    a = gen([crop])[0]
    b = gen(crop[None].float() / 255)[0]
    c = gen(crop[None])[0]
    for o in (b, c):
        assert torch.equal(a["boxes"], o["boxes"]) and torch.equal(a["scores"], o["scores"])


def test_same_proposals_alone_or_in_a_batch(crop):
    gen = ProposalGenerator(**SMALL)
    other = torch.flip(crop, dims=[2])
    third = crop[:, :160, :400]  # a different size in the same list
    alone = gen([crop])[0]
    batch = gen([other, crop, third, crop])
    for o in (batch[1], batch[3]):
        assert torch.equal(alone["boxes"], o["boxes"]) and torch.equal(alone["scores"], o["scores"])
    _check(batch[2], 160, 400, SMALL["top_k"])


def test_deterministic(crop):
    a = propose([crop], ReebConfig(**SMALL))[0]
    b = propose([crop], ReebConfig(**SMALL))[0]
    assert torch.equal(a["boxes"], b["boxes"])


def test_inspect(crop):
    ins = ProposalGenerator(**SMALL).inspect(crop)
    assert isinstance(ins, Inspection)
    h, w = crop.shape[-2:]
    assert ins.edges.shape == (h, w) and ins.road_mask.shape == (h, w) and ins.road_mask.dtype == torch.bool
    assert ins.regions.shape == (7, 4) and ins.entropy.shape == (7,) and ins.share.shape == (7,)
    assert float(ins.regions[0, 0]) == 0 and float(ins.regions[-1, 2]) == pytest.approx(w, abs=2)
    assert bool(((ins.share >= 0) & (ins.share <= 1)).all())
    assert ins.num_groups > 0 and ins.num_windows > ins.boxes.shape[0]


@pytest.mark.parametrize("preset, regions", [("training-free", False), ("paper", True), ("paper", False)])
def test_presets_run(crop, preset, regions):
    cfg = get_preset(preset).replace(use_regions=regions, **SMALL)
    _check(ProposalGenerator(cfg)([crop])[0], *crop.shape[-2:], SMALL["top_k"])


def test_blank_image_gives_empty_result():
    out = ProposalGenerator(**SMALL)([torch.zeros(3, 64, 64)])[0]
    assert out["boxes"].shape == (0, 4)


@pytest.mark.parametrize(
    "images, exc, match",
    [
        (torch.rand(3, 64, 64), ValueError, "one image"),
        (torch.rand(2, 64, 64), ValueError, r"\(B, 3, H, W\)"),
        (torch.rand(1, 4, 64, 64), ValueError, "3 \\(RGB\\) channels"),
        ([torch.rand(1, 64, 64)], ValueError, "3 \\(RGB\\) channels"),
        (torch.full((1, 3, 64, 64), float("nan")), ValueError, "NaN"),
        (torch.rand(1, 3, 64, 64) * 2, ValueError, r"\[0, 1\]"),
        (torch.zeros(1, 3, 64, 64, dtype=torch.int32), TypeError, "float or uint8"),
        ([], ValueError, "empty batch"),
        (torch.zeros(0, 3, 64, 64), ValueError, "empty batch"),
        (torch.rand(1, 3, 10, 64), ValueError, "smaller than the smallest window"),
        ("image.png", TypeError, "Tensor"),
        ([torch.rand(3, 64, 64).numpy()], TypeError, "torch.Tensor"),
    ],
)
def test_bad_input_is_rejected_with_a_clear_message(images, exc, match):
    with pytest.raises(exc, match=match):
        ProposalGenerator(**SMALL)(images)


@pytest.mark.parametrize("value", [float("nan"), float("inf"), -float("inf")])
@pytest.mark.parametrize("where", [(0, 0, 0), (1, 31, 17), (2, 63, 39)])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64, torch.float16])
def test_one_non_finite_value_anywhere_is_rejected(value, where, dtype):
    # the range check is one min/max pass: a single NaN or infinity must still be caught
    x = torch.rand(1, 3, 64, 64).to(dtype)
    x[(0, *where)] = value
    with pytest.raises(ValueError, match="NaN or infinite"):
        ProposalGenerator(**SMALL)(x)
    y = torch.rand(3, 64, 80)[:, :, ::2].to(dtype)  # not contiguous
    y[where] = value
    with pytest.raises(ValueError, match="NaN or infinite"):
        ProposalGenerator(**SMALL)([y])


def test_float_values_are_checked_as_the_front_end_reads_them(sample_image, monkeypatch):
    # the compiled front end counts the values outside [0, 1] as it reads a float image (one
    # read, not two), and the error still names the image, in a batch split between the
    # cores and in one image split by rows
    import reeb_torch._checks as checks

    calls = []
    real = checks._in_unit_range
    monkeypatch.setattr(checks, "_in_unit_range", lambda img: (calls.append(1), real(img))[1])
    x = sample_image[:, :200, :480].float() / 255
    gen = ProposalGenerator(**SMALL)
    gen([x, x.flip(-1), x])
    assert calls == []  # no separate pass over good images on the compiled front end
    for n, bad in ((1, 0), (3, 2), (4, 1)):
        for value, match in ((1.5, r"\[0, 1\]"), (float("nan"), "NaN or infinite"), (-0.25, r"\[0, 1\]")):
            batch = [x.clone() for _ in range(n)]
            batch[bad][1, 150, 300] = value  # in the lower half of the rows: the second core's part
            with pytest.raises(ValueError, match=f"image {bad}: .*{match}"):
                gen(batch)
    road = ProposalGenerator(road_score="reward", **SMALL)  # the colour path: checked apart
    y = x.clone()
    y[0, 5, 5] = 2.0
    with pytest.raises(ValueError, match=r"image 1: .*\[0, 1\]"):
        road([x, y])


def test_float_equal_to_uint8_over_255_gives_the_same_proposals(sample_image):
    # float RGB in [0, 1] that equals uint8 / 255 gives the uint8 input's boxes
    # and scores bit for bit, at full size, alone and in a batch, default and paper preset
    other = torch.flip(sample_image, dims=[2])
    for cfg in (ReebConfig(top_k=500), get_preset("paper").replace(top_k=300)):
        gen = ProposalGenerator(cfg)
        u8 = gen([sample_image, other])
        f32 = gen(torch.stack([sample_image, other]).float() / 255)
        alone = gen([sample_image.float().div(255)])
        for a, b in zip(u8 + u8[:1], f32 + alone):
            assert torch.equal(a["boxes"], b["boxes"]) and torch.equal(a["scores"], b["scores"])


def test_config_type_checked():
    with pytest.raises(TypeError, match="ReebConfig"):
        ProposalGenerator({"top_k": 3})  # type: ignore[arg-type]


@pytest.mark.cuda
def test_cuda_matches_cpu(crop):
    gen = ProposalGenerator(**SMALL)
    cpu = gen([crop])[0]
    gpu = gen([crop.cuda()])[0]
    assert gpu["boxes"].is_cuda
    n = min(50, cpu["boxes"].shape[0])
    torch.testing.assert_close(gpu["scores"][:n].cpu(), cpu["scores"][:n], rtol=1e-3, atol=1e-4)


def test_quota_splits_the_output_by_share():
    gen = ProposalGenerator(top_k=4)
    keep = torch.arange(10)  # already in score order
    region = torch.tensor([0, 0, 0, 0, 0, 1, 1, 0, 1, 2])
    share = torch.tensor([0.5, 0.5, 0.0])
    # quota: 2 for region 0, 2 for region 1, none for region 2
    assert gen.selection.suppression.quota(keep, region, share).tolist() == [0, 1, 5, 6]
    # a region with too few proposals leaves its places to the best of the rest
    share = torch.tensor([0.25, 0.0, 0.75])
    assert gen.selection.suppression.quota(keep, region, share).tolist() == [0, 1, 2, 9]


def test_stage_times_are_recorded(crop):
    gen = ProposalGenerator(**SMALL)
    gen.stage_times = {}
    gen([crop])
    # no road term in the default score: the road mask is not computed at all
    parts = {"ranker.prefilter", "ranker.features", "ranker.model", "ranker.class_head"}
    assert set(gen.stage_times) == {"edges", "groups", "regions", "scoring", "ranker", "nms"} | parts
    assert all(v >= 0 for v in gen.stage_times.values())
    # the learned ranking's parts lie within its stage
    assert sum(gen.stage_times[k] for k in parts) <= gen.stage_times["ranker"]
    gen = ProposalGenerator(**SMALL, ranker="none", road_score="reward")
    gen.stage_times = {}
    gen([crop])
    assert set(gen.stage_times) == {"edges", "groups", "road", "regions", "scoring", "nms"}


def test_batch_equals_single_on_odd_crops(sample_image):
    # two 400x150 crops alone and in a batch: the enclosed sums are float64 and exact (a
    # float32 scatter's order would make them differ from rank 42 on), so the batch cannot matter
    from pathlib import Path

    from reeb_torch import read_image

    other = read_image(Path(__file__).resolve().parents[1] / "examples" / "data" / "kitti_000008.png")
    x = torch.stack([sample_image[:, 200:350, :400], other[:, 200:350, :400]])
    gen = ProposalGenerator()
    both = gen(x)
    for i in range(2):
        one = gen(x[i: i + 1])[0]
        assert torch.equal(both[i]["boxes"], one["boxes"])
        assert torch.equal(both[i]["scores"], one["scores"])


@pytest.mark.parametrize("overrides", [
    {},
    {"location_score": "paper", "score_norm": "area", "min_edge_score": 0.01},
    {"window_geometry": "grid", "location_score": "none", "use_regions": False},
    {"shadow_score": "underneath", "shadow_strip": 0.2},
    {"shadow_score": "underneath", "shadow_power": 0.7, "shadow_margin": 0.3},
    {"vegetation_score": "none"},
    {"vegetation_score": "green", "vegetation_power": 1, "shadow_power": 0.7},
    {"vegetation_score": "green", "vegetation_power": 6, "shadow_score": "none"},
    {"vegetation_box": 1.0, "vegetation_power": 3},
    {"vegetation_box": 0.33},
])
def test_compiled_scoring_equals_the_tensor_path(sample_image, overrides):
    # the compiled CPU pass gives every window the very same float32 score as the
    # per-size tensor ops, -inf included (so the same candidates, boxes and ranking)
    from reeb_torch.selection import WindowScoring

    gen = ProposalGenerator(**overrides)
    seen = {}
    real = WindowScoring.score

    def spy(self, maps, grid):
        out = real(self, maps, grid)
        seen["applies"] = self.compiled_scoring_applies(maps, grid)
        seen["equal"] = torch.equal(out, self.score_torch(maps, grid))
        seen["finite"] = int(torch.isfinite(out).sum())
        return out

    crops = torch.stack([sample_image[:, 100:290, 200:800], sample_image[:, 150:340, 500:1100]])
    WindowScoring.score = spy  # type: ignore[method-assign]
    try:
        gen(crops)
    finally:
        WindowScoring.score = real  # type: ignore[method-assign]
    assert seen["applies"] and seen["equal"] and seen["finite"] > 1000


def test_scoring_falls_back_to_tensor_ops_when_a_term_needs_maps(crop):
    from reeb_torch.selection import ScoreMaps
    from reeb_torch.stages.groups import connected_groups

    e = torch.rand(1, 64, 96)
    g = connected_groups(e, 8)  # groups inside 8-px tiles: every window (>= 16 px) encloses them exactly
    default = ProposalGenerator(**SMALL)
    maps = ScoreMaps(e, g, (64, 96))
    grid = default.selection.window_grid(maps, default.selection.cut.region_bounds(96))
    assert default.selection.scoring.compiled_scoring_applies(maps, grid)
    for overrides in ({"road_score": "reward"},):
        gen = ProposalGenerator(**SMALL, **overrides)
        assert not gen.selection.scoring.compiled_scoring_applies(maps, grid), overrides
        assert gen([crop])[0]["boxes"].shape[0] > 0
    unbounded = connected_groups(e, None)  # one big component: no exact prefix-table sums
    assert not default.selection.scoring.compiled_scoring_applies(ScoreMaps(e, unbounded, (64, 96)), grid)


def test_compiled_selection_equals_the_tensor_path(sample_image):
    # eq. 9's per-region top-k: the compiled CPU pass and the stable sort choose the same windows
    from reeb_torch.selection import RegionCut

    for overrides in ({}, {"use_regions": False}, {"region_assign": "contained"}):
        gen = ProposalGenerator(**overrides)
        seen = {}
        real = RegionCut.region_cut

        def spy(self, scores, grid, share):
            out = real(self, scores, grid, share)
            r = self.settings
            per = r.candidates_per_region if r.use_regions else r.candidates_without_regions
            seen["equal"] = torch.equal(out, self.select_torch(scores, grid, (share * per).round().long()))
            seen["n"] = int(out.sum())
            return out

        RegionCut.region_cut = spy  # type: ignore[method-assign]
        try:
            gen([sample_image[:, 100:300, 100:900]])
        finally:
            RegionCut.region_cut = real  # type: ignore[method-assign]
        assert seen["equal"] and seen["n"] > 1000, overrides


@pytest.mark.parametrize("overrides", [{}, {"vegetation_score": "none"}, {"scale": 0.7}])
def test_compiled_front_end_gives_the_tensor_front_ends_proposals(sample_image, overrides):
    # the uint8 → grey (and green mask) compiled pass changes nothing downstream
    from reeb_torch.stages import edges as E

    crops = [sample_image[:, 100:290, 200:800], sample_image[:, 150:340, 500:1100]]
    gen = ProposalGenerator(**overrides)
    fast = gen(crops)
    real = E.working_gray
    E.working_gray = lambda *a, **k: None
    try:
        slow = gen(crops)
    finally:
        E.working_gray = real
    for a, b in zip(fast, slow):
        assert torch.equal(a["boxes"], b["boxes"]) and torch.equal(a["scores"], b["scores"])
        assert a["boxes"].shape[0] > 100


def test_per_size_tables_stay_cached_for_many_image_sizes(crop):
    """Each image size's tables are built once, however many sizes alternate (a cap on entries
    once cleared them all at every batch past 4 sizes x 8 keys) and the oldest size goes first."""
    from reeb_torch.selection import PLAN_GRIDS

    gen = ProposalGenerator(get_preset("default"), top_k=50)
    built: list[tuple] = []
    caches = (gen.selection.scoring.cache, gen.ranker.cache)  # the window selection's tables, the learned ranking's

    def counting(cached):
        return lambda key, grid, build: cached(key, grid, lambda: built.append((id(grid), key)) or build())

    for cache in caches:
        cache.grid_cached = counting(cache.grid_cached)
    sizes = [crop[:, : 160 - 4 * i, : 240 - 4 * i] for i in range(6)]
    for im in sizes:
        gen([im])
    first = len(built)
    assert first >= 6 * 4
    for im in sizes:  # every size again: nothing rebuilt
        gen([im])
    assert len(built) == first
    assert all(len(cache._plan_cache) == 6 <= PLAN_GRIDS for cache in caches)
