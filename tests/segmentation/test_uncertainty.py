"""jaxcr.segmentation.uncertainty: the Gauss-Newton information matrix against a finite-
difference reference built outside jaxcr's rasteriser (OpenCV projection, NumPy capsule
distances), the tip Jacobian against finite differences, no NaN at a straight tube, and the
depth warning on a depth-ambiguous and a well-conditioned scene.

Small images (160x120) and the arc of tests/helpers/tube_render.py; the covariance is
evaluated at the true coefficients (what a converged refinement returns up to noise), so no
refinement is compiled here. The Monte-Carlo calibration (scatter of refinements over noise
seeds vs the predicted sigmas) takes minutes and lives in
experiments/segmentation/uncertainty_calibration.py.
"""

import cv2
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxcr.camera import Camera
from jaxcr.segmentation.background import no_mask
from jaxcr.segmentation.refine import RefineConfig
from jaxcr.segmentation.shape import perturbed_centreline
from jaxcr.segmentation.uncertainty import depth_ambiguous, laplace_covariance, shape_uncertainty
from tests.helpers.tube_render import arc_base, front_camera, render_tube

W, H = 160, 120
TAU = 0.8
CFG = RefineConfig(
    n_coeffs=3,
    levels=(1, 0),
    steps=(30, 15),
    outer=(2, 1),
    tau=(1.0, TAU),
    band_tiles=96,
    min_tiles=24,
    g_reg=0.5,
    local=False,
    camera_correction=False,
    seg_merge=1,  # one capsule per centreline step: the reference draws the same capsules
)
TRUE = np.array([[0.35, -0.15, 0.05], [0.0, 0.0, 0.0]], np.float32)


def side_camera():
    """Looks along +y at the arc's plane edge-on: it sees the front camera's depth axis."""
    return Camera.look_at([0, -0.3, -1e-3], [0, 0, 0], [0, 0, 1], fx=200.0, size=(W, H))


@pytest.fixture(scope="module")
def uncertainty_fn():
    @eqx.filter_jit
    def run(base, cams, imgs, bgs, coeffs):
        return shape_uncertainty(base, cams, imgs, bgs, CFG, coeffs)

    return run


@pytest.fixture(scope="module")
def arc_scene():
    """The arc with a known in-plane delta-u, rendered (no background mask) in the front and
    side cameras."""
    base = arc_base(2.5e-3)
    truth = perturbed_centreline(base, jnp.asarray(TRUE))
    cams = (front_camera(200.0, (W, H)), side_camera())
    imgs, bgs = [], []
    for k, cam in enumerate(cams):
        img, _ = render_tube(truth, cam, 11 + k, (W, H))
        bg, ip = no_mask(jnp.asarray(img))
        imgs.append(ip)
        bgs.append(bg)
    return base, cams, tuple(imgs), tuple(bgs)


@pytest.fixture(scope="module")
def front_only(arc_scene, uncertainty_fn):
    base, cams, imgs, bgs = arc_scene
    return uncertainty_fn(base, cams[:1], imgs[:1], bgs[:1], jnp.asarray(TRUE))


@pytest.fixture(scope="module")
def stereo(arc_scene, uncertainty_fn):
    base, cams, imgs, bgs = arc_scene
    return uncertainty_fn(base, cams, imgs, bgs, jnp.asarray(TRUE))


# ----------------------------------------------------------------------------- reference


def _soft_reference(base, coeffs, cam, tau):
    """Soft silhouette sigmoid(margin / tau) at every pixel centre (float64): capsules between
    consecutive centreline points projected with cv2.projectPoints, radius sqrt(fx fy) rho / z
    (linear along the capsule), margin = radius - distance to the segment, max over capsules."""
    cl = perturbed_centreline(base, jnp.asarray(coeffs, jnp.float32))
    p = np.asarray(cl.p, np.float64)
    R, t = np.asarray(cam.R, np.float64), np.asarray(cam.t, np.float64)
    K, dist = np.asarray(cam.K, np.float64), np.asarray(cam.dist, np.float64)
    uv = cv2.projectPoints(p, cv2.Rodrigues(R)[0], t, K, dist)[0][:, 0]
    z = p @ R[2] + t[2]
    r = np.sqrt(K[0, 0] * K[1, 1]) * np.asarray(cl.rho, np.float64) / z
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float64)
    P = np.stack([xx.ravel(), yy.ravel()], 1)[:, None, :]  # (n_pix, 1, 2)
    a, b = uv[:-1][None], uv[1:][None]
    d = b - a
    s = np.clip(((P - a) * d).sum(-1) / np.maximum((d * d).sum(-1), 1e-12), 0.0, 1.0)
    dist_ = np.linalg.norm(P - (a + s[..., None] * d), axis=-1)
    margin = np.max(r[:-1][None] + s * (r[1:] - r[:-1])[None] - dist_, axis=1)
    return 1.0 / (1.0 + np.exp(-margin / tau))


