"""Tests of reeb_torch.eval: Table 3 from the package (no checkout needed), frame ranges,
the KITTI-moderate and per-class tables, and that the package never imports ``benchmarks``."""

from __future__ import annotations

import ast
import csv
import json
import shutil
from pathlib import Path

import pytest
import torch

from tests.conftest import DATA
from reeb_torch.eval import table3
from reeb_torch.runs.cli import main as reeb
from reeb_torch.datasets.folders import FrameRange, parse_frame_range, select_frames

REPO = Path(__file__).resolve().parents[2]
PACKAGE = REPO / "reeb_torch"
EXAMPLES = REPO / "examples" / "data"
FRAMES = ("000001", "000008")


def _example_kitti(root: Path, layout: str = "project") -> Path:
    """The bundled frames in a KITTI-format folder (KittiDataset's two layouts)."""
    img, lab = ("images", "labels") if layout == "project" else ("image_2", "label_2")
    for sub in (img, lab, "calib"):
        (root / sub).mkdir(parents=True)
    for i in FRAMES:
        shutil.copy(EXAMPLES / f"kitti_{i}.png", root / img / f"{i}.png")
        shutil.copy(EXAMPLES / f"kitti_{i}.txt", root / lab / f"{i}.txt")
        shutil.copy(EXAMPLES / f"kitti_{i}_calib.txt", root / "calib" / f"{i}.txt")
    return root


def _eval(*args) -> dict:
    """``reeb eval ARGS`` (the folders first), called from Python: its JSON record."""
    return reeb.main(["eval", *map(str, args)], prog_name="reeb", standalone_mode=False)


def _eval_exits(*args) -> int:
    """``reeb eval ARGS`` as from a shell (a usage error is a message and ``SystemExit``)."""
    with pytest.raises(SystemExit) as e:
        reeb.main(["eval", *map(str, args)], prog_name="reeb")
    return e.value.code


def _count_by_hand() -> tuple[dict[str, int], dict[str, int]]:
    """Objects per class, all and KITTI-moderate, read from the label files with plain Python."""
    classes = ("Car", "Pedestrian", "Cyclist", "Truck")
    every, moderate = dict.fromkeys(classes, 0), dict.fromkeys(classes, 0)
    for i in FRAMES:
        for line in (EXAMPLES / f"kitti_{i}.txt").read_text().splitlines():
            f = line.split()
            if not f or f[0] not in classes:
                continue
            every[f[0]] += 1
            trunc, occ, y1, y2 = float(f[1]), int(f[2]), float(f[5]), float(f[7])
            if y2 - y1 >= 25 and occ <= 1 and trunc <= 0.3:
                moderate[f[0]] += 1
    return every, moderate


def test_package_never_imports_benchmarks():
    offenders = []
    for path in PACKAGE.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            names = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            offenders += [f"{path.relative_to(REPO)}: {n}" for n in names if n.split(".")[0] == "benchmarks"]
        text = path.read_text()
        if "benchmarks/table3.py\"" in text or "spec_from_file_location" in text:
            offenders.append(f"{path.relative_to(REPO)}: loads a file from the checkout")
    assert not offenders, offenders
    assert Path(table3.__file__).resolve().parent == PACKAGE / "eval"


def test_the_evaluation_is_a_click_command_and_stays_inside_the_package():
    """``reeb eval`` is click (no argparse in the package); no module of the evaluation
    reaches beside the checkout for data or models (BING's folder is an option)."""
    import click

    assert isinstance(reeb.commands["eval"], click.Command)
    offenders = [f"{p.relative_to(REPO)}: argparse" for p in PACKAGE.rglob("*.py") if "argparse" in p.read_text()]
    offenders += [f"{p.relative_to(REPO)}: {word}" for p in (PACKAGE / "eval").rglob("*.py")
                  for word in ("../shared", '"shared"') if word in p.read_text()]
    assert not offenders, offenders


