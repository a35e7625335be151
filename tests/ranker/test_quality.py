"""The localisation-quality head: its training rows, its fit (after the ranking, which it
leaves as it is), its place in the weights file, its step in the generator (rank_quality)."""

from __future__ import annotations

import copy
import json

import numpy as np
import pytest
import torch

from reeb_torch import ProposalGenerator, ReebConfig
from reeb_torch.ranker import frames as F
from reeb_torch.ranker import fit as RF
from reeb_torch.ranker import NOT_SEEN_BY_RANKER, BoxRanker, RankerWeightsError, load_ranker, save_ranker
from reeb_torch.ranker.features import feature_names

from tests.ranker.test_refine import small_ranker  # noqa: E402


def test_quality_rows_by_hand():
    """With a quality head, the candidates of an object from IoU 0.5 join the rows (the near
    misses with target NaN and weight 0, for the quality head only); each row's IoU, and its
    object's rows weigh 1 together; the ranking's rows are those of the fit without it."""
    gt = torch.tensor([[0.0, 0.0, 10.0, 10.0]])
    boxes = torch.tensor([[0.0, 0.0, 10.0, 10.0],     # IoU 1: positive
                          [0.0, 0.0, 10.0, 12.0],     # IoU 0.83: positive
                          [0.0, 0.0, 10.0, 17.0],     # IoU 0.59: a near miss
                          [0.0, 0.0, 10.0, 25.0],     # IoU 0.4: negative
                          [50.0, 50.0, 60.0, 60.0]])  # background: negative
    feats = torch.arange(5.0)[:, None].expand(5, 3)
    none = torch.zeros(0, 4)
    plain = F.frame_sample(feats, boxes, gt, torch.tensor([2]), none, RF.FitOptions(negatives=1.0),
                           np.random.default_rng(0))
    s = F.frame_sample(feats, boxes, gt, torch.tensor([2]), none, RF.FitOptions(negatives=1.0, quality_hidden=(8,)),
                       np.random.default_rng(0))
    assert s.features[:, 0].tolist() == [0.0, 1.0, 3.0, 4.0, 2.0]
    assert s.target[:4].tolist() == plain.target.tolist() == [1.0, 1.0, 0.0, 0.0] and np.isnan(float(s.target[4]))
    assert s.weight.tolist() == [0.5, 0.5, 1.0, 1.0, 0.0] and s.label.tolist() == [2, 2, -1, -1, 2]
    torch.testing.assert_close(s.iou, torch.tensor([1.0, 10 / 12, 0.4, 0.0, 10 / 17]))
    torch.testing.assert_close(s.object_weight, torch.tensor([1 / 3, 1 / 3, 0.0, 0.0, 1 / 3]))
    assert len(plain.iou) == 0 and len(plain.object_weight) == 0


def _samples(seed: int, n: int = 6000) -> list[RF.Sample]:
    """Rows whose first column says object or not and whose second says how tight a box
    on an object is (its IoU)."""
    g = torch.Generator().manual_seed(seed)
    x = torch.randn(n, 47, generator=g)
    iou = (0.5 + 0.2 * x[:, 1]).clamp(0.0, 1.0)
    obj = x[:, 0] > 0.5
    target = torch.where(obj & (iou >= 0.7), 1.0, torch.where(obj, float("nan"), 0.0))
    weight = torch.where(torch.isnan(target), 0.0, 1.0)
    label = torch.where(obj, 0, -1)
    s = RF.Sample(x, target, weight, label)
    s.iou = torch.where(obj, iou, 0.0)
    s.object_weight = torch.where(obj & (iou >= 0.5), 1.0, 0.0)
    return [s]


def test_the_quality_head_learns_how_tight_a_box_is_and_leaves_the_ranking_alone():
    opts = RF.FitOptions(epochs=8, hidden=(8,), batch=512, class_hidden=(4,), quality_batch=128)
    plain = RF.fit_ranker(_samples(0), feature_names(4), opts, ("Car", "Pedestrian"))
    with_q = RF.fit_ranker(_samples(0), feature_names(4), RF.FitOptions(**{**vars(opts), "quality_hidden": (8,)}),
                          ("Car", "Pedestrian"))
    again = RF.fit_ranker(_samples(0), feature_names(4), RF.FitOptions(**{**vars(opts), "quality_hidden": (8,)}),
                         ("Car", "Pedestrian"))
    assert plain.quality is None and with_q.quality_hidden == (8,)
    for name, p in plain.state_dict().items():  # the ranking, the prefilter, the class head: the same bits
        assert torch.equal(p, with_q.state_dict()[name]), name
    assert all(torch.equal(p, q) for p, q in zip(with_q.state_dict().values(), again.state_dict().values()))
    test = _samples(1)[0]
    on = test.object_weight > 0
    q = with_q.quality_logits(test.features[on])
    assert float(torch.corrcoef(torch.stack([q, test.iou[on]]))[0, 1]) > 0.8
    torch.testing.assert_close(q, with_q.quality(with_q.standardise(test.features[on])).squeeze(1))


