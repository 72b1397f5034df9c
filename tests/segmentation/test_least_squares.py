"""jaxcr.segmentation.least_squares: the least-squares form of the band energy (residual
Jacobian vs finite differences, gradient of 1/2 |r|^2 == the BFGS energy's gradient, the
Gauss-Newton matrix == J_r^T J_r, finite at a straight tube) and ``RefineConfig(solver="gn")``
on the suite's canonical refinement scene (one new compiled program)."""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxcr.camera import project_xy
from jaxcr.segmentation.energy import (
    Weights,
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
from jaxcr.segmentation.silhouette import band_margin
from tests.helpers import energy_x64, refine_scene
from tests.helpers.tube_render import tube_frames

TAU = energy_x64.TAU


def _tiny(curvature: float):
    """A 12 cm tube (curvature ``curvature`` 1/m; 0 = straight) seen at level 1 of a smooth
    96x72 image, x64 (tests/helpers/energy_x64.py, test_energy's scene): ``(centreline,
    camera, region data, band)``. The compiled functions below take it as an argument
    instead of closing over it (closed-over arrays are constants of a program), so both
    curvatures run the same compiled programs."""
    return energy_x64.smooth_scene([curvature, 0.5 * curvature, 0.0])


def _tube(scene, c):
    return energy_x64.level_tube(scene, c)


def _margin(scene, c):
    _, _, d, band = scene
    return band_margin(_tube(scene, c), d.grid, band)


def _image_energy(scene, soft):
    _, _, d, band = scene
    return chan_vese_soft(soft, band, d, Weights(), energy_x64.AREA)[0]


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
    m = _margin(scene, c)
    mr = (m, region_residuals(m, e, TAU).ravel())
    return mr, mr


# compiled once for both curvatures (the scene is an argument; its non-array leaves static).
# The margins and residuals with their Jacobians in one forward-mode pass (the residuals are
# a per-pixel function of the margins): the same program gives the values at c0 and those of
# the central differences (the primal of the pass), instead of two more programs.
_margin_resid_and_jac = eqx.filter_jit(jax.jacfwd(_margin_and_resid, argnums=1, has_aux=True))
_grad_image_energy = eqx.filter_jit(jax.grad(_image_energy, argnums=1))
_fast_normal_terms_j = eqx.filter_jit(_fast_normal_terms)


@pytest.mark.parametrize("curvature", [8.0, 0.0])
def test_residual_jacobian_gradient_and_gauss_newton_matrix(curvature):
    with jax.enable_x64(True):
        scene = _tiny(curvature)
        # numpy points and perturbations (float64): op by op, each jnp operation in x64 was
        # an XLA compilation of its own
        c0 = np.random.default_rng(5).normal(0, 0.05, (2, 3))
        if curvature == 0.0:
            c0 = np.zeros((2, 3))  # the straight tube itself: the singular point to guard
        # the margins at c0 (they do not depend on the pixel weights: zero weights of the
        # margins' shape give them, from the program below)
        shape = jax.eval_shape(_margin, scene, c0)
        _, (m0, _) = _margin_resid_and_jac(scene, c0, np.zeros(shape.shape, shape.dtype))
        soft0 = jax.nn.sigmoid(m0 / TAU)
        # the pixel weights at c0, held fixed (the region means of c0)
        e = _grad_image_energy(scene, soft0)
        assert float(jnp.max(jnp.abs(e))) > 0 and bool(jnp.any(e == 0))  # padding: e = 0

        (dm, jr), (_, r0) = _margin_resid_and_jac(scene, c0, e)
        jr = np.asarray(jr).reshape(-1, 6)
        assert np.all(np.isfinite(jr))
        # 1) residual Jacobian vs central differences. Error of a central difference:
        #    eps^2/6 |r'''| (truncation) + 2 * 1e-16 |r| / eps (x64 rounding). Margins move
        #    ~100 px per unit of c (a 12 cm tube 0.3 m from a 120 px camera, halved at level
        #    1), so with tau = 1.5 px the residuals' third derivative is <~ (100/1.5)^3 |r|
        #    = 3e5 |r|, and eps = 1e-6 gives <~ 5e-8 |r| + 2e-10 |r|: atol 1e-6 max |r|.
        #    Pixels whose margin switches winning segment or capsule end within eps (a kink
        #    of the max) would differ; none does at this seed.
        r0 = np.asarray(r0)
        eps = 1e-6
        fd = np.zeros_like(jr)
        for i in range(6):
            dc = np.zeros(6)
            dc[i] = eps
            dc = dc.reshape(2, 3)
            hi = _margin_resid_and_jac(scene, c0 + dc, e)[1][1]
            lo = _margin_resid_and_jac(scene, c0 - dc, e)[1][1]
            fd[:, i] = (np.asarray(hi) - np.asarray(lo)) / (2 * eps)
        np.testing.assert_allclose(jr, fd, rtol=1e-5, atol=1e-6 * np.abs(r0).max())
        assert np.abs(jr).max() > 1e-3  # not trivially flat
        # 2) grad 1/2 |r|^2 (means fixed) == grad of the BFGS energy (means re-estimated):
        #    the envelope theorem makes them equal in exact arithmetic; float64 sums of
        #    ~1e3 terms: rtol 1e-9
        #    (grad 1/2 |r|^2 = J_r^T r by definition, with J_r checked against finite
        #    differences above: float64 products, no reverse-mode program of its own)
        g_ls = jr.T @ r0
        # (the BFGS energy J without its regulariser: test_energy's compiled value-and-
        # gradient program of tests/helpers/energy_x64.py, regulariser weight 0)
        _, g_cv = energy_x64.energy_value_and_grad(scene, c0, jnp.asarray(0.0, jnp.float64))
        g_cv = np.asarray(g_cv).ravel()
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
