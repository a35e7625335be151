"""The benchmark scripts on the bundled frames (no shared data): diagnose_recall.py's
per-stage recall and list of lost objects agree with each other and with the generator's
own output; ablations.py's --variant rows are configs of the default, paired with it;
selection_variants.py's variants reduce to the default where they change nothing, and
change the ranking as described where they do."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest
import torch
from torchvision.ops import box_iou

from reeb_torch import ProposalGenerator, ReebConfig
from reeb_torch.config_text import SettingError
from reeb_torch.datasets.folders import load_kitti

from tests.eval.test_eval import _example_kitti

REPO = Path(__file__).resolve().parents[2]


def _script(name: str):
    spec = importlib.util.spec_from_file_location(name, REPO / "benchmarks" / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def diagnose():
    return _script("diagnose_recall")


@pytest.fixture(scope="module")
def run(diagnose, tmp_path_factory):
    """--lost with a small top_k, so that objects are lost at NMS and at the top-k cut too."""
    root = _example_kitti(tmp_path_factory.mktemp("kitti"))
    out = root / "d.json"
    record = diagnose.main(["--data", str(root), "--lost", "--set", "top_k=150", "--json", str(out)])
    return root, record, json.loads(out.read_text())


def test_lost_objects_are_those_without_a_final_proposal(run):
    root, record, saved = run
    items, _ = load_kitti(root)
    gen = ProposalGenerator(ReebConfig(top_k=150))
    missed = []
    for it in items:
        boxes = gen([it["image"]])[0]["boxes"]
        best = box_iou(it["boxes"], boxes).max(1).values
        missed += [(it["image_id"], [round(float(v), 1) for v in it["boxes"][g]])
                   for g in torch.nonzero(best < 0.7).squeeze(1).tolist()]
    assert sorted((d["frame"], d["box"]) for d in record["lost"]) == sorted(missed)
    assert len(missed) > 0 and saved["lost"] == record["lost"]
    final = record["splits"]["all"]["stages"]["final top-k"]["R@0.7"]
    assert final == pytest.approx(100.0 * (1 - len(missed) / record["splits"]["all"]["num_objects"]))


def test_each_lost_object_names_a_stage_its_ious_bear_out(run, diagnose):
    _, record, _ = run
    stages = {d["lost_at"] for d in record["lost"]}
    assert stages <= set(diagnose.LOST_AT) and {"nms", "top-k"} & stages
    for d in record["lost"]:
        best = d["best_iou"]
        assert best["final top-k"] < 0.7
        if d["lost_at"] in diagnose.STAGES:  # the first stage whose best window is below 0.7
            i = diagnose.STAGES.index(d["lost_at"])
            assert best[diagnose.STAGES[i]] < 0.7 and all(best[s] >= 0.7 for s in diagnose.STAGES[:i])
        else:  # nms / top-k: a good window was among the region candidates
            assert best["region candidates"] >= 0.7
        if d["lost_at"] == "region candidates":
            assert d["region_rank"] >= d["region_budget"]  # its best good window ranked past the cut
        if d["lost_at"] == "top-k":
            assert d["nms_rank"] >= 150  # it survived NMS, ranked past the output
        if d["lost_at"] == "nms" and "suppressed_by_iou" in d:
            assert d["suppressed_by_iou"] < 0.7


def test_show_draws_every_lost_object(run, diagnose, tmp_path):
    root, record, _ = run
    png = tmp_path / "lost.png"
    diagnose.main(["--data", str(root), "--lost", "--set", "top_k=150", "--show", str(png)])
    import cv2

    sheet = cv2.imread(str(png))
    rows = -(-len(record["lost"]) // 8)
    assert sheet.shape == (rows * (150 + 16), 8 * 200, 3)
    assert all(d["nearest"] is None or len(d["nearest"]) == 4 for d in record["lost"])


def test_show_needs_lost(diagnose, tmp_path):
    with pytest.raises(SystemExit) as info:
        diagnose.main(["--data", str(tmp_path), "--show", str(tmp_path / "x.png")])
    assert info.value.code == 2


@pytest.mark.slow
def test_folds_rank_each_frame_by_a_model_fitted_without_its_block(diagnose, tmp_path):
    from reeb_torch.ranker import frames as F
    from reeb_torch.ranker import fit as RF
    from reeb_torch.ranker import cv as fit_cv
    from reeb_torch.tuning import FrameCache

    root = _example_kitti(tmp_path / "kitti")
    record = diagnose.main(["--data", str(root), "--folds", "2", "--set", "top_k=150"])
    # the very folds, fits and hits of reeb fit's cross-validation, not the shipped model's
    frames = F.load_fit_frames([root])
    cache, cfg, opts = FrameCache(frames), ReebConfig(top_k=150), RF.FitOptions()
    cv = fit_cv.cross_validate(cache, cfg, cfg.training_free(), F.frame_samples(cache, cfg, opts), opts, 2, k=150)
    held_out = 100.0 * float(torch.cat(cv.ranked_hits).float().mean())
    final = record["splits"]["all"]["stages"]
    assert final["final top-k"]["R@0.7"] == pytest.approx(held_out) and record["folds"] == 2
    shipped = diagnose.main(["--data", str(root), "--set", "top_k=150"])["splits"]["all"]["stages"]
    same = json.dumps(shipped["region candidates"]) == json.dumps(final["region candidates"])  # NaN for no object
    assert same  # the candidates do not depend on the model
    with pytest.raises(SystemExit) as info:  # training-free settings have no ranking to fit
        diagnose.main(["--data", str(root), "--folds", "2", "--preset", "training-free"])
    assert info.value.code == 2
    with pytest.raises(SystemExit) as info:  # whole drives of which blocks?
        diagnose.main(["--data", str(root), "--whole-drives"])
    assert info.value.code == 2


@pytest.mark.slow
def test_whole_drives_holds_out_the_drives_of_each_block(diagnose, tmp_path, monkeypatch):
    """--whole-drives: the training frames are reeb fit --whole-drives' (every frame of a
    held-out block's drives out), recorded as such."""
    from reeb_torch.ranker import frames as F

    gaps = []
    real = F.training_frames
    monkeypatch.setattr(F, "training_frames", lambda *a, **k: gaps.append(a[5]) or real(*a, **k))
    root = _example_kitti(tmp_path / "kitti")
    record = diagnose.main(["--data", str(root), "--folds", "2", "--whole-drives", "--set", "top_k=150"])
    frames = F.load_fit_frames([root])
    assert record["whole_drives"] and gaps and set(gaps) == {len(frames)}
    gaps.clear()
    assert not diagnose.main(["--data", str(root), "--folds", "2", "--set", "top_k=150"])["whole_drives"]
    assert gaps and set(gaps) == {2}


