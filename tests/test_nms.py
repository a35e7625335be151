"""nms_top_k equals torchvision's NMS truncated to k."""

from __future__ import annotations

import torch
from torchvision.ops import nms

from reeb_torch.nms import nms_top_k


def _boxes(n: int, gen: torch.Generator) -> torch.Tensor:
    xy = torch.rand(n, 2, generator=gen) * 200
    wh = torch.rand(n, 2, generator=gen) * 60 + 5
    return torch.cat([xy, xy + wh], 1)


def test_matches_torchvision_for_many_k():
    gen = torch.Generator().manual_seed(0)
    for n in (1, 50, 3000):
        b = _boxes(n, gen)
        s = torch.rand(n, generator=gen)
        ref = nms(b, s, 0.7)
        for k in (1, 10, 200, 5000):
            got = nms_top_k(b, s, 0.7, k, first=min(k, 16))
            assert torch.equal(got, ref[:k])


def test_ties_keep_input_order_and_empty_input():
    b = torch.tensor([[0.0, 0, 10, 10], [0, 0, 10, 10], [50, 50, 60, 60]])
    s = torch.tensor([1.0, 1.0, 1.0])
    assert nms_top_k(b, s, 0.5, 5).tolist() == [0, 2]
    assert nms_top_k(torch.zeros(0, 4), torch.zeros(0), 0.5, 5).numel() == 0
