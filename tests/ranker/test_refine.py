"""The box refiner: its features, its place in the weights file, its fit, its step in the generator."""

from __future__ import annotations

import copy
import json
from types import SimpleNamespace

import pytest
import torch
from torchvision.ops import box_iou

from reeb_torch import ProposalGenerator, ReebConfig
from reeb_torch.ranker import frames as F
from reeb_torch.ranker import fit as RF
from reeb_torch.ranker import cv as fit_cv
from reeb_torch.tuning import Frames
from reeb_torch.ranker import (NOT_SEEN_BY_RANKER, BoxRanker, BoxRefiner, RankerWeightsError, load_ranker,
                               offset_targets, refine_feature_names, refine_features, save_ranker)
from reeb_torch.ranker.features import feature_names
from reeb_torch.ranker.refine import OFFSETS, apply_offsets, merge_refined


def _integral(x: torch.Tensor) -> torch.Tensor:
    ii = torch.zeros(x.shape[0], x.shape[1] + 1, x.shape[2] + 1, dtype=torch.float64)
    ii[:, 1:, 1:] = x.double().cumsum(2).cumsum(1)
    return ii


def _rectangle_image(rects: list[tuple[int, int, int, int]], h: int = 120, w: int = 200) -> tuple:
    """Edge and grey maps of one image holding the outlines of ``rects`` (bright inside)."""
    edges = torch.zeros(1, h, w)
    grey = torch.full((1, h, w), 0.2)
    for x1, y1, x2, y2 in rects:
        edges[0, y1:y2, x1] = edges[0, y1:y2, x2 - 1] = 1.0
        edges[0, y1, x1:x2] = edges[0, y2 - 1, x1:x2] = 1.0
        grey[0, y1:y2, x1:x2] = 0.8
    return _integral(edges), _integral(grey)


def test_features_have_their_shape_and_the_true_side_has_the_strongest_edge():
    ii_e, ii_g = _rectangle_image([(60, 30, 140, 90)])
    boxes = torch.tensor([[60.0, 30.0, 140.0, 90.0], [52.0, 36.0, 132.0, 96.0]])
    x = refine_features(ii_e, ii_g, boxes, torch.zeros(2, dtype=torch.long), 0.5)
    names = refine_feature_names()
    assert x.shape == (2, len(names)) and x.dtype == torch.float32 and len(set(names)) == len(names)
    assert torch.isfinite(x).all()
    n = len(OFFSETS)
    strips = x[0, : 4 * n].reshape(4, n)  # left, top, right, bottom
    centre = OFFSETS.index(0.0)
    # the strip on each side of the box that is the rectangle: the strongest
    assert (strips.argmax(1) == centre).all()
    # a box 8 px left of it and 6 below: the strongest left strip 0.1 of its 80 px right of
    # its side, the strongest top strip 0.1 of its 60 px above
    shifted = x[1, : 4 * n].reshape(4, n)
    assert OFFSETS[int(shifted[0].argmax())] == 0.1 and OFFSETS[int(shifted[1].argmax())] == -0.1
    # the brightness profile: the band above the box darker than the box, its middle row brighter
    grey_rows = x[0, names.index("grey_row_0"): names.index("grey_row_0") + 5]
    assert grey_rows[0] < 0 and grey_rows[2] > grey_rows[0] and grey_rows[0] == grey_rows[4]


def test_no_boxes_give_no_rows():
    ii_e, ii_g = _rectangle_image([])
    x = refine_features(ii_e, ii_g, torch.zeros(0, 4), torch.zeros(0, dtype=torch.long), 0.5)
    assert x.shape == (0, len(refine_feature_names()))


def small_ranker(**heads) -> BoxRanker:
    """A small ranker with random weights (seed 0) and the optional ``heads`` given
    (``refine_hidden=``, ``quality_hidden=``)."""
    torch.manual_seed(0)
    m = BoxRanker(feature_names(4), hidden=(8,), prefilter=(4,), classes=("Car", "Pedestrian"),
                  class_hidden=(4,), **heads)
    for p in m.parameters():
        p.data.normal_()
    return m.eval()


