"""Fitting the learned ranking (reeb_torch.ranker.frames, reeb fit): training rows from labelled
candidates (hand-worked), a seeded fit that gives the same bits twice, folds that keep
neighbouring frames of one drive on one side, the command end to end, and the shipped
weights refitted bit for bit from the frames and options they name."""

from __future__ import annotations

import dataclasses
import subprocess
import sys

import numpy as np
import pytest
import torch

from tests.conftest import DATA
from reeb_torch.ranker import frames as F
from reeb_torch.ranker import fit as RF
from reeb_torch.ranker import cv as fit_cv
from reeb_torch.tuning import fold_blocks
from reeb_torch.ranker.features import FEATURE_GROUPS, dropped_columns, feature_names

REPO_DATA = DATA


def test_frame_sample_by_hand():
    """Positives: IoU >= 0.7 with a target, an object's positives weigh 1 together; negatives:
    below 0.5 with every labelled box (targets and the others); the rest left out."""
    gt = torch.tensor([[0.0, 0.0, 10.0, 10.0]])
    ignore = torch.tensor([[100.0, 0.0, 110.0, 10.0]])
    boxes = torch.tensor([[0.0, 0.0, 10.0, 10.0],     # IoU 1: positive
                          [0.0, 0.0, 10.0, 12.0],     # IoU 0.83: positive
                          [0.0, 0.0, 10.0, 17.0],     # IoU 0.59: neither
                          [50.0, 50.0, 60.0, 60.0],   # background: negative
                          [100.0, 0.0, 110.0, 11.0]])  # on an ignored van: neither
    feats = torch.arange(5.0)[:, None].expand(5, 3)
    s = F.frame_sample(feats, boxes, gt, torch.tensor([2]), ignore, RF.FitOptions(negatives=1.0),
                       np.random.default_rng(0))
    assert s.features[:, 0].tolist() == [0.0, 1.0, 3.0]
    assert s.target.tolist() == [1.0, 1.0, 0.0]
    assert s.weight.tolist() == [0.5, 0.5, 1.0]
    assert s.label.tolist() == [2, 2, -1]


def _samples(seed: int, n: int = 3000) -> list[RF.Sample]:
    g = torch.Generator().manual_seed(seed)
    x = torch.randn(n, 47, generator=g)
    y = (x[:, 0] + 0.3 * torch.randn(n, generator=g) > 1).float()
    return [RF.Sample(x, y, torch.ones(n), torch.where(y > 0, 0, -1))]


def test_fit_is_seeded_and_learns():
    opts = RF.FitOptions(epochs=10, hidden=(8,), batch=256)
    a = RF.fit_ranker(_samples(0), feature_names(4), opts)
    torch.randn(3)  # whatever ran between
    b = RF.fit_ranker(_samples(0), feature_names(4), opts)
    assert all(torch.equal(p, q) for p, q in zip(a.state_dict().values(), b.state_dict().values()))
    c = RF.fit_ranker(_samples(0), feature_names(4), RF.FitOptions(epochs=10, hidden=(8,), batch=256, seed=1))
    assert not torch.equal(a.members[0][0].weight, c.members[0][0].weight)
    test = _samples(1)[0]
    with torch.no_grad():
        logit = a(test.features)
    pos, neg = logit[test.target == 1], logit[test.target == 0]
    assert float((pos[:, None] > neg[None, :]).float().mean()) > 0.8  # AUC on new rows (0.5: chance)
    with pytest.raises(ValueError, match="cannot be fitted"):
        RF.fit_ranker([RF.Sample(torch.zeros(3, 47), torch.zeros(3), torch.ones(3), torch.full((3,), -1))],
                     feature_names(4), opts)