def test_reeb_eval_without_a_bing_model_skips_bing_with_a_note(tmp_path, capsys):
    data = _example_kitti(tmp_path / "kitti")
    record = _eval(data, "--methods", "bing", "--out", tmp_path / "t3")
    assert record["methods"]["bing"]["skipped"].startswith("no BING model folder given (--bing-model DIR")
    assert "skipped BING: no BING model folder given" in capsys.readouterr().out
    assert record["rerun"] == f"reeb eval {data} --out {tmp_path / 't3'} --methods bing"


@pytest.mark.parametrize(
    "text, first, last",
    [("0:39", 0, 39), ("40:59", 40, 59), ("40:", 40, None), (":9", None, 9), ("7", 7, 7), (" 000040:000059 ", 40, 59)],
)
def test_parse_frame_range(text, first, last):
    r = parse_frame_range(text)
    assert (r.first, r.last) == (first, last)


@pytest.mark.parametrize("bad", ["", ":", "a:3", "3:1", "1:2:3", "-1:4", "1.5"])
def test_parse_frame_range_rejects(bad):
    with pytest.raises(ValueError, match="frame range"):
        parse_frame_range(bad)


def test_select_frames_inclusive_and_numeric():
    ids = [f"{i:06d}" for i in range(60)]
    halves = [parse_frame_range("0:39"), parse_frame_range("40:59")]
    assert select_frames(ids, halves[:1]) == ids[:40]
    assert select_frames(ids, halves[1:]) == ids[40:]
    assert select_frames(ids, halves) == ids
    assert select_frames(ids, []) == ids
    assert select_frames(ids, [FrameRange(58, None, "58:")]) == ["000058", "000059"]
    with pytest.raises(ValueError, match="'kitti_000001' is not numeric"):
        select_frames(["kitti_000001"], halves)