def _ranker(refine: bool) -> BoxRanker:
    return small_ranker(refine_hidden=(8, 8) if refine else None)


@pytest.mark.parametrize("refine", [False, True])
def test_weights_round_trip_with_and_without_a_refiner(tmp_path, refine):
    m = _ranker(refine)
    path = save_ranker(m, tmp_path / "m.safetensors")
    back = load_ranker(str(path))
    assert (back.refiner is None) == (not refine)
    a, b = m.state_dict(), back.state_dict()
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    assert (b"refine_hidden" in path.read_bytes()) == refine


def _rewrite(src, dst, change_tensor=None, change_meta=None):
    from safetensors import safe_open
    from safetensors.torch import save_file

    with safe_open(str(src), framework="pt") as f:
        meta = f.metadata()
        tensors = {k: f.get_tensor(k) for k in f.keys()}
    if change_tensor:
        change_tensor(tensors)
    if change_meta:
        info = json.loads(meta["reeb-ranker"])
        change_meta(info)
        meta["reeb-ranker"] = json.dumps(info)
    save_file(tensors, str(dst), metadata=meta)
    return dst


@pytest.mark.parametrize("damage, message", [
    (dict(change_tensor=lambda t: t["refiner.mlp.2.weight"].__setitem__((0, 0), float("nan"))),
     "'refiner.mlp.2.weight' holds 1 value that is not finite"),
    (dict(change_tensor=lambda t: t.update({"refiner.mlp.4.bias": torch.zeros(3)})),
     "'refiner.mlp.4.bias' has shape [3], expected [4]"),
    (dict(change_tensor=lambda t: t["refiner.scale"].__setitem__(0, 0.0)), "'refiner.scale' is 0.0"),
    (dict(change_tensor=lambda t: t.pop("refiner.mean")), "'refiner.mean' is missing"),
    (dict(change_meta=lambda i: i.update(refine_hidden="wide")), "'refine_hidden' is \"wide\""),
    (dict(change_meta=lambda i: i.update(refine_features=i["refine_features"][:-1])), "box refiner reads 48"),
    (dict(change_meta=lambda i: i.pop("refine_hidden")), "'refiner.mean' is not one of the model's"),
])
def test_a_damaged_refiner_is_refused_in_one_line(tmp_path, damage, message):
    good = save_ranker(_ranker(True), tmp_path / "good.safetensors")
    bad = _rewrite(good, tmp_path / "bad.safetensors", **damage)
    with pytest.raises(RankerWeightsError) as e:
        load_ranker(str(bad))
    assert message in str(e.value) and "\n" not in str(e.value)