def test_lost_table_prints_every_object(run, diagnose):
    _, record, _ = run
    text = diagnose.format_lost(record["lost"])
    assert text.count("\n") == len(record["lost"]) + 1
    assert f"{len(record['lost'])} objects without a final proposal" in text


def test_ablation_variants_run_beside_the_default_only(tmp_path):
    ablations = _script("ablations")
    root = _example_kitti(tmp_path / "kitti")
    rows = ablations.main(["--data", str(root), "--batch", "2", "--out", str(tmp_path / "out"),
                           "--variant", "top_k=100; shadow_score=none", "--variant", "top_k=100"])
    assert [r["variant"] for r in rows] == ["default", "top_k=100, shadow_score=none", "top_k=100"]
    assert rows[0]["versus_default"] is None
    # top_k=100 keeps a prefix of the default's 2000 proposals: it finds nothing new, and its
    # recall is the default's less the objects it loses
    items, _ = load_kitti(root)
    n = sum(len(it["boxes"]) for it in items)
    pair = rows[2]["versus_default"]
    assert pair["gained"] == 0 and pair["lost"] > 0
    assert rows[2]["recall_07"] == pytest.approx(rows[0]["recall_07"] - pair["lost"] / n)
    # the bundled frames are KITTI frames the shipped ranking was fitted on: the table says so
    text = (tmp_path / "out" / "ablations.txt").read_text()
    assert "# ranking 'kitti': fitted on 2 of these 2 frames (000001, 000008): its rows are in-sample" in text


