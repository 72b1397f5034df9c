"""jaxcr.segmentation.least_squares: the least-squares form of the band energy (residual
Jacobian vs finite differences, gradient of 1/2 |r|^2 == the BFGS energy's gradient, the
Gauss-Newton matrix == J_r^T J_r, finite at a straight tube) and ``RefineConfig(solver="gn")``
on the suite's canonical refinement scene (one new compiled program)."""

import dataclasses

import cv2
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxcr.camera import Camera, project_xy
from jaxcr.segmentation.energy import (
    Weights,
    chan_vese_energy,
    chan_vese_soft,
)
from jaxcr.segmentation.least_squares import (
    band_normal_terms,
    normal_terms,
    region_residuals,
    winner_margins,
)
from jaxcr.segmentation.metrics import iou
from jaxcr.segmentation.refine import refine_frame_jit
from jaxcr.segmentation.shape import perturbed_centreline
from jaxcr.segmentation.silhouette import band_margin, project_tube, scale_tube
from tests.helpers import refine_scene

# compiled: input construction only (shared with test_energy's x64 scene through the cache)
from tests.helpers.jitted import integrate_centreline, prepare_region_data, select_band
from tests.helpers.tube_render import tube_frames

W, H = 96, 72
TAU = 1.5
AREA = 500.0


def _tiny(curvature: float):
    """A 12 cm tube (curvature ``curvature`` 1/m; 0 = straight) seen at level 1 of a smooth
    96x72 image (smooth so the energy is smooth at the finite-difference step), x64: the
    scene ``(centreline, camera, region data, band)``. The compiled functions below take it
    as an argument instead of closing over it (closed-over arrays are constants of a
    program), so both curvatures run the same eight compiled programs; each curvature
    compiled all eight again before (~15 s of CPU)."""
    n = 33
    s = jnp.linspace(0.0, 0.12, n, dtype=jnp.float64)
    u = jnp.tile(jnp.array([curvature, 0.5 * curvature, 0.0], jnp.float64), (n - 1, 1))
    R0 = jnp.array([[0.0, 0, 1], [0, 1, 0], [-1, 0, 0]], jnp.float64)
    cl = integrate_centreline(
        s, u, jnp.full(n, 4e-3, jnp.float64), jnp.array([-0.05, 0.0, 0.0], jnp.float64), R0
    )
    cam = Camera.look_at([0, 0, -0.3], [0, 0, 0], [0, -1, 0], fx=120.0, size=(W, H))
    cam = jax.tree.map(lambda x: jnp.asarray(x, jnp.float64) if hasattr(x, "dtype") else x, cam)
    rng = np.random.default_rng(4)
    img = cv2.GaussianBlur(rng.random((H, W, 3)), (0, 0), 3).astype(np.float64)
    img[..., 0] += np.linspace(0, 0.5, W)[None]
    bg = np.zeros((H, W), bool)
    bg[:, :10] = True  # background pixels: e_p = g_pen/A > 0 there, 0 on the padding
    d = prepare_region_data(jnp.asarray(img), jnp.asarray(bg), 1, 8)
    band = select_band(scale_tube(project_tube(cam, cl), 1), d.grid, 30, 8)
    return cl, cam, d, band


def _tube(scene, c):
    cl, cam, _, _ = scene
    return scale_tube(project_tube(cam, perturbed_centreline(cl, c)), 1)


def _margin(scene, c):
    _, _, d, band = scene
    return band_margin(_tube(scene, c), d.grid, band)


def _resid(scene, c, e):
    return region_residuals(_margin(scene, c), e, TAU).ravel()


def _image_energy(scene, soft):
    _, _, d, band = scene
    return chan_vese_soft(soft, band, d, Weights(), AREA)[0]


def _bfgs_energy(scene, c):
    """What the BFGS solver minimises (regulariser left out)."""
    _, _, d, band = scene
    return chan_vese_energy(_tube(scene, c), band, d, 0.0, Weights(), TAU, AREA)[0]


def _fast_normal_terms(scene, c, e):
    """The refinement's path: winner_margins + band_normal_terms."""
    _, _, d, band = scene

    def fields(c):
        t = _tube(scene, c)
        return jnp.stack([t.ax, t.ay, t.bx, t.by, t.ra, t.rb]), t

    fj, t = jax.jacfwd(fields, has_aux=True)(c)
    m, dfield, slot = winner_margins(t, d.grid, band)
    return m, band_normal_terms(m, dfield, slot, fj.reshape(6, -1, 6), band, e, TAU)


def _margin_and_resid(scene, c, e):
    return _margin(scene, c), _resid(scene, c, e)


# compiled once for both curvatures (the scene is an argument; its non-array leaves static)
_margin_j = eqx.filter_jit(_margin)
_resid_j = eqx.filter_jit(_resid)
_grad_image_energy = eqx.filter_jit(jax.grad(_image_energy, argnums=1))
# the margin and residual Jacobians in one forward-mode pass (the residuals are a per-pixel
# function of the margins: one program instead of two that each pushed the six tangents
# through the rasteriser, ~3.5 s of CPU each)
_jac_margin_and_resid = eqx.filter_jit(jax.jacfwd(_margin_and_resid, argnums=1))
_grad_bfgs = eqx.filter_jit(jax.grad(_bfgs_energy, argnums=1))
_fast_normal_terms_j = eqx.filter_jit(_fast_normal_terms)


