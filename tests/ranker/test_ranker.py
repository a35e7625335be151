"""The learned ranking (reeb_torch.ranker, ReebConfig.ranker): the model's contract, its
weights files (safetensors, read back the same; missing, corrupt, foreign and stale files
refused in one line naming the file), the shipped model, and the generator with a ranker
(the output contract, one image alone as in a batch, 'none' is the training-free path)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from reeb_torch import ProposalGenerator, ReebConfig
from reeb_torch.ranker import (ORIENTATION_NAMES, SHIPPED, BoxRanker, RankerWeightsError, load_ranker, save_ranker,
                               shipped_path)
from reeb_torch.ranker.features import FEATURES_VERSION, feature_names


def _model(seed: int = 0, **kw) -> BoxRanker:
    torch.manual_seed(seed)
    return BoxRanker(feature_names(4), **kw).eval()


def test_model_contract():
    m = _model()
    x = torch.randn(5, 47)
    assert m(x).shape == (5,) and m(x).dtype == torch.float32
    assert m.prefilter_scores(x[:, : m.cheap]).shape == (5,)
    with pytest.raises(ValueError, match=r"\[K, 47\]"):
        m(torch.randn(5, 46))
    with pytest.raises(ValueError, match="no prefilter"):
        _model(prefilter=None).prefilter_scores(x[:, :18])
    two = BoxRanker(feature_names(4), members=2)
    assert torch.allclose(two(x), (two.members[0](two.standardise(x)) + two.members[1](two.standardise(x))).squeeze(1) / 2)


@pytest.mark.parametrize("members", [1, 2])
def test_rank_is_forward_with_the_standardisation_folded_in(members, monkeypatch):
    """rank(): the inference path the generator takes gives forward()'s logits to float32
    rounding, on features far from standardised (as the real ones are), and takes no grad."""
    from reeb_torch.ranker import model as model_module

    m = _model(members=members)
    torch.manual_seed(1)
    m.mean.copy_(torch.randn(47) * 50)
    m.scale.copy_(torch.rand(47) * 20 + 0.1)
    x = torch.randn(300, 47) * m.scale + m.mean
    got = m.rank(x)
    assert got.shape == (300,) and got.dtype == torch.float32 and not got.requires_grad
    torch.testing.assert_close(got, m(x), rtol=1e-5, atol=1e-4)
    # taken in blocks of rows (the last one short): the same logits
    monkeypatch.setattr(model_module, "RANK_ROWS", 64)
    torch.testing.assert_close(m.rank(x), got, rtol=1e-6, atol=1e-6)
    assert m.rank(x[:0]).shape == (0,)
    with pytest.raises(ValueError, match=r"\[K, 47\]"):
        m.rank(torch.randn(5, 46))


def test_class_logits_are_the_head_with_the_standardisation_folded_in(monkeypatch):
    """class_logits(): the class head's logits as the head computes them on standardised
    features (to float32 rounding), in blocks of rows too; class_probs() is their softmax."""
    from reeb_torch.ranker import model as model_module

    m = _model(classes=("Car", "Pedestrian", "Cyclist"))
    torch.manual_seed(2)
    m.mean.copy_(torch.randn(47) * 50)
    m.scale.copy_(torch.rand(47) * 20 + 0.1)
    x = torch.randn(300, 47) * m.scale + m.mean
    got = m.class_logits(x)
    assert got.shape == (300, 3) and got.dtype == torch.float32 and not got.requires_grad
    with torch.no_grad():
        want = m.classifier(m.standardise(x))
    torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-4)
    torch.testing.assert_close(m.class_probs(x), torch.softmax(want, 1), rtol=1e-5, atol=1e-5)
    monkeypatch.setattr(model_module, "RANK_ROWS", 64)
    torch.testing.assert_close(m.class_logits(x), got, rtol=1e-6, atol=1e-6)
    with pytest.raises(ValueError, match="no class head"):
        _model().class_logits(x)


def test_weights_round_trip(tmp_path):
    m = _model(3, hidden=(8,), members=2)
    p = save_ranker(m, tmp_path / "r.safetensors", provenance={"frames": 2}, config={"horizon": 0.5})
    got = load_ranker(str(p))
    assert got.hidden == (8,) and len(got.members) == 2 and got.prefilter_hidden == (16,)
    assert all(torch.equal(a, b) for a, b in zip(m.state_dict().values(), got.state_dict().values()))
    assert got.meta == {"provenance": {"frames": 2}, "config": {"horizon": 0.5}}
    save_ranker(m, tmp_path / "s.safetensors", provenance={"frames": 2}, config={"horizon": 0.5})
    assert (tmp_path / "r.safetensors").read_bytes() == (tmp_path / "s.safetensors").read_bytes()
    assert not any(p.requires_grad for p in got.parameters())
    hinted = _model(4, classes=("Car", "Pedestrian"), class_hidden=(6,))
    got = load_ranker(str(save_ranker(hinted, tmp_path / "c.safetensors")))
    assert got.classes == ("Car", "Pedestrian") and got.class_hidden == (6,)
    assert list(got.state_dict()) == list(hinted.state_dict())
    assert all(torch.equal(a, b) for a, b in zip(hinted.state_dict().values(), got.state_dict().values()))


def test_weights_files_get_the_umasks_permissions(tmp_path):
    """A weights file is as readable as any file the user writes (a shared folder, Ray workers
    running as another user), not its owner's alone."""
    import os
    import stat

    old = os.umask(0o022)
    try:
        p = save_ranker(_model(), tmp_path / "shared.safetensors")
    finally:
        os.umask(old)
    assert stat.S_IMODE(p.stat().st_mode) == 0o644


