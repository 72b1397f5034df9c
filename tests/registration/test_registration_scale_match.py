"""Scale-matched colour term (jaxcr.registration.projective.scale_matching_blur,
blurred_image): the extra blur against its closed form, the masked blur against scipy's
Gaussian filter, and the whole chain on a sinusoidal texture seen by box-integrating pixels
at two distances, whose blurred amplitudes have a closed form. Host-side numpy only (no
compile)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

from jaxcr.registration.clouds import organised_cloud
from jaxcr.registration.projective import (
    blurred_image,
    chromaticity,
    depth_image,
    scale_matching_blur,
)

F = 90.0


def _K(w, h):
    return np.array([[F, 0, (w - 1) / 2], [0, F, (h - 1) / 2], [0, 0, 1.0]])


@pytest.mark.parametrize("z_src, z_tgt", [(0.6, 0.3), (0.25, 0.55), (0.4, 0.4)])
def test_scale_matching_blur_equalises_the_blur_on_the_surface(z_src, z_tgt):
    b2 = 1.0 + 1.0 / 12.0  # base blur 1 px and the pixel's box variance
    e_s, e_t = scale_matching_blur(z_src, z_tgt)
    assert min(e_s, e_t) == 0.0  # only the nearer view is blurred
    # metric variance (px^2 x (z/f)^2) of both views equal (float64 closed form)
    np.testing.assert_allclose((b2 + e_s**2) * z_src**2, (b2 + e_t**2) * z_tgt**2, rtol=1e-12)
    assert scale_matching_blur(z_tgt, z_src) == (e_t, e_s)
    assert scale_matching_blur(float("nan"), 0.3) == (0.0, 0.0)


def _image(rgb, z, mask=None):
    h, w = rgb.shape[:2]
    depth = np.full((h, w), z)
    if mask is not None:
        depth = np.where(mask, depth, np.nan)
    P, C, N, ok = organised_cloud(rgb, depth, _K(w, h))
    return depth_image(P, C, N, ok, _K(w, h))


def test_blurred_image_is_a_normalised_gaussian_over_the_valid_pixels():
    h, w, sigma = 40, 56, 1.5
    rng = np.random.default_rng(0)
    v, u = np.mgrid[0:h, 0:w]
    mask = (u - 30) ** 2 + (v - 20) ** 2 < 15**2
    rgb = np.where(mask[..., None], rng.uniform(0.2, 1.0, (h, w, 3)), 0.0).astype(np.float32)
    img = _image(rgb, 0.4, mask)
    ok = np.asarray(img.mask)
    out = blurred_image(img, sigma)
    m = ok.astype(np.float64)
    total = np.hypot(1.0, sigma)  # depth_image's 1 px and the extra blur, from raw colours
    raw = {"intensity": rgb.mean(-1)[..., None], "chroma": chromaticity(rgb)}
    for name in ("intensity", "chroma"):
        x = np.asarray(getattr(img, name), np.float64).reshape(h, w, -1)
        y = np.asarray(getattr(out, name), np.float64).reshape(h, w, -1)
        for c in range(x.shape[-1]):
            # scipy: the same 4-sigma truncation and mirrored border as cv2.GaussianBlur
            with np.errstate(invalid="ignore", divide="ignore"):
                ref = gaussian_filter(m * raw[name][..., c], total, mode="mirror") / (
                    gaussian_filter(m, total, mode="mirror")
                )
            # float32 sums of <= 15^2 terms in [0, 1] (rel. ~1e-6) divided by the mask
            # weight, >= ~0.2 on the valid pixels: < 1e-5
            np.testing.assert_allclose(y[..., c][ok], ref[ok], atol=1e-5)
            np.testing.assert_array_equal(y[..., c][~ok], x[..., c][~ok])
    g = np.asarray(out.chroma_gradient)[..., 0, :]
    gv, gu = np.gradient(np.asarray(out.chroma)[..., 0])
    np.testing.assert_allclose(g[1:-1, 1:-1, 0], gu[1:-1, 1:-1], atol=1e-6)
    np.testing.assert_allclose(g[1:-1, 1:-1, 1], gv[1:-1, 1:-1], atol=1e-6)
    np.testing.assert_array_equal(np.asarray(out.points), np.asarray(img.points))
    assert blurred_image(img, 0.0) is img


def test_blurred_image_keeps_a_uniform_object_colour_up_to_its_silhouette():
    h, w = 32, 40
    v, u = np.mgrid[0:h, 0:w]
    mask = (abs(u - 20) < 9) & (abs(v - 16) < 7)
    rgb = np.where(mask[..., None], np.array([0.6, 0.3, 0.1]), 0.0).astype(np.float32)
    img = _image(rgb, 0.3, mask)
    # normalised over the valid pixels: the uniform colour everywhere on the object, up to
    # float32 rounding of a ratio of two sums of <= 21^2 terms (~1e-6 relative)
    ok = np.asarray(img.mask)
    out = blurred_image(img, 2.5)
    np.testing.assert_allclose(np.asarray(out.chroma)[ok], [[0.6, 0.3]] * ok.sum(), atol=2e-6)
    np.testing.assert_allclose(np.asarray(out.intensity)[ok], 1.0 / 3.0, atol=1e-6)


def _sinusoid_view(z, wavelength, w=120, h=12):
    """Fronto-parallel plane at depth z with grey texture 0.5 + 0.3 sin(k X) (X metres along
    the image rows), each pixel the exact box integral of the texture over its footprint."""
    k = 2 * np.pi / wavelength
    d = z / F  # pixel footprint (m)
    x = (np.arange(w) - (w - 1) / 2) * d
    box = (np.cos(k * (x - d / 2)) - np.cos(k * (x + d / 2))) / (k * d)
    grey = np.broadcast_to(0.5 + 0.3 * box, (h, w))
    return _image(np.repeat(grey[..., None], 3, -1).astype(np.float32), z), x, k


def _amplitude(img, x, k, margin):
    row = np.asarray(img.intensity, np.float64)[6, margin:-margin]
    xs = x[margin:-margin]
    A = np.stack([np.ones_like(xs), np.cos(k * xs), np.sin(k * xs)], 1)
    c = np.linalg.lstsq(A, row, rcond=None)[0]
    return np.hypot(c[1], c[2])


def test_scale_matched_views_see_the_same_texture_amplitude():
    z_far, z_near = 0.6, 0.3
    wavelength = 10 * z_far / F  # 10 far pixels, 20 near ones
    far, x_far, k = _sinusoid_view(z_far, wavelength)
    near, x_near, _ = _sinusoid_view(z_near, wavelength)
    _, e = scale_matching_blur(z_far, z_near)
    a_far = _amplitude(far, x_far, k, 12)
    a_near = _amplitude(near, x_near, k, 24)
    a_matched = _amplitude(blurred_image(near, e), x_near, k, 24)
    # Closed form: box pixel (sinc) times Gaussian. The Gaussian stand-in for the box,
    # exp(-x^2/6) vs sinc(x), differs by ~x^4/180 with x = k d / 2 <= 0.32 (far): 6e-5;
    # cv2's 4-sigma truncation ~1e-4; the fit in float32 images ~1e-6. Bound 2e-3.
    assert abs(a_matched / a_far - 1) < 2e-3
    assert a_near / a_far - 1 > 0.05  # unmatched: the near view's texture is sharper