@pytest.mark.slow
def test_class_head_is_seeded_learns_and_leaves_the_ranking_alone():
    """Given classes, a class head is fitted on the positives after the ranking parts: the
    ranking's weights are those of the fit without it, bit for bit; the head tells the
    classes apart on new rows; the same seed gives the same head."""
    def samples(seed, n=20000):
        g = torch.Generator().manual_seed(seed)
        x = torch.randn(n, 47, generator=g)
        y = (x[:, 0] + 0.3 * torch.randn(n, generator=g) > 1).float()
        label = torch.where(x[:, 1] > 0.3, 1, 0)  # the class shows in another column
        return [RF.Sample(x, y, torch.ones(n), torch.where(y > 0, label, -1))]

    opts = RF.FitOptions(epochs=20, hidden=(8,), batch=512, class_hidden=(8,))
    plain = RF.fit_ranker(samples(0), feature_names(4), opts)
    a = RF.fit_ranker(samples(0), feature_names(4), opts, ("Car", "Pedestrian"))
    b = RF.fit_ranker(samples(0), feature_names(4), opts, ("Car", "Pedestrian"))
    assert plain.classifier is None and a.classes == ("Car", "Pedestrian")
    for name, p in plain.state_dict().items():
        assert torch.equal(p, a.state_dict()[name]), name
    assert all(torch.equal(p, q) for p, q in zip(a.state_dict().values(), b.state_dict().values()))
    test = samples(1)[0]
    probs = a.class_probs(test.features[test.target == 1])
    assert probs.shape == (int(test.target.sum()), 2)
    torch.testing.assert_close(probs.sum(1), torch.ones(len(probs)))
    truth = test.label[test.target == 1]
    assert float((probs.argmax(1) == truth).float().mean()) > 0.85
    assert RF.fit_ranker(samples(0), feature_names(4), RF.FitOptions(epochs=2, hidden=(8,), class_hidden=None),
                        ("Car", "Pedestrian")).classifier is None


def test_dropped_features_change_no_score():
    """drop_features: the ranking, the prefilter (eager and folded for inference) and the class
    head give the same scores whatever the dropped columns hold, though the labels follow one
    of them; a model fitted with them reads them; an unknown name is refused, naming it."""
    names = feature_names(4)
    top = names.index("top")
    g = torch.Generator().manual_seed(5)
    n = 6000
    x = torch.randn(n, 47, generator=g)
    y = (x[:, 0] + x[:, top] > 1).float()  # the place column tells half of it
    samples = [RF.Sample(x, y, torch.ones(n), torch.where(y > 0, (x[:, top] > 0).long(), -1))]
    opts = RF.FitOptions(epochs=4, hidden=(8,), batch=512, class_hidden=(8,))
    free = RF.fit_ranker(samples, names, dataclasses.replace(opts, drop_features=("place", "log_v")),
                        ("Car", "Pedestrian"))
    kept = RF.fit_ranker(samples, names, opts, ("Car", "Pedestrian"))
    moved = x[:50].clone()
    cols = [names.index(c) for c in (*FEATURE_GROUPS["place"], "log_v")]
    moved[:, cols] = torch.randn(50, len(cols), generator=g) * 5
    cheap = free.cheap
    with torch.no_grad():
        for a, b in [(free(x[:50]), free(moved)), (free.rank(x[:50]), free.rank(moved)),
                     (free.class_probs(x[:50]), free.class_probs(moved)),
                     (free.prefilter_scores(x[:50, :cheap]), free.prefilter_scores(moved[:, :cheap]))]:
            torch.testing.assert_close(a, b)
        assert not torch.allclose(kept(x[:50]), kept(moved))
    assert dropped_columns(names, ["place"]) == sorted(names.index(c) for c in FEATURE_GROUPS["place"])
    with pytest.raises(ValueError, match="'lattitude' is no feature column or group"):
        RF.fit_ranker(samples, names, dataclasses.replace(opts, drop_features=("lattitude",)))


def test_prefilter_balance_weighs_only_the_prefilter():
    """prefilter_balance: the prefilter's class weights apart from the MLP's; the MLP's weights
    are those of the fit without it, bit for bit, and None is the balance's own."""
    g = torch.Generator().manual_seed(3)
    n = 20000
    x = torch.randn(n, 47, generator=g)
    y = (x[:, 0] + 0.3 * torch.randn(n, generator=g) > 1).float()
    label = torch.where(x[:, 1] > 1.0, 1, 0)  # a rare class among the positives
    samples = [RF.Sample(x, y, torch.ones(n), torch.where(y > 0, label, -1))]
    opts = RF.FitOptions(epochs=3, hidden=(8,), batch=512, class_hidden=None)
    base = RF.fit_ranker(samples, feature_names(4), opts)
    same = RF.fit_ranker(samples, feature_names(4), dataclasses.replace(opts, prefilter_balance=opts.balance))
    other = RF.fit_ranker(samples, feature_names(4), dataclasses.replace(opts, prefilter_balance=1.0))
    assert all(torch.equal(p, q) for p, q in zip(base.state_dict().values(), same.state_dict().values()))
    assert all(torch.equal(p, q) for p, q in zip(base.members.state_dict().values(), other.members.state_dict().values()))
    assert not all(torch.equal(p, q) for p, q in zip(base.prefilter.state_dict().values(),
                                                     other.prefilter.state_dict().values()))