def test_bad_weights_files_are_one_line_errors(tmp_path):
    with pytest.raises(RankerWeightsError, match="no such file") as e:
        load_ranker(str(tmp_path / "missing.safetensors"))
    assert "\n" not in str(e.value) and "'none'" in str(e.value)
    bad = tmp_path / "bad.safetensors"
    bad.write_bytes(b"\x10\x00\x00\x00\x00\x00\x00\x00{not json")
    with pytest.raises(RankerWeightsError, match="not a readable safetensors file") as e:
        load_ranker(str(bad))
    assert "\n" not in str(e.value) and str(bad) in str(e.value)
    from safetensors.torch import save_file

    other = tmp_path / "other.safetensors"
    save_file({"w": torch.zeros(2)}, str(other), metadata={"format": "pt"})
    with pytest.raises(RankerWeightsError, match="not a reeb-torch ranker's"):
        load_ranker(str(other))
    good = save_ranker(_model(), tmp_path / "old.safetensors")
    with open(good, "rb") as f:
        raw = f.read()
    n = int.from_bytes(raw[:8], "little")
    header = json.loads(raw[8: 8 + n])
    info = json.loads(header["__metadata__"]["reeb-ranker"])
    info["features_version"] = FEATURES_VERSION - 1
    header["__metadata__"]["reeb-ranker"] = json.dumps(info)
    blob = json.dumps(header).encode()
    blob += b" " * (-len(blob) % 8)
    stale = tmp_path / "stale.safetensors"
    stale.write_bytes(len(blob).to_bytes(8, "little") + blob + raw[8 + n:])
    with pytest.raises(RankerWeightsError, match=f"version {FEATURES_VERSION - 1}.*version {FEATURES_VERSION}"):
        load_ranker(str(stale))
    info["features_version"], info["provenance"] = FEATURES_VERSION, ["not", "a", "record"]
    header["__metadata__"]["reeb-ranker"] = json.dumps(info)
    blob = json.dumps(header).encode()
    blob += b" " * (-len(blob) % 8)
    edited = tmp_path / "edited.safetensors"
    edited.write_bytes(len(blob).to_bytes(8, "little") + blob + raw[8 + n:])
    with pytest.raises(RankerWeightsError, match="'provenance' metadata is not a JSON object") as e:
        load_ranker(str(edited))
    assert "\n" not in str(e.value) and str(edited) in str(e.value)


def test_weights_for_other_features_are_refused(tmp_path):
    p = save_ranker(_model(), tmp_path / "four.safetensors")
    with pytest.raises(RankerWeightsError, match="47 features.*this config gives 46"):
        ProposalGenerator(ReebConfig(ranker=str(p), class_heights_m=(1.5, 3.2, 1.72), class_weights=(1, 1, 1),
                                     object_templates=ReebConfig().object_templates[:3]))


