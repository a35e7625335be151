"""The helper thread that runs the second half of a batch's compiled kernels."""

from __future__ import annotations


def test_on_two_cores_covers_the_batch_once_nested_and_after_fork():
    import os
    import sys

    from reeb_torch.stages._threads import on_two_cores

    for b in (0, 1, 2, 7, 8):
        seen: list[tuple[int, int]] = []
        on_two_cores(lambda lo, hi: seen.append((lo, hi)), b)
        assert sorted(i for lo, hi in seen for i in range(lo, hi)) == list(range(b))
    nested: list[tuple[int, int]] = []
    on_two_cores(lambda lo, hi: on_two_cores(lambda a, c: nested.append((lo + a, lo + c)), hi - lo), 8)
    assert sorted(i for lo, hi in nested for i in range(lo, hi)) == list(range(8))  # no deadlock
    if sys.platform != "win32":
        r, w = os.pipe()
        pid = os.fork()
        if pid == 0:  # the child must not wait on the parent's helper thread
            got: list[tuple[int, int]] = []
            on_two_cores(lambda lo, hi: got.append((lo, hi)), 4)
            os.write(w, b"ok" if sorted(got) == [(0, 2), (2, 4)] else b"no")
            os._exit(0)
        os.waitpid(pid, 0)
        assert os.read(r, 2) == b"ok"


def test_either_half_raises_in_the_caller_and_two_callers_each_cover_their_items():
    import threading

    import numpy as np
    import pytest

    from reeb_torch.stages._threads import on_two_cores

    def boom_at(k):
        def run(lo, hi):
            if lo <= k < hi:
                raise ValueError(f"item {k}")
        return run

    for k in (0, 7):  # the caller's half, then the helper's half
        with pytest.raises(ValueError, match=f"item {k}"):
            on_two_cores(boom_at(k), 8)
    seen: list[tuple[int, int]] = []
    on_two_cores(lambda lo, hi: seen.append((lo, hi)), 8)  # the helper survived both
    assert sorted(seen) == [(0, 4), (4, 8)]

    lock = threading.Lock()
    counts = np.zeros(64, np.int64)

    def caller(offset):
        for _ in range(50):
            def run(lo, hi):
                with lock:
                    counts[offset + lo: offset + hi] += 1
            on_two_cores(run, 32)

    threads = [threading.Thread(target=caller, args=(o,)) for o in (0, 32)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=60)
    assert (counts == 50).all()  # two callers share the helper thread: each item once per call


def test_torch_threads_are_one_inside_a_cpu_call_and_restored_after(sample_image):
    # torch's idle OpenMP workers would spin against the kernels' helper thread
    import pytest
    import torch

    from reeb_torch import ProposalGenerator
    from reeb_torch.stages._threads import torch_single_threaded

    before = torch.get_num_threads()
    seen = []
    gen = ProposalGenerator(top_k=50)
    real = gen._propose_batch
    gen._propose_batch = lambda *a, **k: (seen.append(torch.get_num_threads()), real(*a, **k))[1]
    gen([sample_image[:, :200, :400]])
    assert seen == [1] and torch.get_num_threads() == before
    with pytest.raises(RuntimeError):  # restored when the block raises, and nested blocks restore once
        with torch_single_threaded():
            with torch_single_threaded():
                assert torch.get_num_threads() == 1
            assert torch.get_num_threads() == 1
            raise RuntimeError
    assert torch.get_num_threads() == before


def test_scratch_memory_is_reused_only_inside_the_outermost_block():
    import numpy as np

    from reeb_torch.stages import _scratch

    outside = _scratch.empty("t.a", (3, 4))
    with _scratch.reusing():
        a = _scratch.empty("t.a", (3, 4))
        with _scratch.reusing():  # a nested call (a first call's warm-up) gets its own arrays
            assert not np.shares_memory(_scratch.empty("t.a", (3, 4)), a)
        b = _scratch.empty("t.b", (2, 2), np.int32)
    with _scratch.reusing():
        again = _scratch.empty("t.a", (2, 5), np.float32)  # the same memory, any dtype and shape
        bigger = _scratch.empty("t.b", (100, 100), np.int32)
    assert np.shares_memory(a, again) and not np.shares_memory(a, outside)
    assert not np.shares_memory(b, bigger) and bigger.shape == (100, 100) and bigger.flags.c_contiguous
    _scratch.release()
    with _scratch.reusing():
        assert not np.shares_memory(_scratch.empty("t.a", (3, 4)), a)


