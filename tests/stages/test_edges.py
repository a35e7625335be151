"""Sec. 3.4 denoising and edges, against OpenCV."""

from __future__ import annotations

import cv2
import numpy as np
import torch

from reeb_torch.stages.edges import (edge_map, gaussian_blur, green_mask, remove_isolated, sobel_gradients, sobel_magnitude,
                              to_gray)
from reeb_torch.stages.scoring import count_integral


def test_sobel_matches_opencv_inside_the_border():
    gen = torch.Generator().manual_seed(0)
    g = torch.rand(1, 1, 30, 40, generator=gen)
    ours = sobel_magnitude(g)[0].numpy()
    a = g[0, 0].numpy().astype(np.float64)
    gx = cv2.Sobel(a, cv2.CV_64F, 1, 0, ksize=3) / 4.0  # unit step -> 1
    gy = cv2.Sobel(a, cv2.CV_64F, 0, 1, ksize=3) / 4.0
    ref = np.minimum(np.sqrt(gx**2 + gy**2), 1.0)
    np.testing.assert_allclose(ours[1:-1, 1:-1], ref[1:-1, 1:-1], atol=1e-5)


def test_separable_sobel_matches_kornia_everywhere():
    import kornia

    g = torch.rand(2, 1, 17, 23, generator=torch.Generator().manual_seed(2))
    gx, gy = sobel_gradients(g)
    ref = kornia.filters.spatial_gradient(g, mode="sobel", order=1, normalized=True) / 0.5
    torch.testing.assert_close(gx, ref[:, 0, 0])
    torch.testing.assert_close(gy, ref[:, 0, 1])


def test_blur_matches_opencv():
    gen = torch.Generator().manual_seed(0)
    g = torch.rand(1, 1, 30, 40, generator=gen)
    ours = gaussian_blur(g, 1.0)[0, 0].numpy()
    ref = cv2.GaussianBlur(g[0, 0].numpy(), (5, 5), 1.0, borderType=cv2.BORDER_REFLECT_101)
    np.testing.assert_allclose(ours, ref, atol=1e-5)


def test_unit_step_has_magnitude_one_and_thins_to_one_pixel():
    img = torch.zeros(1, 1, 20, 20)
    img[..., 10:] = 1.0
    e = edge_map(img, 0.5, 0.05, isolated=True, thinning=True)[0]
    cols = torch.nonzero(e[5]).flatten().tolist()
    assert len(cols) == 1 and cols[0] in (9, 10)
    thick = edge_map(img, 0.5, 0.05, isolated=True, thinning=False)[0]
    assert int((thick[5] > 0).sum()) >= 2
    assert float(sobel_magnitude(gaussian_blur(img, 0.5)).max()) <= 1.0


def test_isolated_pixels_are_removed():
    m = torch.zeros(1, 7, 7, dtype=torch.bool)
    m[0, 1, 1] = True  # alone
    m[0, 4, 4] = m[0, 5, 5] = True  # diagonal neighbours: kept
    out = remove_isolated(m)[0]
    assert not out[1, 1] and out[4, 4] and out[5, 5]


def test_gray_weights():
    rgb = torch.tensor([1.0, 0.0, 0.0]).view(1, 3, 1, 1)
    assert abs(float(to_gray(rgb)) - 0.299) < 1e-6


def test_compiled_edge_map_equals_the_tensor_ops(sample_image):
    # the CPU default path (blur + Sobel, thinning, isolated pixels in numba) gives
    # the tensor ops' edge map bit for bit, on the sample and on noise, at several settings
    from reeb_torch.stages import edges as E

    def tensor_ops(g, sigma, threshold):
        gx, gy = E.sobel_gradients(E.gaussian_blur(g, sigma))
        mag = E.gradient_magnitude(gx, gy)
        return mag * E.remove_isolated((mag > threshold) & E.thin(mag, gx, gy))

    gen = torch.Generator().manual_seed(2)
    sample = E.to_gray(sample_image[None, :, :150, :400].float() / 255)
    for g in (sample, torch.rand(3, 1, 23, 37, generator=gen)):
        for sigma, threshold in ((1.0, 0.05), (0.7, 0.02), (1.5, 0.1)):
            got = E.edge_map(g, sigma, threshold, True, True)
            assert torch.equal(got, tensor_ops(g, sigma, threshold)), (sigma, threshold)
            assert int((got > 0).sum()) > 0
    # narrow and short images: the end columns and rows take the clamped (replicated) paths
    for h, w in ((5, 5), (4, 6), (64, 3), (3, 64), (9, 2)):
        g = torch.rand(2, 1, h, w, generator=gen)
        g[:, :, ::3] *= 0.2
        assert torch.equal(E.edge_map(g, 0.5, 0.05, True, True), tensor_ops(g, 0.5, 0.05)), (h, w)