def test_shipped_weights_load_and_say_where_they_come_from():
    assert set(SHIPPED) == {"kitti"}
    assert shipped_path("kitti").stat().st_size < 100_000
    m = load_ranker("kitti", feature_names(4) + ORIENTATION_NAMES)
    prov = m.meta["provenance"]
    assert prov["frames"] == 106 and prov["command"].startswith("reeb fit ")
    assert load_ranker("kitti") is m  # loaded once
    assert len(prov["frame_hashes"]) == 106 and "kitti/000001" in prov["frame_hashes"]


def test_frame_hash_survives_encoding_and_size_and_tells_frames_apart(sample_image):
    import cv2

    from reeb_torch.io import read_image
    from reeb_torch.ranker import SAME_IMAGE_BITS, frame_hash, hash_distance

    h = frame_hash(sample_image)
    assert len(h) == 64 and int(h, 16) >= 0
    assert frame_hash(sample_image.float() / 255) == h  # float in [0, 1] as uint8
    ok, jpeg = cv2.imencode(".jpg", sample_image.permute(1, 2, 0).numpy()[:, :, ::-1].copy(),
                            [cv2.IMWRITE_JPEG_QUALITY, 70])
    again = torch.from_numpy(cv2.imdecode(jpeg, cv2.IMREAD_COLOR)[:, :, ::-1].copy()).permute(2, 0, 1)
    half = torch.nn.functional.interpolate(sample_image[None].float(), scale_factor=0.5, mode="area")[0]
    assert hash_distance(frame_hash(again), h) <= SAME_IMAGE_BITS
    assert hash_distance(frame_hash(half.round().to(torch.uint8)), h) <= SAME_IMAGE_BITS
    other = read_image(Path(__file__).resolve().parents[2] / "examples" / "data" / "kitti_000008.png")
    assert hash_distance(frame_hash(other), h) > 4 * SAME_IMAGE_BITS
    assert hash_distance(frame_hash(sample_image.flip(2)), h) > 4 * SAME_IMAGE_BITS
    with pytest.raises(ValueError, match=r"\[3, H, W\]"):
        frame_hash(sample_image[0])


def test_fitted_frames_names_the_pictures_a_model_saw(sample_image):
    from reeb_torch.ranker import fitted_frames, frame_hash

    shipped = load_ranker("kitti")  # fitted on KITTI object frames 000000-000059, the sample among them
    assert fitted_frames(shipped, [sample_image, sample_image.flip(2)]) == ["kitti/000001", None]
    made = BoxRanker(feature_names(4))
    assert fitted_frames(made, [sample_image]) == [None]  # no record: nothing said
    made.meta = {"provenance": {"frame_hashes": {"mine/a": frame_hash(sample_image.flip(2))},
                                "init": {"model": "kitti", "frame_hashes": {"kitti/000001": frame_hash(sample_image)}}}}
    assert fitted_frames(made, [sample_image.flip(2), sample_image]) == ["mine/a", "kitti:kitti/000001"]
    made.meta = {"provenance": {"frame_hashes": {"x": "not hex", "y": 7, "z": frame_hash(sample_image)},
                                "init": "kitti"}}  # a hand-edited file: what can be read is used
    assert fitted_frames(made, [sample_image]) == ["z"]
    made.meta = {"provenance": ["not", "a", "record"]}
    assert fitted_frames(made, [sample_image]) == [None]


def test_generator_with_ranker_contract(sample_image):
    gen = ProposalGenerator()
    assert gen.config.ranker == "kitti" and gen.ranker is not None and gen.ranker.model is not None
    out = gen([sample_image])[0]
    b, s = out["boxes"], out["scores"]
    assert b.dtype == s.dtype == torch.float32 and 0 < len(b) <= gen.config.top_k
    assert bool((s[:-1] >= s[1:]).all())
    h, w = sample_image.shape[-2:]
    assert bool((b[:, 0] >= 0).all() & (b[:, 2] <= w).all() & (b[:, 0] < b[:, 2]).all() & (b[:, 3] <= h).all())
    batch = gen([sample_image, sample_image.flip(-1), sample_image])
    assert torch.equal(batch[0]["boxes"], b) and torch.equal(batch[2]["scores"], s)
    assert torch.equal(gen(sample_image[None].float() / 255)[0]["boxes"], b)
    # the class hints of the shipped model's class head, one per box, alone as in a batch
    assert gen.classes == ("Car", "Pedestrian", "Cyclist", "Truck")
    labels, probs = out["labels"], out["class_probs"]
    assert labels.dtype == torch.int64 and labels.shape == (len(b),) and probs.shape == (len(b), 4)
    assert probs.dtype == torch.float32 and torch.equal(labels, probs.argmax(1))
    torch.testing.assert_close(probs.sum(1), torch.ones(len(b)))
    assert torch.equal(batch[2]["labels"], labels) and torch.equal(batch[0]["class_probs"], probs)
    # kitti_000001's car at (387, 181)-(423, 203): its best box is hinted a car
    car = torch.tensor([[387.0, 181, 423, 203]])
    from torchvision.ops import box_iou

    best = box_iou(car, b)[0].argmax()
    assert gen.classes[int(labels[best])] == "Car"