@pytest.mark.parametrize("layout", ["project", "kitti"])
def test_table3_on_bundled_frames(tmp_path, monkeypatch, layout):
    data = _example_kitti(tmp_path / "kitti", layout)
    captured: dict[str, list[torch.Tensor]] = {}
    run_method = table3.run_method

    def spy(method, images, *args, **kwargs):
        boxes, timing = run_method(method, images, *args, **kwargs)
        captured[method.key] = boxes
        return boxes, timing

    monkeypatch.setattr(table3, "run_method", spy)
    monkeypatch.chdir(tmp_path)  # nothing is read from the checkout
    out = tmp_path / "t3"
    record = _eval(data, "--methods", "reeb-default", "--batch", "0", "--out", out, "--frames", "1", "--frames", "8")

    every, moderate = _count_by_hand()
    assert record["num_images"] == 2 and record["image_ids"] == list(FRAMES)
    assert record["num_objects"] == sum(every.values()) == 9
    assert record["splits"] == {"all": list(FRAMES), "1": ["000001"], "8": ["000008"]}
    res = record["methods"]["reeb-default"]
    assert res["recall"]["num_per_class"] == every
    assert res["recall_moderate"]["num_per_class"] == moderate
    assert sum(moderate.values()) == 5  # frame 1: the truck; frame 8: 4 of 6 cars

    # the recalls, another way: plain IoU loops over the captured proposals
    from reeb_torch.datasets.kitti import KittiDataset

    ds = KittiDataset(data)
    boxes = captured["reeb-default"]
    hits = {"all": [0, 0], "moderate": [0, 0]}
    per_class_hits: dict[str, list[int]] = {}
    few = {(k, t): 0 for k in (100, 300) for t in (0.3, 0.5, 0.7)}  # objects found by the top 100 / 300
    for i, item in enumerate(ds[j] for j in range(len(ds))):
        props = boxes[i][:2000].tolist()
        for g, name, occ, trunc in zip(item["boxes"].tolist(), item["class_names"],
                                       item["occluded"].tolist(), item["truncated"].tolist()):
            best = max((_iou(g, p) for p in props), default=0.0)
            for k, t in few:
                few[k, t] += max((_iou(g, p) for p in props[:k]), default=0.0) >= t
            hit = best >= 0.7
            hits["all"][0] += hit
            hits["all"][1] += 1
            per_class_hits.setdefault(name, [0, 0])
            per_class_hits[name][0] += hit
            per_class_hits[name][1] += 1
            if g[3] - g[1] >= 25 and occ <= 1 and trunc <= 0.3 + 1e-6:
                hits["moderate"][0] += hit
                hits["moderate"][1] += 1
    assert res["recall"]["micro"]["2000"]["0.7"] == pytest.approx(hits["all"][0] / hits["all"][1])
    assert res["recall_moderate"]["micro"]["2000"]["0.7"] == pytest.approx(
        hits["moderate"][0] / hits["moderate"][1])
    for name, (h, n) in per_class_hits.items():
        assert res["per_class_headline"]["all"][name] == pytest.approx(h / n)
    assert res["per_class_headline"]["all"]["Pedestrian"] is None  # no pedestrian: undefined
    assert record["ks"] == [100, 300, 500, 1000, 2000]
    for (k, t), n in few.items():
        assert res["recall"]["micro"][str(k)][f"{t:g}"] == pytest.approx(n / hits["all"][1]), (k, t)
    assert few[100, 0.7] < hits["all"][0]  # 100 proposals find fewer than 2000 here: the columns differ
    assert set(res["ar_micro"]) == {"100", "300", "500", "1000", "2000"}
    assert res["ar_micro"]["100"] <= res["ar_micro"]["300"] <= res["ar_micro"]["2000"]
    ci = res["splits"]["all"]["headline_interval"]  # the headline, with a frame-bootstrap interval
    assert ci["recall"] == pytest.approx(hits["all"][0] / hits["all"][1])
    assert ci["low"] <= ci["recall"] <= ci["high"] and ci["level"] == 0.95

    text = (out / "table3.txt").read_text()
    assert "over all objects (micro" in text and "headline" in text
    head = next(line for line in text.splitlines() if "proposals" in line and "|" in line)
    assert [c.strip() for c in head.split("|")[1:6]] == [f"{k} proposals" for k in (100, 300, 500, 1000, 2000)]
    assert "micro @100 / @300 / @500 / @1000 / @2000" in text  # AR at each count
    row_text = next(line for line in text.splitlines() if line.startswith("Ours** + learned ranking (default) "))
    shown = [float(v) for v in row_text.split("|")[1].split()]  # 100 proposals: IoU 0.5 and 0.7
    assert shown == [round(100 * few[100, t] / hits["all"][1], 1) for t in (0.5, 0.7)]
    # both bundled frames are KITTI frames the shipped ranking was fitted on: said, not hidden
    assert record["in_sample"] == {"reeb-default": {"000001": "kitti/000001", "000008": "kitti/000008"}}
    assert "In-sample: 2 of these 2 frames are pictures the learned ranking was fitted on" in text
    from types import SimpleNamespace

    two = SimpleNamespace(images=[ds[0]["image"], ds[1]["image"].flip(2)], ids=list(FRAMES))
    assert table3.in_sample_frames(["reeb-default", "reeb-training-free"], two) == \
        {"reeb-default": {"000001": "kitti/000001"}}  # a mirrored frame is another picture; V learns nothing
    assert "KITTI-moderate objects (micro, 5 objects" in text
    assert "Per-class recall (%) at 2000 proposals, IoU 0.7" in text
    assert "=== frames 1:" in text and "=== frames 8:" in text
    assert "with its 95 % interval" in text
    assert res["splits"]["all"]["versus_reference"] == {"reference": "reeb-default", "gained": 0, "lost": 0,
                                                        "p_value": 1.0}  # the default against itself
    assert json.loads((out / "table3.json").read_text())["methods"]["reeb-default"]["label"] == "Ours** + learned ranking (default)"
    rows = list(csv.DictReader(open(out / "table3.csv")))
    # 3 frame sets (all, 1, 8) x 2 object sets x (micro, class mean, 4 classes)
    assert len(rows) == 3 * 2 * 6
    row = next(r for r in rows if r["frames"] == "all" and r["objects"] == "moderate" and r["average"] == "micro")
    assert float(row["R@2000_IoU0.7"]) == pytest.approx(100 * hits["moderate"][0] / hits["moderate"][1], abs=0.006)
    whole = next(r for r in rows if r["frames"] == "all" and r["objects"] == "all" and r["average"] == "micro")
    assert float(whole["R@100_IoU0.3"]) == pytest.approx(100 * few[100, 0.3] / hits["all"][1], abs=0.006)
    assert float(whole["R@300_IoU0.7"]) == pytest.approx(100 * few[300, 0.7] / hits["all"][1], abs=0.006)
    assert {"AR@100", "AR@300"} <= set(whole)
    assert row["num_objects"] == "5"