def _info_reference(base, coeffs, cam, img, tau, h=1e-3):
    """Gauss-Newton information of the soft-rendered image model (docs/uncertainty.md U2)
    with a central-difference Jacobian of the reference soft silhouette."""
    c0 = np.asarray(coeffs, np.float64).ravel()
    s0 = _soft_reference(base, c0.reshape(2, 3), cam, tau)
    I = np.asarray(img, np.float64).reshape(-1, 3)
    mu_in = (s0[:, None] * I).sum(0) / s0.sum()
    mu_out = ((1 - s0)[:, None] * I).sum(0) / (1 - s0).sum()
    e = (s0 * ((I - mu_in) ** 2).sum(1)).sum() + ((1 - s0) * ((I - mu_out) ** 2).sum(1)).sum()
    sigma2 = e / (3.0 * I.shape[0])
    J = np.zeros((s0.size, c0.size))
    for i in range(c0.size):
        dc = np.zeros_like(c0)
        dc[i] = h
        J[:, i] = (
            _soft_reference(base, (c0 + dc).reshape(2, 3), cam, tau)
            - _soft_reference(base, (c0 - dc).reshape(2, 3), cam, tau)
        ) / (2 * h)
    return ((mu_in - mu_out) ** 2).sum() * J.T @ J / sigma2, sigma2


# ----------------------------------------------------------------------------- tests


def test_information_matches_finite_difference_reference(arc_scene, front_only):
    base, cams, imgs, _ = arc_scene
    ref, sigma2 = _info_reference(base, TRUE, cams[0], imgs[0], TAU)
    got = np.asarray(front_only.hessian, np.float64)
    # Tolerance 3 % of the largest entry: the central differences move the silhouette by
    # ~0.07 px with float32 centreline points (error ~1e-5 px, 1e-4 relative), the band
    # leaves out pixels farther than ~4 px = 5 tau from the boundary (sigmoid' < 0.7 % of its
    # peak there), and the float32 sums over ~6000 band pixels are good to 1e-5.
    scale = np.max(np.abs(ref))
    np.testing.assert_allclose(got, ref, atol=0.03 * scale)
    # the noise estimate is the residual variance of the two-region model (same pixels)
    assert float(front_only.noise_std[0]) ** 2 == pytest.approx(sigma2, rel=0.02)


def test_covariance_is_pseudo_inverse_and_tip_sigma_matches_reference(arc_scene, stereo):
    base, cams, imgs, _ = arc_scene
    ref = sum(_info_reference(base, TRUE, c, im, TAU)[0] for c, im in zip(cams, imgs, strict=True))
    cov_ref = np.linalg.inv(ref)
    Jt = np.asarray(stereo.tip_jacobian, np.float64)
    tip_cov_ref = Jt @ cov_ref @ Jt.T
    assert int(stereo.null_dims) == 0
    for k, cam in enumerate(cams):
        R = np.asarray(cam.R, np.float64)
        depth_ref = np.sqrt(R[2] @ tip_cov_ref @ R[2])
        # image plane: the projected tip's pixel covariance (OpenCV's projection Jacobian
        # w.r.t. the camera-frame point, times R), and that at the tip's depth in metres
        tip = np.asarray(stereo.tip, np.float64)
        jac = cv2.projectPoints(tip[None], cv2.Rodrigues(R)[0], np.asarray(cam.t, np.float64),
                                np.asarray(cam.K, np.float64), np.zeros(5))[1][:, 3:6] @ R  # fmt: skip
        px_ref = np.sqrt(np.linalg.eigvalsh(jac @ tip_cov_ref @ jac.T)[-1])
        z = tip @ R[2] + float(cam.t[2])
        lat_ref = px_ref * z / np.sqrt(float(cam.K[0, 0] * cam.K[1, 1]))
        assert float(stereo.sigma_px[k]) == pytest.approx(px_ref, rel=0.10)
        # 10 %: the information entries agree to ~3 % (previous test); the sigma of a
        # direction is a square root of an inverse: about half that relative error times the
        # conditioning of the 2-3 coefficient combinations that move the tip most
        assert float(stereo.sigma_depth[k]) == pytest.approx(depth_ref, rel=0.10)
        assert float(stereo.sigma_lateral[k]) == pytest.approx(lat_ref, rel=0.10)