def _ranked(gen: ProposalGenerator, images: list) -> tuple:
    """The generator's stages up to the learned ranking on ``images``: ``(maps, grid, scores
    (V), share, entropy, kept, ranked)``, ``ranked`` holding ``LearnedRanking.rank``'s ``(bi, ni,
    features)``."""
    sel, rk = gen.selection, gen.ranker
    front = gen.front_end(gen.prepare(images))
    maps = front.maps
    bounds, entropy, share = gen.selection.regions(front.working.gray)
    grid = sel.window_grid(maps, bounds)
    scores = sel.score(maps, grid)
    chosen = sel.select(scores, grid, share)
    ranked: list = []
    _, kept = rk.rank(maps, grid, scores, chosen, share, entropy, ranked)
    return maps, grid, scores, share, entropy, kept, ranked


def test_class_hints_reuse_the_ranked_features(sample_image):
    """The hints read the features the ranking computed (rows looked up, not recomputed):
    the same probabilities as features computed afresh, and a window the ranking did not
    rank (here: every other one dropped from what it hands over) is computed."""
    gen = ProposalGenerator()
    rk = gen.ranker
    maps, grid, scores, share, entropy, kept, ranked = _ranked(gen, [sample_image, sample_image.flip(-1)])
    bi, ni, feats = ranked[0]
    assert feats.shape == (int(kept.sum()), 55)  # with the orientation columns the shipped model reads
    assert torch.equal(torch.stack([bi, ni]), torch.stack(kept.nonzero(as_tuple=True)))
    windows = [torch.nonzero(kept[i]).squeeze(1)[::7] for i in range(2)]
    fresh = rk.class_hints(maps, grid, scores, share, entropy, windows)
    for part in (ranked[0], tuple(t[::2] for t in ranked[0])):
        for a, b in zip(rk.class_hints(maps, grid, scores, share, entropy, windows, part), fresh):
            assert torch.equal(a, b)


def test_no_class_hints_without_a_class_head(sample_image, tmp_path):
    free = ProposalGenerator(ReebConfig().training_free())
    assert free.classes is None and set(free([sample_image])[0]) == {"boxes", "scores"}
    path = save_ranker(_model(), tmp_path / "plain.safetensors")  # a ranker fitted without classes
    plain = ProposalGenerator(ranker=str(path))
    assert plain.classes is None and set(plain([sample_image])[0]) == {"boxes", "scores"}
    with pytest.raises(ValueError, match="no class head"):
        plain.ranker.model.class_probs(torch.randn(3, 47))


def test_ranker_none_is_the_training_free_ranking(sample_image):
    a = ProposalGenerator(ReebConfig().training_free())([sample_image])[0]
    b = ProposalGenerator(ReebConfig(ranker="none", candidates_per_region=12000))([sample_image])[0]
    assert torch.equal(a["boxes"], b["boxes"])
    assert ReebConfig().training_free().ranker == "none"


def test_ranker_keep_bounds_the_ranked_candidates(sample_image):
    gen = ProposalGenerator(ranker_keep=500, top_k=5000)
    assert len(gen([sample_image])[0]["boxes"]) <= 500


def _ranked_with(gen: ProposalGenerator, images: list) -> list[tuple]:
    """Per call of LearnedRanking.rank: (V [B, N], the region cut's chosen, the candidates it ranked)."""
    calls, rank = [], gen.ranker.rank

    def spy(maps, grid, scores, chosen, *a, **k):
        out, kept = rank(maps, grid, scores, chosen, *a, **k)
        calls.append((scores.clone(), chosen.clone(), kept.clone()))
        return out, kept

    gen.ranker.rank = spy
    gen(images)
    return calls


