"""Sec. 3.4 — denoising and edge detection: Gaussian blur, Sobel magnitude, isolated
edge removal.

All functions take and return batched tensors; shapes are stated per function.
"""

from __future__ import annotations

import functools
import math

import kornia
import numba
import numpy as np
import torch
import torch.nn.functional as F
from numba.core import types as _nbtypes
from numba.extending import intrinsic
from torch import Tensor

from . import _scratch
from ._threads import images_or_rows

__all__ = ["working_size", "working_images", "to_gray", "working_gray", "green_mask", "gaussian_blur", "sobel_magnitude",
           "gradient_magnitude", "thin", "remove_isolated", "edge_map"]


def working_size(height: int, width: int, scale: float) -> tuple[int, int]:
    """``(h, w)`` of a ``height × width`` image at the working resolution ``scale``
    (rounded, at least one pixel): the one rule the resize, the compiled front end and the
    size check share."""
    return max(1, int(round(height * scale))), max(1, int(round(width * scale)))


def working_images(images: list[Tensor], scale: float) -> Tensor:
    """``(B, 3, h, w)`` float32: equal-sized ``(3, H, W)`` images (uint8, or float32 in
    [0, 1]) at the working resolution (:func:`working_size`), each resized on its own
    (antialiased bilinear when shrinking) and then stacked (stacking the full-resolution
    images first would copy 4× the data); uint8 images are converted to [0, 1] first. The
    tensor path of the front end (:func:`working_gray` is the compiled one)."""
    images = [x.float().div_(255.0) if x.dtype == torch.uint8 else x for x in images]
    if scale == 1.0:
        return torch.stack(images) if len(images) > 1 else images[0][None]
    size = working_size(images[0].shape[-2], images[0].shape[-1], scale)
    small = [F.interpolate(x[None], size=size, mode="bilinear", align_corners=False, antialias=scale < 1)
             for x in images]
    return torch.cat(small) if len(small) > 1 else small[0]


def to_gray(images: Tensor) -> Tensor:
    """RGB ``(B, 3, H, W)`` in [0, 1] to grey ``(B, 1, H, W)`` in [0, 1] (ITU-R 601 weights,
    as OpenCV's ``COLOR_RGB2GRAY``)."""
    return kornia.color.rgb_to_grayscale(images)


def working_gray(images: list[Tensor], scale: float, with_green: bool = False,
                 outside: list[int] | None = None) -> tuple[Tensor, Tensor | None] | None:
    """``(grey, green_counts)`` at the working resolution from equal-sized ``(3, H, W)``
    images (uint8, or float32 in [0, 1]): grey ``(B, 1, h, w)`` float32 with ``h, w`` =
    :func:`working_size`, and with ``with_green`` the pixel counts of :func:`green_mask`
    of the resized colour image, ``int32 (B, h + 1, w + 1)``, the same table as
    ``scoring.count_integral(green_mask(...))``, counted as the rows come out (else
    ``None``). ``None`` where this compiled path does not apply (then resize with
    ``F.interpolate`` and use :func:`to_gray`). Given a list ``outside``, it is filled with
    each image's count of values outside [0, 1] (NaN included), counted as the pass reads
    them (no second pass over a float image; −1 where the pass does not read every input
    row, so the count is unknown).

    It is the same computation as ``to_gray(F.interpolate(x / 255, antialias=True))``,
    operation for operation and bit for bit (tested): torch's antialiased bilinear
    weights (read off torch itself, per image size), its horizontal-then-vertical passes
    with fused multiply-adds, and kornia's ``addcmul`` grey, in one compiled pass per
    image (numba) that never writes the colour image at either resolution. It applies on
    the CPU for ``scale < 1`` where torch's kernels are the fused multiply-add builds (x86
    AVX2/AVX-512) and, for filters longer than four taps (``scale < 0.5``, or an odd
    width such as KITTI's 1241 px at 0.5), where :func:`_sums_as_torch` finds torch's
    order of summing; elsewhere it returns ``None``."""
    x0 = images[0]
    if not (0 < scale < 1) or x0.device.type != "cpu" or x0.dtype not in (torch.uint8, torch.float32):
        return None
    if torch.backends.cpu.get_cpu_capability() not in ("AVX2", "AVX512"):
        return None
    _, h, w = x0.shape
    ho, wo = working_size(h, w, scale)
    if not _sums_as_torch(h, w, ho, wo):
        return None
    xlo, xn, xw = _aa_weights(w, wo)
    ylo, yn, yw = _aa_weights(h, ho)
    span = _regular_span(w, wo)
    arrays = [_kernel_pair(im) for im in images]
    out = _scratch.empty("front.grey", (len(images), 1, ho, wo), np.float32)
    green = (_scratch.empty("front.green", (len(images), ho + 1, wo + 1), np.int32) if with_green
             else np.empty((len(images), 0, 0), np.int32))

    parts = []
    counts: list[tuple[int, int]] = []

    def run(lo: int, hi: int, r0: int, r1: int) -> None:
        for i in range(lo, hi):
            counts.append((i, _working_gray_kernel(*arrays[i], xlo, xn, xw, ylo, yn, yw, span, out[i, 0], green[i],
                                                   r0, r1)))
        parts.append((lo, hi, r0, r1))

    images_or_rows(run, len(images), ho)
    if outside is not None:
        every_row = _reads_every_row(h, ho)
        outside[:] = [sum(c for j, c in counts if j == i) if every_row else -1 for i in range(len(images))]
    if with_green:  # a part of the rows below the first counted from zero at its first row
        for lo, hi, r0, r1 in sorted(parts, key=lambda p: p[2]):
            if r0 > 0:
                green[lo:hi, r0 + 1: r1 + 1] += green[lo:hi, r0: r0 + 1]
    return torch.from_numpy(out), torch.from_numpy(green) if with_green else None


