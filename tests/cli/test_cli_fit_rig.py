"""What a lab's own rig needs from ``jaxcr fit`` and the dataset format (docs/your-own-rig.md):
backbones recorded in a camera's frame (``--in-camera``), the pose start at the measured base
(``pose_start``), the base term, multi-start fits, and dataset cameras taken from a stereo
calibration file (``{"stereo": FILE, "camera": N, "T_rig_robot": ...}``) whose robot pose
``fit --fit-pose --frame`` updates."""

from __future__ import annotations

import json

import jax.numpy as jnp
import numpy as np
import pytest

from jaxcr.camera import camera_from_arrays
from jaxcr.cli import main
from jaxcr.geometry import se3_exp
from jaxcr.io.calibration import load_stereo, save_stereo
from jaxcr.io.dataset import load_dataset
from jaxcr.io.robot import load_robot
from jaxcr.kinematics import ConstantCurvature
from jaxcr.kinematics.fit import _cold_forward, backbone_residual, pose_start, start_set
from tests.helpers.example_rig import load_example_rig

SS = {"kind": "single_segment", "length": 0.1, "radius": 0.003, "n_points": 24}
Q_TRUE = [0.55, 0.8]
#: the robot of docs/make_example_rig.py (tests/cli/test_tutorial.py), for the pose fit: with
#: its 25 backbone points and the tutorial's options (--in-camera cam1 --fit-pose --starts 9
#: --max-steps 300) the pose fit is the tutorial's first `jaxcr fit` program, loaded from the
#: run's compilation cache instead of compiled (tests/conftest.py LONGEST_FIRST runs the
#: tutorial early); an SS pose fit of its own cost ~6 s of CPU
CC3 = load_example_rig().ROBOT
#: the true shape (kappa 1/m, phi rad, length m per section) and the start the tutorial's
#: dataset gives (straight, nominal lengths)
Q_CC3 = [8.0, 0.4, 0.040, 14.0, -0.9, 0.033, 20.0, 1.3, 0.025]
Q0_CC3 = [1.0, 0.0, 0.042, 1.0, 0.0, 0.034, 1.0, 0.0, 0.027]
K = [[300.0, 0, 159.5], [0, 300.0, 119.5], [0, 0, 1]]


def _pose(twist) -> np.ndarray:
    return np.asarray(se3_exp(jnp.asarray(twist, jnp.float32)), np.float64)


# The robot stands 0.25 m in front of camera 1, turned well away from its axes.
T_RIG_ROBOT = _pose([0.01, -0.02, 0.25, 1.2, -0.6, 0.4])
T_CAM2_CAM1 = _pose([-0.2, 0.0, 0.05, 0.0, 0.7, 0.0])


@pytest.fixture(scope="module")
def rig(tmp_path_factory):
    d = tmp_path_factory.mktemp("fit_rig")
    (d / "ss.json").write_text(json.dumps(SS))
    model = load_robot(d / "ss.json")
    p = np.asarray(_cold_forward(model, jnp.asarray(Q_TRUE)).centreline.p, np.float64)
    rng = np.random.default_rng(5)
    pts = p[np.r_[0 : len(p) : 3, len(p) - 1]] + rng.normal(scale=1e-4, size=(9, 3))
    np.save(d / "bb_robot.npy", pts)
    np.save(d / "bb_cam1.npy", pts @ T_RIG_ROBOT[:3, :3].T + T_RIG_ROBOT[:3, 3])
    # the tutorial rig's recorded backbone: 25 points along the 64 samples, 0.1 mm noise
    (d / "cc3.json").write_text(json.dumps(CC3))
    p3 = np.asarray(_cold_forward(load_robot(d / "cc3.json"), jnp.asarray(Q_CC3)).centreline.p)
    idx = np.linspace(0, len(p3) - 1, 25).round().astype(int)
    pts3 = p3[idx].astype(np.float64) + np.random.default_rng(5).normal(scale=1e-4, size=(25, 3))
    np.save(d / "bb_cc3_cam1.npy", pts3 @ T_RIG_ROBOT[:3, :3].T + T_RIG_ROBOT[:3, 3])
    c1 = camera_from_arrays(np.array(K), np.zeros(5), np.eye(4), 320, 240)
    c2 = camera_from_arrays(np.array(K), np.zeros(5), T_CAM2_CAM1, 320, 240)
    (d / "calib").mkdir()
    save_stereo(c1, c2, d / "calib" / "stereo.yaml")
    return d