def test_ranker_v_share_keeps_each_images_best_by_v_beside_the_prefilters(sample_image):
    keep, by_v = 3000, 1000
    share = by_v / keep
    ((v, chosen, kept),) = _ranked_with(ProposalGenerator(ranker_keep=keep, ranker_v_share=share), [sample_image])
    ((_, _, alone),) = _ranked_with(ProposalGenerator(ranker_keep=keep, ranker_v_share=0), [sample_image])
    ((_, _, all_v),) = _ranked_with(ProposalGenerator(ranker_keep=keep, ranker_v_share=1), [sample_image])
    cand = torch.where(chosen[0], v[0], torch.tensor(float("-inf")))
    order = torch.sort(cand, descending=True, stable=True).indices
    assert int(kept.sum()) == int(alone.sum()) == int(all_v.sum()) == keep < int(chosen.sum())  # as many ranked
    assert bool(kept[0, order[:by_v]].all())  # V's best, whatever the prefilter says
    assert not bool(alone[0, order[:by_v]].all())  # (the prefilter alone drops some of them)
    assert torch.equal(all_v[0].nonzero().squeeze(1), order[:keep].sort().values)  # all by V: V's best
    rest = kept[0].clone()
    rest[order[:by_v]] = False
    assert bool((rest <= alone[0]).all())  # the others are the prefilter's best
    gen = ProposalGenerator(ranker_keep=keep, ranker_v_share=share)
    assert all(torch.equal(a, b) for a, b in zip(gen([sample_image.flip(-1), sample_image])[1].values(),
                                                   gen([sample_image])[0].values()))  # alone as in a batch
    assert ReebConfig().ranker_keep == 12000 and ReebConfig().ranker_v_share == 0.0  # the default: the prefilter alone


def test_bad_ranker_settings():
    with pytest.raises(ValueError, match="ReebConfig.ranker must be"):
        ReebConfig(ranker="")
    with pytest.raises(ValueError, match="ranker_keep"):
        ReebConfig(ranker_keep=0)
    for bad in (-0.1, 1.5):
        with pytest.raises(ValueError, match="ranker_v_share must be"):
            ReebConfig(ranker_v_share=bad)


def test_class_quota_shares_the_output_by_the_hints(sample_image):
    """class_quota: each class's share of top_k goes first to its best boxes after NMS (by
    the class head's hint), the rest to the best of the others, in score order."""
    shares = (0.0, 0.5, 0.25, 0.25)
    every = ProposalGenerator(class_quota=shares, top_k=10**6)([sample_image])[0]  # all NMS survivors
    gen = ProposalGenerator(class_quota=shares, top_k=200)
    got = gen([sample_image])[0]
    batch = gen([sample_image.flip(-1), sample_image])  # alone as in a batch
    assert all(torch.equal(batch[1][k], got[k]) for k in got)
    assert len(got["boxes"]) == 200 and bool((got["scores"][:-1] >= got["scores"][1:]).all())
    assert torch.equal(got["labels"], got["class_probs"].argmax(1))
    key = lambda o: {tuple(b) for b in o["boxes"].tolist()}  # noqa: E731
    assert key(got) <= key(every)
    for c, share in enumerate(shares):
        best = every["boxes"][every["labels"] == c][: int(share * 200)]
        assert {tuple(b) for b in best.tolist()} <= key(got)  # the class's best, whatever their rank
    # without a quota the same generator ranks all classes as one
    plain = ProposalGenerator(top_k=200)([sample_image])[0]
    assert int((plain["labels"] == 1).sum()) < int((got["labels"] == 1).sum())