def green_mask(images: Tensor) -> Tensor:
    """Green-dominant pixels of RGB ``(B, 3, H, W)``: ``float32 (B, H, W)``, 1 where G > R
    and G > B, else 0 (vegetation, for ``ReebConfig.vegetation_score``)."""
    r, g, b = images.unbind(1)
    return ((g > r) & (g > b)).float()


_NO_UINT8 = np.empty((3, 0, 0), np.uint8)
_NO_FLOAT = np.empty((3, 0, 0), np.float32)


def _kernel_pair(image: Tensor) -> tuple[np.ndarray, np.ndarray]:
    """``(uint8, float32)`` arrays for :func:`_working_gray_kernel` of a ``(3, H, W)``
    image of either type, the other one empty."""
    a = image.contiguous().numpy()
    return (a, _NO_FLOAT) if a.dtype == np.uint8 else (_NO_UINT8, a)


@functools.lru_cache(maxsize=16)
def _aa_weights(n_in: int, n_out: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """torch's antialiased bilinear weights from ``n_in`` to ``n_out`` samples: each
    output's first input index and count of taps as torch's ``_compute_indices_min_size_
    weights_aa`` sets them in float32 (an end tap may weigh 0; the count decides torch's
    order of summing, :func:`_unfused_taps`), and the float32 weights ``(n_out, k)``, read
    off ``F.interpolate`` of one-hot rows (a weight times 1.0 is exact)."""
    eye = torch.eye(n_in, dtype=torch.float32)[None, None]
    wts = F.interpolate(eye, size=(n_in, n_out), mode="bilinear", align_corners=False, antialias=True)[0, 0].T
    scale = np.float32(n_in) / np.float32(n_out)  # float32, as torch's area_pixel_compute_scale<float>
    support = scale if scale >= 1 else np.float32(1.0)
    centre = (np.float64(scale) * (np.arange(n_out) + 0.5)).astype(np.float32)
    first = np.maximum(((centre - support).astype(np.float64) + 0.5).astype(np.int64), 0)
    end = np.minimum(((centre + support).astype(np.float64) + 0.5).astype(np.int64), n_in)
    count = np.clip(end - first, 0, int(np.ceil(support)) * 2 + 1)
    cols = torch.from_numpy(first[:, None] + np.arange(int(count.max()))[None])
    inside = cols < torch.from_numpy(first + count)[:, None]
    tab = wts.gather(1, cols.clamp(max=n_in - 1)) * inside
    if not torch.equal((tab != 0).sum(1), (wts != 0).sum(1)):  # a weight outside the taps: not this torch
        raise RuntimeError(f"antialiased weights {n_in} -> {n_out} are not where torch's formula puts them")
    return first, count, tab.contiguous().numpy()


@functools.lru_cache(maxsize=16)
def _regular_span(n_in: int, n_out: int) -> np.ndarray:
    """``int64 [i0, i1, off]``: the longest run of outputs of :func:`_aa_weights` ``(n_in,
    n_out)`` with four taps starting at ``2·i + off`` and the same weights as output ``i0``
    (a halving: all but the two end outputs), which the front end computes in a vectorised
    loop; ``i0 == i1`` (``= n_out``) where there is none."""
    lo, n, w = _aa_weights(n_in, n_out)
    best = (n_out, n_out, 0)
    if w.shape[1] < 4:
        return np.array(best, np.int64)
    i = 0
    while i < n_out:
        j = i
        while j < n_out and n[j] == 4 and lo[j] - 2 * j == lo[i] - 2 * i and np.array_equal(w[j, :4], w[i, :4]):
            j += 1
        if j - i > best[1] - best[0]:
            best = (i, j, int(lo[i] - 2 * i))
        i = max(j, i + 1)
    return np.array(best, np.int64)


@functools.lru_cache(maxsize=16)
def _sums_as_torch(h: int, w: int, ho: int, wo: int) -> bool:
    """Whether the compiled front end gives ``F.interpolate``'s numbers from ``h × w`` to
    ``ho × wo`` on this machine's torch: ``True`` outright for filters of at most four
    taps (the fused multiply-adds of torch's AVX2/AVX-512 builds, tested); for longer
    ones the order of :func:`_unfused_taps` depends on how torch's build vectorised its
    loop, so once per size a random image is resized both ways and compared bit for bit."""
    try:
        xlo, xn, xw = _aa_weights(w, wo)
        ylo, yn, yw = _aa_weights(h, ho)
    except RuntimeError:  # another torch's weights
        return False
    if max(xw.shape[1], yw.shape[1]) <= 4:
        return True
    probe = torch.rand((3, h, w), generator=torch.Generator().manual_seed(0))
    got = np.empty((ho, wo), np.float32)
    _working_gray_kernel(*_kernel_pair(probe), xlo, xn, xw, ylo, yn, yw, _regular_span(w, wo), got,
                         np.empty((0, 0), np.int32), 0, ho)
    want = F.interpolate(probe[None], size=(ho, wo), mode="bilinear", align_corners=False, antialias=True)
    return bool(torch.equal(torch.from_numpy(got), to_gray(want)[0, 0]))


@functools.lru_cache(maxsize=16)
def _reads_every_row(n_in: int, n_out: int) -> bool:
    """Whether the vertical taps of :func:`_aa_weights` ``(n_in, n_out)`` read every input
    row (then the front end's range count has seen every value of the image)."""
    lo, n, _ = _aa_weights(n_in, n_out)
    seen = np.zeros(n_in, np.bool_)
    for a, k in zip(lo.tolist(), n.tolist()):
        seen[a: a + k] = True
    return bool(seen.all())


@intrinsic
def _fma(typingctx, a, b, c):  # pragma: no cover - compiled
    """``a·b + c`` rounded once (llvm.fma), as torch's AVX2/AVX-512 kernels compute it."""
    sig = _nbtypes.float32(_nbtypes.float32, _nbtypes.float32, _nbtypes.float32)

    def codegen(context, builder, signature, args):
        return builder.fma(*args)

    return sig, codegen


_INV_255 = np.float32(1.0) / np.float32(255.0)


@numba.njit(cache=True, nogil=True)
def _unit8(v: int) -> float:  # pragma: no cover - compiled
    """A uint8 pixel in [0, 1] as ``x.float().div_(255.0)`` (torch's correctly rounded
    float32 division): a product by 1/255 corrected by its residual (two fused
    multiply-adds; the same float32 as the division for each of the 256 values, tested):
    quicker than the vectorised division, and than a 256-entry table, a gather per pixel
    (timed with ``benchmarks/kernel_ab.py``)."""
    x = np.float32(v)
    q = x * _INV_255
    return _fma(_fma(-q, np.float32(255.0), x), _INV_255, q)


@numba.njit(cache=True, nogil=True, inline="always")
def _unfused_taps(n: int) -> int:  # pragma: no cover - compiled
    """How many of an ``n``-tap filter's taps after the first torch's antialiased resize
    adds as rounded products, in order: its compiled loop over taps ``1 .. n-1`` runs in
    blocks of four lanes (products, then added in order) and fuses the rest, so 0 for up
    to four taps (all fused) and ``4·⌊(n-1)/4⌋`` beyond (found by trying every order of
    up to 26 taps against ``F.interpolate``; :func:`_sums_as_torch` checks it per size)."""
    return (n - 1) // 4 * 4


@numba.njit(cache=True, nogil=True, inline="always")
def _row_taps(fr: np.ndarray, fg: np.ndarray, fb: np.ndarray, xlo: np.ndarray, xn: np.ndarray, xw: np.ndarray,
              dr: np.ndarray, dg: np.ndarray, db: np.ndarray, i0: int, i1: int) -> None:  # pragma: no cover
    """The horizontal pass of outputs ``[i0, i1)`` of one row of the three channels (``fr,
    fg, fb`` in [0, 1]): each output's taps in order as torch sums them, the first a
    product, then (:func:`_unfused_taps`) taps each added as a rounded product, the rest
    fused multiply-adds (both as one ``fma``: ``fma(x·w, 1, r)`` is ``r + x·w`` rounded
    twice, ``fma(x·1, w, r)`` the fused one; one loop compiles in less time than two)."""
    for i in range(i0, i1):
        a = xlo[i]
        n = xn[i]
        w0 = xw[i, 0]
        r = fr[a] * w0
        g = fg[a] * w0
        b = fb[a] * w0
        q = _unfused_taps(n)
        for j in range(1, n):
            # a rounded product added, fma(x·w, 1, r), or a fused one, fma(x·1, w, r): one loop
            wj = xw[i, j]
            pj, fj = (wj, np.float32(1.0)) if j <= q else (np.float32(1.0), wj)
            r = _fma(fr[a + j] * pj, fj, r)
            g = _fma(fg[a + j] * pj, fj, g)
            b = _fma(fb[a + j] * pj, fj, b)
        dr[i], dg[i], db[i] = r, g, b


@numba.njit(cache=True, nogil=True, inline="always")
def _column_taps(rows: np.ndarray, a: int, n: int, wts: np.ndarray, lr: np.ndarray, lg: np.ndarray,
                 lb: np.ndarray) -> None:  # pragma: no cover
    """The vertical pass of one output row into ``lr, lg, lb``: rows ``a .. a+n-1`` of the
    horizontal pass ``rows`` ``(3, H, w)``, weighted by ``wts`` and summed as
    :func:`_row_taps` sums, a whole row per tap."""
    wo = lr.shape[0]
    w0 = wts[0]
    for i in range(wo):
        lr[i] = rows[0, a, i] * w0
        lg[i] = rows[1, a, i] * w0
        lb[i] = rows[2, a, i] * w0
    q = _unfused_taps(n)
    for j in range(1, n):
        wj = wts[j]
        pj, fj = (wj, np.float32(1.0)) if j <= q else (np.float32(1.0), wj)  # as in _row_taps
        r0, g0, b0 = rows[0, a + j], rows[1, a + j], rows[2, a + j]
        for i in range(wo):
            lr[i] = _fma(r0[i] * pj, fj, lr[i])
            lg[i] = _fma(g0[i] * pj, fj, lg[i])
            lb[i] = _fma(b0[i] * pj, fj, lb[i])


@numba.njit(cache=True, nogil=True)
def _unit_rows(img8: np.ndarray, img: np.ndarray, y: int, f: np.ndarray) -> int:  # pragma: no cover - compiled
    """Row ``y`` of the three channels in [0, 1] into ``f`` ``(3, W)``, from uint8 ``img8``
    or, where that is empty, float32 ``img``; returns how many of them lie outside [0, 1]
    or are NaN (0 for uint8)."""
    if img8.shape[1] > 0:
        for c in range(3):
            src8, dst = img8[c, y], f[c]
            for x in range(dst.shape[0]):
                dst[x] = _unit8(src8[x])
        return 0
    bad = 0
    for c in range(3):
        src, dst = img[c, y], f[c]
        for x in range(dst.shape[0]):
            v = src[x]
            dst[x] = v
            bad += 0 if (v >= 0) & (v <= 1) else 1
    return bad


@numba.njit(cache=True, nogil=True)
def _working_gray_kernel(img8: np.ndarray, img: np.ndarray, xlo: np.ndarray, xn: np.ndarray, xw: np.ndarray,
                         ylo: np.ndarray, yn: np.ndarray, yw: np.ndarray, span: np.ndarray,
                         out: np.ndarray, green: np.ndarray, y0: int, y1: int) -> int:  # pragma: no cover - compiled
    """:func:`working_gray` of one ``(3, H, W)`` image, uint8 ``img8`` or, where that is
    empty, float32 ``img`` (one kernel for both types, compiled once), into output rows
    ``[y0, y1)`` of ``out`` ``(h, w)``: the horizontal pass for the three channels together (the input
    rows those output rows read; outputs ``span[0] <= i < span[1]`` have four taps at
    ``2·i + span[2]`` with the weights of output ``span[0]``, a loop the compiler
    vectorises), then the vertical pass a whole output row at a time,
    then the grey; and unless ``green`` ``(h + 1, w + 1)`` is empty, the running counts of
    :func:`green_mask` into its rows ``y0 + 1 .. y1``, counted from row ``y0`` as zero
    (the caller adds row ``y0``'s counts where ``y0 > 0``). Returns how many of the
    values it read (every column of the input rows those output rows read) lie outside
    [0, 1] or are NaN (0 for uint8)."""
    as8 = img8.shape[1] > 0
    _, h, win = img8.shape if as8 else img.shape
    wo = xlo.shape[0]
    bad = 0  # values read outside [0, 1] (NaN included): returned
    if y1 <= y0:
        return bad
    rows = np.empty((3, h, wo), np.float32)
    f = np.empty((3, win), np.float32)  # one input row of each channel in [0, 1]
    top, bottom = ylo[y0], ylo[y0] + yn[y0]
    for yo in range(y0 + 1, y1):
        bottom = max(bottom, ylo[yo] + yn[yo])
        top = min(top, ylo[yo])
    i0, i1, off = span[0], span[1], span[2]
    for y in range(top, bottom):
        bad += _unit_rows(img8, img, y, f)
        fr, fg, fb = f[0], f[1], f[2]
        dr, dg, db = rows[0, y], rows[1, y], rows[2, y]
        _row_taps(fr, fg, fb, xlo, xn, xw, dr, dg, db, 0, i0)
        if i1 > i0:
            c0, c1, c2, c3 = xw[i0, 0], xw[i0, 1], xw[i0, 2], xw[i0, 3]
            a0 = 2 * i0 + off
            for c in range(3):  # on slices from the first output, by an index from 0: the compiler
                src, dst = f[c, a0:], rows[c, y, i0:i1]  # sees it is never negative and vectorises
                for t in range(i1 - i0):  # the loop (with 2·i + off, its test for negative indices
                    a = 2 * t  # kept it scalar, many times slower)
                    dst[t] = _fma(src[a + 3], c3, _fma(src[a + 2], c2, _fma(src[a + 1], c1, src[a] * c0)))
        _row_taps(fr, fg, fb, xlo, xn, xw, dr, dg, db, i1, wo)
    wr, wg, wb = np.float32(0.299), np.float32(0.587), np.float32(0.114)
    lr, lg, lb = np.empty(wo, np.float32), np.empty(wo, np.float32), np.empty(wo, np.float32)
    gm = np.empty(wo, green.dtype)
    for yo in range(y0, y1):
        _column_taps(rows, ylo[yo], yn[yo], yw[yo], lr, lg, lb)
        line = out[yo]
        for i in range(wo):
            line[i] = _fma(lb[i], wb, _fma(lg[i], wg, lr[i] * wr))
        if green.shape[0] > 0:
            if yo == y0:
                if y0 == 0:
                    green[0].fill(0)
                above = np.zeros(wo + 1, green.dtype)
            else:
                above = green[yo]
            below = green[yo + 1]
            below[0] = 0
            for i in range(wo):  # the mask first, in a loop the compiler vectorises (not a
                gm[i] = (lg[i] > lr[i]) & (lg[i] > lb[i])  # branch inside the running count)
            run = 0
            for i in range(wo):
                run += gm[i]
                below[i + 1] = above[i + 1] + run
    return bad


def gaussian_blur(gray: Tensor, sigma: float) -> Tensor:
    """Separable Gaussian blur of ``(B, 1, H, W)``; kernel side ``2*ceil(2σ)+1``, reflected
    borders (OpenCV's ``BORDER_REFLECT_101``), kornia's kernel weights.

    Computed as a fixed-order sum of shifted slices rather than a convolution: a
    convolution backend may block a batch differently from one image, which changes the
    float rounding, and every later stage would then depend on the batch."""
    _, _, h, w = gray.shape
    wts = _blur_weights(sigma, h, w, gray).tolist()
    k, r = len(wts), len(wts) // 2
    p = F.pad(gray, (r, r, r, r), mode="reflect")[:, 0]
    rows = wts[0] * p[:, :, 0:w]
    for i in range(1, k):
        rows = rows + wts[i] * p[:, :, i: i + w]
    out = wts[0] * rows[:, 0:h]
    for i in range(1, k):
        out = out + wts[i] * rows[:, i: i + h]
    return out[:, None]


def _blur_weights(sigma: float, h: int, w: int, like: Tensor) -> Tensor:
    """kornia's Gaussian weights for :func:`gaussian_blur` (side ``2*ceil(2σ)+1``, ``like``'s
    device and dtype), after checking that an ``h × w`` image can be reflected that far."""
    k = 2 * math.ceil(2 * sigma) + 1
    r = k // 2
    if r >= h or r >= w:  # reflection needs more pixels than the kernel radius
        raise ValueError(f"blur_sigma={sigma} needs an image of at least {r + 1}×{r + 1} working "
                         f"pixels, got {h}×{w}")
    return _gaussian_1d(k, float(sigma), like.device, like.dtype)


@functools.lru_cache(maxsize=16)
def _gaussian_1d(k: int, sigma: float, device: torch.device, dtype: torch.dtype) -> Tensor:
    """kornia's ``get_gaussian_kernel1d(k, sigma)[0]``, built once per setting (building it
    costs more than a blur of a KITTI image at the working size); the tensor is read, never
    written."""
    return kornia.filters.get_gaussian_kernel1d(k, sigma, device=device, dtype=dtype)[0]


def sobel_gradients(gray: Tensor) -> tuple[Tensor, Tensor]:
    """Sobel derivatives ``(gx, gy)``, each ``(B, H, W)``, of ``(B, 1, H, W)``, scaled so a
    unit step gives 1 (the 3×3 Sobel kernels / 4), replicated borders.

    Computed separably with shifted slices (the same numbers as
    ``kornia.filters.spatial_gradient(..., normalized=True) / 0.5``, and faster than a
    one-channel ``conv2d`` on the CPU).
    """
    p = F.pad(gray, (1, 1, 1, 1), mode="replicate")[:, 0]
    dx = p[:, :, 2:] - p[:, :, :-2]  # (B, H + 2, W)
    dy = p[:, 2:, :] - p[:, :-2, :]  # (B, H, W + 2)
    gx = (dx[:, :-2] + 2.0 * dx[:, 1:-1] + dx[:, 2:]) * 0.25
    gy = (dy[:, :, :-2] + 2.0 * dy[:, :, 1:-1] + dy[:, :, 2:]) * 0.25
    return gx, gy


def sobel_magnitude(gray: Tensor) -> Tensor:
    """Sobel gradient magnitude ``(B, H, W)`` of ``(B, 1, H, W)``, scaled so that a unit
    step edge has magnitude 1, clipped to [0, 1]."""
    return gradient_magnitude(*sobel_gradients(gray))


def gradient_magnitude(gx: Tensor, gy: Tensor) -> Tensor:
    """``sqrt(gx² + gy²)`` clipped to [0, 1], float32 ``(B, H, W)``. The squares and their
    sum are float32 ops; the root is correctly rounded (taken in float64, which rounds to
    the nearest float32 exactly), as a compiled ``sqrt`` computes it. torch's vectorised
    float32 ``sqrt`` is not correctly rounded (about one result in seven is an ulp off),
    so it could not be matched by a compiled pass."""
    g2 = gx * gx + gy * gy
    return torch.sqrt(g2.double()).to(g2.dtype).clamp_(max=1.0)


def thin(mag: Tensor, gx: Tensor, gy: Tensor) -> Tensor:
    """Non-maximum suppression along the gradient (Canny-style, 4 directions): keep a
    pixel of ``mag`` ``(B, H, W)`` only where it is not smaller than its two neighbours
    across the edge. Returns a bool mask ``(B, H, W)``."""
    p = F.pad(mag[:, None], (1, 1, 1, 1), mode="replicate")[:, 0]
    c = p[:, 1:-1, 1:-1]
    right, left = p[:, 1:-1, 2:], p[:, 1:-1, :-2]
    down, up = p[:, 2:, 1:-1], p[:, :-2, 1:-1]
    dr, ul = p[:, 2:, 2:], p[:, :-2, :-2]
    dl, ur = p[:, 2:, :-2], p[:, :-2, 2:]
    ax, ay = gx.abs(), gy.abs()
    t = 0.4142135623730951  # tan(22.5°)
    horiz = ay <= t * ax  # gradient along x: compare left/right
    vert = ax <= t * ay
    same = (gx * gy) > 0  # gradient along the main diagonal (down-right in image rows)
    keep_h = (c >= left) & (c >= right)
    keep_v = (c >= up) & (c >= down)
    keep_d1 = (c >= ul) & (c >= dr)
    keep_d2 = (c >= ur) & (c >= dl)
    return torch.where(horiz, keep_h, torch.where(vert, keep_v, torch.where(same, keep_d1, keep_d2)))


def remove_isolated(mask: Tensor) -> Tensor:
    """Drop edge pixels that have no edge pixel among their 8 neighbours.

    ``mask``: bool ``(B, H, W)``. Returns a bool tensor of the same shape.
    """
    m = mask.to(torch.float32).unsqueeze(1)
    neighbours = F.avg_pool2d(m, 3, stride=1, padding=1, count_include_pad=True) * 9.0 - m
    return mask & (neighbours[:, 0] > 0.5)


def edge_map(gray: Tensor, sigma: float, threshold: float, isolated: bool, thinning: bool = False) -> Tensor:
    """Blur, Sobel, threshold and clean: grey ``(B, 1, H, W)`` → ``(B, H, W)`` edge
    magnitudes in [0, 1], zero where there is no edge.
    ``thinning`` keeps only the ridge of each edge (one pixel wide), as the thinned edge
    maps Edge Boxes scores.

    On the CPU the default path (grey, thinned, isolated pixels removed) runs as two
    compiled passes (numba) with the same float32 arithmetic, operation for operation, as
    the tensor ops (tested equal bit for bit)."""
    b, _, h, w = gray.shape
    if thinning and isolated and gray.device.type == "cpu" and gray.dtype == torch.float32:
        return _edge_map_cpu(gray, sigma, threshold)
    gx, gy = sobel_gradients(gaussian_blur(gray.reshape(b, 1, h, w), sigma))
    mag = gradient_magnitude(gx, gy)
    mask = mag > threshold
    if thinning:
        mask &= thin(mag, gx, gy)
    if isolated:
        mask = remove_isolated(mask)
    return mag * mask


@numba.njit(cache=True, nogil=True)
def _blur_sobel_kernel(gray: np.ndarray, wts: np.ndarray, gx: np.ndarray, gy: np.ndarray,
                       mag: np.ndarray, y0: int, y1: int) -> None:  # pragma: no cover - compiled
    """:func:`sobel_gradients` of :func:`gaussian_blur` for ``gray`` ``(B, H, W)``, and their
    :func:`gradient_magnitude`, in rows ``[y0, y1)``: reflected borders for the blur,
    replicated for Sobel, the same float32 operations in the same order."""
    nb, h, w = gray.shape
    k = wts.shape[0]
    r = k // 2
    rows = np.empty((h + 2 * r, w), np.float32)
    blur = np.empty((h, w), np.float32)
    line = np.empty(w + 2 * r, np.float32)
    b0, b1 = max(y0 - 1, 0), min(y1 + 1, h)  # the blurred rows the Sobel rows read
    for b in range(nb):
        img = gray[b]
        for yy in range(b0, b1 + 2 * r):
            y = yy - r
            y = -y if y < 0 else (2 * (h - 1) - y if y >= h else y)
            src = img[y]
            inner = line[r: r + w]  # (slices indexed from 0: no test for negative indices)
            for x in range(w):  # the row, then its ends reflected
                inner[x] = src[x]
            for xi in range(r):
                line[xi] = src[r - xi]
                line[w + r + xi] = src[w - 2 - xi]
            dst = rows[yy]  # tap by tap over the whole row (vectorised), the same sum per pixel
            w0 = wts[0]
            for x in range(w):
                dst[x] = w0 * line[x]
            for i in range(1, k):
                wi = wts[i]
                tap = line[i: i + w]
                for x in range(w):
                    dst[x] = dst[x] + wi * tap[x]
        for y in range(b0, b1):
            dst = blur[y]
            w0 = wts[0]
            src = rows[y]
            for x in range(w):
                dst[x] = w0 * src[x]
            for i in range(1, k):
                wi = wts[i]
                src = rows[y + i]
                for x in range(w):
                    dst[x] = dst[x] + wi * src[x]
        for y in range(y0, y1):
            ym, yp = max(y - 1, 0), min(y + 1, h - 1)
            up, mid, down = blur[ym], blur[y], blur[yp]
            ox, oy, om = gx[b, y], gy[b, y], mag[b, y]
            _sobel_at(up, mid, down, 0, 0, min(1, w - 1), ox, oy, om)
            if w > 2:  # replicated borders: the end columns clamp their neighbours
                _sobel_inner(up, mid, down, ox[1: w - 1], oy[1: w - 1], om[1: w - 1])
            if w > 1:
                _sobel_at(up, mid, down, w - 1, w - 2, w - 1, ox, oy, om)


@numba.njit(cache=True, nogil=True, inline="always")
def _sobel_px(ul: np.float32, uc: np.float32, ur: np.float32, ml: np.float32, mr: np.float32, dl: np.float32,
              dc: np.float32, dr: np.float32) -> tuple:  # pragma: no cover - compiled
    """Sobel ``gx, gy`` (the 3×3 kernels / 4) and the magnitude (clipped to 1) of one pixel
    of the blurred image from its neighbours: rows up, mid(dle) and down, columns l(eft),
    c(entre) and r(ight)."""
    two = np.float32(2.0)
    quarter = np.float32(0.25)
    u = (((ur - ul) + two * (mr - ml)) + (dr - dl)) * quarter
    v = (((dl - ul) + two * (dc - uc)) + (dr - ur)) * quarter
    return u, v, min(np.sqrt(u * u + v * v), np.float32(1.0))


@numba.njit(cache=True, nogil=True, inline="always")
def _sobel_at(up: np.ndarray, mid: np.ndarray, down: np.ndarray, x: int, xm: int, xp: int,
              gx: np.ndarray, gy: np.ndarray, mag: np.ndarray) -> None:  # pragma: no cover - compiled
    """:func:`_sobel_px` at column ``x`` of a row, from the rows above, at and below it
    (columns ``xm, xp`` its neighbours: the end columns clamp theirs)."""
    gx[x], gy[x], mag[x] = _sobel_px(up[xm], up[x], up[xp], mid[xm], mid[xp], down[xm], down[x], down[xp])


@numba.njit(cache=True, nogil=True, inline="always")
def _sobel_inner(up: np.ndarray, mid: np.ndarray, down: np.ndarray, gx: np.ndarray, gy: np.ndarray,
                 mag: np.ndarray) -> None:  # pragma: no cover - compiled
    """:func:`_sobel_px` at columns ``1 .. w − 2`` of a row (``gx, gy, mag``: those columns'
    outputs), as one loop over slices indexed from 0: no test for negative indices, so the
    compiler vectorises it (with ``x − 1`` and ``x + 1`` it stayed scalar)."""
    n = gx.shape[0]
    u0, u1, u2 = up[0:n], up[1: n + 1], up[2: n + 2]
    m0, m2 = mid[0:n], mid[2: n + 2]
    d0, d1, d2 = down[0:n], down[1: n + 1], down[2: n + 2]
    for t in range(n):
        gx[t], gy[t], mag[t] = _sobel_px(u0[t], u1[t], u2[t], m0[t], m2[t], d0[t], d1[t], d2[t])


@numba.njit(cache=True, nogil=True, inline="always")
def _ridge(m: np.ndarray, a: np.float32, d: np.float32, y: int, x: int, ym: int, yp: int, xm: int, xp: int,
           tan: np.float32, threshold: np.float32) -> bool:  # pragma: no cover - compiled
    """Whether pixel ``(y, x)`` of ``m`` passes the threshold and is not smaller than its
    two neighbours across the edge (gradient ``a, d``; rows ``ym, yp`` and columns ``xm,
    xp`` its neighbours): every comparison made, then one chosen, so that a row of them
    compiles to vector selects."""
    c = m[y, x]
    ax, ay = abs(a), abs(d)
    horiz = ay <= tan * ax
    vert = ax <= tan * ay
    diag = a * d > 0
    keep_h = (c >= m[y, xm]) & (c >= m[y, xp])
    keep_v = (c >= m[ym, x]) & (c >= m[yp, x])
    keep_d1 = (c >= m[ym, xm]) & (c >= m[yp, xp])
    keep_d2 = (c >= m[ym, xp]) & (c >= m[yp, xm])
    ok = keep_h if horiz else (keep_v if vert else (keep_d1 if diag else keep_d2))
    return (c > threshold) & ok


@numba.njit(cache=True, nogil=True)
def _thin_isolated_kernel(mag: np.ndarray, gx: np.ndarray, gy: np.ndarray, threshold: np.float32,
                          out: np.ndarray, y0: int, y1: int) -> None:  # pragma: no cover - compiled
    """``mag`` where it passes the threshold, :func:`thin` and :func:`remove_isolated`, else
    0, in rows ``[y0, y1)``: the thinned pixels into a table with a border of False (so the
    isolation test reads its eight neighbours without bounds checks)."""
    nb, h, w = mag.shape
    tan = np.float32(0.4142135623730951)
    zero = np.float32(0.0)
    keep = np.zeros((h + 2, w + 2), np.bool_)
    k0, k1 = max(y0 - 1, 0), min(y1 + 1, h)  # the thinned rows the isolation test reads
    for b in range(nb):
        m = mag[b]
        for y in range(k0, k1):
            ym, yp = max(y - 1, 0), min(y + 1, h - 1)
            a, d, kr = gx[b, y], gy[b, y], keep[y + 1]
            kr[1] = _ridge(m, a[0], d[0], y, 0, ym, yp, 0, min(1, w - 1), tan, threshold)
            for x in range(1, w - 1):  # replicated borders: the end columns clamp their neighbours
                kr[x + 1] = _ridge(m, a[x], d[x], y, x, ym, yp, x - 1, x + 1, tan, threshold)
            if w > 1:
                kr[w] = _ridge(m, a[w - 1], d[w - 1], y, w - 1, ym, yp, w - 2, w - 1, tan, threshold)
        for y in range(y0, y1):
            up, mid, down, row, dst = keep[y], keep[y + 1], keep[y + 2], m[y], out[b, y]
            for x in range(w):
                near = (up[x] | up[x + 1] | up[x + 2] | mid[x] | mid[x + 2] | down[x] | down[x + 1] | down[x + 2])
                dst[x] = row[x] if mid[x + 1] & near else zero


def _edge_map_cpu(gray: Tensor, sigma: float, threshold: float) -> Tensor:
    """:func:`edge_map`'s default path on the CPU: ``(B, 1, H, W)`` float32 → ``(B, H, W)``.
    Blur, Sobel and the magnitude, then thinning and isolated pixels: two compiled passes,
    both in one hand-over to the second core. One image is split by rows: each core also
    computes the two Sobel rows past each end of its half that its thinning reads (the same
    numbers either way), into its own buffers, so the two passes need no wait between them."""
    b, _, h, w = gray.shape
    wts = _blur_weights(sigma, h, w, gray)
    g, wt = gray[:, 0].contiguous().numpy(), wts.contiguous().numpy()
    bufs = [[_scratch.empty(f"edges.{name}.{part}", (b, h, w), np.float32) for name in ("gx", "gy", "mag")]
            for part in range(2 if b == 1 else 1)]
    out = _scratch.empty("edges.out", (b, h, w), np.float32)
    t = np.float32(threshold)

    def run(lo: int, hi: int, r0: int, r1: int) -> None:
        gx, gy, mag = bufs[1 if r0 > 0 else 0]
        _blur_sobel_kernel(g[lo:hi], wt, gx[lo:hi], gy[lo:hi], mag[lo:hi], max(r0 - 2, 0), min(r1 + 2, h))
        _thin_isolated_kernel(mag[lo:hi], gx[lo:hi], gy[lo:hi], t, out[lo:hi], r0, r1)

    images_or_rows(run, b, h)
    return torch.from_numpy(out)
