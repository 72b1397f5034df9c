"""jaxcr.segmentation.refine multi-camera refinement with the rig-level camera correction
(``RefineConfig.camera_correction_mode = "rig"``): the cameras keep their calibrated relative
pose (closed form), one camera reduces to the per-camera parameterisation, a clean stereo
scene with a shared registration error and a known out-of-plane delta-u is recovered in 3-D
(depth included), gradients are finite at zero correction, warm starts round-trip.

Small images (160x120) and a small config; the compiled refinement is a module fixture.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from jaxcr.camera import Camera
from jaxcr.errors import InputError
from jaxcr.segmentation.metrics import iou, tip_error, tip_error_components
from jaxcr.segmentation.refine import (
    CAM_ROT_UNIT,
    CAM_T_UNIT,
    RefineConfig,
    _corrected_camera,
    _pose_delta,
    _rig_cameras,
    _rig_corrections_to_params,
    refine_frame,
)
from jaxcr.segmentation.silhouette import project_tube
from tests.helpers import refine_scene
from tests.helpers.jitted import colour_mask, perturbed_centreline  # input construction
from tests.helpers.tube_render import arc_base, render_tube

W, H = refine_scene.W, refine_scene.H
FX = 200.0
BASELINE = 0.24  # m
# one full-resolution level keeps the compile short; shared with test_refine's two-camera
# test (tests/helpers/refine_scene.py: the same compiled program)
CFG = refine_scene.RIG_CFG

# A bend about the body y axis (row 1): the tube leaves the arc's plane, i.e. moves along
# the cameras' optical axes, which one view cannot see; plus a small in-plane part
TRUE_C = np.array([[0.1, 0.0, 0.0], [0.4, -0.15, 0.0]], np.float32)
# shared robot-to-rig registration error (camera 0 frame): 0.4 deg and 1.5 mm
TRUE_E = np.array([0.004, -0.005, 0.002, 1.0e-3, -0.8e-3, 0.7e-3], np.float32)


def _stereo():
    """Converging rig: baseline across the arc's main direction (x), 0.24 m wide, both
    cameras 0.3 m in front of the arc looking at its middle; the second one slightly rolled
    (relative poses are not just a translation)."""
    cams = [
        Camera.look_at([0, y, -0.3], [0, -0.01, 0], [0, -1, 0], fx=FX, size=(W, H))
        for y in (-BASELINE / 2, BASELINE / 2)
    ]
    T1 = np.asarray(cams[1].T_cam_robot, np.float64)
    T1[:3] = Rotation.from_rotvec([0.0, 0.0, 0.05]).as_matrix() @ T1[:3]
    cams[1] = eqx.tree_at(lambda c: c.T_cam_robot, cams[1], jnp.asarray(T1, jnp.float32))
    return tuple(cams)


def _T(cam):
    return np.asarray(cam.T_cam_robot, np.float64)


def _E(p6):
    """4x4 correction X' = R X + d from physical (rotation vector, translation)."""
    E = np.eye(4)
    E[:3, :3] = Rotation.from_rotvec(np.asarray(p6[:3], np.float64)).as_matrix()
    E[:3, 3] = np.asarray(p6[3:], np.float64)
    return E


def _z_ref(base, cams):
    return tuple(jnp.mean(base.p @ c.R[2] + c.t[2]) for c in cams)


# The library's pose helpers compiled (one program per signature) instead of run op by op:
# eager, each primitive of the SO(3) maps was its own XLA compilation (~130 programs, ~5 s of
# CPU in this module). jit == eager needs no check here: refine_frame only ever runs them jitted.
_rig_cameras_j = eqx.filter_jit(_rig_cameras)


@pytest.fixture(scope="module")
def scene():
    base = arc_base(2.5e-3)
    cams = _stereo()
    truth = perturbed_centreline(base, jnp.asarray(TRUE_C))
    E = _E(TRUE_E)
    T0 = _T(cams[0])
    views = []
    for k, cam in enumerate(cams):
        T_true = _T(cam) @ np.linalg.inv(T0) @ E @ T0
        true_cam = eqx.tree_at(lambda c: c.T_cam_robot, cam, jnp.asarray(T_true, jnp.float32))
        img, mask = render_tube(truth, true_cam, 30 + k, (W, H))
        bg, ip = colour_mask(jnp.asarray(img))
        views.append((ip, bg, mask))
    return base, cams, truth, views


