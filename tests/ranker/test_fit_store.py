"""Fits in bounded memory: the on-disk row store (reeb_torch.ranker.store) that a fit appends
each frame's rows to and trains from, its checks (a kill mid-append, damage, another key),
the same weights from the store as from rows in memory, and training states that a killed
fit goes on from to the weights of one never stopped."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest
import torch

from reeb_torch.ranker import frames as F
from reeb_torch.ranker import fit as RF
from reeb_torch.ranker.training import fit_member
from reeb_torch.ranker.features import feature_names
from reeb_torch.ranker.store import Checkpoints, RowStore, StoreError

FIELDS = {"features": (torch.float32, [3]), "target": (torch.float32, []), "label": (torch.int64, [])}


def _frame(i: int, n: int) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(i)
    return {"features": torch.randn(n, 3, generator=g), "target": torch.rand(n, generator=g),
            "label": torch.arange(n) - i}


def test_store_keeps_finished_frames_and_cuts_what_a_kill_left(tmp_path):
    store = RowStore(tmp_path / "s", {"a": 1}, FIELDS)
    assert len(store) == 0 and store.rebuilt is None
    frames = [_frame(i, n) for i, n in enumerate([4, 0, 7])]
    for f in frames:
        store.append(f)
    again = RowStore(tmp_path / "s", {"a": 1}, FIELDS)
    assert len(again) == 3 and again.rebuilt is None
    for i, f in enumerate(frames):
        got = again.frames()[i]
        assert all(torch.equal(getattr(got, k), v) for k, v in f.items())
    # a kill mid-append: rows written without their index line, and half an index line
    with open(tmp_path / "s" / "features.bin", "ab") as fh:
        fh.write(b"\0" * 20)
    with open(tmp_path / "s" / "index.jsonl", "a") as fh:
        fh.write('{"frame": 3, "ro')
    cut = RowStore(tmp_path / "s", {"a": 1}, FIELDS)
    assert len(cut) == 3 and cut.rebuilt is None
    assert (tmp_path / "s" / "features.bin").stat().st_size == 11 * 3 * 4
    assert torch.equal(cut.frames().gathered("features"), torch.cat([f["features"] for f in frames]))


def test_store_of_other_settings_or_damaged_is_made_again(tmp_path):
    store = RowStore(tmp_path / "s", {"a": 1}, FIELDS)
    store.append(_frame(0, 5))
    assert RowStore(tmp_path / "s", {"a": 2}, FIELDS).rebuilt == "made with other settings, frames or version"
    store = RowStore(tmp_path / "s", {"a": 1}, FIELDS)
    store.append(_frame(0, 5))
    store.append(_frame(1, 5))
    data = bytearray((tmp_path / "s" / "target.bin").read_bytes())
    data[25] ^= 0xFF  # one byte of frame 1
    (tmp_path / "s" / "target.bin").write_bytes(bytes(data))
    damaged = RowStore(tmp_path / "s", {"a": 1}, FIELDS)
    assert damaged.rebuilt and "checksum" in damaged.rebuilt and len(damaged) == 0


def test_store_that_cannot_be_written_is_one_line(tmp_path):
    (tmp_path / "file").write_text("x")
    with pytest.raises(StoreError, match="cannot write the fit's row store"):
        RowStore(tmp_path / "file" / "s", {}, FIELDS)


def _frames(n_frames: int = 6, rows: int = 500) -> list[RF.Sample]:
    out = []
    for i in range(n_frames):
        g = torch.Generator().manual_seed(i)
        x = torch.randn(rows, len(feature_names(4)), generator=g)
        y = (x[:, 0] + 0.3 * torch.randn(rows, generator=g) > 1).float()
        label = torch.where(y > 0, torch.randint(0, 2, (rows,), generator=g), -1)
        out.append(RF.Sample(x, y, torch.rand(rows, generator=g) + 0.5, label))
    return out


def _stored(samples: list[RF.Sample], folder) -> RowStore:
    names = feature_names(4)
    fields = {"features": (torch.float32, [len(names)]), "target": (torch.float32, []),
              "weight": (torch.float32, []), "label": (torch.int64, []),
              "refine_x": (torch.float32, [1]), "refine_y": (torch.float32, [4]),
              "iou": (torch.float32, []), "object_weight": (torch.float32, [])}
    store = RowStore(folder, "test", fields)
    for s in samples:
        store.append({**{f.name: getattr(s, f.name) for f in dataclasses.fields(s)},
                      "refine_x": torch.zeros(0, 1)})
    return store


@pytest.mark.parametrize("orientation", [True, False])
def test_fit_from_the_store_gives_the_weights_of_rows_in_memory(tmp_path, orientation):
    """The rows read by minibatch from the memory maps (standardised per batch, the moments
    from the map) give the same weights bit for bit, for all frames and for a subset, with and
    without a column selection."""
    samples = _frames()
    store = _stored(samples, tmp_path / "s")
    opts = RF.FitOptions(epochs=3, hidden=(8,), batch=256, class_hidden=(4,), orientation=orientation)
    names = feature_names(4)
    for pick in (list(range(6)), [0, 2, 3, 5]):
        a = RF.fit_ranker([samples[i] for i in pick], names, opts, ("Car", "Pedestrian"))
        b = RF.fit_ranker(store.frames().subset(pick), names, opts, ("Car", "Pedestrian"))
        sa, sb = a.state_dict(), b.state_dict()
        assert sa.keys() == sb.keys() and all(torch.equal(sa[k], sb[k]) for k in sa)


class Killed(Exception):
    """What stops a fit in these tests (as a kill would, between two saved states)."""


class KillAfter:
    """A checkpoint slot that saves, then stops the fit once ``state[key]`` reaches ``n``."""

    def __init__(self, slot, n: int, key: str = "epoch") -> None:
        self.slot, self.n, self.key = slot, n, key

    def load(self):
        return self.slot.load()

    def save(self, state):
        self.slot.save(state)
        if state[self.key] >= self.n:
            raise Killed


def test_a_killed_fit_goes_on_to_the_weights_of_one_never_stopped(tmp_path):
    samples = _frames(2)
    x = torch.cat([s.features for s in samples])
    y = torch.cat([s.target for s in samples])
    w = torch.ones(len(y))
    opts = RF.FitOptions(epochs=4, batch=128)

    def net() -> torch.nn.Module:
        return torch.nn.Sequential(torch.nn.Linear(x.shape[1], 8), torch.nn.ReLU(), torch.nn.Linear(8, 1))

    whole = net()
    fit_member(whole, x, y, w, opts, seed=3)
    states = Checkpoints(tmp_path / "c", ["key"])
    broken = net()
    with pytest.raises(Killed):
        fit_member(broken, x, y, w, opts, seed=3, checkpoint=KillAfter(states.slot("m"), 2))
    resumed = net()
    fit_member(resumed, x, y, w, opts, seed=3, checkpoint=states.slot("m"))
    assert all(torch.equal(p, q) for p, q in zip(whole.state_dict().values(), resumed.state_dict().values()))
    other = Checkpoints(tmp_path / "c", ["another key"]).slot("m")
    assert other.load() is None  # a state saved for other options is not read


def test_checkpoint_on_a_full_disk_is_one_warning_and_the_fit_goes_on(tmp_path, monkeypatch):
    states = Checkpoints(tmp_path / "c", 1)
    slot = states.slot("m")
    slot.save({"epoch": 1})

    def full(*args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(torch, "save", full)
    with pytest.warns(RuntimeWarning, match="not keeping the training state.*No space left on device"):
        slot.save({"epoch": 2})
    monkeypatch.undo()
    slot.save({"epoch": 3})  # no more states once one failed: a kill now starts the training again
    assert slot.load() == {"epoch": 1}  # the state before stays
    assert [p.name for p in (tmp_path / "c").iterdir()] == ["m.pt"]


def test_image_files_decode_when_read(tmp_path):
    from reeb_torch.io import read_image

    src = str(Path(__file__).resolve().parents[2] / "examples" / "data" / "kitti_000001.png")
    images = F.ImageFiles([src, src], budget=0)
    assert len(images) == 2 and torch.equal(images[1], read_image(src))
    assert images._kept == {} and images[-1].shape[0] == 3
    stamps = images.stamps()
    assert stamps[0][0] == src and stamps[0][1] > 0
    json.dumps(stamps)


def test_reeb_fit_on_a_full_disk_is_one_line_and_the_weights_stay(tiny_kitti, tmp_path, monkeypatch):
    from click.testing import CliRunner

    from reeb_torch.runs.cli import main

    out = tmp_path / "r.safetensors"
    out.write_bytes(b"the weights before")

    def full(self, tensors):
        raise StoreError(f"{self.folder}: cannot write the fit's row store (No space left on device)")

    monkeypatch.setattr(RowStore, "append", full)
    res = CliRunner().invoke(main, ["fit", str(tiny_kitti), "--folds", "2", "-q", "-o", str(out), "--overwrite"])
    assert res.exit_code == 1 and "Traceback" not in res.output, res.output
    lines = [line for line in res.output.splitlines() if line.strip()]
    assert len(lines) == 1 and "No space left on device" in lines[0] and f"{out} is unchanged" in lines[0]
    assert out.read_bytes() == b"the weights before"


@pytest.mark.slow
def test_reeb_fit_stopped_goes_on_from_its_rows(tiny_kitti, tmp_path, monkeypatch):
    """A fit stopped after its rows (here: the final fit fails) leaves its store; the same
    command then says it goes on from it, makes no frame's rows again, and writes the weights
    a fit never stopped writes."""
    from click.testing import CliRunner
    from safetensors.torch import load_file

    from reeb_torch.ranker import fit as RF
    from reeb_torch.runs.cli import main

    args = ["fit", str(tiny_kitti), "--folds", "2", "--epochs", "1"]
    clean = CliRunner().invoke(main, [*args, "-q", "-o", str(tmp_path / "clean.safetensors")])
    assert clean.exit_code == 0, clean.output
    real = RF.fit_ranker
    calls = []

    def stop_at_the_final_fit(*a, **k):
        calls.append(1)
        if len(calls) == 3:  # two fold models, then the final fit
            raise Killed
        return real(*a, **k)

    monkeypatch.setattr(RF, "fit_ranker", stop_at_the_final_fit)
    out = tmp_path / "r.safetensors"
    with pytest.raises(Killed):
        CliRunner().invoke(main, [*args, "-q", "-o", str(out)], catch_exceptions=False)
    assert (tmp_path / ".r.safetensors.store" / "index.jsonl").read_text().count("\n") == 2
    monkeypatch.setattr(RF, "fit_ranker", real)
    made = []
    monkeypatch.setattr(F, "_frame_rows", lambda *a, **k: made.append(1) or pytest.fail("rows made again"))
    again = CliRunner().invoke(main, [*args, "-o", str(out)])
    assert again.exit_code == 0, again.output
    assert "going on from" in again.output and "2 of 2 frames' rows made before" in again.output
    a, b = load_file(tmp_path / "clean.safetensors"), load_file(out)
    assert all(torch.equal(a[k], b[k]) for k in a)
