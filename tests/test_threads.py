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