def test_fine_tuning_starts_from_the_model_keeps_its_shape_and_leaves_it_alone(tmp_path):
    """FitOptions.init: the model's widths and standardisation are kept (the options' widths
    do not apply); with no pass the weights are the model's, bit for bit; a pass moves them,
    the same seed the same way; the loaded (shared) model is not touched; its class head is
    tuned on the classes it has, by name."""
    from reeb_torch.ranker import load_ranker, save_ranker

    names = feature_names(4)
    start = RF.fit_ranker(_samples(0), names, RF.FitOptions(epochs=3, hidden=(8,), batch=512, class_hidden=(4,)),
                         ("Car", "Pedestrian"))
    path = save_ranker(start, tmp_path / "start.safetensors", {"frames_digest": "abc"})
    shared = load_ranker(str(path))
    before = {k: v.clone() for k, v in shared.state_dict().items()}
    opts = RF.FitOptions(init=str(path), hidden=(64, 64), prefilter=None, tune_batch=512)
    samples = _samples(1)  # labels 0 (a positive's class, "Car" here) and -1
    still = dataclasses.replace(opts, tune_epochs=0, class_epochs=0)
    none = RF.fit_ranker(samples, names, still, ("Car", "Pedestrian"))
    assert all(torch.equal(p, q) for p, q in zip(none.state_dict().values(), before.values()))
    a = RF.fit_ranker(samples, names, opts, ("Car", "Pedestrian"))
    b = RF.fit_ranker(samples, names, opts, ("Car", "Pedestrian"))
    assert a.hidden == (8,) and a.prefilter is not None and a.classes == ("Car", "Pedestrian")
    assert torch.equal(a.mean, shared.mean) and torch.equal(a.scale, shared.scale)
    assert all(torch.equal(p, q) for p, q in zip(a.state_dict().values(), b.state_dict().values()))
    for part in ("members", "prefilter", "classifier"):
        moved = [not torch.equal(p, before[f"{part}.{k}"]) for k, p in getattr(a, part).state_dict().items()]
        assert any(moved), part
    assert all(torch.equal(p, before[k]) for k, p in shared.state_dict().items())  # the shared model is untouched
    assert a.meta["provenance"] == {"frames_digest": "abc"} and not any(p.requires_grad for p in a.parameters())
    # a head without the frames' classes is left as it is; by name, not by position
    other = RF.fit_ranker(samples, names, opts, ("Truck", "Tram"))
    assert all(torch.equal(p, before[f"classifier.{k}"]) for k, p in other.classifier.state_dict().items())
    assert RF._relabelled(torch.tensor([0, 1, -1, 2]), ("Pedestrian", "Car", "Van"), ("Car", "Pedestrian")).tolist() \
        == [1, 0, -1, -1]


def test_fine_tuning_refuses_a_model_it_cannot_tune(tmp_path):
    from reeb_torch.ranker import RankerWeightsError, save_ranker

    with pytest.raises(RankerWeightsError, match="no such file"):
        RF.fit_ranker(_samples(0), feature_names(4), RF.FitOptions(init=str(tmp_path / "nope.safetensors")))
    path = save_ranker(RF.fit_ranker(_samples(0), feature_names(4), RF.FitOptions(epochs=1, hidden=(4,))),
                       tmp_path / "four.safetensors")
    x = _samples(0)[0]
    three = [RF.Sample(x.features[:, :len(feature_names(3))], x.target, x.weight, x.label)]
    with pytest.raises(RankerWeightsError, match="read 47 features"):
        RF.fit_ranker(three, feature_names(3), RF.FitOptions(init=str(path)))


def test_hinted_classes_by_hand():
    gts = [torch.tensor([[0.0, 0, 10, 10], [20, 20, 30, 30], [50, 50, 60, 60]]), torch.zeros(0, 4)]
    out = {"boxes": torch.tensor([[0.0, 0, 10, 9], [0, 0, 10, 10], [20, 20, 30, 31], [50, 50, 51, 51]]),
           "labels": torch.tensor([2, 1, 0, 3])}
    got = fit_cv.hinted_classes([out, {"boxes": torch.zeros(0, 4), "labels": torch.zeros(0, dtype=torch.long)}], gts)
    assert got[0].tolist() == [1, 0, -1] and got[1].shape == (0,)  # the best box's hint; a miss is -1
    assert fit_cv.hinted_classes([out], gts[:1], k=1)[0].tolist() == [2, -1, -1]  # only the top k count
    assert fit_cv.hinted_classes([{"boxes": out["boxes"]}], gts[:1])[0].tolist() == [-1, -1, -1]  # no hints


