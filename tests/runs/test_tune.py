"""reeb tune (reeb_torch.tuning and runs/tune.py): the search space is checked against
ReebConfig, the frame cache gives the generator's boxes bit for bit, a tiny study is
deterministic with a seed and resumable from SQLite, bad input is refused."""

from __future__ import annotations

import json

import pytest
import torch
from click.testing import CliRunner

from reeb_torch import ProposalGenerator, ReebConfig
from reeb_torch import tuning as T

pytest.importorskip("optuna")

BASE = ReebConfig(top_k=300, candidates_per_region=1500, size_ratio=1.6, min_window=24)  # a light base: the test times the search, not REEB
SPACE = {"nms_iou": {"type": "float", "low": 0.7, "high": 0.8}, "kappa": {"type": "float", "low": 1.4, "high": 1.8}}


@pytest.fixture(scope="module")
def small_kitti(kitti_dir, tmp_path_factory):
    """Four KITTI frames cut to 400 × 200 px around their objects (fast), in KITTI's layout."""
    from PIL import Image

    from reeb_torch.datasets.kitti import read_kitti_labels

    root = tmp_path_factory.mktemp("small_kitti")
    (root / "images").mkdir()
    (root / "labels").mkdir()
    made = 0
    for lp in sorted((kitti_dir / "labels").glob("*.txt")):
        objs = [o for o in read_kitti_labels(lp) if o.type in ("Car", "Pedestrian", "Cyclist", "Truck")]
        if not objs:
            continue
        cx = min(max((objs[0].box[0] + objs[0].box[2]) / 2 - 200, 0), 1242 - 400)
        x0, y0 = int(cx), 120
        lines = []
        for o in objs:
            x1, y1, x2, y2 = o.box
            if x1 >= x0 and x2 <= x0 + 400 and y1 >= y0 and y2 <= y0 + 200:
                lines.append(f"{o.type} 0.00 0 0 {x1 - x0:.2f} {y1 - y0:.2f} {x2 - x0:.2f} {y2 - y0:.2f} "
                             "1.5 1.6 3.9 0 1.6 10 0")
        if not lines:
            continue
        img = Image.open(next((kitti_dir / "images").glob(lp.stem + ".*"))).convert("RGB")
        img.crop((x0, y0, x0 + 400, y0 + 200)).save(root / "images" / f"{lp.stem}.png")
        (root / "labels" / lp.name).write_text("\n".join(lines) + "\n")
        made += 1
        if made == 4:
            break
    return root


def test_space_is_checked_against_the_config(tmp_path):
    assert set(T.load_space(None)) >= {"horizon", "camera_height_m", "kappa", "nms_iou", "candidates_per_region"}
    with pytest.raises(ValueError, match="unknown ReebConfig field.*not_a_field"):
        T.load_space({"not_a_field": {"type": "float", "low": 0, "high": 1}})
    with pytest.raises(ValueError, match="low <= high"):
        T.load_space({"kappa": {"type": "float", "low": 2, "high": 1}})
    with pytest.raises(ValueError, match="not a valid setting"):
        T.load_space({"nms_iou": {"type": "float", "low": 0.5, "high": 1.5}})
    with pytest.raises(ValueError, match="expected"):
        T.load_space({"kappa": {"type": "normal"}})
    p = tmp_path / "space.json"
    p.write_text("{not json")
    with pytest.raises(ValueError, match="not valid JSON"):
        T.load_space(p)


def test_bootstrap_interval():
    hits = [torch.tensor([True, False]), torch.tensor([True]), torch.tensor([], dtype=torch.bool)]
    labels = [torch.tensor([0, 1]), torch.tensor([1]), torch.tensor([], dtype=torch.int64)]
    est = T.bootstrap_interval(hits, labels, samples=500)
    assert est.recall == pytest.approx(2 / 3) and est.num_images == 2 and est.num_objects == 3
    assert 0 <= est.low <= est.recall <= est.high <= 1
    bal = T.bootstrap_interval(hits, labels, balanced=True, samples=500)
    assert bal.recall == pytest.approx((1 + 0.5) / 2)
    with pytest.raises(ValueError, match="no ground-truth"):
        T.bootstrap_interval(hits[2:], labels[2:])