def test_ablations_say_when_a_model_cannot_tell_which_frames_it_saw(tmp_path, sample_image):
    from reeb_torch.ranker import BoxRanker, save_ranker
    from reeb_torch.ranker.features import feature_names

    ablations = _script("ablations")
    old = save_ranker(BoxRanker(feature_names(4)), tmp_path / "old.safetensors", {"frames": 3})
    lines: list[str] = []
    ablations.say_in_sample(lines.append, {"none", "kitti", str(old)}, [sample_image.flip(2)],
                            [{"image_id": "000009"}])
    assert lines == [f"# ranking {str(old)!r}: its file records no frame hashes (written before they were kept): "
                     "which of these frames it saw is unknown",
                     "# ranking 'kitti': fitted on 0 of these 1 frames (the same pictures, by frame hash)"]


def test_ablations_pair_with_another_reference(tmp_path):
    """--reference training-free: that row comes first and every other row pairs with it."""
    ablations = _script("ablations")
    root = _example_kitti(tmp_path / "kitti")
    rows = ablations.main(["--data", str(root), "--batch", "2", "--out", str(tmp_path / "out"),
                           "--reference", "training-free", "--only", "training-free", "paper"])
    assert [r["variant"] for r in rows][:1] == ["training-free"] and rows[0]["versus_default"] is None
    assert len(rows) > 1 and all(r["versus_default"] is not None for r in rows[1:])


def test_ablations_pair_each_folder(tmp_path):
    """Two --data folders: each row's recall and pairing with the default per folder, and the
    pairing over both is the sum of the folders'."""
    ablations = _script("ablations")
    a, b = _example_kitti(tmp_path / "a"), _example_kitti(tmp_path / "b")
    rows = ablations.main(["--data", str(a), str(b), "--batch", "2", "--out", str(tmp_path / "out"),
                           "--variant", "top_k=100"])
    per = rows[1]["versus_default_per_range"]
    assert list(per) == list(rows[1]["recall_07_per_range"]) == ["a", "b"]
    both = rows[1]["versus_default"]
    assert both["lost"] == per["a"]["lost"] + per["b"]["lost"] > 0 and both["gained"] == 0
    assert rows[1]["recall_07_per_range"]["a"] == rows[1]["recall_07_per_range"]["b"]  # the same frames


def test_a_bad_ablation_variant_is_a_usage_error_before_any_work(tmp_path, capsys):
    ablations = _script("ablations")
    with pytest.raises(SystemExit) as info:
        ablations.main(["--data", str(tmp_path / "absent"), "--out", str(tmp_path / "out"),
                        "--variant", "kappa=1.5;no_such_field=1"])
    assert info.value.code == 2
    assert "no_such_field" in capsys.readouterr().err and not (tmp_path / "out").exists()


@pytest.fixture(scope="module")
def variants_mod():
    return _script("selection_variants")


@pytest.fixture(scope="module")
def bundled(tmp_path_factory):
    items, _ = load_kitti(_example_kitti(tmp_path_factory.mktemp("kitti_sv")))
    return [it["image"] for it in items]


def test_selection_variants_at_their_neutral_settings_are_the_default(variants_mod, bundled):
    """Each variant reduces to the pipeline itself where it changes nothing: NMS at IoU 1
    inside the regions, no box narrower than 0 × its height, an empty second list."""
    cfg = ReebConfig()
    base, region, narrow = (ProposalGenerator(cfg), variants_mod.with_cut(cfg, variants_mod.RegionNMS, 1.0),
                            variants_mod.with_cut(cfg, variants_mod.NarrowShadow, 0.0, 0.2, False))
    plain = ProposalGenerator(cfg.replace(shadow_score="none"))
    for im in bundled:
        ref = base([im])[0]["boxes"]
        assert torch.equal(region([im])[0]["boxes"], ref)
        narrow.selection.cut.plain = variants_mod.run_captured(plain, im)[1]["scores"]
        assert torch.equal(narrow([im])[0]["boxes"], ref)
        assert torch.equal(variants_mod.interleave(ref, ref[:0], 0.3), ref)