@pytest.mark.parametrize("curvature", [8.0, 0.0])
def test_residual_jacobian_gradient_and_gauss_newton_matrix(curvature):
    with jax.enable_x64(True):
        scene = _tiny(curvature)
        c0 = jnp.asarray(np.random.default_rng(5).normal(0, 0.05, (2, 3)))
        if curvature == 0.0:
            c0 = jnp.zeros((2, 3))  # the straight tube itself: the singular point to guard
        m0 = _margin_j(scene, c0)
        soft0 = jax.nn.sigmoid(m0 / TAU)
        # the pixel weights at c0, held fixed (the region means of c0)
        e = _grad_image_energy(scene, soft0)
        assert float(jnp.max(jnp.abs(e))) > 0 and bool(jnp.any(e == 0))  # padding: e = 0

        dm, jr = _jac_margin_and_resid(scene, c0, e)
        jr = np.asarray(jr).reshape(-1, 6)
        assert np.all(np.isfinite(jr))
        # 1) residual Jacobian vs central differences. Error of a central difference:
        #    eps^2/6 |r'''| (truncation) + 2 * 1e-16 |r| / eps (x64 rounding). Margins move
        #    ~100 px per unit of c (a 12 cm tube 0.3 m from a 120 px camera, halved at level
        #    1), so with tau = 1.5 px the residuals' third derivative is <~ (100/1.5)^3 |r|
        #    = 3e5 |r|, and eps = 1e-6 gives <~ 5e-8 |r| + 2e-10 |r|: atol 1e-6 max |r|.
        #    Pixels whose margin switches winning segment or capsule end within eps (a kink
        #    of the max) would differ; none does at this seed.
        r0 = np.asarray(_resid_j(scene, c0, e))
        eps = 1e-6
        fd = np.zeros_like(jr)
        for i in range(6):
            dc = jnp.zeros(6).at[i].set(eps).reshape(2, 3)
            hi, lo = _resid_j(scene, c0 + dc, e), _resid_j(scene, c0 - dc, e)
            fd[:, i] = (np.asarray(hi) - np.asarray(lo)) / (2 * eps)
        np.testing.assert_allclose(jr, fd, rtol=1e-5, atol=1e-6 * np.abs(r0).max())
        assert np.abs(jr).max() > 1e-3  # not trivially flat
        # 2) grad 1/2 |r|^2 (means fixed) == grad of the BFGS energy (means re-estimated):
        #    the envelope theorem makes them equal in exact arithmetic; float64 sums of
        #    ~1e3 terms: rtol 1e-9
        #    (grad 1/2 |r|^2 = J_r^T r by definition, with J_r checked against finite
        #    differences above: float64 products, no reverse-mode program of its own)
        g_ls = jr.T @ r0
        g_cv = np.asarray(_grad_bfgs(scene, c0)).ravel()
        np.testing.assert_allclose(g_ls, g_cv, rtol=1e-9, atol=1e-12 * np.abs(g_cv).max())
        # 3) normal_terms (closed form, no square root) == (J_r^T r, J_r^T J_r)
        dm = dm.reshape(*m0.shape, 6)
        g, G = normal_terms(m0, dm, e, TAU)
        np.testing.assert_allclose(np.asarray(g), g_cv, rtol=1e-9, atol=1e-12 * np.abs(g_cv).max())
        np.testing.assert_allclose(
            np.asarray(G), jr.T @ jr, rtol=1e-9, atol=1e-12 * np.abs(G).max()
        )
        assert np.all(np.isfinite(np.asarray(G))) and np.all(np.isfinite(np.asarray(g)))
        # 4) the refinement's path (per-pixel derivatives w.r.t. the winning capsule's six
        #    fields, chained through the tube Jacobian) gives the same margins, g and G
        m1, (g1, G1) = _fast_normal_terms_j(scene, c0, e)
        np.testing.assert_allclose(np.asarray(m1), np.asarray(m0), rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(np.asarray(g1), g_cv, rtol=1e-9, atol=1e-12 * np.abs(g_cv).max())
        np.testing.assert_allclose(
            np.asarray(G1), np.asarray(G), rtol=1e-9, atol=1e-12 * np.abs(G).max()
        )


def test_gauss_newton_refinement_recovers_known_delta_u():
    """solver="gn" on test_refine's two frames and config (refine_frame_jit, the per-frame
    program): the same recovery criteria as test_refine.test_recovers_known_delta_u, with
    the solve stopped by the image-space test (status 0), not its step budget."""
    W0, H0 = refine_scene.W, refine_scene.H
    cfg = dataclasses.replace(refine_scene.CFG, solver="gn")
    base, cam = refine_scene.base(), refine_scene.camera()
    true_coeffs = [
        np.array([[0.35, -0.15, 0.05], [0.0, 0.0, 0.0]], np.float32),
        np.array([[-0.3, 0.1, 0.0], [0.0, 0.0, 0.0]], np.float32),
    ]
    R = np.asarray(cam.R)

    def lateral_error(p, truth_p):
        return np.mean(np.linalg.norm(((np.asarray(p) - truth_p) @ R.T)[:, :2], axis=1))

    for f in tube_frames(base, cam, true_coeffs, (W0, H0)):
        r = refine_frame_jit(base, cam, f["img"], f["bg"], cfg)
        assert bool(r.ok) and int(r.failure) == 0 and int(r.status) == 0
        assert float(iou(r.nominal_masks[0], f["mask"])) < 0.5
        assert float(iou(r.masks[0], f["mask"])) > 0.85
        truth_p = np.asarray(f["truth"].p)
        assert lateral_error(r.centreline.p, truth_p) < lateral_error(base.p, truth_p) / 3
        u1, v1, _ = project_xy(cam, r.centreline.p)
        u2, v2, _ = project_xy(cam, f["truth"].p)
        assert float(jnp.mean(jnp.hypot(u1 - u2, v1 - v2))) < 1.5
        assert float(r.energy.total) < float(r.energy.total_nominal)
        assert int(r.num_steps) == int(jnp.sum(r.steps_per_level)) > 0