def test_results_and_kept_maps_do_not_share_the_reused_memory(sample_image):
    # a second call must not change what the first returned, nor the maps inspect keeps
    import torch

    from reeb_torch import ProposalGenerator

    gen = ProposalGenerator(top_k=300)
    a, b = sample_image[:, :220, :500], sample_image[:, 120:340, 600:1100]
    first = gen([a, a.flip(-1)])
    kept = [{k: v.clone() for k, v in r.items()} for r in first]
    front = gen.front_end([a])  # what reeb tune caches per frame
    edges = front[1].edges.clone()
    tables = front[1].tables().anchor.clone()
    gen([b, b.flip(-1)])
    for r, k in zip(first, kept):
        assert torch.equal(r["boxes"], k["boxes"]) and torch.equal(r["scores"], k["scores"])
    assert torch.equal(front[1].edges, edges) and torch.equal(front[1].tables().anchor, tables)
    again = gen.back_end([a], front)[0]
    alone = ProposalGenerator(top_k=300)([a])[0]
    assert torch.equal(again["boxes"], alone["boxes"]) and torch.equal(again["scores"], alone["scores"])


def test_a_mixed_batch_split_between_the_cores_equals_each_image_alone(sample_image):
    # each core takes half the images (grouped by size within its half): the same boxes and
    # scores as one image at a time, in the caller's order
    import torch

    from reeb_torch import ProposalGenerator

    crops = [sample_image[:, :200, :400], sample_image[:, 100:300, 300:700], sample_image[:, :180, :360],
             sample_image[:, 150:350, 600:1000], sample_image[:, 50:230, 800:1160]]
    gen = ProposalGenerator(top_k=200)
    gen.stage_times = {}
    both = gen(crops)
    stages = {k for k in gen.stage_times if "." not in k}  # not the ranking's parts (ranker.features, ...)
    assert stages == {"edges", "groups", "regions", "scoring", "ranker", "nms"}
    for crop, got in zip(crops, both):
        alone = gen([crop])[0]
        assert torch.equal(got["boxes"], alone["boxes"]) and torch.equal(got["scores"], alone["scores"])


def test_a_mixed_batch_gives_the_same_boxes_when_the_threads_switch_at_every_step(sample_image):
    # the two halves share the generator's caches: switching threads as often as Python
    # allows gives a race every chance to show, in the boxes or as an error
    import sys

    import torch

    from reeb_torch import ProposalGenerator

    crops = [sample_image[:, :200, :400], sample_image[:, 100:300, 300:700], sample_image[:, :180, :360],
             sample_image[:, 150:350, 600:1000], sample_image[:, 50:230, 800:1160]]
    gen = ProposalGenerator(top_k=200)
    alone = [gen([c])[0] for c in crops]
    before = sys.getswitchinterval()
    sys.setswitchinterval(1e-6)
    try:
        for r in range(6):
            order = [(r + k) % len(crops) for k in range(len(crops))]
            g = gen if r % 2 else ProposalGenerator(top_k=200)  # warm caches, and cold ones
            for i, got in zip(order, g([crops[i] for i in order])):
                assert torch.equal(got["boxes"], alone[i]["boxes"]) and torch.equal(got["scores"], alone[i]["scores"])
    finally:
        sys.setswitchinterval(before)