@pytest.mark.slow
def test_selection_variants_change_the_ranking(variants_mod, bundled):
    """Narrow boxes scored x 0 instead of the shadow term score 0 and rank behind every
    other box; with NMS at 0.5 inside the regions no two candidates of a region overlap
    more than that (the default's candidates do)."""
    cfg = ReebConfig().training_free()
    plain = ProposalGenerator(cfg.replace(shadow_score="none"))
    narrow = variants_mod.with_cut(cfg, variants_mod.NarrowShadow, 0.6, 0.0, False)
    im = bundled[0]
    narrow.selection.cut.plain = variants_mod.run_captured(plain, im)[1]["scores"]
    out = narrow([im])[0]
    w, h = out["boxes"][:, 2] - out["boxes"][:, 0], out["boxes"][:, 3] - out["boxes"][:, 1]
    thin = w < 0.6 * h
    assert bool((out["scores"][thin] == 0).all()) and bool((out["scores"][~thin] > 0).all())
    if bool(thin.any()):
        assert int(torch.nonzero(thin)[0]) == int((~thin).sum())  # all of them after the rest
    for gen, most in ((variants_mod.with_cut(cfg, variants_mod.RegionNMS, 0.5), 0.5), (ProposalGenerator(cfg), None)):
        _, cap = variants_mod.run_captured(gen, im)
        worst = 0.0
        for idx in cap["grid"].region_windows:
            c = cap["grid"].boxes[idx[cap["chosen"][0][idx]]]
            worst = max(worst, float(box_iou(c, c).fill_diagonal_(0).max())) if len(c) > 1 else worst
        assert worst <= 0.5 + 1e-6 if most else worst > 0.5


def test_selection_variants_script_prints_paired_rows(variants_mod, tmp_path, capsys):
    root = _example_kitti(tmp_path / "kitti")
    record = variants_mod.main(["--data", str(root), "--family", "region-nms", "--out", str(tmp_path / "o")])
    assert [r["variant"] for r in record["rows"]][0] == "default"
    assert len(record["rows"]) == 4 and all("p_value" in r for r in record["rows"][1:])
    assert (tmp_path / "o" / "selection_variants.txt").read_text().startswith("# rerun: python benchmarks/selection_variants.py")


def test_speed_ab_pairs_runs_and_gives_the_exact_sign_test():
    from reeb_torch.metrics.recall import sign_test

    ab = _script("speed_ab")
    assert sign_test(6, 0) == pytest.approx(2 / 64)  # all six pairs one way: p = 0.031
    assert sign_test(5, 1) == pytest.approx(2 * 7 / 64)
    assert sign_test(0, 0) == 1.0 and sign_test(3, 3) == 1.0
    pairs = [({"batch 8": 6.0, "batch 1": 9.0}, {"batch 8": 5.0, "batch 1": 9.9}),
             ({"batch 8": 7.0, "batch 1": 10.0}, {"batch 8": 6.3, "batch 1": 9.0}),
             ({"batch 8": 5.0, "batch 1": 8.0}, {"batch 8": 5.5, "batch 1": 7.2})]
    s = ab.summarise(pairs)
    assert s["batch 8"]["ratios"] == [0.833, 0.9, 1.1] and s["batch 8"]["median_ratio"] == 0.9
    assert (s["batch 8"]["faster"], s["batch 8"]["slower"]) == (2, 1)
    assert s["batch 1"]["base_ms"] == [9.0, 10.0, 8.0] and s["batch 1"]["this_ms"] == [9.9, 9.0, 7.2]