def test_tip_jacobian_matches_finite_differences(arc_scene, front_only):
    base = arc_scene[0]
    c0 = TRUE.astype(np.float64).ravel()
    h = 1e-2
    fd = np.zeros((3, c0.size))
    for i in range(c0.size):
        dc = np.zeros_like(c0)
        dc[i] = h
        tip = [
            np.asarray(perturbed_centreline(base, jnp.asarray((c0 + sgn * dc).reshape(2, 3),
                                                              jnp.float32)).p[-1], np.float64)
            for sgn in (1, -1)
        ]  # fmt: skip
        fd[:, i] = (tip[0] - tip[1]) / (2 * h)
    J = np.asarray(front_only.tip_jacobian, np.float64)
    # central differences: truncation h^2 |d3 tip| / 6 ~ 1e-4 * 0.12 m / 6, float32 rounding
    # of the 0.12 m tip over 2h ~ 1e-8 / 2e-2: both far under 1e-3 of |J| (~0.1 m / unit)
    np.testing.assert_allclose(J, fd, atol=1e-3 * np.abs(fd).max())


def test_straight_tube_is_nan_free_and_reports_unbounded_depth(uncertainty_fn):
    from tests.helpers.jitted import integrate_centreline

    n = 41
    s = jnp.linspace(0.0, 0.12, n)
    R0 = jnp.array([[0.0, 0, 1], [0, 1, 0], [-1, 0, 0]])
    base = integrate_centreline(s, jnp.zeros((n - 1, 3)), jnp.full(n, 2.5e-3),
                                jnp.array([-0.06, 0.0, 0.0]), R0)  # fmt: skip
    cam = front_camera(200.0, (W, H))
    img, _ = render_tube(base, cam, 5, (W, H))
    bg, ip = no_mask(jnp.asarray(img))
    u = uncertainty_fn(base, (cam,), (ip,), (bg,), jnp.zeros((2, 3)))
    for name in ("hessian", "cov_coeffs", "tip", "tip_jacobian", "tip_cov", "noise_std",
                 "sigma_lateral", "sigma_px"):  # fmt: skip
        assert np.all(np.isfinite(np.asarray(getattr(u, name)))), name
    assert not np.any(np.isnan(np.asarray(u.sigma_depth)))
    assert not np.any(np.isnan(np.asarray(u.depth_ratio)))
    # bending towards the camera moves a straight tube's projection only at second order:
    # its depth is bounded by this view far less than the image position (measured ratio
    # ~9), and the frame is flagged
    assert float(u.sigma_depth[0]) > 3 * float(u.sigma_lateral[0])
    assert bool(depth_ambiguous(u))


def test_warning_fires_on_single_view_not_on_orthogonal_stereo(front_only, stereo):
    assert bool(depth_ambiguous(front_only))
    assert float(front_only.depth_ratio[0]) > 3.0
    assert not bool(depth_ambiguous(stereo))
    # with a second, orthogonal view the front camera's depth is the side camera's image
    # plane: the two sigmas are of the same order
    assert float(stereo.depth_ratio[0]) < 3.0
    assert float(stereo.sigma_depth[0]) < 0.2 * float(front_only.sigma_depth[0])


def test_laplace_covariance_singular_and_non_finite():
    # rank-1 information: one observable direction, one unobservable
    v = np.array([3.0, 4.0]) / 5.0
    info = jnp.asarray(np.outer(v, v) * 50.0, jnp.float32)
    # compiled once for both calls (same shape): op by op its eigendecomposition and guards
    # were ~45 XLA compilations; shape_uncertainty only ever runs it jitted
    laplace = jax.jit(laplace_covariance)
    lam, dirs, cov, null = laplace(info)
    assert int(np.sum(np.asarray(null))) == 1
    # the finite part is a generalised inverse (H G H = H), so any quantity the information
    # sees (a in range(H)) has the variance of numpy's Moore-Penrose inverse (float64)
    H = np.outer(v, v) * 50.0
    G = np.asarray(cov, np.float64)
    np.testing.assert_allclose(H @ G @ H, H, rtol=1e-4, atol=1e-4)
    assert v @ G @ v == pytest.approx(v @ np.linalg.pinv(H) @ v, rel=1e-4)
    nd = np.asarray(dirs)[:, np.asarray(null)][:, 0]
    assert abs(nd @ v) < 1e-3  # the null direction is orthogonal to the observed one
    lam, dirs, cov, null = laplace(jnp.full((2, 2), jnp.nan))
    assert np.all(np.asarray(null)) and np.all(np.asarray(cov) == 0)
