"""Shading-invariant colour term of the projective ICP (jaxcr.registration.projective:
chromaticity, photometric_channels, photometric_terms with several channels) and its use in
the geometry's degenerate directions only, against closed forms, a slow per-point
finite-difference reference and a textured plane under camera-fixed shading."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.ndimage import map_coordinates
from scipy.spatial.transform import Rotation

from jaxcr.registration.clouds import organised_cloud
from jaxcr.registration.icp import IcpConfig
from jaxcr.registration.metrics import pose_error
from jaxcr.registration.pairwise import register_pair
from jaxcr.registration.projective import (
    chromaticity,
    depth_image,
    photometric_channels,
    photometric_terms,
    projective_icp_jit,
)
from tests.helpers.rgbd_pair import shifted_pair

W, H = 96, 72
F = 90.0
K = np.array([[F, 0, (W - 1) / 2], [0, F, (H - 1) / 2], [0, 0, 1.0]])


def test_chromaticity_closed_form_and_shading_invariance():
    rng = np.random.default_rng(0)
    rgb = rng.uniform(0.1, 1.0, (H, W, 3))
    shade = rng.uniform(0.3, 1.0, (H, W, 1))  # any per-pixel grey shading
    ch = chromaticity(rgb)
    s = rgb.sum(-1)
    np.testing.assert_allclose(ch[..., 0], rgb[..., 0] / s, rtol=1e-6)
    np.testing.assert_allclose(ch[..., 1], rgb[..., 1] / s, rtol=1e-6)
    np.testing.assert_allclose(chromaticity(rgb * shade), ch, atol=1e-6)
    dark = np.zeros((4, 4, 3))
    assert np.all(chromaticity(dark) == 0.0)  # no hue, no division by zero


def test_depth_image_chroma_channels_are_smoothed_chromaticity_and_its_gradient():
    rng = np.random.default_rng(1)
    rgb = rng.uniform(0.1, 1.0, (H, W, 3)).astype(np.float32)
    depth = np.full((H, W), 0.5)
    P, C, N, ok = organised_cloud(rgb, depth, K)
    img = depth_image(P, C, N, ok, K, blur=0.0)  # no smoothing: exact closed forms
    ch = chromaticity(rgb)
    np.testing.assert_allclose(np.asarray(img.chroma), ch, atol=1e-6)
    for k in range(2):
        gv, gu = np.gradient(ch[..., k])  # central differences inside
        np.testing.assert_allclose(
            np.asarray(img.chroma_gradient)[1:-1, 1:-1, k, 0], gu[1:-1, 1:-1], atol=1e-6
        )
        np.testing.assert_allclose(
            np.asarray(img.chroma_gradient)[1:-1, 1:-1, k, 1], gv[1:-1, 1:-1], atol=1e-6
        )
    im, gr = photometric_channels(img, "intensity")
    assert im.shape == (H, W, 1) and gr.shape == (H, W, 1, 2)
    with pytest.raises(ValueError):
        photometric_channels(img, "hue")


def _smooth_scene():
    """A fronto-parallel plane at 0.5 m with a smooth two-colour pattern (long wavelengths,
    so the interpolated central-difference gradient equals the true derivative to < 1 %)."""
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    r = 0.5 + 0.3 * np.sin(u / 9.0) * np.cos(v / 11.0)
    g = 0.5 + 0.3 * np.cos(u / 13.0 + 0.5)
    b = 0.4 + 0.2 * np.sin(v / 10.0)
    rgb = np.stack([r, g, b], -1)
    depth = np.full((H, W), 0.5)
    P, C, N, ok = organised_cloud(rgb, depth, K)
    return depth_image(P, C, N, ok, K, blur=0.0)


def test_photometric_terms_match_slow_finite_difference_reference():
    img = _smooth_scene()
    rng = np.random.default_rng(2)
    n = 60
    uv = np.c_[rng.uniform(8, W - 9, n), rng.uniform(8, H - 9, n)]
    z = 0.5 + rng.uniform(-0.02, 0.02, n)
    ps = np.c_[(uv[:, 0] - K[0, 2]) / F * z, (uv[:, 1] - K[1, 2]) / F * z, z]
    chan = np.asarray(img.chroma, np.float64)
    i_src = np.stack(
        [map_coordinates(chan[..., c], [uv[:, 1], uv[:, 0]], order=1) for c in range(2)], -1
    ) + rng.normal(0, 0.01, (n, 2))
    w = rng.uniform(0.5, 1.0, n)
    pl = rng.normal(0, 1e-3, n)
    keep = np.ones(n, bool)
    args = (
        jnp.asarray(ps, jnp.float32),
        jnp.asarray(i_src, jnp.float32),
        img,
        jnp.asarray(w, jnp.float32),
        jnp.asarray(pl, jnp.float32),
        jnp.asarray(keep),
        "chromaticity",
    )
    Hj, gj = photometric_terms(*args)
    # jit == eager
    Hk, gk = jax.jit(photometric_terms, static_argnums=(6,))(*args)
    np.testing.assert_allclose(
        np.asarray(Hk), np.asarray(Hj), rtol=1e-4, atol=1e-6 * float(jnp.abs(Hj).max())
    )
    np.testing.assert_allclose(
        np.asarray(gk), np.asarray(gj), rtol=1e-4, atol=1e-6 * float(jnp.abs(gj).max())
    )

    # slow reference: residual per point and channel, Jacobian by central differences of
    # r(delta) = I_t(pi(exp(omega) p + v)) - I_s (bilinear sampling by scipy)
    def resid(p, c, d):
        q = Rotation.from_rotvec(d[3:]).apply(p) + d[:3]
        uu, vv = F * q[0] / q[2] + K[0, 2], F * q[1] / q[2] + K[1, 2]
        return map_coordinates(chan[..., c], [[vv], [uu]], order=1)[0] - i_src_row[c]

    r_all = np.zeros((n, 2))
    J_all = np.zeros((n, 2, 6))
    eps = 1e-6
    for i in range(n):
        i_src_row = i_src[i]
        for c in range(2):
            r_all[i, c] = resid(ps[i], c, np.zeros(6))
            for a in range(6):
                e = np.zeros(6)
                e[a] = eps
                J_all[i, c, a] = (resid(ps[i], c, e) - resid(ps[i], c, -e)) / (2 * eps)
    s_i = 1.4826 * np.median(np.abs(r_all)) + 1e-4
    s_g = 1.4826 * np.median(np.abs(pl)) + 1e-6
    wc = w[:, None] * np.exp(-(r_all**2) / (2 * (3 * s_i) ** 2)) * (s_g / s_i) ** 2
    H_ref = np.einsum("nc,nca,ncb->ab", wc, J_all, J_all)
    g_ref = np.einsum("nc,nca,nc->a", wc, J_all, r_all)
    # tolerance: the gradient image is a central difference (not the interpolant's
    # derivative): < 1 % on this smooth pattern
    np.testing.assert_allclose(np.asarray(gj), g_ref, rtol=0.03, atol=0.03 * np.abs(g_ref).max())
    np.testing.assert_allclose(np.asarray(Hj), H_ref, rtol=0.03, atol=0.03 * np.abs(H_ref).max())


def _shaded_plane_view(shift_x):
    """A textured (coloured) plane Z = 0.5 m seen by a camera displaced by ``shift_x`` (m)
    along x, lit by a lamp on the camera: a grey shading 0.45 + 0.55 u / W across the image
    that moves with the camera (brightness constancy is violated, hue is not)."""
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    z = np.full((H, W), 0.5)
    X = (u - K[0, 2]) / F * z + shift_x
    Y = (v - K[1, 2]) / F * z
    tex = np.stack(
        [
            0.5 + 0.3 * np.sin(60 * X) * np.cos(45 * Y),
            0.5 + 0.3 * np.cos(50 * Y + 20 * X),
            0.5 + 0.2 * np.sin(35 * X + 55 * Y),
        ],
        -1,
    )
    shade = (0.45 + 0.55 * u / W)[..., None]
    return organised_cloud(tex * shade, z, K)


@pytest.fixture(scope="module")
def shaded_planes():
    return shifted_pair(_shaded_plane_view, K, 0.003)


CFG = IcpConfig(
    iterations=25, max_dist=0.03, min_dist=0.004, keypoint_weight=0.0, degeneracy_ratio=0.01
)


def test_chromaticity_term_recovers_the_plane_slide_under_camera_fixed_shading(shaded_planes):
    # target <- source = +3 mm in the plane: invisible to the geometry (degenerate), taken
    # from the colour term. The grey level is dragged by the shading that travels with the
    # camera; the chromaticity is not.
    src, tgt, src_img, T_true = shaded_planes
    T0 = jnp.eye(4, dtype=jnp.float32)
    grey = projective_icp_jit(
        src, tgt, T0, CFG, window=0, src_image=src_img, photometric="intensity"
    )
    hue = projective_icp_jit(
        src, tgt, T0, CFG, window=0, src_image=src_img, photometric="chromaticity"
    )
    _, t_grey = pose_error(np.asarray(grey.T, np.float64), T_true)
    r_hue, t_hue = pose_error(np.asarray(hue.T, np.float64), T_true)
    assert t_grey > 1e-4, t_grey  # measured 0.21 mm (7 % of the shift)
    assert t_hue < 3e-5 and r_hue < 0.01, (t_hue, r_hue)  # measured 0.005 mm
    # the colour term acts only in the degenerate directions: depth (observable) exact
    assert abs(float(hue.T[2, 3])) < 1e-5


def test_register_pair_rejects_unknown_photometric_mode():
    with pytest.raises(ValueError, match="photometric"):
        register_pair(None, None, K, photometric="hue")