def test_bad_class_quotas(tmp_path):
    with pytest.raises(ValueError, match="class_quota must be shares >= 0 that sum to at most 1"):
        ReebConfig(class_quota=(0.5, 0.6))
    with pytest.raises(ValueError, match="class_quota must be shares >= 0 .* distinct names"):
        ReebConfig(class_quota={"Pedestrian": 0.6, "Cyclist": 0.5})
    with pytest.raises(ValueError, match="class_quota must be shares >= 0 .* distinct names"):
        ReebConfig(class_quota=(("Pedestrian", 0.2), ("Pedestrian", 0.1)))
    with pytest.raises(TypeError, match="class_quota must be a tuple of tuples"):
        ReebConfig(class_quota=(("Pedestrian", 0.2), 0.1))
    with pytest.raises(ValueError, match="a ranker .* with class_quota given in the ranker's class order"):
        ReebConfig(class_quota=(0.2,), ranker="none")
    with pytest.raises(ValueError, match="class_quota has 2 shares, but the ranker 'kitti' has the classes Car, "
                                         "Pedestrian, Cyclist, Truck"):
        ProposalGenerator(class_quota=(0.5, 0.5))
    with pytest.raises(ValueError, match="class_quota names 'Person', but the ranker 'kitti' hints the classes Car, "
                                         "Pedestrian, Cyclist, Truck"):
        ProposalGenerator(class_quota={"Person": 0.2})
    path = save_ranker(_model(), tmp_path / "plain.safetensors")
    with pytest.raises(ValueError, match="has no class head: give the shares by class name"):
        ProposalGenerator(ranker=str(path), class_quota=(0.1,))
    # the training-free copy of a class-quota config drops the quota with the ranker,
    assert ReebConfig(class_quota=(0, 0.3, 0.1, 0.05)).training_free() == ReebConfig().training_free()
    # and its unranked copy (the candidates ranked by V, as reeb fit takes them) too
    assert ReebConfig(class_quota=(0, 0.3, 0.1, 0.05)).unranked() == ReebConfig(ranker="none")


def test_class_quota_by_name(tmp_path, sample_image):
    """class_quota by class name: the same quota as the shares in the head's order (classes
    not named get none), kept as hashable pairs that survive a JSON round trip; without a
    class head it gives way (ranker='none' silently, a head-less weights file with a warning)."""
    import json

    named = ReebConfig(class_quota={"Cyclist": 0.05, "Pedestrian": 0.2})
    assert named.class_quota == (("Cyclist", 0.05), ("Pedestrian", 0.2)) and hash(named) == hash(named.replace())
    assert ReebConfig.from_dict(json.loads(json.dumps(named.to_dict()))) == named
    assert named.class_shares(("Car", "Pedestrian", "Cyclist", "Truck")) == (0.0, 0.2, 0.05, 0.0)
    assert named.class_shares(None) is None and ReebConfig().class_shares(("Car",)) is None
    by_name = ProposalGenerator(named, top_k=200)
    assert by_name.ranker.class_share == (0.0, 0.2, 0.05, 0.0)
    got = by_name([sample_image])[0]
    want = ProposalGenerator(class_quota=(0.0, 0.2, 0.05, 0.0), top_k=200)([sample_image])[0]
    assert all(torch.equal(got[k], want[k]) for k in want)
    # no class head: no quota
    none = ProposalGenerator(named.replace(ranker="none"), top_k=200)
    assert none.ranker is None
    assert torch.equal(none([sample_image])[0]["boxes"], ProposalGenerator(ranker="none", top_k=200)([sample_image])[0]["boxes"])
    path = save_ranker(_model(), tmp_path / "plain.safetensors")
    with pytest.warns(UserWarning, match="class_quota is ignored: the ranker .* has no class head"):
        plain = ProposalGenerator(ranker=str(path), class_quota={"Pedestrian": 0.2})
    assert plain.ranker.class_share is None


@pytest.mark.cuda
def test_cuda_ranking_matches_the_cpu(sample_image):
    cpu = ProposalGenerator()([sample_image])[0]
    gpu = ProposalGenerator().to("cuda")([sample_image.cuda()])[0]
    from torchvision.ops import box_iou

    iou = box_iou(cpu["boxes"][:200], gpu["boxes"][:200].cpu()).amax(1)
    assert float((iou > 0.99).float().mean()) > 0.9  # the prefilter and MLP round differently there


def test_a_config_the_model_was_not_fitted_with_is_warned_about():
    import warnings

    with pytest.warns(UserWarning, match=r"fitted with other settings: horizon=0\.5 \(fitted with 0\.47\)"):
        ProposalGenerator(horizon=0.5)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        ProposalGenerator(top_k=100, ranker_keep=5000, nms_iou=0.7)  # act after the model: no warning