def _interpolated(images, scale):
    """The tensor ops the compiled front end replaces: [0, 1] floats, antialiased resize."""
    import torch.nn.functional as F

    h, w = images[0].shape[-2:]
    size = (max(1, int(round(h * scale))), max(1, int(round(w * scale))))
    unit = [x.float().div_(255.0) if x.dtype == torch.uint8 else x for x in images]
    return torch.cat([F.interpolate(x[None], size=size, mode="bilinear", align_corners=False, antialias=True)
                      for x in unit])


def test_green_mask_marks_green_dominant_pixels():
    rgb = torch.tensor([[0.2, 0.5, 0.1], [0.5, 0.5, 0.1], [0.1, 0.5, 0.6], [0.0, 0.0, 0.0]]).T.reshape(1, 3, 1, 4)
    assert green_mask(rgb).tolist() == [[[1.0, 0.0, 0.0, 0.0]]]


def test_compiled_working_gray_equals_interpolate_then_grey(sample_image):
    # the CPU front end (antialiased resize + grey in one compiled pass, from uint8)
    # gives torch's interpolate + kornia's grey bit for bit, where it applies
    from reeb_torch.stages.edges import _regular_span, working_gray

    if torch.backends.cpu.get_cpu_capability() not in ("AVX2", "AVX512"):
        assert working_gray([sample_image], 0.5) is None
        return
    gen = torch.Generator().manual_seed(3)
    crops = [sample_image[:, :150, :400], sample_image[:, 20:170, 100:500]]
    odd = [sample_image[:, :151, :401]]  # like KITTI's 1241 px: a few outputs of five taps at 0.5
    noise = [torch.randint(0, 256, (3, 31, 47), dtype=torch.uint8, generator=gen) for _ in range(3)]
    # 400 → 200 columns: all but the end outputs take the vectorised four-tap loop
    assert _regular_span(400, 200).tolist() == [1, 199, -1]
    for images in (crops, [x.float() / 255 for x in crops], odd, noise, [x.float() / 255 for x in noise]):
        # below 0.5 the filters are longer than four taps: torch adds them in another order
        for scale in (0.5, 0.51, 0.7, 0.9, 0.49, 0.3, 0.2):
            got, none = working_gray(images, scale)
            assert got.dtype == torch.float32 and none is None
            assert torch.equal(got, to_gray(_interpolated(images, scale))), (images[0].dtype, scale)
            grey, green = working_gray(images, scale, with_green=True)
            assert torch.equal(grey, got)
            ref = count_integral(green_mask(_interpolated(images, scale)))
            assert green.dtype == torch.int32 and torch.equal(green, ref), (images[0].dtype, scale)


def test_compiled_uint8_to_unit_is_the_division_for_every_value():
    # the front end's product-and-residual quotient is torch's x.float() / 255 for each of
    # the 256 values a uint8 pixel can take
    import numba

    from reeb_torch.stages.edges import _unit8

    @numba.njit
    def units(x):
        out = np.empty(x.shape[0], np.float32)
        for i in range(x.shape[0]):
            out[i] = _unit8(x[i])
        return out

    every = torch.arange(256, dtype=torch.uint8)
    got = units(every.numpy())
    assert np.array_equal(got.view(np.uint32), (every.float() / 255).numpy().view(np.uint32))


def test_compiled_working_gray_declines_where_it_would_differ(sample_image, monkeypatch):
    # no resize, upsampling, float64, or a torch that sums long filters in another order
    # than the probe found: the caller takes the tensor ops
    from reeb_torch.stages import edges
    from reeb_torch.stages.edges import working_gray

    for scale in (1.0, 1.5):
        assert working_gray([sample_image], scale) is None
    assert working_gray([sample_image.double() / 255], 0.5) is None
    assert edges._sums_as_torch(151, 401, *edges.working_size(151, 401, 0.5))  # five taps: probed
    monkeypatch.setattr(edges, "_sums_as_torch", lambda *size: False)
    assert working_gray([sample_image[:, :151, :401]], 0.5) is None