def test_speed_ab_first_call_child_reports_the_warm_up_in_seconds(capsys):
    import json

    ab = _script("speed_ab")
    ab.main(["--child-first-call", "--preset", "default"])  # here the kernels are cached: it loads them
    got = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert list(got) == ["first call, s"] and 0 < got["first call, s"] < 60


def test_kernel_ab_times_a_kernel_against_a_revision_on_captured_inputs(tmp_path):
    import subprocess

    import numpy as np

    if subprocess.run(["git", "rev-parse", "HEAD"], cwd=REPO, capture_output=True).returncode != 0:
        pytest.skip("not a git checkout")
    ab = _script("kernel_ab")
    root = _example_kitti(tmp_path / "kitti")
    res = ab.main(["stages.scoring._integral_kernel", "--base", "HEAD", "--data", str(root), "--frames", "2",
                   "--batch", "1", "--reps", "2"])
    # the two bundled frames, one call per integral (edges, grey) each; HEAD's kernel is this one's
    assert res["images"] == 2 and res["calls"] >= 4 and res["same_outputs"]
    assert res["faster"] + res["slower"] <= 2 and res["base_ms"] > 0 and res["this_ms"] > 0
    a, b = [np.zeros(3), np.ones(2, np.int32)], [np.zeros(3), np.ones(2, np.int32)]
    assert ab.same_bits(a, b)
    b[0][1] = -0.0  # equal as numbers, not as bits
    assert not ab.same_bits(a, b) and not ab.same_bits(a, a[:1])


def test_speed_table_gives_the_ratio_of_medians_and_each_pass_spread():
    import statistics

    from reeb_torch.io import read_image

    speed = _script("speed")
    images = [read_image(p) for p in sorted((REPO / "examples" / "data").glob("kitti_*.png"))]
    res = {"default": speed.measure("default", images, [2, 1], 100, 3, "cpu")}
    main = res["default"]["uint8/b2"]
    floors = res["default"]["opencv_all"]
    assert len(main["all_totals"]) == len(floors) == len(main["to_opencv"]) == 3
    assert main["to_opencv"] == [t / f for t, f in zip(main["all_totals"], floors)]
    table = speed._table(res, ["default"], [2, 1])
    lines = table.splitlines()
    ratio = next(ln for ln in lines if ln.startswith("Total / OpenCV pass"))
    assert ratio.split()[-1] == f"{statistics.median(main['all_totals']) / statistics.median(floors):.1f}"
    spreads = [ln.split()[-1] for ln in lines if "lowest-highest" in ln]
    assert spreads == [f"{min(main['all_totals']):.1f}-{max(main['all_totals']):.1f}",
                       f"{min(main['to_opencv']):.1f}-{max(main['to_opencv']):.1f}"]


def test_speed_interleaves_the_columns_in_each_pass(monkeypatch):
    """Every pass runs every (column, input, batch) once, in a rotating order, so that the
    columns meet the same spells of the machine (they were timed one after another)."""
    from reeb_torch.io import read_image

    speed = _script("speed")
    order: list[str] = []
    timed = speed._timed_pass
    monkeypatch.setattr(speed, "_timed_pass", lambda gen, imgs, b, dev: order.append(gen.config.ranker) or
                        timed(gen, imgs, b, dev))
    images = [read_image(p) for p in sorted((REPO / "examples" / "data").glob("kitti_*.png"))][:1]
    res = speed.measure_all({"a": "training-free", "b": "default"}, images, [1], 50, 2, "cpu")
    assert len(order) == 2 * 2 * 2  # 2 passes x 2 columns x 2 inputs
    assert order[:4] != order[4:] and sorted(order[:4]) == sorted(order[4:]) == ["kitti", "kitti", "none", "none"]
    assert res["a"]["opencv_all"] == res["b"]["opencv_all"] and len(res["a"]["uint8/b1"]["all_totals"]) == 2