def test_one_image_split_by_rows_equals_the_same_image_in_one_piece(sample_image):
    # batch-1 latency: one image's kernels take half its rows (or strips, or
    # regions) each; every part must give the numbers of the whole image in one call
    import numpy as np
    import torch

    from reeb_torch.stages import edges as E
    from reeb_torch.stages import entropy as H
    from reeb_torch.stages import groups as G
    from reeb_torch.stages import scoring as S
    from reeb_torch.stages._threads import images_or_rows, serially

    seen: list[tuple[int, int, int, int]] = []
    images_or_rows(lambda *a: seen.append(a), 1, 9)
    assert sorted(seen) == [(0, 1, 0, 5), (0, 1, 5, 9)]
    seen.clear()
    images_or_rows(lambda *a: seen.append(a), 3, 9)
    assert sorted(seen) == [(0, 2, 0, 9), (2, 3, 0, 9)]

    x = sample_image[:, :102, :334]  # 51 × 167 working pixels: unequal halves
    for img in (x, x.float() / 255):
        split = E.working_gray([img], 0.5, with_green=True)
        with serially():
            whole = E.working_gray([img], 0.5, with_green=True)
        assert torch.equal(split[0], whole[0]) and torch.equal(split[1], whole[1])
        gray = split[0].clone()
        e_split = E.edge_map(gray, 1.0, 0.05, True, True).clone()
        bounds = torch.tensor([[0, 60], [40, 120], [100, 167]])
        h_split = H.region_entropy(gray, bounds)
        g_split = G.connected_groups(e_split, 8)  # cut at row 24, a tile border
        with serially():
            assert torch.equal(e_split, E.edge_map(gray, 1.0, 0.05, True, True))
            assert torch.equal(h_split, H.region_entropy(gray, bounds))
        pair = G.connected_groups(torch.cat([e_split, e_split]), 8)  # two images: each in one piece
        first = pair.batch == 0
        assert len(g_split) > 20 and bool((g_split.y2 >= 24).any()) and bool((g_split.y1 < 24).any())
        for f in ("batch", "x1", "y1", "x2", "y2", "magnitude"):
            assert torch.equal(getattr(g_split, f), getattr(pair, f)[first]), f

    g = torch.Generator().manual_seed(0)
    scores = torch.rand(1, 500, generator=g)
    scores[0, ::7] = float("-inf")
    members = np.concatenate([np.arange(0, 200), np.arange(150, 380), np.arange(300, 500)])
    starts = np.array([0, 200, 430, 630])
    budget = torch.tensor([[50, 300, 20]])
    split = S.select_per_region_cpu(scores, members, starts, budget).clone()
    with serially():
        assert torch.equal(split, S.select_per_region_cpu(scores, members, starts, budget))
    assert 200 < int(split.sum()) < 500  # every region marked some, not all


def test_started_runs_on_the_helper_and_its_wait_raises_what_it_raised():
    import threading

    import pytest

    from reeb_torch.stages._threads import serially, started

    where: list[str] = []
    wait = started(lambda: where.append(threading.current_thread().name))
    wait()
    assert where and where[0].startswith("reeb-half")
    with serially():  # the caller keeps both cores' work: here and now
        wait = started(lambda: where.append(threading.current_thread().name))
        assert where[-1] == threading.current_thread().name
        wait()

    def boom():
        raise ValueError("in the helper")

    wait = started(boom)
    with pytest.raises(ValueError, match="in the helper"):
        wait()


def test_one_image_builds_its_tables_beside_the_regions_and_waits_for_them(sample_image, monkeypatch):
    # batch-1 latency: one image's enclosed-sum tables are built on the helper
    # thread while the caller takes the regions; the same boxes as a batch's, and a stage
    # that raises meanwhile still waits for the helper (its tables are reused memory)
    import pytest
    import torch

    from reeb_torch import ProposalGenerator, ReebConfig
    from reeb_torch.selection import ScoreMaps

    gen = ProposalGenerator(ReebConfig(top_k=300))
    x = sample_image[:, :200, :600]
    gen([x])  # the first call's warm-up runs pictures of its own
    started: list[int] = []
    real_start = ScoreMaps.start_tables
    monkeypatch.setattr(ScoreMaps, "start_tables", lambda self: (started.append(1), real_start(self))[1])
    alone = gen([x])[0]
    assert started == [1]
    pair = gen([x, x.flip(-1)])[0]  # two images: each core takes one (serially: tables inline)
    assert torch.equal(alone["boxes"], pair["boxes"]) and torch.equal(alone["scores"], pair["scores"])

    settled: list[int] = []
    real_settle = ScoreMaps.settle
    monkeypatch.setattr(ScoreMaps, "settle", lambda self: (settled.append(self._pending is not None),
                                                           real_settle(self))[1])
    monkeypatch.setattr(gen.selection, "regions", lambda gray: (_ for _ in ()).throw(RuntimeError("regions")))
    with pytest.raises(RuntimeError, match="regions"):
        gen([x])
    assert settled == [True]  # still pending when the stage raised, then waited for