def _dataset(rig, name, cameras, robot="ss.json", q=(1.0, 0.0)) -> str:
    ds = rig / name
    (ds / "images").mkdir(parents=True)
    import cv2

    cv2.imwrite(str(ds / "images" / "a.png"), np.zeros((240, 320, 3), np.uint8))
    frame = {"id": "000", "q": list(q), "images": {c: "images/a.png" for c in cameras}}
    d = {"format": "jaxcr.dataset/1", "robot": f"../{robot}", "cameras": cameras,
         "frames": [frame]}  # fmt: skip
    (ds / "dataset.json").write_text(json.dumps(d))
    return str(ds)


def test_stereo_camera_entries_load_as_the_stereo_file(rig):
    T = T_RIG_ROBOT.tolist()
    cams = {
        "cam1": {"stereo": "../calib/stereo.yaml", "camera": 1},
        "cam2": {"stereo": "../calib/stereo.yaml", "camera": 2, "T_rig_robot": T},
    }
    ds = load_dataset(_dataset(rig, "ds_entries", cams))
    ref1, ref2 = load_stereo(rig / "calib" / "stereo.yaml")
    np.testing.assert_array_equal(np.asarray(ds.cameras["cam1"].K), np.asarray(ref1.K))
    np.testing.assert_array_equal(
        np.asarray(ds.cameras["cam1"].T_cam_robot), np.asarray(ref1.T_cam_robot)
    )
    # camera 2 = [R | T] of the file composed with T_rig_robot (float32 cameras: 1e-6)
    np.testing.assert_allclose(
        np.asarray(ds.cameras["cam2"].T_cam_robot), T_CAM2_CAM1 @ T_RIG_ROBOT, atol=1e-6
    )
    np.testing.assert_array_equal(np.asarray(ds.cameras["cam2"].K), np.asarray(ref2.K))


@pytest.mark.parametrize(
    "entry, message",
    [
        ({"stereo": "../calib/stereo.yaml", "camera": 3}, "expected 1 or 2"),
        ({"stereo": "../calib/nope.yaml", "camera": 1}, "stereo calibration file not found"),
        ({"stereo": "../calib/stereo.yaml", "camera": 1, "T_rig_robt": np.eye(4).tolist()},
         "did you mean 'T_rig_robot'"),
    ],
)  # fmt: skip
def test_bad_stereo_camera_entry_is_one_line(rig, capsys, entry, message):
    ds = _dataset(rig, f"bad_{abs(hash(json.dumps(entry))) % 10**6}", {"cam1": entry})
    assert main(["validate", ds]) == 2
    err = capsys.readouterr()
    assert message in err.out + err.err


def test_in_camera_equals_the_robot_frame_fit(rig, capsys):
    """Points in camera 1's frame with --in-camera give the q of the same points in the robot
    frame: the mapping is exact up to float32 rounding on 0.25 m (~3e-8 m), far under the
    solver's resolution (rtol 1e-6 on unit-scale q; 1e-4 with margin)."""
    cams = {"cam1": {"stereo": "../calib/stereo.yaml", "camera": 1,
                     "T_rig_robot": T_RIG_ROBOT.tolist()}}  # fmt: skip
    ds = _dataset(rig, "ds_in_camera", cams)
    out_a, out_b = str(rig / "fa"), str(rig / "fb")
    args = ["--unit", "m"]
    assert main(["fit", str(rig / "ss.json"), "--backbone", str(rig / "bb_robot.npy"),
                 *args, "-o", out_a]) == 0  # fmt: skip
    assert main(["fit", ds, "--backbone", str(rig / "bb_cam1.npy"), "--in-camera", "cam1",
                 *args, "-o", out_b]) == 0  # fmt: skip
    qa = json.loads((rig / "fa" / "fit.json").read_text())["q"]
    qb = json.loads((rig / "fb" / "fit.json").read_text())["q"]
    np.testing.assert_allclose(qb, qa, atol=1e-4)
    np.testing.assert_allclose(qa, Q_TRUE, atol=0.05)  # 0.1 mm noise on a 0.1 m arc
    assert main(["fit", ds, "--backbone", str(rig / "bb_cam1.npy"), "--in-camera", "camX",
                 *args, "-o", out_b]) == 2  # fmt: skip
    assert "unknown camera 'camX'" in capsys.readouterr().err