def _iou(a: list[float], b: list[float]) -> float:
    iw = max(0.0, min(a[2], b[2]) - max(a[0], b[0]))
    ih = max(0.0, min(a[3], b[3]) - max(a[1], b[1]))
    inter = iw * ih
    union = (a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter
    return inter / union if union > 0 else 0.0


def test_table3_usage_errors_exit_2(tmp_path, capsys):
    empty = tmp_path / "empty"
    (empty / "images").mkdir(parents=True)
    no_labels = tmp_path / "nolabels"
    (no_labels / "images").mkdir(parents=True)
    shutil.copy(EXAMPLES / "kitti_000001.png", no_labels / "images" / "000001.png")
    data = _example_kitti(tmp_path / "kitti")
    cases = [
        ([empty], "no images"),
        ([no_labels], "no label folder"),
        ([data, "--frames", "20:30"], "no frame with an id in 20:30"),
        ([data, "--frames", "9:3"], "first id 9 is after last id 3"),
        ([data, "--max-proposals", "100"], "--top-k must be at least 2000"),
        ([data, "--cross-validate", "1"], "--cross-validate needs at least 2 folds, got 1"),
        ([data, "--cross-validate", "3"], "--cross-validate 3 needs at least as many frames, got 2"),
        ([data, "--leave-folder-out"], "--leave-folder-out needs two or more --data folders"),
        ([data, "--whole-drives"], "--whole-drives needs --cross-validate FOLDS"),
    ]
    for argv, message in cases:
        code = _eval_exits(*argv, "--out", tmp_path / "o")
        assert code == 2, argv
        assert message in capsys.readouterr().err, argv


@pytest.mark.slow
def test_reeb_eval_from_a_wheel_outside_the_checkout(tmp_path):
    """``pip install`` of a built wheel (not editable) into a fresh environment, then
    ``reeb eval`` from a folder outside the checkout. The fresh environment reuses this
    one's dependencies through a ``.pth`` line (no torch download); the package itself
    comes from the wheel only."""
    import site
    import subprocess
    import sys
    import sysconfig

    src = tmp_path / "src"
    src.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(REPO / name, src / name)
    shutil.copytree(PACKAGE, src / "reeb_torch", ignore=shutil.ignore_patterns("__pycache__"))
    wheels = tmp_path / "wheels"
    build = subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation",
                            "-w", str(wheels), str(src)], capture_output=True, text=True)
    if build.returncode != 0:
        pytest.skip(f"cannot build a wheel here: {build.stderr.strip()[-300:]}")
    env_dir = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(env_dir)], check=True)
    py = env_dir / "bin" / "python"
    purelib = subprocess.run([str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                             capture_output=True, text=True, check=True).stdout.strip()
    # this environment's packages (torch, ...) after the fresh one's own site-packages
    deps = [p for p in [*site.getsitepackages(), sysconfig.get_paths()["purelib"]] if Path(p).is_dir()]
    Path(purelib, "deps.pth").write_text("\n".join(dict.fromkeys(deps)) + "\n")
    (wheel,) = wheels.glob("reeb_torch-*.whl")
    subprocess.run([sys.executable, "-m", "pip", "--python", str(py), "install", "-q", "--no-deps", str(wheel)],
                   check=True, capture_output=True)

    work = tmp_path / "elsewhere"
    work.mkdir()
    data = _example_kitti(tmp_path / "kitti")
    where = subprocess.run([str(py), "-c", "import reeb_torch.eval as e; print(e.__file__)"], cwd=work,
                           capture_output=True, text=True, check=True).stdout.strip()
    assert Path(where).is_relative_to(purelib), where  # the wheel's copy, not the checkout
    assert Path(purelib, "reeb_torch", "py.typed").is_file()  # PEP 561: type checkers read its annotations
    r = subprocess.run([str(env_dir / "bin" / "reeb"), "eval", str(data), "--methods", "reeb-default",
                        "--frames", "1", "--batch", "0", "-o", "t3"], cwd=work, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "KITTI-moderate objects" in r.stdout and "Per-class recall" in r.stdout
    assert json.loads((work / "t3" / "table3.json").read_text())["num_objects"] == 3


def test_table3_exclude_fitted_leaves_out_the_frames_the_learned_ranking_saw(tmp_path, monkeypatch, capsys):
    """--exclude-fitted: the bundled frames (KITTI frames the shipped model was fitted on) are
    left out, a mirrored frame (another picture) stays; with nothing else, a usage error."""
    import cv2

    data = _example_kitti(tmp_path / "kitti")
    image = cv2.imread(str(data / "images" / "000008.png"))
    cv2.imwrite(str(data / "images" / "000009.png"), image[:, ::-1])
    width = image.shape[1]
    lines = []
    for line in (data / "labels" / "000008.txt").read_text().splitlines():
        f = line.split()
        f[4], f[6] = f"{width - float(f[6]):.2f}", f"{width - float(f[4]):.2f}"
        lines.append(" ".join(f))
    (data / "labels" / "000009.txt").write_text("\n".join(lines) + "\n")
    shutil.copy(data / "calib" / "000008.txt", data / "calib" / "000009.txt")
    monkeypatch.chdir(tmp_path)
    record = _eval(data, "--methods", "reeb-default,reeb-training-free", "--batch", "0", "--out", "t3",
                   "--exclude-fitted")
    assert record["image_ids"] == ["000009"] and record["in_sample"] == {}
    assert record["excluded_fitted"] == {"000001": "kitti/000001", "000008": "kitti/000008"}
    assert "--exclude-fitted: left out 2 frames the learned ranking was fitted on (000001, 000008)" in \
        capsys.readouterr().out
    assert "In-sample" not in (tmp_path / "t3" / "table3.txt").read_text()
    (data / "images" / "000009.png").unlink()
    code = _eval_exits(data, "--methods", "reeb-default", "--batch", "0", "--out", "t3b", "--exclude-fitted")
    assert code == 2 and "--exclude-fitted leaves 0 of the 2 frames" in capsys.readouterr().err
    # training-free rows alone learn nothing: nothing is left out
    free = _eval(data, "--methods", "reeb-training-free", "--batch", "0", "--out", "t3c", "--exclude-fitted")
    assert free["image_ids"] == ["000001", "000008"] and free["excluded_fitted"] == {}


def test_table3_on_two_folders_reports_each_and_both(tmp_path, monkeypatch):
    """Several --data folders: one run, every table for each folder and for all of them, each
    folder's numbers equal to a run on that folder alone."""
    a = _example_kitti(tmp_path / "a" / "kitti")
    b = _example_kitti(tmp_path / "b" / "kitti")  # same name: told apart by the path
    (b / "images" / "000008.png").unlink()  # b holds frame 1 only
    monkeypatch.chdir(tmp_path)
    both = _eval(a, b, "--methods", "reeb-default", "--batch", "0", "--out", "t3")
    assert both["data"] == [str(a), str(b)]
    assert both["splits"] == {"all": ["000001", "000008", "000001"], "a/kitti": ["000001", "000008"],
                              "b/kitti": ["000001"]}
    alone = _eval(a, "--methods", "reeb-default", "--batch", "0", "--out", "t3a")
    split = both["methods"]["reeb-default"]["splits"]
    assert split["a/kitti"]["all"]["recall"] == alone["methods"]["reeb-default"]["recall"]
    assert both["num_objects"] == alone["num_objects"] + split["b/kitti"]["all"]["recall"]["num_objects"]
    text = (tmp_path / "t3" / "table3.txt").read_text()
    assert "=== folder a/kitti: 2 frames" in text and "=== folder b/kitti: 1 frames" in text


def test_folder_names_and_splits():
    from reeb_torch.datasets.folders import folder_names, folder_splits

    assert folder_names(["/x/kitti", "/x/kitti_tracking"]) == ["kitti", "kitti_tracking"]
    assert folder_names(["/p/a/kitti", "/p/b/kitti"]) == ["a/kitti", "b/kitti"]
    items = [{"folder": "k"}, {"folder": "t"}, {"folder": "k"}]
    assert folder_splits(items) == [("k", [0, 2]), ("t", [1])]
    assert folder_splits([{"folder": "k"}] * 3) == []  # one folder: no split of its own


@pytest.mark.slow
@pytest.mark.kitti
def test_table3_cross_validated_row_is_reeb_fits_estimate(kitti_dir, tmp_path, monkeypatch):
    """--cross-validate: a row of the default ranked by the models reeb fit's cross-validation
    fits on the same frames (its hits are cross_validate's), placed after the default's own
    row, which is in sample; every row is then paired with training-free."""
    from reeb_torch import ReebConfig
    from reeb_torch.ranker import frames as F
    from reeb_torch.ranker import fit as RF
    from reeb_torch.ranker import cv as fit_cv
    from reeb_torch.tuning import FrameCache

    monkeypatch.chdir(tmp_path)
    record = _eval(kitti_dir, "--limit", "6", "--methods", "reeb-training-free,reeb-default", "--batch", "0",
                   "--out", "t3", "--cross-validate", "2")
    assert list(record["methods"]) == ["reeb-training-free", "reeb-default", "reeb-default-cv"]
    row = record["methods"]["reeb-default-cv"]
    assert row["timing"]["ms_per_img"] is None and row["timing"]["folds"] == 2
    frames = F.load_fit_frames([str(kitti_dir)], limit=6)
    cache = FrameCache(frames)
    cfg, opts = ReebConfig(), RF.FitOptions()
    cv = fit_cv.cross_validate(cache, cfg, cfg.training_free(), F.frame_samples(cache, cfg, opts), opts, 2)
    found = sum(int(h.sum()) for h in cv.ranked_hits)
    objects = sum(h.numel() for h in cv.ranked_hits)
    assert row["splits"]["all"]["headline_interval"]["recall"] == pytest.approx(found / objects)
    assert row["recall"]["micro"]["2000"]["0.7"] == pytest.approx(found / objects)
    paired = row["splits"]["all"]["versus_reference"]
    assert paired["reference"] == "reeb-training-free"
    assert (paired["gained"], paired["lost"]) == (
        sum(int((r & ~b).sum()) for r, b in zip(cv.ranked_hits, cv.base_hits)),
        sum(int((b & ~r).sum()) for r, b in zip(cv.ranked_hits, cv.base_hits)))
    text = (tmp_path / "t3" / "table3.txt").read_text()
    assert "Cross-validated: the row Ours** + learned ranking (cross-validated) ranks each of 2 blocks" in text
    assert "In-sample: 6 of these 6 frames" in text  # the default's own row
    assert "(fit " in text


TRACKING = DATA / "kitti_tracking"
DRIVE_FRAMES = ("t0000_000000", "t0000_000030", "t0000_000060", "t0000_000090", "t0000_000120", "t0000_000153",
                "t0016_000002", "t0016_000007", "t0016_000012")  # 6 frames of one drive, 3 of another


@pytest.mark.slow
def test_table3_whole_drives_row_never_fits_on_a_frame_of_a_held_out_drive(tmp_path, monkeypatch):
    """--whole-drives: a row before the cross-validated one, ranked by models fitted without
    any frame of the held-out block's drives (the training frames of each fit, checked by
    drive), the same models as reeb fit --whole-drives; the cross-validated row's models do see
    other frames of those drives here (so the check can fail); the row is in every table."""
    if not (TRACKING / "images").is_dir():
        pytest.skip(f"{TRACKING} is absent (set $REEB_DATA to the folder holding kitti_tracking/)")
    from reeb_torch import ReebConfig
    from reeb_torch.ranker import frames as F
    from reeb_torch.ranker import fit as RF
    from reeb_torch.ranker import cv as fit_cv
    from reeb_torch.tuning import FrameCache

    data = tmp_path / "kitti_tracking"
    for sub, ext in (("images", "png"), ("labels", "txt"), ("calib", "txt")):
        (data / sub).mkdir(parents=True)
        for f in DRIVE_FRAMES:
            shutil.copy(TRACKING / sub / f"{f}.{ext}", data / sub / f"{f}.{ext}")
    fits: list[tuple[int, set[str], set[str]]] = []  # (gap, held-out drives, training drives) per fit
    training_frames = F.training_frames

    def spy(blocks, held, ids, folders, similar=(), gap=2):
        train = training_frames(blocks, held, ids, folders, similar, gap)
        fits.append((gap, {F.drive_of(ids[i], folders[i]) for i in blocks[held]},
                     {F.drive_of(ids[i], folders[i]) for i in train}))
        return train

    monkeypatch.setattr(F, "training_frames", spy)
    monkeypatch.chdir(tmp_path)
    record = _eval(data, "--methods", "reeb-training-free,reeb-default", "--batch", "0", "--out", "t3",
                   "--cross-validate", "3", "--whole-drives")
    assert list(record["methods"]) == ["reeb-training-free", "reeb-default", "reeb-default-wd", "reeb-default-cv"]
    whole = [(held, train) for gap, held, train in fits if gap == len(DRIVE_FRAMES)]
    assert len(whole) == 3 and all(train and not held & train for held, train in whole)
    assert any(held & train for gap, held, train in fits if gap == 2)  # 10-fold style: the drive's other frames
    row = record["methods"]["reeb-default-wd"]
    assert row["label"] == "Ours** + learned ranking (whole drives held out)"
    assert row["timing"]["whole_drives"] and row["timing"]["folds"] == 3

    monkeypatch.setattr(F, "training_frames", training_frames)
    frames = F.load_fit_frames([str(data)])
    cache = FrameCache(frames)
    cfg, opts = ReebConfig(), RF.FitOptions()
    cv = fit_cv.cross_validate(cache, cfg, cfg.training_free(), F.frame_samples(cache, cfg, opts), opts, 3,
                          gap=len(frames))  # reeb fit --whole-drives's estimate
    found, objects = sum(int(h.sum()) for h in cv.ranked_hits), sum(h.numel() for h in cv.ranked_hits)
    assert row["recall"]["micro"]["2000"]["0.7"] == pytest.approx(found / objects)
    paired = row["splits"]["all"]["versus_reference"]
    assert paired["reference"] == "reeb-training-free"
    assert paired["gained"] == sum(int((r & ~b).sum()) for r, b in zip(cv.ranked_hits, cv.base_hits))

    text = (tmp_path / "t3" / "table3.txt").read_text()
    label, other = row["label"], record["methods"]["reeb-default-cv"]["label"]
    assert "Whole drives held out - the estimate to read first: the row " + label in text
    assert text.index("Whole drives held out") < text.index("Cross-validated: the row")
    lines = text.splitlines()
    # micro, moderate, class mean, the interval and its pairing, per class, AR: the row in each, before the 10-fold row
    assert sum(line.startswith(label + " ") for line in lines) == 7
    firsts = [i for i, line in enumerate(lines) if line.startswith(label + " ")]
    seconds = [i for i, line in enumerate(lines) if line.startswith(other + " ")]
    assert all(a < b for a, b in zip(firsts, seconds))
    csv_rows = list(csv.DictReader(open(tmp_path / "t3" / "table3.csv")))
    assert any(r["method"] == "reeb-default-wd" and r["average"] == "Pedestrian" for r in csv_rows)


def test_reeb_eval_scores_your_own_settings_as_reeb_propose_takes_them(tmp_path, monkeypatch):
    """``reeb eval --config FILE --set FIELD=VALUE``: a row with those settings (built as ``reeb
    propose`` builds them) beside the preset's own; the rerun line names them."""
    import json as _json

    from reeb_torch.runs import cli

    data = _example_kitti(tmp_path / "kitti")
    camera = tmp_path / "camera.json"
    camera.write_text(_json.dumps({"config": {"horizon": 0.47, "camera_height_m": 1.65}, "fit": {"route": "images"}}))
    monkeypatch.chdir(tmp_path)
    record = cli.main.main(["eval", str(data), "--preset", "training-free", "--config", str(camera), "--set",
                            "seed=0", "--batch", "0", "--out", "t3", "--device", "cpu"],
                           prog_name="reeb", standalone_mode=False)
    rows = record["methods"]
    assert list(rows) == ["reeb-training-free", "reeb-config"]  # the preset's row, then the settings'
    assert rows["reeb-config"]["label"].startswith("REEB with your settings")
    # the same settings as the preset's (the file holds its defaults): the same recall, object for object
    assert rows["reeb-config"]["recall"] == rows["reeb-training-free"]["recall"]
    assert "--config" in record["rerun"] and "--set seed=0" in record["rerun"]
    camera.write_text(_json.dumps({"config": {"horizon": 0.30}}))
    record = cli.main.main(["eval", str(data), "--preset", "training-free", "--config", str(camera), "--methods",
                            "reeb-training-free", "--batch", "0", "--out", "t3", "--device", "cpu"],
                           prog_name="reeb", standalone_mode=False)
    assert record["methods"]["reeb-config"]["recall"] != record["methods"]["reeb-training-free"]["recall"]


@pytest.mark.parametrize("args,words", [(["--set", "horizon=2"], "horizon"), (["--set", "nope=1"], "nope"),
                                        (["--top-k", "100"], "at least 2000")])
def test_reeb_eval_refuses_bad_settings_in_one_line(tmp_path, args, words):
    from click.testing import CliRunner

    from reeb_torch.runs.cli import main

    data = _example_kitti(tmp_path / "kitti")
    res = CliRunner().invoke(main, ["eval", str(data), "--out", str(tmp_path / "t3"), *args])
    assert res.exit_code == 2 and "Traceback" not in res.output, res.output
    assert words in res.output and not (tmp_path / "t3").exists()


def test_reeb_eval_runs_the_quick_rows_unless_asked_for_all(tmp_path, monkeypatch):
    """Without --methods: Edge Boxes and REEB's two presets, BING with its model; `all` and the
    benchmark's command run every row."""
    from click.testing import CliRunner

    from reeb_torch.eval import command as C
    from reeb_torch.eval.methods import DEFAULT_METHODS
    from reeb_torch.runs.cli import main

    data = _example_kitti(tmp_path / "kitti")
    seen = []
    monkeypatch.setattr(C, "run_table3", lambda options, out, rerun: seen.append(tuple(options.methods)) or {})
    bing = tmp_path / "bing"
    bing.mkdir()
    for args in ([], ["--bing-model", str(bing)], ["--methods", "all"]):
        res = CliRunner().invoke(main, ["eval", str(data), "--out", str(tmp_path / "t3"), *args])
        assert res.exit_code == 0, res.output
    assert set(seen[0]) == set(C.QUICK_METHODS) and set(seen[1]) == {"bing", *C.QUICK_METHODS}
    assert set(seen[2]) == set(DEFAULT_METHODS)
    C.table3_command("t3", data_default=[str(data)]).main(["--out", str(tmp_path / "t3")], standalone_mode=False)
    assert set(seen[3]) == set(DEFAULT_METHODS)
