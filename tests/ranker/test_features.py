"""Per-box features of the learned ranking (reeb_torch.ranker.features): the columns against
sums over the maps' pixels computed another way (numpy slices), the compiled path against the
tensor path bit for bit, the window columns cached per grid, and the compiled prefilter
against the model's tensor ops."""

from __future__ import annotations

import math

import pytest
import torch

from reeb_torch import ProposalGenerator, ReebConfig
from reeb_torch.ranker import features as F
from reeb_torch.ranker.prefilter import prefilter_cpu


@pytest.fixture(scope="module")
def batch(sample_image):
    """A two-image batch taken to its candidates: the maps, the grid, V, the cut, the regions."""
    from reeb_torch._checks import check_images
    from reeb_torch.ranker import CandidateFeatures

    gen = ProposalGenerator(ReebConfig().training_free().replace(candidates_per_region=30000))
    x = check_images([sample_image, sample_image.flip(-1)], gen.min_side, gen.config.front_end, keep_uint8=True)
    front = gen.front_end(x)
    maps = front.maps
    bounds, entropy, share = gen.selection.regions(front.working.gray)
    sel, rk = gen.selection, CandidateFeatures.from_config(gen.config)
    grid = sel.window_grid(maps, bounds)
    scores = sel.score(maps, grid)
    chosen = sel.select(scores, grid, share)
    return dict(gen=gen, rk=rk, maps=maps, grid=grid, scores=scores, chosen=chosen, share=share, entropy=entropy)


def _tensor_features(b, bi, ni, cheap=False):
    rk, grid = b["rk"], b["grid"]
    region = grid.region_of[ni]
    boxes = grid.boxes[ni].round().long()
    return F.box_features(rk.box_maps(b["maps"]), boxes, bi, b["scores"][bi, ni], b["share"][bi, region],
                          b["entropy"][bi, region], cheap=cheap)


def test_names_count_and_cheap_prefix():
    names = F.feature_names(4)
    assert len(names) == len(set(names)) == 47
    assert names[: len(F.window_names(4))] == F.window_names(4)
    assert names[F.cheap_count(4) - 3: F.cheap_count(4)] == ("log_v", "region_share", "region_entropy")
    assert len(F.feature_names(2)) == 45