def test_folds_keep_neighbouring_frames_of_a_drive_apart():
    ids = [f"{i:06d}" for i in range(6)] + [f"t0000_{i:06d}" for i in range(0, 30, 3)]
    folders = ["kitti"] * 6 + ["kitti_tracking"] * 10
    blocks = fold_blocks(len(ids), 4)
    assert sorted(i for b in blocks for i in b) == list(range(16))
    for held, block in enumerate(blocks):
        train = F.training_frames(blocks, held, ids, folders, gap=2)
        assert not set(train) & set(block)
        drive = [i for i in range(6, 16)]
        for i in block:
            if i in drive:  # no frame of the drive within 2 of a held-out one
                assert all(abs(j - i) > 2 for j in train if j in drive)
        assert all(j in train for j in range(6) if j not in block)  # object frames name no drive
    similar = [set() for _ in ids]
    similar[0], similar[5] = {5}, {0}
    assert 5 not in F.training_frames(blocks, 0, ids, folders, similar)
    assert F.drive_of("t0016_000002", "x") == "x/t0016" and F.drive_of("000002", "x") is None


def test_reeb_fit_says_where_a_model_saw_some_of_the_frames(sample_image):
    """A model that saw some of the frames (the same pictures, whatever their names) makes
    its row in-sample there; one that saw all of them, or whose file records only the frame
    list's digest, no estimate; one that saw none, nothing."""
    from reeb_torch.ranker import BoxRanker, frame_hash
    from reeb_torch.runs.fit import _seen_note
    from reeb_torch.ranker.features import feature_names

    model = BoxRanker(feature_names(4))
    model.meta = {"provenance": {"frame_hashes": {"kitti/000001": frame_hash(sample_image)}}}
    some = _seen_note("the model", model, _Frames([sample_image, sample_image.flip(2), sample_image.flip(1)]),
                      "d", "its row")
    assert some == ["  (the model was fitted on 1 of these 3 frames: its row is in-sample there)"]
    assert _seen_note("the model", model, _Frames([sample_image]), "d", "its row") == \
        ["  (the model was fitted on these frames: its row is no estimate)"]
    assert _seen_note("the model", model, _Frames([sample_image.flip(2)]), "d", "its row") == []
    model.meta = {"provenance": {"frames_digest": "d"}}  # a file written before frame hashes
    assert _seen_note("the model", model, _Frames([sample_image.flip(2)]), "d", "its row") == \
        ["  (the model was fitted on these frames: its row is no estimate)"]


class _Frames(list):
    """Frames as :func:`_seen_note` reads them: ``images`` and a length."""

    @property
    def images(self):
        return list(self)


def test_similar_frames_finds_near_copies(sample_image):
    other = torch.roll(sample_image, 300, dims=2)
    frames = [sample_image, sample_image.clone(), other, sample_image.flip(1)]
    sim = F.similar_frames(frames)
    assert sim[0] == {1} and sim[1] == {0} and 2 not in sim[0]


@pytest.mark.slow
@pytest.mark.kitti
def test_cross_validate_runs_after_the_model_settings_with_the_same_fold_models(kitti_dir):
    """``also``: each config runs with the very fold models of ``cfg`` (cv_paired.py's
    pairing): the same config gives the same hits, a shorter output a subset of them."""
    import dataclasses

    from reeb_torch import ReebConfig
    from reeb_torch.tuning import FrameCache

    frames = F.load_fit_frames([str(kitti_dir)], limit=6)
    cache = FrameCache(frames)
    cfg, opts = ReebConfig(), dataclasses.replace(RF.FitOptions(), epochs=2, class_hidden=None)
    samples = F.frame_samples(cache, cfg, opts)
    cv = fit_cv.cross_validate(cache, cfg, cfg.training_free(), samples, opts, 2, also=[cfg, cfg.replace(top_k=100)])
    same, short = cv.also_hits
    assert all(torch.equal(a, b) for a, b in zip(same, cv.ranked_hits))
    assert all(bool((b <= a).all()) for a, b in zip(cv.ranked_hits, short))
    assert fit_cv.cross_validate(cache, cfg, cfg.training_free(), samples, opts, 2).also_hits == []