def test_fit_pose_frame_places_the_robot_in_both_stereo_cameras(rig):
    """A backbone in camera 1's frame, --fit-pose --frame: both entries get the same
    T_rig_robot, and the model drawn through it lies on the points with its base at the
    measured base and its z axis along the true one. The tutorial rig's robot (three
    constant-curvature sections) and options, see CC3.

    Bounds: 0.1 mm noise per coordinate gives a point-to-model distance rms of
    0.1 * sqrt(3) * sqrt(1 - 15 / 75) = 0.15 mm (15 parameters, 75 residuals): under 0.3 mm.
    The base is held by the base term at the first point (its noise: 0.17 mm rms) and by the
    shape: within 0.5 mm, ~3 sigma. The z axis is the initial direction over the first
    centimetres (points 4.3 mm apart, each 0.1 mm off: ~1-2 deg for a tangent from two
    points; the arcs' shape holds it tighter): within 2 deg. Measured on noise seeds 0-7:
    rms 0.10-0.14 mm, base 0.06-0.32 mm, z 0.2-1.1 deg (seed 5, used here: 0.11 mm, 0.12 mm,
    0.85 deg)."""
    cams = {
        "cam1": {"stereo": "../calib/stereo.yaml", "camera": 1},
        "cam2": {"stereo": "../calib/stereo.yaml", "camera": 2},
    }
    ds = _dataset(rig, "ds_pose", cams, robot="cc3.json", q=Q0_CC3)
    assert main(["fit", ds, "--backbone", str(rig / "bb_cc3_cam1.npy"), "--unit", "m",
                 "--in-camera", "cam1", "--fit-pose", "--starts", "9", "--max-steps", "300",
                 "--frame", "000", "-o", str(rig / "fp")]) == 0  # fmt: skip
    d = json.loads((rig / "ds_pose" / "dataset.json").read_text())
    T1 = np.asarray(d["cameras"]["cam1"]["T_rig_robot"])
    np.testing.assert_array_equal(T1, np.asarray(d["cameras"]["cam2"]["T_rig_robot"]))
    fit = json.loads((rig / "fp" / "fit.json").read_text())
    assert fit["ok"] and fit["rms"] < 3e-4 and fit["starts"] == 9
    np.testing.assert_allclose(T1[:3, 3], T_RIG_ROBOT[:3, 3], atol=5e-4)
    cos = float(T1[:3, 2] @ T_RIG_ROBOT[:3, 2])
    assert np.degrees(np.arccos(min(cos, 1.0))) < 2.0
    loaded = load_dataset(ds)
    np.testing.assert_allclose(
        np.asarray(loaded.cameras["cam2"].T_cam_robot), T_CAM2_CAM1 @ T1, atol=1e-6
    )
    assert loaded.frames[0].q.tolist() == pytest.approx(fit["q"])


def test_pose_start_is_the_measured_base_frame():
    """Closed form: a straight line from a known origin along a known direction gives that
    origin and z; points already in the robot frame (base at 0, leaving along +z) give the
    identity."""
    o, z = np.array([0.1, -0.05, 0.3]), np.array([0.3, 0.4, 0.5])
    z = z / np.linalg.norm(z)
    pts = o + np.linspace(0, 0.08, 20)[:, None] * z
    T = pose_start(pts)
    np.testing.assert_allclose(T[:3, 3], o, atol=1e-12)
    np.testing.assert_allclose(T[:3, 2], z, atol=1e-9)
    np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-12)
    assert np.linalg.det(T[:3, :3]) > 0
    arc = np.stack([np.zeros(20), 0.5 * (1 - np.cos(np.linspace(0, 0.3, 20))),
                    0.5 * np.sin(np.linspace(0, 0.3, 20))], 1)  # fmt: skip
    # an arc of curvature 2/m: the quadratic's slope at the base is the tangent to O(s^2)
    np.testing.assert_allclose(pose_start(arc), np.eye(4), atol=2e-3)


def test_base_term_and_start_set():
    """The base term is base_weight x (first point - model base), appended last; start_set
    begins with q0 and varies only the bending planes (and CC's start curvature)."""
    model = ConstantCurvature.make([0.04, 0.03], [0.002] * 2, joints=("kappa", "phi", "length"))
    q = jnp.asarray([10.0, 0.3, 0.04, 15.0, -1.0, 0.03])
    pts = jnp.asarray(np.random.default_rng(0).normal(scale=0.02, size=(6, 3)), jnp.float32)
    eye = jnp.eye(4)
    r0 = backbone_residual(model, q, eye, pts, 1.0)
    r1 = backbone_residual(model, q, eye, pts, 1.0, None, 2.0)
    np.testing.assert_array_equal(np.asarray(r1[:-3]), np.asarray(r0))
    base = np.asarray(model.forward(q).centreline.p[0])
    np.testing.assert_allclose(np.asarray(r1[-3:]), 2.0 * (np.asarray(pts[0]) - base), atol=1e-7)
    q0 = np.array([1.0, 0.0, 0.04, 1.0, 0.0, 0.03])
    S = start_set(model, 9, q0=q0)
    assert S.shape == (9, 6)
    np.testing.assert_array_equal(S[0], q0)
    np.testing.assert_array_equal(S[1:, [2, 5]], np.tile([0.04, 0.03], (8, 1)))
    assert len({tuple(np.round(s[[1, 4]], 6)) for s in S[1:]}) == 8  # distinct plane pairs