@pytest.fixture(scope="module")
def run():
    return eqx.filter_jit(refine_frame)


@pytest.fixture(scope="module")
def rig_result(scene, run):
    base, cams, _, views = scene
    # explicit zero warm starts: the warm-start test reuses this compiled signature
    zc, zcam = jnp.zeros(CFG.coeff_shape), jnp.zeros((2, 6))
    return run(
        base, cams, tuple(v[0] for v in views), tuple(v[1] for v in views), CFG, zc, True, zcam
    )


def test_rig_keeps_relative_poses_closed_form(scene):
    """T_0' = E T_0 and T_i' = (T_i T_0^-1) E T_0 (float64 reference with scipy rotations),
    so T_i' T_0'^-1 = T_i T_0^-1; with a residual, camera i >= 1 gets R_i on the left."""
    base, cams, _, _ = scene
    z = _z_ref(base, cams)
    p = jnp.asarray([[0.7, -1.2, 0.4, 1.5, -0.6, 2.0], [0.3, 0.2, -0.5, -1.0, 0.4, 0.2]])
    phys = [
        np.concatenate(
            [CAM_ROT_UNIT * np.asarray(p[i, :3]), CAM_T_UNIT * float(z[i]) * np.asarray(p[i, 3:])]
        )
        for i in range(2)
    ]
    T0, T1 = _T(cams[0]), _T(cams[1])
    rigid = _rig_cameras_j(cams, p, z, residual=False)
    ref0 = _E(phys[0]) @ T0
    ref1 = T1 @ np.linalg.inv(T0) @ _E(phys[0]) @ T0
    np.testing.assert_allclose(_T(rigid[0]), ref0, atol=2e-6)
    np.testing.assert_allclose(_T(rigid[1]), ref1, atol=2e-6)
    rel = _T(rigid[1]) @ np.linalg.inv(_T(rigid[0]))
    np.testing.assert_allclose(rel, T1 @ np.linalg.inv(T0), atol=2e-6)
    with_res = _rig_cameras_j(cams, p, z, residual=True)
    np.testing.assert_allclose(_T(with_res[0]), ref0, atol=2e-6)
    np.testing.assert_allclose(_T(with_res[1]), _E(phys[1]) @ ref1, atol=2e-6)
    # exactly the calibrated cameras at zero correction
    zero = _rig_cameras_j(cams, jnp.zeros((2, 6)), z, residual=True)
    for c, c0 in zip(zero, cams, strict=True):
        assert np.array_equal(np.asarray(c.T_cam_robot), np.asarray(c0.T_cam_robot))


def test_one_camera_rig_is_the_per_camera_parameterisation(scene):
    """With one camera the rig correction is the per-camera one (bitwise), so both modes
    give the same refinement."""
    base, cams, _, _ = scene
    z = _z_ref(base, cams[:1])
    p = jnp.asarray([[0.7, -1.2, 0.4, 1.5, -0.6, 2.0]])
    for residual in (False, True):
        a = _rig_cameras(cams[:1], p, z, residual)[0]
        b = _corrected_camera(cams[0], p[0], z[0])
        assert np.array_equal(np.asarray(a.T_cam_robot), np.asarray(b.T_cam_robot))


def test_rig_recovers_shared_pose_and_out_of_plane_delta_u(scene, rig_result):
    """Clean stereo pair rendered (independent renderer) with a shared registration error
    (0.4 deg, 1.5 mm) and an out-of-plane delta-u: the 3-D tip error, and its component along
    camera 0's optical axis, fall far below the nominal's; masks overlap their truths; the
    estimated effective corrections keep the cameras' relative pose."""
    base, cams, truth, views = scene
    r = rig_result
    assert bool(r.ok) and r.camera_correction.shape == (2, 6)
    tip_nom = float(tip_error(base.p, truth.p))
    tip_ref = float(tip_error(r.centreline.p, truth.p))
    _, dep_nom = tip_error_components(base.p, truth.p, cams[0].R)
    _, dep_ref = tip_error_components(r.centreline.p, truth.p, cams[0].R)
    assert tip_nom > 5e-3 and float(dep_nom) > 4e-3, (tip_nom, float(dep_nom))
    # measured 2.04 of 26.2 mm and 1.65 of 25.0 mm
    assert tip_ref < 0.25 * tip_nom, (tip_ref, tip_nom)
    assert float(dep_ref) < 0.25 * float(dep_nom), (float(dep_ref), float(dep_nom))
    for k in range(2):
        assert float(iou(r.masks[k], views[k][2])) > 0.8
    # effective corrections applied to the calibrated cameras keep the relative pose
    cc = np.asarray(r.camera_correction, np.float64)
    T0n, T1n = _E(cc[0]) @ _T(cams[0]), _E(cc[1]) @ _T(cams[1])
    rel_err = (T1n @ np.linalg.inv(T0n)) @ np.linalg.inv(_T(cams[1]) @ np.linalg.inv(_T(cams[0])))
    assert np.linalg.norm(Rotation.from_matrix(rel_err[:3, :3]).as_rotvec()) < 1e-5
    assert np.linalg.norm(rel_err[:3, 3]) < 1e-6