@pytest.mark.slow
def test_held_out_outputs_are_the_cross_validated_models(kitti_dir):
    """held_out_outputs: each frame's proposals from the model fitted without its block, the
    very models of cross_validate (the same hits)."""
    import dataclasses

    from reeb_torch import ReebConfig
    from reeb_torch.metrics.recall import object_hits
    from reeb_torch.tuning import FrameCache

    frames = F.load_fit_frames([str(kitti_dir)], limit=6)
    cache = FrameCache(frames)
    cfg, opts = ReebConfig(), dataclasses.replace(RF.FitOptions(), epochs=2, class_hidden=None)
    samples = F.frame_samples(cache, cfg, opts)
    outputs = fit_cv.held_out_outputs(cache, cfg, samples, opts, 3)
    cv = fit_cv.cross_validate(cache, cfg, cfg.training_free(), samples, opts, 3)
    hits = object_hits([o["boxes"] for o in outputs], frames.gts, 2000, 0.7)
    assert all(torch.equal(a, b) for a, b in zip(hits, cv.ranked_hits))
    given = fit_cv.held_out_outputs(cache, cfg, samples, opts, fold_blocks(6, 3))  # the blocks themselves
    assert all(torch.equal(a["boxes"], b["boxes"]) for a, b in zip(given, outputs))
    assert all(0 < len(o["boxes"]) <= 2000 and "labels" not in o for o in outputs)  # no class head here
    others = F.other_boxes(kitti_dir, frames.ids)
    assert len(others) == 6 and all(torch.equal(a, b) for a, b in zip(others, frames.ignore))
    assert sum(len(b) for b in others) > 0  # vans, DontCare, ... in the first frames