def test_columns_against_pixel_sums(batch):
    """Means over the box's pixels, its ring, its grid cells and its green pixels, from the maps."""
    b = batch
    bi, ni = torch.nonzero(b["chosen"], as_tuple=True)
    pick = torch.linspace(0, len(bi) - 1, 40).long()
    bi, ni = bi[pick], ni[pick]
    f = _tensor_features(b, bi, ni).double()
    col = {n: i for i, n in enumerate(F.feature_names(4))}
    edges, grey = b["maps"].edges.double().numpy(), b["maps"].grey.double().numpy()
    h, w = edges.shape[-2:]
    for k, (i, n) in enumerate(zip(bi.tolist(), ni.tolist())):
        x0, y0, x1, y1 = (int(v) for v in b["grid"].boxes[n].round().long())
        e, g = edges[i, y0:y1, x0:x1], grey[i, y0:y1, x0:x1]
        assert f[k, col["edge_inside"]] == pytest.approx(e.mean(), rel=1e-5, abs=1e-7)
        assert f[k, col["grey_mean"]] == pytest.approx(g.mean(), rel=1e-5)
        assert f[k, col["grey_std"]] == pytest.approx(g.std(), rel=1e-3, abs=1e-4)
        dx, dy = round((x1 - x0) * F.RING), round((y1 - y0) * F.RING)
        rx0, ry0, rx1, ry1 = max(x0 - dx, 0), max(y0 - dy, 0), min(x1 + dx, w), min(y1 + dy, h)
        ring_n = (rx1 - rx0) * (ry1 - ry0) - e.size
        ring = (edges[i, ry0:ry1, rx0:rx1].sum() - e.sum()) / ring_n if ring_n else 0.0
        assert f[k, col["edge_ring"]] == pytest.approx(ring, rel=1e-5, abs=1e-7)
        xs = [x0 + (x1 - x0) * q // 3 for q in range(4)]
        ys = [y0 + (y1 - y0) * q // 3 for q in range(4)]
        cell = edges[i, ys[1]:max(ys[2], ys[1] + 1), xs[1]:max(xs[2], xs[1] + 1)].mean()
        ref = max(e.mean(), 1e-6) + 1e-4
        assert f[k, col["edge_cell_11"]] == pytest.approx(math.log((cell + 1e-4) / ref), rel=1e-4, abs=1e-5)
        assert f[k, col["log_v"]] == pytest.approx(math.log(max(float(b["scores"][i, n]), 1e-6)), rel=1e-6)
        assert f[k, col["depth"]] == pytest.approx((y1 - 0.47 * h) / h, rel=1e-6, abs=1e-7)
    assert bool(torch.isfinite(f).all())


def test_compiled_path_is_the_tensor_path(batch):
    b = batch
    bi, ni = torch.nonzero(b["chosen"], as_tuple=True)
    window = b["rk"].window_table(b["maps"], b["grid"])
    for cheap in (False, True):
        ref = _tensor_features(b, bi, ni, cheap)
        got = F.box_features_cpu(b["rk"].box_maps(b["maps"]), b["grid"].boxes, window, b["scores"], b["share"],
                                 b["entropy"], b["grid"].region_of, bi, ni, cheap)
        assert got.dtype == torch.float32 and got.shape == ref.shape
        assert torch.equal(got, ref)


def test_box_features_need_the_tables_past_the_cheap_columns(batch):
    """BoxMaps made for the geometry alone serve the cheap columns, on both paths, and refuse
    the others with a message that says what is missing."""
    b = batch
    bi, ni = torch.nonzero(b["chosen"], as_tuple=True)
    bi, ni = bi[:50], ni[:50]
    geometry = b["rk"].box_maps(b["maps"], geometry_only=True)
    assert geometry.tables is None
    boxes = b["grid"].boxes[ni].round().long()
    region = b["grid"].region_of[ni]
    args = (b["scores"][bi, ni], b["share"][bi, region], b["entropy"][bi, region])
    assert torch.equal(F.box_features(geometry, boxes, bi, *args, cheap=True), _tensor_features(b, bi, ni, True))
    with pytest.raises(ValueError, match="integral images and the groups' enclosed-sum tables"):
        F.box_features(geometry, boxes, bi, *args)
    window = b["rk"].window_table(b["maps"], b["grid"])
    with pytest.raises(ValueError, match="geometry_only=True"):
        F.box_features_cpu(geometry, b["grid"].boxes, window, b["scores"], b["share"], b["entropy"],
                           b["grid"].region_of, bi, ni, False)


def test_window_table_is_cached_per_grid(batch):
    b = batch
    t1 = b["rk"].window_table(b["maps"], b["grid"])
    assert t1 is b["rk"].window_table(b["maps"], b["grid"])
    assert t1.shape == (b["grid"].count, len(F.window_names(4)))


def test_compiled_prefilter_matches_the_model(batch):
    from reeb_torch.ranker import BoxRanker

    b = batch
    torch.manual_seed(0)
    model = BoxRanker(F.feature_names(4)).eval()
    bi, ni = torch.nonzero(b["chosen"], as_tuple=True)
    with torch.no_grad():
        ref = model.prefilter_scores(_tensor_features(b, bi, ni, cheap=True))
        got = b["rk"].prefilter(model, b["maps"], b["grid"], b["scores"], b["share"], b["entropy"], bi, ni)
    assert got.shape == ref.shape
    assert torch.allclose(got, ref, rtol=1e-4, atol=1e-5)


def test_prefilter_cpu_by_hand():
    """w_out · relu(table[ni] + w_dyn · d) + b_out with d the standardised (log V, share, entropy)."""
    table = torch.tensor([[1.0, -2.0], [0.5, 0.25]])
    scores = torch.tensor([[math.e, 1.0]])
    share, entropy = torch.tensor([[0.5]]), torch.tensor([[4.0]])
    out = prefilter_cpu(table, scores, share, entropy, torch.tensor([0, 0]), torch.tensor([0, 0]),
                          torch.tensor([1, 0]), torch.tensor([0.0, 0.0, 0.0]), torch.tensor([1.0, 1.0, 2.0]),
                          torch.tensor([[1.0, 0.0, 0.0], [0.0, 2.0, 1.0]]), torch.tensor([3.0, -1.0]), 0.5)
    # window 1, V = 1: d = (0, 0.5, 2): hidden (0.5, 0.25 + 1 + 2) -> 3·0.5 − 3.25 + 0.5
    # window 0, V = e: d = (1, 0.5, 2): hidden (2, −2 + 3 = 1) -> 3·2 − 1 + 0.5
    assert out.tolist() == pytest.approx([-1.25, 5.5])