def _training_rows(seed: int, count: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Refiner rows of boxes jittered about rectangles of several sizes and places."""
    gen = torch.Generator().manual_seed(seed)
    xs, ys = [], []
    for _ in range(count):
        w, h = (torch.randint(30, 80, (2,), generator=gen)).tolist()
        x1, y1 = torch.randint(10, 200 - w - 10, (1,), generator=gen).item(), torch.randint(
            10, 120 - h - 10, (1,), generator=gen).item()
        rect = torch.tensor([[x1, y1, x1 + w, y1 + h]], dtype=torch.float32)
        ii_e, ii_g = _rectangle_image([(x1, y1, x1 + w, y1 + h)])
        jitter = (torch.rand(16, 4, generator=gen) - 0.5) * 0.4 * torch.tensor([w, h, w, h])
        boxes = rect + jitter
        xs.append(refine_features(ii_e, ii_g, boxes, torch.zeros(16, dtype=torch.long), 0.5))
        ys.append(offset_targets(boxes, rect.expand(16, 4)))
    return torch.cat(xs), torch.cat(ys)


_TINY = RF.FitOptions(refine_hidden=(32, 32), refine_epochs=40, refine_batch=128, refine_lr=1e-2)


def test_a_tiny_fit_moves_a_shifted_box_towards_the_rectangle():
    x, y = _training_rows(0, 40)
    refiner = RF.fit_refiner(x, y, _TINY)
    rect = torch.tensor([[70.0, 35.0, 130.0, 85.0]])
    ii_e, ii_g = _rectangle_image([(70, 35, 130, 85)])
    shifted = rect + torch.tensor([[7.0, -5.0, 7.0, -5.0]])
    moved = refiner.refine(ii_e, ii_g, shifted, torch.zeros(1, dtype=torch.long), 0.5, (120, 200))
    assert float(box_iou(moved, rect)) > float(box_iou(shifted, rect)) + 0.05


def test_the_fit_is_deterministic():
    x, y = _training_rows(1, 6)
    opts = RF.FitOptions(refine_hidden=(16,), refine_epochs=3, refine_batch=32)
    a, b = RF.fit_refiner(x, y, opts), RF.fit_refiner(x, y, opts)
    assert all(torch.equal(p, q) for p, q in zip(a.state_dict().values(), b.state_dict().values()))
    c = RF.fit_refiner(x, y, RF.FitOptions(refine_hidden=(16,), refine_epochs=3, refine_batch=32, seed=1))
    assert not torch.equal(a.mlp[0].weight, c.mlp[0].weight)


def test_refined_boxes_stay_in_the_image_and_valid():
    boxes = torch.tensor([[5.0, 5.0, 50.0, 40.0], [150.0, 80.0, 199.0, 119.0], [10.0, 10.0, 20.0, 20.0]])
    offsets = torch.tensor([[-2.0, -2.0, 0.5, 0.5], [0.1, 0.1, 3.0, 3.0], [2.0, 0.0, -2.0, 0.0]])
    out = apply_offsets(boxes, offsets, (120, 200))
    assert (out[:, 0] >= 0).all() and (out[:, 1] >= 0).all() and (out[:, 2] <= 200).all() and (out[:, 3] <= 120).all()
    assert (out[:, 2] > out[:, 0]).all() and (out[:, 3] > out[:, 1]).all()
    assert torch.equal(out[2], boxes[2])  # turned inside out: kept as it was


def test_merge_puts_the_refined_boxes_beside_their_originals():
    r = {"boxes": torch.arange(16.0).reshape(4, 4), "scores": torch.tensor([4.0, 3.0, 2.0, 1.0]),
         "labels": torch.tensor([0, 1, 0, 1])}
    refined = -torch.arange(8.0).reshape(2, 4) - 1
    inter = merge_refined(r, refined, "interleave", 5)
    assert torch.equal(inter["boxes"], torch.stack([r["boxes"][0], refined[0], r["boxes"][1], refined[1],
                                                   r["boxes"][2]]))
    assert inter["scores"].tolist() == [4.0, 4.0, 3.0, 3.0, 2.0] and inter["labels"].tolist() == [0, 0, 1, 1, 0]
    first = merge_refined(r, refined, "refined_first", 3)
    assert torch.equal(first["boxes"], torch.stack([refined[0], refined[1], r["boxes"][0]]))
    same = {"boxes": torch.tensor([[0.0, 0, 10, 10], [50, 50, 60, 60]]), "scores": torch.tensor([2.0, 1.0])}
    nms = merge_refined(same, torch.tensor([[0.0, 0, 10, 10.5]]), "interleave", 10, nms_iou=0.9)
    assert nms["boxes"].tolist() == [[0, 0, 10, 10], [50, 50, 60, 60]]  # the near-copy made room


def test_refine_settings_act_after_the_model():
    assert {"refine_top", "refine_order", "refine_steps", "refine_nms"} <= set(NOT_SEEN_BY_RANKER)
    assert ReebConfig().refine_top == 0
    with pytest.raises(ValueError, match="refine_steps"):
        ReebConfig(refine_steps=0)


@pytest.fixture(scope="module")
def refiner_file(tmp_path_factory):
    """The shipped model with a seeded, untrained refiner added."""
    model = copy.deepcopy(load_ranker("kitti"))
    model.meta = copy.deepcopy(load_ranker("kitti").meta)
    torch.manual_seed(0)
    model.refiner = BoxRefiner(refine_feature_names(), (8,))
    for p in model.refiner.mlp.parameters():
        p.data.normal_(0, 0.1)
    path = tmp_path_factory.mktemp("refiner") / "kitti_refine.safetensors"
    return str(save_ranker(model, path, model.meta.get("provenance"), model.meta.get("config")))


def test_refine_top_0_gives_todays_boxes_and_refine_top_adds_refined_ones(sample_image, refiner_file):
    image = sample_image[:, :160, :480]
    today = ProposalGenerator(ReebConfig(top_k=300))([image])[0]
    off = ProposalGenerator(ReebConfig(top_k=300, ranker=refiner_file))([image])[0]
    assert all(torch.equal(today[k], off[k]) for k in today)
    gen = ProposalGenerator(ReebConfig(top_k=300, ranker=refiner_file, refine_top=100))
    gen.stage_times = {}
    on = gen([image])[0]
    assert gen.stage_times.get("ranker.refine", 0) > 0
    b = on["boxes"]
    assert len(b) == 300 and torch.equal(b[0::2][:100], today["boxes"][:100])
    assert torch.equal(b[200:], today["boxes"][100:200])
    assert not torch.equal(b[1::2][:100], today["boxes"][:100])
    assert torch.equal(on["labels"][1::2][:100], today["labels"][:100])
    h, w = image.shape[-2:]
    assert (b[:, 0] >= 0).all() and (b[:, 1] >= 0).all() and (b[:, 2] <= w).all() and (b[:, 3] <= h).all()
    assert (b[:, 2] > b[:, 0]).all() and (b[:, 3] > b[:, 1]).all()


def test_training_free_and_paper_ignore_refine_top(sample_image):
    from reeb_torch import get_preset

    image = sample_image[:, :160, :480]
    for preset in ("training-free", "paper"):
        cfg = get_preset(preset)
        a = ProposalGenerator(cfg)([image])[0]["boxes"]
        assert torch.equal(a, ProposalGenerator(cfg.replace(refine_top=500))([image])[0]["boxes"])


def test_a_ranker_without_a_refiner_warns_that_refine_top_is_ignored():
    with pytest.warns(UserWarning, match="refine_top is ignored"):
        ProposalGenerator(ReebConfig(refine_top=100))


def test_the_refiner_is_fitted_only_on_the_training_side(monkeypatch, tmp_path):
    """Every held-out model's refiner sees the rows of its training frames only: the frames of
    the held-out block (and their drive neighbours) give it none."""
    names = feature_names(4)
    n = 8
    frames = Frames([torch.rand(3, 24, 80) * (i + 1) / n for i in range(n)], [torch.zeros(0, 4)] * n,
                    [torch.zeros(0, dtype=torch.long)] * n, ("Car", "Pedestrian"),
                    [f"d{i // 4}_{i:06d}" for i in range(n)], ["a"] * n)
    gen = torch.Generator().manual_seed(0)
    samples = [RF.Sample(torch.randn(6, len(names), generator=gen), torch.tensor([1.0, 1, 0, 0, 0, 0]), torch.ones(6),
                        torch.tensor([0, 1, -1, -1, -1, -1]), torch.full((3, len(refine_feature_names())), float(i)),
                        torch.zeros(3, 4)) for i in range(n)]
    seen: list[set[int]] = []

    def recording(x, y, opts):
        seen.append({int(v) for v in x[:, 0].tolist()})
        return BoxRefiner(refine_feature_names(), opts.refine_hidden)

    monkeypatch.setattr(RF, "fit_refiner", recording)
    opts = RF.FitOptions(hidden=(4,), prefilter=None, class_hidden=None, epochs=1, refine_hidden=(4,))
    cache = SimpleNamespace(frames=frames)
    with fit_cv._HeldOutModels(cache, names, samples, opts, 4, gap=n, scratch=tmp_path) as models:
        for f in range(len(models.blocks)):
            model = load_ranker(str(models.fit(f)))
            assert model.refiner is not None
            train = F.training_frames(models.blocks, f, frames.ids, frames.folders, models.similar, n)
            assert seen[-1] == set(train) and not seen[-1] & set(models.blocks[f])


def test_the_compiled_features_are_the_tensor_ops():
    from reeb_torch.ranker.refine import refine_features_tensor

    g = torch.Generator().manual_seed(0)
    ii_e = _integral(torch.rand(2, 60, 90, generator=g))
    ii_g = _integral(torch.rand(2, 60, 90, generator=g))
    corner = torch.rand(300, 2, generator=g) * torch.tensor([80.0, 50.0])
    boxes = torch.cat([corner, corner + torch.rand(300, 2, generator=g) * 40 + 1], 1)
    boxes[0] = torch.tensor([0.0, 0.0, 90.0, 60.0])
    bi = torch.randint(0, 2, (300,), generator=g)
    compiled = refine_features(ii_e, ii_g, boxes, bi, 0.47)
    assert torch.allclose(compiled, refine_features_tensor(ii_e, ii_g, boxes, bi, 0.47), atol=1e-5, rtol=0)
    assert compiled[0, -4:].tolist() == [1.0, 1.0, 1.0, 1.0]  # the whole image touches every border


def test_merge_refines_the_boxes_named_and_keeps_their_hints():
    r = {"boxes": torch.arange(16.0).reshape(4, 4), "scores": torch.tensor([4.0, 3.0, 2.0, 1.0]),
         "labels": torch.tensor([0, 1, 0, 1])}
    refined = -torch.arange(8.0).reshape(2, 4) - 1
    which = torch.tensor([1, 3])
    inter = merge_refined(r, refined, "interleave", 10, which=which)
    assert torch.equal(inter["boxes"], torch.stack([r["boxes"][0], r["boxes"][1], refined[0], r["boxes"][2],
                                                   r["boxes"][3], refined[1]]))
    assert inter["labels"].tolist() == [0, 1, 1, 0, 1, 1]
    first = merge_refined(r, refined, "refined_first", 3, which=which)
    assert torch.equal(first["boxes"], torch.stack([refined[0], refined[1], r["boxes"][0]]))
    assert first["scores"].tolist() == [3.0, 1.0, 4.0]


def test_refine_class_refines_only_the_boxes_hinted_as_it(sample_image, refiner_file):
    image = sample_image[:, :160, :480]
    today = ProposalGenerator(ReebConfig(top_k=300))([image])[0]
    car = ProposalGenerator(ReebConfig(top_k=300, ranker=refiner_file, refine_top=20, refine_class="Car",
                                       refine_order="refined_first"))
    out = car([image])[0]
    cars = torch.nonzero(today["labels"] == car.classes.index("Car")).squeeze(1)[:20]
    assert len(cars) and torch.equal(out["labels"][: len(cars)], today["labels"][cars])
    assert torch.equal(out["boxes"][len(cars):], today["boxes"][: 300 - len(cars)])
    with pytest.raises(ValueError, match="refine_class 'Bus' is not a class"):
        ProposalGenerator(ReebConfig(ranker=refiner_file, refine_top=20, refine_class="Bus"))


@pytest.mark.cuda
def test_cuda_refinement_matches_the_cpu(sample_image, refiner_file):
    cfg = ReebConfig(ranker=refiner_file, refine_top=200)
    cpu = ProposalGenerator(cfg)([sample_image])[0]
    gpu = ProposalGenerator(cfg).to("cuda")([sample_image.cuda()])[0]
    iou = box_iou(cpu["boxes"][:400], gpu["boxes"][:400].cpu()).amax(1)
    assert float((iou > 0.99).float().mean()) > 0.9  # the ranking rounds differently there


def test_replace_puts_each_refined_box_in_its_originals_place():
    r = {"boxes": torch.arange(16.0).reshape(4, 4), "scores": torch.tensor([4.0, 3.0, 2.0, 1.0])}
    refined = -torch.arange(8.0).reshape(2, 4) - 1
    out = merge_refined(r, refined, "replace", 3, which=torch.tensor([1, 3]))
    assert torch.equal(out["boxes"], torch.stack([r["boxes"][0], refined[0], r["boxes"][2]]))
    assert out["scores"].tolist() == [4.0, 3.0, 2.0] and torch.equal(r["boxes"], torch.arange(16.0).reshape(4, 4))