@pytest.mark.slow
@pytest.mark.kitti
def test_reeb_fit_end_to_end(kitti_dir, tmp_path):
    out = tmp_path / "mine.safetensors"
    r = subprocess.run([sys.executable, "-m", "reeb_torch.runs.cli", "fit", str(kitti_dir), "--limit", "8",
                        "--folds", "2", "--epochs", "2", "-q", "-o", str(out)], capture_output=True, text=True,
                       timeout=600)
    assert r.returncode == 0, r.stderr
    assert "training-free" in r.stdout and "fitted (cross-validated)" in r.stdout and "shipped kitti model" in r.stdout
    assert "8 frames: with 5 or 10 frames of a drive, fine-tuning" in r.stdout  # the hint for few frames
    assert "the shipped model was fitted on these frames: its row is no estimate" in r.stdout  # 000000-000007
    from reeb_torch import ProposalGenerator, ReebConfig
    from reeb_torch.ranker import load_ranker
    import json

    cfg = json.loads(out.with_suffix(".json").read_text())
    assert cfg["ranker"] == out.name  # beside the config: it reads from any folder
    cfg["ranker"] = str(out)
    assert load_ranker(str(out)).meta["provenance"]["frames"] == 8
    assert load_ranker(str(out)).refiner is None  # a box refiner only with --refiner
    assert not any(k.startswith("refine_") for k in load_ranker(str(out)).meta["provenance"]["options"])
    gen = ProposalGenerator(ReebConfig.from_dict(cfg))
    assert gen.ranker.model is load_ranker(str(out))
    tuned = tmp_path / "tuned.safetensors"
    r = subprocess.run([sys.executable, "-m", "reeb_torch.runs.cli", "fit", str(kitti_dir), "--limit", "6",
                        "--folds", "2", "--epochs", "1", "--init", str(out), "-q", "-o", str(tuned),
                        "--set", "horizon=0.48", "--refiner"], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    assert load_ranker(str(tuned)).refiner is not None
    assert load_ranker(str(tuned)).meta["provenance"]["options"]["refine_hidden"] == [64, 64]
    assert "fitted with other settings" not in r.stderr  # the start and the shipped model, on purpose
    assert "fine-tuned (cross-validated)" in r.stdout and "mine.safetensors as it is" in r.stdout
    assert "fine-tuning a model fitted elsewhere" not in r.stdout
    assert f"the model fine-tuned, {out}, was fitted on these frames: the fine-tuned" in r.stdout
    meta = load_ranker(str(tuned)).meta["provenance"]
    assert len(meta["frame_hashes"]) == 6 and len(meta["init"]["frame_hashes"]) == 8
    assert meta["init"]["model"] == str(out) and meta["init"]["frames_digest"] == \
        load_ranker(str(out)).meta["provenance"]["frames_digest"] and meta["options"]["tune_epochs"] == 1
    for args, message in ((["--init", "kitti", "--hidden", "8"], "give --hidden or --init"),
                          (["--init", str(tmp_path / "none.safetensors")], "no such file")):
        bad = subprocess.run([sys.executable, "-m", "reeb_torch.runs.cli", "fit", str(kitti_dir), "--limit", "4",
                              "--folds", "2", "-q", "-o", str(tmp_path / "x.safetensors"), *args],
                             capture_output=True, text=True, timeout=300)
        assert bad.returncode == 2 and message in bad.stderr, bad.stderr
    bad = subprocess.run([sys.executable, "-m", "reeb_torch.runs.cli", "fit", str(kitti_dir), "--limit", "1",
                          "--folds", "2", "-o", str(tmp_path / "x.safetensors")], capture_output=True, text=True,
                         timeout=300)
    assert bad.returncode == 2 and "cannot make 2 folds" in bad.stderr


@pytest.mark.slow
@pytest.mark.kitti
def test_reeb_fit_on_two_folders_reports_a_model_fitted_on_the_other(kitti_dir, tmp_path):
    """Frames of several folders: a row ranked, on each folder, by a model fitted on the
    others (the blocks of held_out_outputs), paired with training-free; one folder: none."""
    from reeb_torch import ReebConfig
    from reeb_torch.metrics.recall import object_hits
    from reeb_torch.tuning import FrameCache
    from reeb_torch.runs.fit import run_fit

    tracking = REPO_DATA / "kitti_tracking"
    if not tracking.is_dir():
        pytest.skip(f"{tracking} is absent")
    opts = dataclasses.replace(RF.FitOptions(), epochs=2, class_hidden=None)
    roots = [str(kitti_dir), str(tracking)]
    done = run_fit(roots, str(tmp_path / "m.safetensors"), ReebConfig(), opts, 2, limit=3, quiet=True)
    line = next(x for x in done["text"].splitlines() if "fitted on other folders" in x)
    frames = F.load_fit_frames(roots, limit=3)
    cache = FrameCache(frames)
    outputs = fit_cv.held_out_outputs(cache, ReebConfig(), F.frame_samples(cache, ReebConfig(), opts), opts,
                                 [[0, 1, 2], [3, 4, 5]])
    hits = object_hits([o["boxes"] for o in outputs], frames.gts, 2000, 0.7)
    found, total = sum(int(h.sum()) for h in hits), sum(h.numel() for h in hits)
    assert f"{100 * found / total:5.1f} %" in line and "against training-free" in line
    alone = run_fit(roots[:1], str(tmp_path / "a.safetensors"), ReebConfig(), opts, 2, limit=3, quiet=True)
    assert "other folders" not in alone["text"]
    whole = run_fit(roots, str(tmp_path / "w.safetensors"), ReebConfig(), opts, 2, limit=3, quiet=True,
                    whole_drives=True)
    assert "no frame of a held-out block's drives on the training side" in whole["text"]
    assert whole["provenance"]["whole_drives"] is True and "whole_drives" not in done["provenance"]



def test_whole_drives_keeps_every_frame_of_a_held_out_drive_out(tmp_path):
    """reeb fit --whole-drives: the training frames of a held-out block hold no frame of its
    drives (gap = all frames); by default only those within 2 frames are left out."""
    ids = [f"{i:06d}" for i in range(4)] + [f"t0000_{3 * i:06d}" for i in range(8)]
    folders = ["kitti"] * 4 + ["kitti_tracking"] * 8
    blocks = fold_blocks(len(ids), 4)  # [0-2], [3-5], [6-8], [9-11]
    near = F.training_frames(blocks, 2, ids, folders, gap=2)
    whole = F.training_frames(blocks, 2, ids, folders, gap=len(ids))
    assert near == [0, 1, 2, 3, 11] and whole == [0, 1, 2, 3]


@pytest.mark.slow
@pytest.mark.kitti
def test_shipped_weights_refit(kitti_dir):
    """The model in the shipped file is the fit on all the frames it names, with its options:
    refitted here, the same columns and tensors, and the same model to the float rounding of
    this CPU (a fit's thousands of steps carry a CPU's own rounding of its matrix products,
    so weights match bit for bit only on the kind of CPU that fitted them): its scores of the
    fit's own rows correlate with the shipped model's and put the same rows first."""
    from reeb_torch import ReebConfig
    from reeb_torch.tuning import FrameCache
    from reeb_torch.ranker import load_ranker

    shipped = load_ranker("kitti")
    prov = shipped.meta["provenance"]
    dirs = [REPO_DATA / d for d in prov["data"]]
    if not all(d.is_dir() for d in dirs):
        pytest.skip(f"the frames the shipped weights were fitted on are absent: {dirs}")
    opts = RF.FitOptions(**{k: tuple(v) if isinstance(v, list) else v for k, v in prov["options"].items()})
    frames = F.load_fit_frames(dirs)
    assert len(frames) == prov["frames"]
    cache = FrameCache(frames)
    samples = F.frame_samples(cache, ReebConfig(), opts)
    model = RF.fit_ranker(samples, cache.candidates(ReebConfig().unranked(), 0).feature_names, opts, shipped.classes)
    assert model.feature_names == shipped.feature_names
    assert {k: v.shape for k, v in model.state_dict().items()} == {k: v.shape for k, v in shipped.state_dict().items()}
    rows = torch.cat([s.features for s in samples])
    with torch.no_grad():
        a, b = shipped(rows).flatten(), model(rows).flatten()
    assert float(torch.corrcoef(torch.stack([a, b]))[0, 1]) > 0.995
    top = max(1, len(a) // 20)  # the rows either model puts in its top 5 %
    same = len(set(a.topk(top).indices.tolist()) & set(b.topk(top).indices.tolist())) / top
    assert same > 0.9, same


def test_mirrored_boxes_by_hand():
    """A box flipped with its image of width W: x1' = W − x2, x2' = W − x1; twice, itself."""
    boxes = torch.tensor([[10.0, 5, 30, 20], [0, 0, 100, 50]])
    assert torch.equal(F._mirror_boxes(boxes, 100), torch.tensor([[70.0, 5, 90, 20], [0, 0, 100, 50]]))
    assert torch.equal(F._mirror_boxes(F._mirror_boxes(boxes, 100), 100), boxes)
    assert F._mirror_boxes(torch.zeros(0, 4), 100).shape == (0, 4)
    assert RF.FitOptions().mirror is False


@pytest.mark.kitti
def test_mirror_adds_each_frames_mirror_image_rows_cached_apart(kitti_dir):
    """With ``mirror`` a frame's sample is its own rows, unchanged, then those of its mirror
    image (candidates of the flipped image, front ends cached apart from the frame's own);
    seeded: the same rows twice."""
    from reeb_torch import ReebConfig
    from reeb_torch.tuning import FrameCache

    frames = F.load_fit_frames([str(kitti_dir)], limit=3)
    cfg = ReebConfig()
    cache = FrameCache(frames)
    plain = F.frame_samples(cache, cfg, RF.FitOptions())
    assert cache.front_computed == 3
    opts = RF.FitOptions(mirror=True)
    both = F.frame_samples(cache, cfg, opts)
    assert cache.front_computed == 6  # the mirror images' front ends, the frames' own kept
    assert all(torch.equal(a.features, b.features) and torch.equal(a.weight, b.weight)
               for a, b in zip(plain, F.frame_samples(cache, cfg, RF.FitOptions())))
    for i, (p, b) in enumerate(zip(plain, both)):
        m = F.mirrored_sample(cache, cfg, opts, i)
        n = len(p.target)
        assert len(b.target) == n + len(m.target) and 0.5 * n < len(m.target) < 2 * n  # about twice the rows
        for field in ("features", "target", "weight", "label"):
            assert torch.equal(getattr(b, field), torch.cat([getattr(p, field), getattr(m, field)])), field
        assert 0 < float(m.weight[m.target == 1].sum()) <= len(frames.gts[i]) + 1e-4  # each object weighs 1
        flipped = cache.candidates(cfg.unranked(), i, mirrored=True)
        own = cache.candidates(cfg.unranked(), i)
        assert not torch.equal(flipped.boxes[: len(own.boxes)], own.boxes[: len(flipped.boxes)])
    again = F.frame_samples(FrameCache(frames), cfg, opts)
    assert all(torch.equal(a.features, b.features) and torch.equal(a.target, b.target) for a, b in zip(both, again))


@pytest.mark.kitti
def test_mirror_and_jitter_leave_the_held_out_frames_as_they_are(kitti_dir):
    """The cross-validation of a fit with ``mirror`` and ``jitter`` scores its held-out frames as they are:
    no mirror image or copy is run once the rows are drawn, and the hits are of the frames' objects."""
    from reeb_torch import ReebConfig
    from reeb_torch.tuning import FrameCache

    frames = F.load_fit_frames([str(kitti_dir)], limit=4)
    cache = FrameCache(frames)
    cfg = ReebConfig()
    opts = dataclasses.replace(RF.FitOptions(mirror=True, jitter=0.2), epochs=2, class_hidden=None)
    samples = F.frame_samples(cache, cfg, opts)
    seen = []
    front_of = cache._front_of
    cache._front_of = lambda c, i, mirrored=False, photometric=None: (
        seen.append(mirrored or photometric is not None) or front_of(c, i, mirrored, photometric))
    cv = fit_cv.cross_validate(cache, cfg, cfg.training_free(), samples, opts, 2)
    assert seen and not any(seen)
    assert [len(h) for h in cv.ranked_hits] == [len(g) for g in frames.gts]


def test_photometric_jitter_by_hand():
    """Contrast about the image's mean, then brightness; rounded and clipped to uint8."""
    from reeb_torch.tuning import photometric_jitter

    image = torch.tensor([[[100, 140], [120, 160]]] * 3, dtype=torch.uint8)  # mean 130
    assert torch.equal(photometric_jitter(image, 1.0, 0.0), image)
    assert photometric_jitter(image, 2.0, 10.0)[0].tolist() == [[80, 160], [120, 200]]
    assert photometric_jitter(image, 1.0, 200.0).max() == 255 and photometric_jitter(image, 1.0, -200.0).max() == 0
    c, b = F.jitter_of(RF.FitOptions(jitter=0.2, seed=3), 5)
    assert 0.8 <= c <= 1.2 and -51 <= b <= 51 and (c, b) == F.jitter_of(RF.FitOptions(jitter=0.2, seed=3), 5)
    assert (c, b) != F.jitter_of(RF.FitOptions(jitter=0.2, seed=3), 6) != F.jitter_of(RF.FitOptions(jitter=0.2), 5)


@pytest.mark.kitti
def test_jitter_adds_each_frames_jittered_copy_rows(kitti_dir):
    """With ``jitter`` a frame's sample is its own rows, then those of its jittered copy (its
    own boxes; front ends cached apart); with ``mirror`` too: own, mirrored, jittered."""
    from reeb_torch import ReebConfig
    from reeb_torch.tuning import FrameCache

    frames = F.load_fit_frames([str(kitti_dir)], limit=2)
    cfg = ReebConfig()
    cache = FrameCache(frames)
    plain = F.frame_samples(cache, cfg, RF.FitOptions())
    mirrored = F.frame_samples(cache, cfg, RF.FitOptions(mirror=True))
    opts = RF.FitOptions(jitter=0.2)
    jittered = F.frame_samples(cache, cfg, opts)
    both = F.frame_samples(cache, cfg, RF.FitOptions(mirror=True, jitter=0.2))
    assert cache.front_computed == 6
    for p, m, j, b in zip(plain, mirrored, jittered, both):
        n, k = len(p.target), len(m.target)
        assert 1.5 * n < len(j.target) < 3 * n and 0 < float(j.weight[n:][j.target[n:] == 1].sum())
        assert torch.equal(j.features[:n], p.features) and torch.equal(b.features[:k], m.features)
        assert torch.equal(b.features[k:], j.features[n:]) and torch.equal(b.target[k:], j.target[n:])


@pytest.mark.kitti
def test_hard_negatives_fit_the_mlp_on_what_the_prefilter_keeps(kitti_dir):
    """FitOptions.hard_negatives: the prefilter, fitted first on the uniform rows, is the same
    bit for bit; the MLP learns from the candidates it keeps (each frame's best ranker_keep),
    seeded; without the frames (no hard_rows) the option changes nothing."""
    import dataclasses

    from reeb_torch import ReebConfig
    from reeb_torch.tuning import FrameCache

    frames = F.load_fit_frames([str(kitti_dir)], limit=3)
    cache = FrameCache(frames)
    cfg = ReebConfig(ranker_keep=3000)
    opts = dataclasses.replace(RF.FitOptions(), epochs=2, class_hidden=None)
    hard = dataclasses.replace(opts, hard_negatives=0.2)
    samples = F.frame_samples(cache, cfg, opts)
    names = cache.candidates(cfg.unranked(), 0).feature_names
    plain = RF.fit_ranker(samples, names, opts)
    rows = fit_cv.kept_rows(cache, cfg, hard, range(3))
    cascade = RF.fit_ranker(samples, names, hard, None, rows)
    assert all(torch.equal(a, b) for a, b in zip(plain.prefilter.state_dict().values(),
                                                 cascade.prefilter.state_dict().values()))
    assert not torch.equal(plain.members[0][0].weight, cascade.members[0][0].weight)
    assert torch.equal(RF.fit_ranker(samples, names, hard, None, rows).members[0][0].weight,
                       cascade.members[0][0].weight)
    assert torch.equal(RF.fit_ranker(samples, names, hard).members[0][0].weight, plain.members[0][0].weight)
    kept = rows(cascade)[0]
    pre = cascade.prefilter_scores(cache.candidates(cfg.unranked(), 0).features[:, : cascade.cheap])
    cut = float(pre.sort(descending=True).values[cfg.ranker_keep - 1])
    assert bool((cascade.prefilter_scores(kept.features[:, : cascade.cheap]) >= cut - 1e-4).all())
    negatives = int((kept.target == 0).sum())
    assert 0.1 * cfg.ranker_keep < negatives < 0.3 * cfg.ranker_keep and bool((kept.target == 1).any())