def test_speed_columns_are_presets_then_labelled_variants_of_the_default():
    speed = _script("speed")
    cols = speed.columns(["training-free"], [("keep 6000", "ranker_keep=6000; nms_iou=0.7")])
    assert list(cols) == ["training-free", "keep 6000"] and cols["training-free"] == "training-free"
    assert cols["keep 6000"] == ReebConfig(ranker_keep=6000, nms_iou=0.7)
    with pytest.raises(SettingError, match="no_such_field"):  # as reeb propose --set refuses it
        speed.columns([], [("bad", "no_such_field=1")])


def test_cv_paired_takes_only_settings_after_the_model():
    """cv_paired.py pairs settings that act after the ranking model (its fold models are the
    default's): a preset or --set pairs that change only those, and refuses the others."""
    cv = _script("cv_paired")
    assert cv.parse_variant('class_quota={"Pedestrian": 0.3, "Cyclist": 0.1, "Truck": 0.05}') == \
        ReebConfig(class_quota={"Pedestrian": 0.3, "Cyclist": 0.1, "Truck": 0.05})
    assert cv.parse_variant("top_k=500;nms_iou=0.7") == ReebConfig(top_k=500, nms_iou=0.7)
    with pytest.raises(ValueError, match="changes candidates_per_region, which the ranking model reads"):
        cv.parse_variant("candidates_per_region=20000")
    with pytest.raises(ValueError, match="'training-free' changes candidates_per_region, ranker"):
        cv.parse_variant("training-free")


def test_cv_paired_refit_takes_fit_options_and_the_fields_the_model_reads():
    cv = _script("cv_paired")
    cfg, opts = cv.parse_refit("hidden=32,32; members=2; candidates_per_region=20000; class_hidden=none")
    assert cfg == ReebConfig(candidates_per_region=20000)
    assert opts == {"hidden": (32, 32), "members": 2, "class_hidden": None}
    assert cv.parse_refit("balance=1") == (ReebConfig(), {"balance": 1.0})
    assert cv.parse_refit("prefilter_balance=1") == (ReebConfig(), {"prefilter_balance": 1.0})
    assert cv.parse_refit("prefilter_balance=none") == (ReebConfig(), {"prefilter_balance": None})
    assert cv.parse_refit("init=kitti; tune_lr=3e-4; tune_epochs=20") == \
        (ReebConfig(), {"init": "kitti", "tune_lr": 3e-4, "tune_epochs": 20})
    with pytest.raises(ValueError, match="no ranker="):
        cv.parse_refit("ranker=mine.safetensors")
    with pytest.raises(ValueError, match="members=two"):
        cv.parse_refit("members=two")
    assert cv.parse_refit("mirror=1") == (ReebConfig(), {"mirror": True})
    assert cv.parse_refit("mirror=off") == (ReebConfig(), {"mirror": False})
    assert cv.parse_refit("jitter=0.2") == (ReebConfig(), {"jitter": 0.2})
    assert cv.parse_refit("drop_features=place,log_v") == (ReebConfig(), {"drop_features": ("place", "log_v")})
    with pytest.raises(ValueError, match="mirror=2"):
        cv.parse_refit("mirror=2")


@pytest.mark.kitti
def test_cv_paired_refit_with_the_defaults_options_gives_the_defaults_hits(kitti_dir):
    """A refit that changes nothing fits the very fold models again (seeded): the same hits."""
    from reeb_torch.ranker import frames as F
    from reeb_torch.tuning import FrameCache

    cv = _script("cv_paired")
    cache = FrameCache(F.load_fit_frames([str(kitti_dir)], limit=6))
    default, again = cv.cross_validated_hits(cache, [], 0, 2, refits=[cv.parse_refit("")])
    assert all(torch.equal(a, b) for a, b in zip(default, again))