def test_settings_the_model_was_fitted_with_are_compared_with_a_tolerance():
    """A setting written to 3 or 4 digits is the one fitted (camera_height_m=1.676 against a fitted
    1.67575): no warning; a setting that differs beyond that, or a list of them, is warned about."""
    import warnings

    from reeb_torch import ReebConfig
    from reeb_torch.ranker.step import _same, warn_if_fitted_elsewhere

    fitted = json.loads(json.dumps(ReebConfig(camera_height_m=1.67575, horizon=0.4714).to_dict(), default=list))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        warn_if_fitted_elsewhere(ReebConfig(camera_height_m=1.676, horizon=0.4714), fitted)
        warn_if_fitted_elsewhere(ReebConfig(camera_height_m=1.6758, horizon=0.47142), fitted)
    with pytest.warns(UserWarning, match=r"camera_height_m=1\.7 \(fitted with 1\.67575\)"):
        warn_if_fitted_elsewhere(ReebConfig(camera_height_m=1.7, horizon=0.4714), fitted)
    assert _same([1.0, [2.0, 3.0]], [1.0004, [2.0, 3.001]]) and not _same([1.0, 2.0], [1.0, 2.1])
    assert not _same(None, 0.0) and _same("a", "a") and not _same("a", "b") and not _same([1.0], [1.0, 2.0])


def test_chosen_pairs_are_torch_nonzero_and_gather_reads_them():
    """The CPU's candidate pairs (numpy, an image at a time) are torch.nonzero's, in its order;
    _gather reads the values at them as torch's indexing does."""
    from reeb_torch.ranker.step import _chosen, _gather

    torch.manual_seed(0)
    for mask in (torch.rand(3, 1000) < 0.3, torch.zeros(2, 50, dtype=torch.bool), torch.ones(1, 7, dtype=torch.bool),
                 torch.zeros(0, 9, dtype=torch.bool), (torch.rand(4, 64) < 0.5)[:, ::2]):
        bi, ni = _chosen(mask)
        want = torch.nonzero(mask, as_tuple=True)
        assert bi.dtype == ni.dtype == torch.int64 and torch.equal(bi, want[0]) and torch.equal(ni, want[1])
        # and the values at those pairs, gathered an image row at a time, are torch's
        values = torch.randn(len(mask), 2 * mask.shape[1])[:, ::2]  # strided, as a view may be
        got = _gather(values, bi, ni, torch.bincount(bi, minlength=len(mask)))
        assert got.dtype == torch.float32 and torch.equal(got, values[bi, ni])


def test_best_per_image_keeps_the_best_ties_to_the_earlier():
    """Each image's best `keep` values, ties to the earlier, ascending: as a stable sort."""
    from reeb_torch.ranker.step import _best_per_image

    torch.manual_seed(0)
    values = torch.randint(0, 20, (300,)).float()  # many ties
    counts = torch.tensor([120, 5, 0, 175])
    got = _best_per_image(values, counts, 30)
    want, start = [], 0
    for n in counts.tolist():
        part = values[start: start + n]
        want.append(torch.sort(part, descending=True, stable=True).indices[:30].sort().values + start)
        start += n
    assert torch.equal(got, torch.cat(want))


def test_class_hints_take_the_quotas_logits_of_the_ranked_rows(sample_image):
    """On the class_quota path the head runs once over the ranked rows (class_map); the hints
    of the output read those rows' logits: the same probabilities as the head run on them anew."""
    gen = ProposalGenerator(class_quota={"Pedestrian": 0.3, "Cyclist": 0.1, "Truck": 0.05}, top_k=300)
    rk = gen.ranker
    maps, grid, scores, share, entropy, kept, ranked = _ranked(gen, [sample_image])
    class_of, logits = rk.class_map(ranked[0], tuple(scores.shape))
    assert logits.shape == (int(kept.sum()), len(gen.classes))
    assert torch.equal(class_of[kept].long(), logits.argmax(1))
    windows = [torch.nonzero(kept[0]).squeeze(1)[::5], torch.nonzero(~kept[0]).squeeze(1)[:7]]  # 7 misses
    windows = [torch.cat(windows).sort().values]
    fresh = rk.class_hints(maps, grid, scores, share, entropy, windows)
    reused = rk.class_hints(maps, grid, scores, share, entropy, windows, ranked[0], logits)
    torch.testing.assert_close(reused[0], fresh[0], rtol=0, atol=1e-6)