def _ranker(quality: bool) -> BoxRanker:
    return small_ranker(quality_hidden=(6,) if quality else None)


@pytest.mark.parametrize("quality", [False, True])
def test_weights_round_trip_with_and_without_a_quality_head(tmp_path, quality):
    m = _ranker(quality)
    path = save_ranker(m, tmp_path / "m.safetensors")
    back = load_ranker(str(path))
    assert (back.quality is None) == (not quality) and back.quality_hidden == m.quality_hidden
    a, b = m.state_dict(), back.state_dict()
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    assert (b"quality_hidden" in path.read_bytes()) == quality


@pytest.mark.parametrize("change, message", [
    (lambda info: info.update(quality_hidden="wide"), "'quality_hidden' is \"wide\""),
    (lambda info: info.pop("quality_hidden"), "'quality.0.bias' is not one of the model's"),
    (lambda info: info.update(quality_hidden=[7]), "'quality.0.weight' has shape [6, 47], expected [7, 47]"),
])
def test_a_damaged_quality_head_is_refused_in_one_line(tmp_path, change, message):
    from safetensors import safe_open
    from safetensors.torch import save_file

    good = save_ranker(_ranker(True), tmp_path / "good.safetensors")
    with safe_open(str(good), framework="pt") as f:
        meta, tensors = f.metadata(), {k: f.get_tensor(k) for k in f.keys()}
    info = json.loads(meta["reeb-ranker"])
    change(info)
    meta["reeb-ranker"] = json.dumps(info)
    save_file(tensors, str(tmp_path / "bad.safetensors"), metadata=meta)
    with pytest.raises(RankerWeightsError) as e:
        load_ranker(str(tmp_path / "bad.safetensors"))
    assert message in str(e.value) and "\n" not in str(e.value)


@pytest.fixture(scope="module")
def quality_file(tmp_path_factory):
    """The shipped model with a seeded, untrained quality head added."""
    model = copy.deepcopy(load_ranker("kitti"))
    model.meta = copy.deepcopy(load_ranker("kitti").meta)
    torch.manual_seed(0)
    model.set_quality((8,))
    for p in model.quality.parameters():
        p.data.normal_(0, 0.5)
    path = tmp_path_factory.mktemp("quality") / "kitti_quality.safetensors"
    return str(save_ranker(model, path, model.meta.get("provenance"), model.meta.get("config")))


def test_rank_quality_adds_the_heads_sigmoid_to_the_logit(sample_image, quality_file):
    """rank_quality 0 (the default) gives the shipped model's boxes; above 0 each candidate's
    score is its logit plus rank_quality times the head's sigmoid, which reorders them."""
    image = sample_image[:, :160, :480]
    today = ProposalGenerator(ReebConfig(top_k=300))([image])[0]
    off = ProposalGenerator(ReebConfig(top_k=300, ranker=quality_file))([image])[0]
    assert all(torch.equal(today[k], off[k]) for k in today)
    gen = ProposalGenerator(ReebConfig(top_k=300, ranker=quality_file, rank_quality=3.0))
    on = gen([image])[0]
    assert not torch.equal(on["boxes"], today["boxes"])
    assert bool((on["scores"][:-1] >= on["scores"][1:]).all())
    lo, hi = float(today["scores"].min()), float(today["scores"].max())
    assert lo <= float(on["scores"].max()) <= hi + 3.0


def test_rank_quality_acts_after_the_model_and_warns_without_a_head(sample_image):
    from reeb_torch import get_preset

    assert "rank_quality" in NOT_SEEN_BY_RANKER and ReebConfig().rank_quality == 0
    with pytest.warns(UserWarning, match="rank_quality is ignored"):
        ProposalGenerator(ReebConfig(rank_quality=1.0))
    with pytest.raises(ValueError, match="rank_quality"):
        ReebConfig(rank_quality=-1.0)
    image = sample_image[:, :160, :480]
    cfg = get_preset("training-free")
    assert torch.equal(ProposalGenerator(cfg)([image])[0]["boxes"],
                       ProposalGenerator(cfg.replace(rank_quality=2.0))([image])[0]["boxes"])