def _random_frames(n: int, seed: int) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
    """``n`` frames of 0-5 objects of 3 classes, about 70 % found (some frames empty)."""
    gen = torch.Generator().manual_seed(seed)
    sizes = torch.randint(0, 6, (n,), generator=gen).tolist()
    hits = [torch.rand(k, generator=gen) < 0.7 for k in sizes]
    return hits, [torch.randint(0, 3, (k,), generator=gen) for k in sizes]


def test_bootstrap_interval_is_recall_interval():
    """reeb fit's and reeb tune's interval of micro recall is Table 3's, to the last bit, for
    any seed and number of draws (the same frames left out, the same draws)."""
    from reeb_torch.metrics.recall import recall_interval

    hits, labels = _random_frames(60, 0)
    assert T.bootstrap_interval(hits, labels) == recall_interval(hits)
    assert T.bootstrap_interval(hits, labels, level=0.9, samples=300, seed=5) == \
        recall_interval(hits, level=0.9, samples=300, seed=5)
    assert T.bootstrap_interval(hits, labels) != recall_interval(hits, seed=1)  # the seed matters
    with pytest.raises(ValueError, match="samples"):
        T.bootstrap_interval(hits, labels, balanced=True, samples=0)


def test_balanced_interval_uses_recall_intervals_draws():
    """The class-balanced interval is taken on recall_interval's draws: with one class it is the
    micro interval exactly, and with several it is the mean class recall on those very draws."""
    from reeb_torch.metrics.recall import recall_interval

    hits, labels = _random_frames(60, 1)
    one = [torch.zeros_like(lab) for lab in labels]
    bal, micro = T.bootstrap_interval(hits, one, balanced=True), recall_interval(hits)
    assert (bal.low, bal.high) == (micro.low, micro.high)
    keep = [i for i, h in enumerate(hits) if h.numel()]
    draw = torch.randint(len(keep), (500, len(keep)), generator=torch.Generator().manual_seed(2))
    vals = []
    for row in draw.tolist():
        h = torch.cat([hits[keep[i]] for i in row])
        lab = torch.cat([labels[keep[i]] for i in row])
        vals.append(sum(float(h[lab == c].double().mean()) for c in lab.unique()) / len(lab.unique()))
    low, high = torch.quantile(torch.tensor(vals, dtype=torch.float64),
                               torch.tensor([(1 - 0.95) / 2, (1 + 0.95) / 2], dtype=torch.float64)).tolist()
    est = T.bootstrap_interval(hits, labels, balanced=True, samples=500, seed=2)
    assert est.low == pytest.approx(low, abs=1e-12) and est.high == pytest.approx(high, abs=1e-12)
    assert est.recall == pytest.approx(T.objective(hits, labels, balanced=True))


def test_folds_need_frames():
    assert T.fold_blocks(5, 2) == [[0, 1, 2], [3, 4]]
    with pytest.raises(ValueError, match="3 labelled frames cannot make 4 folds"):
        T.fold_blocks(3, 4)


def test_objective_micro_and_balanced():
    hits = [torch.tensor([True, False, False]), torch.tensor([True])]
    labels = [torch.tensor([0, 0, 0]), torch.tensor([1])]
    assert T.objective(hits, labels) == pytest.approx(0.5)
    assert T.objective(hits, labels, balanced=True) == pytest.approx((1 / 3 + 1) / 2)


def test_cache_gives_the_generators_boxes(small_kitti):
    frames = T.load_frames([small_kitti], limit=2)
    cache = T.FrameCache(frames)
    cache.proposals(ReebConfig(), [0, 1])
    cfg = ReebConfig(kappa=1.5, horizon=0.3, nms_iou=0.7)
    got = cache.proposals(cfg, [0, 1])
    assert cache.front_computed == 2  # the second config reused the edges, groups and tables
    want = [ProposalGenerator(cfg)([im])[0]["boxes"] for im in frames.images]
    assert all(torch.equal(a, b) for a, b in zip(got, want))
    cache.proposals(cfg.replace(edge_threshold=0.1), [0])
    assert cache.front_computed == 3


