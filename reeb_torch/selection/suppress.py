"""Eq. 13: greedy NMS of each image's candidates, best first, to ``top_k``; with the class
quota (``class_quota``), each class's share of the output first."""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from ..config import NmsSettings
from ..stages import windows as _windows
from ..stages.nms import boxes_valid, nms_top_k_many, nms_windows_cpu
from .grid_cache import GridCache
from .maps import ScoreMaps

__all__ = ["Suppression"]


class Suppression:
    """The final proposals: NMS (eq. 13), the quotas, the boxes in input pixels.

    Args:
        nms: the IoU thresholds and the number of proposals (``top_k``).
        cache: the per-grid tables, shared with the other parts (a new one if None).
    """

    def __init__(self, nms: NmsSettings, cache: GridCache | None = None) -> None:
        self.nms = nms
        self.cache = cache if cache is not None else GridCache()

    def suppress(self, maps: ScoreMaps, grid: _windows.WindowGrid, chosen: Tensor, scores: Tensor,
                 windows_out: list[Tensor] | None = None,
                 class_of: Tensor | None = None,
                 class_shares: tuple[float, ...] | None = None) -> list[dict[str, Tensor]]:
        """Greedy NMS (eq. 13) of each image's candidates, best first, stopping at ``top_k``
        (with ``class_of`` ``int8 [B, N]``, the class hinted for each candidate
        (:meth:`~reeb_torch.ranker.LearnedRanking.class_map`), and ``class_shares``, one
        share of ``top_k`` a class, each class's share first: :meth:`quota`): one dict per
        image, ``boxes`` ``float32 [N, 4]`` in input pixels and ``scores`` ``float32 [N]``.
        ``chosen``: ``bool [B, N]`` the candidates, ``scores``: ``float32 [B, N]`` theirs. On
        the CPU the windows are gathered, sorted and suppressed in one compiled pass
        (:func:`reeb_torch.stages.nms.nms_windows_cpu`), elsewhere by
        :func:`reeb_torch.stages.nms.nms_top_k_many`. ``windows_out``, if given, gets each
        image's ``int64 [N]`` window index of each output row."""
        b, dev = scores.shape[0], scores.device
        fx, fy = maps.fx, maps.fy
        to_input = torch.tensor([fx, fy, fx, fy], device=dev)
        boxes_in = self.cache.grid_cached(("boxes_in", fx, fy, str(dev)), grid,
                                    lambda: self.cache.device_tensor(grid.boxes, dev) / to_input)
        class_share = (torch.tensor(class_shares, device=dev)
                       if class_of is not None and class_shares is not None else None)
        quota = class_share is not None
        ok = (self.cache.grid_cached(("boxes_ok", fx, fy), grid, lambda: boxes_valid(boxes_in))
              if dev.type == "cpu" and boxes_in.dtype == torch.float32 else None)
        groups = need = None  # with a quota: past top_k only until each class has its share of the kept boxes
        if class_share is not None:
            assert class_of is not None  # class_share is made only with it
            groups, need = class_of.long().clamp(min=0), self.quota_counts(class_share)
        thin = (self.nms.nms_iou_thin, self.nms.nms_thin_aspect)
        kept = nms_windows_cpu(chosen, boxes_in, scores, self.nms.nms_iou, self.nms.top_k, ok, groups, need, thin)
        cands = None
        if kept is not None:
            pairs = [(boxes_in, scores[i]) for i in range(b)]
            windows = kept
        else:
            cands = [torch.nonzero(chosen[i]).squeeze(1) for i in range(b)]
            pairs = [(boxes_in[c], scores[i, c]) for i, c in enumerate(cands)]
            kept = nms_top_k_many(pairs, self.nms.nms_iou, max(len(p[1]) for p in pairs) if quota else self.nms.top_k,
                                  thin=thin)
            windows = [c[k] for c, k in zip(cands, kept)]
        results = []
        h_in, w_in = maps.input_size
        for i, ((bx, sc), keep_idx, win) in enumerate(zip(pairs, kept, windows)):
            if class_share is not None:
                assert class_of is not None  # class_share is made only with it
                keep_idx = self.quota(keep_idx, class_of[i, win].long().clamp(min=0), class_share,
                                      whole=True)[: self.nms.top_k]
            if windows_out is not None:
                windows_out.append(keep_idx if cands is None else cands[i][keep_idx])
            # the contract 0 <= x1 < x2 <= W, 0 <= y1 < y2 <= H in input pixels: a window on
            # the last working column maps back to W plus a rounding error (odd sides at
            # scale 0.5: 99.0000076 for W = 99); after NMS, so the ranking is unchanged
            if bx.device.type == "cpu":  # numpy's take and clip: the same copies, without torch's pool
                idx = keep_idx.numpy()
                b_np = np.take(bx.numpy(), idx, axis=0)
                np.clip(b_np[:, 0::2], 0.0, float(w_in), out=b_np[:, 0::2])
                np.clip(b_np[:, 1::2], 0.0, float(h_in), out=b_np[:, 1::2])
                results.append({"boxes": torch.from_numpy(b_np), "scores": torch.from_numpy(np.take(sc.numpy(), idx))})
                continue
            boxes = bx[keep_idx].contiguous()  # a copy (indexed): clamped in place below
            boxes[:, 0::2] = boxes[:, 0::2].clamp(0.0, float(w_in))
            boxes[:, 1::2] = boxes[:, 1::2].clamp(0.0, float(h_in))
            results.append({"boxes": boxes, "scores": sc[keep_idx].contiguous()})
        return results

    def quota(self, keep: Tensor, region: Tensor, share: Tensor, whole: bool = False) -> Tensor:
        """Eq. 9 on the output: of the ``top_k`` proposals, region r gets up to
        ``top_k · share_r / Σ share`` (its best after NMS); places a region leaves empty go
        to the best of the rest. ``keep`` is in descending score order and stays so. With
        ``whole``, the shares are fractions of ``top_k`` as they are (not normalised): the
        class quota (``region`` then each box's class)."""
        k = self.nms.top_k
        if keep.numel() <= k:
            return keep
        total = 1.0 if whole else float(share.sum())
        if total <= 0:
            return keep
        quota = self.quota_counts(share, total)  # (R,)
        onehot = torch.nn.functional.one_hot(region, share.numel())
        rank = (onehot.cumsum(0) * onehot).sum(1)  # 1-based rank within its region
        first = rank <= quota[region]
        n_first = int(first.sum())
        rest = torch.nonzero(~first).squeeze(1)[: max(0, k - n_first)]
        sel = torch.cat([torch.nonzero(first).squeeze(1), rest]).sort().values
        return keep[sel]

    def quota_counts(self, share: Tensor, total: float = 1.0) -> Tensor:
        """``int64 [R]``: how many of the ``top_k`` proposals each share draws in :meth:`quota`
        (``floor(top_k · share / total)``)."""
        return torch.floor(share * (self.nms.top_k / total)).long()