def test_rig_corrections_round_trip_to_parameters():
    """Warm start (``init_cam``) in the rig mode: effective per-camera corrections computed
    from rig parameters (shared E, residual of camera 1) convert back to those parameters."""
    base = arc_base(2.5e-3)
    cams = _stereo()
    z = _z_ref(base, cams)
    p = jnp.asarray([[0.7, -1.2, 0.4, 1.5, -0.6, 2.0], [0.3, 0.2, -0.5, -1.0, 0.4, 0.2]])
    for residual, rows in ((True, 2), (False, 1)):
        out = _rig_cameras(cams, p[:rows], z, residual)
        corr = jnp.stack(
            [_pose_delta(c.T_cam_robot, c0.T_cam_robot) for c, c0 in zip(out, cams, strict=True)]
        )
        back = _rig_corrections_to_params(cams, corr, z, residual)
        np.testing.assert_allclose(np.asarray(back), np.asarray(p[:rows]), atol=2e-3)


def test_warm_start_from_the_result(scene, rig_result, run):
    """Refining again from the result (coefficients and ``init_cam`` = its effective
    corrections, same compiled function) stays as good: J and tip within tolerance."""
    base, cams, truth, views = scene
    r2 = run(
        base,
        cams,
        tuple(v[0] for v in views),
        tuple(v[1] for v in views),
        CFG,
        rig_result.coeffs,
        True,
        rig_result.camera_correction,
    )
    assert bool(r2.ok)
    assert float(r2.energy.total) <= float(rig_result.energy.total) + 0.02
    assert float(tip_error(r2.centreline.p, rig_result.centreline.p)) < 2e-3


def test_gradient_finite_at_zero_correction(scene):
    """Projected points and effective corrections (so3_log at the identity) have finite
    gradients at zero correction; the projection gradient matches central differences."""
    base, cams, _, _ = scene
    z = _z_ref(base, cams)
    cl = perturbed_centreline(base, jnp.asarray(TRUE_C))

    def f(p):
        out = _rig_cameras(cams, p, z, residual=True)
        return sum(jnp.sum(project_tube(c, cl).ax) for c in out)

    p0 = jnp.zeros((2, 6))
    # one compiled program for f and its gradient (not one per primitive); its value serves
    # the central differences too, so no program computes f alone
    f_and_g = jax.jit(jax.value_and_grad(f))
    g = np.asarray(f_and_g(p0)[1])
    assert np.all(np.isfinite(g)) and np.any(g != 0)
    h = 1e-2
    for i, j in ((0, 1), (0, 3), (1, 2), (1, 5)):
        e = jnp.zeros((2, 6)).at[i, j].set(h)
        fd = (float(f_and_g(p0 + e)[0]) - float(f_and_g(p0 - e)[0])) / (2 * h)
        assert abs(fd - g[i, j]) < 0.02 * abs(g).max(), (i, j, fd, g[i, j])

    def corr(p):
        out = _rig_cameras(cams, p, z, residual=True)
        return sum(
            jnp.sum(_pose_delta(c.T_cam_robot, c0.T_cam_robot))
            for c, c0 in zip(out, cams, strict=True)
        )

    assert np.all(np.isfinite(np.asarray(jax.jit(jax.grad(corr))(p0))))


def test_bad_mode_raises_input_error():
    with pytest.raises(InputError):
        RefineConfig(camera_correction_mode="stereo")
    with pytest.raises(InputError):
        RefineConfig(camera_correction_mode="rig", g_cam_rel=0.0)