def test_cache_reads_a_weights_file_written_again(small_kitti, tmp_path):
    """A weights file written again under the same path ranks with its new weights (the
    generator of a config reads its model once: the cache keys it by the file too)."""
    import os

    from reeb_torch.ranker import load_ranker, save_ranker

    frames = T.load_frames([small_kitti], limit=1)
    cache = T.FrameCache(frames)
    path = tmp_path / "model.safetensors"
    shipped = load_ranker("kitti")
    save_ranker(shipped, path)
    cfg = ReebConfig(ranker=str(path), top_k=300)
    first = cache.outputs(cfg, [0])[0]["scores"]
    flipped = __import__("copy").deepcopy(shipped)
    for m in flipped.members:
        m[-1].weight.neg_()
        m[-1].bias.neg_()
    save_ranker(flipped, path)
    os.utime(path, ns=(1, 1))  # another stamp even where the clock is coarse
    again = cache.outputs(cfg, [0])[0]["scores"]
    want = ProposalGenerator(cfg)([frames.images[0]])[0]["scores"]
    assert torch.equal(again, want) and not torch.equal(again, first)


def _tune(root, out, **kw):
    from reeb_torch.runs.tune import run_tune

    args = dict(trials=2, folds=2, seed=3, storage=None, resume=False, timeout=None, balanced=False, k=300,
                iou=0.5, limit=2, quiet=True, plots=False)
    args.update(kw)
    space = out.parent / "space.json"
    space.write_text(json.dumps(SPACE))
    return run_tune([str(root)], str(out), BASE, str(space), **args)


def test_tiny_tune_is_deterministic_and_resumable(small_kitti, tmp_path):
    db = f"sqlite:///{tmp_path / 'tune.db'}"
    a = _tune(small_kitti, tmp_path / "a.json", storage=db, plots=True)
    b = _tune(small_kitti, tmp_path / "b.json")
    for key in ("estimate", "base_estimate", "per_fold"):
        assert a["tune"][key] == b["tune"][key]
    assert a["config"] == b["config"]
    assert "cross-validated estimate" in a["text"] and "base" in a["text"]
    pytest.importorskip("matplotlib")
    assert (tmp_path / "a_trials.png").is_file()
    saved = json.loads((tmp_path / "a.json").read_text())
    ReebConfig.from_dict({**ReebConfig().to_dict(), **saved["config"]})
    with pytest.raises(ValueError, match="--resume"):
        _tune(small_kitti, tmp_path / "c.json", storage=db)  # the studies exist: resume or another storage
    c = _tune(small_kitti, tmp_path / "c.json", storage=db, resume=True, trials=3)
    import optuna

    assert c["tune"]["trials_completed"] == 3
    names = [s.study_name for s in optuna.get_all_study_summaries(db)]
    assert len(names) == 3 and all(len(optuna.load_study(study_name=n, storage=db).trials) == 3 for n in names)


def test_cli_tune_refuses_bad_input(small_kitti, tmp_path):
    from reeb_torch.runs.cli import main

    space = tmp_path / "space.json"
    space.write_text(json.dumps({"bogus": {"type": "float", "low": 0, "high": 1}}))
    run = CliRunner().invoke
    res = run(main, ["tune", str(small_kitti), "--space", str(space), "-o", str(tmp_path / "t.json")])
    assert res.exit_code == 2 and "bogus" in res.output
    res = run(main, ["tune", str(small_kitti), "--folds", "5", "-o", str(tmp_path / "t.json")])
    assert res.exit_code == 2 and "cannot make 5 folds" in res.output
    res = run(main, ["tune", str(small_kitti), "--resume", "-o", str(tmp_path / "t.json")])
    assert res.exit_code == 2 and "--storage" in res.output
    (tmp_path / "nolabels" / "images").mkdir(parents=True)
    (tmp_path / "nolabels" / "images" / "000000.png").write_bytes((small_kitti / "images").iterdir().__next__().read_bytes())
    res = run(main, ["tune", str(tmp_path / "nolabels"), "-o", str(tmp_path / "t.json")])
    assert res.exit_code == 2 and "no label folder" in res.output


def test_cli_tune_ctrl_c_points_to_resume(small_kitti, tmp_path, monkeypatch):
    from reeb_torch.runs import tune as R
    from reeb_torch.runs.cli import main

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(R, "run_tune", interrupted)
    db = f"sqlite:///{tmp_path / 't.db'}"
    res = CliRunner().invoke(main, ["tune", str(small_kitti), "--storage", db, "-o", str(tmp_path / "t.json")])
    assert res.exit_code == 130 and "--resume" in res.output