def test_cv_paired_over_seeds_counts_each_object_once():
    cv = _script("cv_paired")
    t, f = torch.tensor([True]), torch.tensor([False])
    # per seed: [default hits, variant hits], per frame; 3 objects over 2 frames
    seeds = [[[torch.tensor([True, False]), t], [torch.tensor([True, True]), f]],
             [[torch.tensor([False, False]), t], [torch.tensor([True, False]), t]]]
    # object 0: 1 seed against 2 (gained); object 1: 0 against 1 (gained); object 2: 2 against 1 (lost)
    assert cv.over_seeds(seeds, 1, [0, 1]) == {"gained": 2, "lost": 1, "p_value": 1.0}
    assert cv.over_seeds(seeds, 1, [1]) == {"gained": 0, "lost": 1, "p_value": 1.0}


def test_cv_paired_cuts_and_ar_come_from_each_objects_best_iou():
    cv = _script("cv_paired")
    # two frames; columns: best IoU within the top 2000, within the top 500
    best = [torch.tensor([[0.9, 0.6], [0.55, 0.55]]), torch.tensor([[0.72, 0.72]])]
    assert [h.tolist() for h in cv.hits_at(best, "@2000 IoU .7")] == [[True, False], [True]]
    assert [h.tolist() for h in cv.hits_at(best, "@500 IoU .7")] == [[False, False], [True]]
    assert [h.tolist() for h in cv.hits_at(best, "@2000 IoU .5")] == [[True, True], [True]]
    # AR over IoU 0.5, 0.55, ..., 0.95: 0.9 clears 9 of the 10 thresholds, 0.55 two, 0.72 five
    assert cv.average_recall(best, [0, 1]) == pytest.approx(100 * (9 + 2 + 5) / 30)


@pytest.mark.slow
def test_adapt_scores_four_ways_on_frames_away_from_the_adapt_block(tmp_path):
    """adapt.py: per ordered pair of folders, a base model fitted on the source, the first /
    last k target frames to adapt with, the other target frames to test on; the record
    holds each condition's recall and the fine-tuned model's pairings."""
    import shutil

    adapt = _script("adapt")
    a = _example_kitti(tmp_path / "a")
    b = tmp_path / "b"
    shutil.copytree(a, b)
    frames = __import__("reeb_torch.ranker.frames", fromlist=["x"]).load_fit_frames([str(a), str(b)])
    scens = adapt.scenarios(frames, [1], gap=2)
    assert [s["name"] for s in scens] == ["a -> b, first 1", "a -> b, last 1", "b -> a, first 1", "b -> a, last 1"]
    for s in scens:
        assert not set(s["test"]) & set(s["adapt"]) and set(s["source"]).isdisjoint(s["test"] + s["adapt"])
        assert len(s["test"]) == 1 and len(s["adapt"]) == 1
    record = adapt.main(["--data", str(a), str(b), "--k", "1", "--seeds", "0", "--out", str(tmp_path / "out")])
    assert set(record["scenarios"]) == {s["name"] for s in scens}
    for row in record["scenarios"].values():
        assert set(row["mean_recall"]) == set(adapt.CONDITIONS)
        assert set(row["hints_right"]) == {"base", "scratch", "fine-tuned"}
        assert all(0 <= v <= 100 for v in row["hints_right"].values())
        assert all(0 <= v <= 100 for v in row["mean_recall"].values())
    for pairs in record["paired"].values():
        assert set(pairs) == {"training-free", "base", "scratch"}
        assert all(p["low"] <= p["points"] <= p["high"] for p in pairs.values())
    assert (tmp_path / "out" / "adapt.txt").read_text().startswith("# rerun: python benchmarks/adapt.py")
    png = tmp_path / "out" / "adapt.png"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    png.unlink()
    assert adapt.main(["--plot", str(tmp_path / "out" / "adapt.json")]) == json.loads(
        (tmp_path / "out" / "adapt.json").read_text()) and png.is_file()  # redrawn from the record


