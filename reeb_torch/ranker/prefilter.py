"""The learned ranking's prefilter, compiled: the first layer of a one-hidden-layer MLP over
the cheap feature columns (:func:`~reeb_torch.ranker.features.cheap_count`) of every
candidate, with the window columns' share of it tabulated once per window grid
(:class:`~reeb_torch.ranker.step.LearnedRanking` builds the table).
"""

from __future__ import annotations

import numba
import numpy as np
import torch
from torch import Tensor

from ..stages._threads import on_two_cores

__all__ = ["prefilter_cpu"]


@numba.njit(cache=True, nogil=True, fastmath={"reassoc", "nsz", "contract"})
def _prefilter_kernel(table: np.ndarray, scores: np.ndarray, share: np.ndarray, entropy: np.ndarray,
                      region_of: np.ndarray, bi: np.ndarray, ni: np.ndarray, mean: np.ndarray, scale: np.ndarray,
                      w_dyn: np.ndarray, w_out: np.ndarray, b_out: np.float32, out: np.ndarray, lo: int,
                      hi: int) -> None:  # pragma: no cover - compiled
    """Rows ``lo:hi`` of :func:`prefilter_cpu`. The hidden units in SIMD lanes: the ReLU a
    ``max``, not a branch (a unit's sign is a coin toss from row to row), and the output's
    sum over the units reassociated (``fastmath``), not one dependent add after another
    (the logits move by float32 rounding; timed with ``benchmarks/speed_ab.py``, docs/results.md)."""
    nh = table.shape[1]
    wv, ws, we = w_dyn[:, 0].copy(), w_dyn[:, 1].copy(), w_dyn[:, 2].copy()
    zero = np.float32(0.0)
    for k in range(lo, hi):
        b, n = bi[k], ni[k]
        r = region_of[n]
        d0 = (np.float32(np.log(max(float(scores[b, n]), 1e-6))) - mean[0]) / scale[0]
        d1 = (np.float32(share[b, r]) - mean[1]) / scale[1]
        d2 = (np.float32(entropy[b, r]) - mean[2]) / scale[2]
        acc = zero
        for j in range(nh):
            acc += w_out[j] * max(table[n, j] + wv[j] * d0 + ws[j] * d1 + we[j] * d2, zero)
        out[k] = acc + b_out


def prefilter_cpu(table: Tensor, scores: Tensor, share: Tensor, entropy: Tensor, region_of: Tensor, bi: Tensor,
                  ni: Tensor, mean: Tensor, scale: Tensor, w_dynamic: Tensor, w_out: Tensor, b_out: float) -> Tensor:
    """A one-hidden-layer ReLU network over the cheap columns of the candidates ``(bi, ni)``,
    compiled: ``w_out · relu(table[ni] + w_dynamic · d) + b_out``, ``float32 [K]``, where ``d``
    is the candidate's V (log), its region's share and entropy (``scores [B, N]``, ``share``,
    ``entropy [B, R]``, ``region_of [N]``), standardised by ``mean`` and ``scale`` ``[3]``.

    ``table``: ``float32 [N, H]`` the hidden layer's input from the window columns
    (:func:`window_features`, standardised, times their weights, plus the bias) of every window
    of the grid, computed once per grid; ``w_dynamic [H, 3]`` and ``w_out [H]`` the weights. The
    same function as the tensor ops to float32 rounding (the sums run in another order)."""
    out = np.empty(len(bi), np.float32)
    f32 = lambda t: t.detach().float().contiguous().numpy()  # noqa: E731
    args = (table.numpy(), scores.numpy(), share.double().numpy(), entropy.double().numpy(), region_of.numpy(),
            bi.numpy(), ni.numpy(), f32(mean), f32(scale), f32(w_dynamic), f32(w_out), np.float32(b_out), out)
    on_two_cores(lambda lo, hi: _prefilter_kernel(*args, lo, hi), len(bi))
    return torch.from_numpy(out)