@pytest.mark.kitti
def test_quality_head_adds_a_head_and_keeps_the_ranking(kitti_dir, tmp_path):
    """benchmarks/quality_head.py: the shipped ranking, bit for bit, plus a quality head that
    the generator reads with rank_quality."""
    from reeb_torch.ranker import load_ranker

    out = _script("quality_head").main(["--data", str(kitti_dir), "--limit", "3", "--hidden", "8",
                                        "--out", str(tmp_path / "q.safetensors")])
    model, shipped = load_ranker(str(out)), load_ranker("kitti")
    assert model.quality_hidden == (8,) and "quality_head" in model.meta["provenance"]
    for name, t in shipped.state_dict().items():
        assert torch.equal(t, model.state_dict()[name]), name


@pytest.mark.slow
def test_cuda_check_compares_and_times_on_the_device_it_is_given(tmp_path):
    """The GPU machine's prepared run, checked on the CPU: the boxes of a device against
    themselves are identical, recall is the same, and every preset and the detector is timed."""
    check = _script("cuda_check")
    root = _example_kitti(tmp_path / "kitti")
    out = check.main(["--data", str(root), "--device", "cpu", "--limit", "1", "--repeats", "1", "--no-tests",
                      "--out", str(tmp_path / "out")])
    record = json.loads(out.with_suffix(".json").read_text())
    assert set(record["boxes"]) == {"default", "training-free", "paper"}
    for r in record["boxes"].values():
        assert r["identical"] == r["frames"] == 1 and r["recall_cpu"] == r["recall_device"]
    assert set(record["speed"]) == {"default", "training-free", "detector kitti"}
    assert all(v > 0 for r in record["speed"].values() for v in r.values())
    assert "pytest -m cuda" not in out.read_text()


def test_cuda_check_refuses_a_missing_device(tmp_path, capsys):
    if torch.cuda.is_available():
        pytest.skip("this machine has a CUDA device")
    with pytest.raises(SystemExit):
        _script("cuda_check").main(["--out", str(tmp_path)])
    assert "no CUDA device here" in capsys.readouterr().err


def test_map_spread_compares_each_case_with_the_first_of_its_precision(tmp_path):
    """Two float32 cases on one thread compute the same maps: nothing differs; and the
    comparison counts what a changed value changes."""
    spread = _script("map_spread")
    images = tmp_path / "images"
    images.mkdir()
    (images / "a.png").write_bytes((REPO / "examples" / "data" / "kitti_000001.png").read_bytes())
    assert spread.main([str(images), "--limit", "1", "--case", "float32:1", "float32:1",
                        "--out", str(tmp_path / "out")]) == 0
    rows = json.loads((tmp_path / "out" / "spread.json").read_text())["rows"]
    assert [(r["reference"], r["differ_pct"], r["rel_l2"]) for r in rows] == [("float32:1", 0.0, 0.0)] * 2
    a = {"x": torch.tensor([1.0, 2.0, 3.0, 4.0], dtype=torch.float16)}
    b = {"x": torch.tensor([1.0, 2.0, 3.0, 4.5], dtype=torch.float16)}
    assert spread.compare(a, b) == {"differ_pct": 25.0, "max_abs": 0.5, "rel_l2": float(f"{0.5 / 30 ** 0.5:.3g}")}


def test_detector_cv_says_whether_the_seeds_agree_on_a_difference():
    cv = _script("detector_cv")
    a = [{"ap": {"Car": 50.0, "mAP": 40.0}}, {"ap": {"Car": 52.0, "mAP": 41.0}}]
    b = [{"ap": {"Car": 51.0, "mAP": 38.0}}, {"ap": {"Car": 51.5, "mAP": 40.0}}]
    d = cv.seed_differences(a, b)
    assert d == {"Car": {"per_seed": [1.0, -0.5], "seeds_agree": False},
                 "mAP": {"per_seed": [-2.0, -1.0], "seeds_agree": True}}
    assert cv.seed_line(d) == "per seed, B - A: Car +1.0 / -0.5 (seeds disagree), mAP -2.0 / -1.0 (seeds agree)"
    one = cv.seed_differences(a[:1], b[:1])
    assert one["mAP"] == {"per_seed": [-2.0], "seeds_agree": False} and "agree" not in cv.seed_line(one)
