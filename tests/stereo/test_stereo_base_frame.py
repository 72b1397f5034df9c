"""The markerless base frame (jaxcr.stereo.base_frame), the per-view tip pixel
(jaxcr.stereo.view2d) and stereo.json's "base" validation, against independent references:
cv2.triangulatePoints, closed-form arcs, drawn masks."""

import json

import cv2
import numpy as np
import pytest

from jaxcr.camera import camera_from_arrays
from jaxcr.cli.stereo import parse_base
from jaxcr.errors import InputError
from jaxcr.stereo.base_frame import (
    frame_from_direction,
    initial_direction,
    relative_pose,
    triangulate_entry,
)
from jaxcr.stereo.view2d import polyline_px, tip_pixel


def _rig(dist=(0.0,) * 5):
    """Two 320x240 cameras 0.2 m apart, converging on a point ~0.25 m in front."""
    K = np.array([[300.0, 0, 160.0], [0, 300.0, 120.0], [0, 0, 1]])
    R2 = cv2.Rodrigues(np.array([0.0, -0.7, 0.05]))[0]
    T2 = np.eye(4)
    T2[:3, :3] = R2
    T2[:3, 3] = [0.17, 0.0, 0.08]
    c1 = camera_from_arrays(K, np.array(dist), np.eye(4), 320, 240)
    c2 = camera_from_arrays(K, np.array(dist), T2, 320, 240)
    return c1, c2, T2


def _project(cam, T, X):
    uv, _ = cv2.projectPoints(
        np.asarray(X, np.float64).reshape(1, 1, 3), cv2.Rodrigues(T[:3, :3])[0], T[:3, 3],
        np.asarray(cam.K, np.float64), np.asarray(cam.dist, np.float64),
    )  # fmt: skip
    return uv.reshape(2)


@pytest.mark.parametrize("seed", range(4))
def test_triangulate_entry_matches_cv2_triangulatepoints(seed):
    rng = np.random.default_rng(seed)
    c1, c2, T2 = _rig(dist=(-0.1, 0.02, 0.001, -0.001, 0.0))
    X = np.array([0.0, 0.0, 0.25]) + rng.uniform(-0.03, 0.03, 3)
    # Pixel noise (0.5 px) so that the rays do not meet: both solve the same DLT least
    # squares, on the same undistorted normalised coordinates.
    uv1 = _project(c1, np.eye(4), X) + rng.normal(0, 0.5, 2)
    uv2 = _project(c2, T2, X) + rng.normal(0, 0.5, 2)
    got, residual, depths = triangulate_entry(c1, c2, uv1, uv2)
    n1 = cv2.undistortPoints(uv1.reshape(1, 1, 2), np.asarray(c1.K), np.asarray(c1.dist))
    n2 = cv2.undistortPoints(uv2.reshape(1, 1, 2), np.asarray(c2.K), np.asarray(c2.dist))
    Xh = cv2.triangulatePoints(np.eye(4)[:3], T2[:3], n1.reshape(2, 1), n2.reshape(2, 1))
    ref = Xh[:3, 0] / Xh[3, 0]
    # float64 SVD of a 4x4 system of condition ~1e3: agreement to ~1e-12 m; 1e-9 m margin.
    np.testing.assert_allclose(got, ref, atol=1e-9)
    # 0.5 px noise per view, reprojection after the fit is below the noise (3 sigma).
    assert residual < 3 * 0.5 * np.sqrt(2)
    assert min(depths) > 0
    # noise-free pixels give the point back (float64, ~1e-12 m).
    exact, res0, _ = triangulate_entry(c1, c2, _project(c1, np.eye(4), X), _project(c2, T2, X))
    np.testing.assert_allclose(exact, X, atol=1e-9)
    assert res0 < 1e-6


def test_relative_pose_composes_the_extrinsics():
    c1, c2, T2 = _rig()
    T0 = np.eye(4)
    T0[:3, :3] = cv2.Rodrigues(np.array([0.3, -0.2, 0.1]))[0]
    T0[:3, 3] = [0.01, -0.02, 0.03]
    a = camera_from_arrays(c1.K, c1.dist, T0, 320, 240)
    b = camera_from_arrays(c2.K, c2.dist, T2 @ T0, 320, 240)
    # float32 camera storage: 1e-6 relative on unit-scale entries.
    np.testing.assert_allclose(relative_pose(a, b), T2, atol=1e-5)


@pytest.mark.parametrize("z", [[0, 0, 1], [0.3, -0.5, 0.8], [1, 0.05, 0], [-0.2, 1, 0.1]])
def test_frame_from_direction_convention(z):
    z = np.asarray(z, float) / np.linalg.norm(z)
    T = frame_from_direction(np.array([0.1, 0.2, 0.3]), z)
    R = T[:3, :3]
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_allclose(R[:, 2], z, atol=1e-12)
    np.testing.assert_allclose(T[:3, 3], [0.1, 0.2, 0.3])
    x = R[:, 0]
    if abs(z[0]) <= np.cos(np.radians(18)):
        # x is camera 1's x axis made perpendicular to z: in the plane of e_x and z.
        ref = np.array([1.0, 0, 0]) - z[0] * z
        np.testing.assert_allclose(x, ref / np.linalg.norm(ref), atol=1e-12)
    else:
        ref = np.array([0, 1.0, 0]) - z[1] * z
        np.testing.assert_allclose(x, ref / np.linalg.norm(ref), atol=1e-12)


@pytest.mark.parametrize("kappa", [0.0, 10.0, 25.0])
def test_initial_direction_on_a_circular_arc(kappa):
    """Closed-form arc: tangent t0 at the origin, bending towards n."""
    rng = np.random.default_rng(int(kappa))
    t0 = np.array([0.2, -0.3, 0.93])
    t0 /= np.linalg.norm(t0)
    n = np.cross(t0, [1.0, 0, 0])
    n /= np.linalg.norm(n)
    s = np.arange(0.002, 0.04, 5e-4)  # first 2 mm hidden at the entry
    if kappa == 0:
        p = s[:, None] * t0
    else:
        p = (np.sin(kappa * s) / kappa)[:, None] * t0 + ((1 - np.cos(kappa * s)) / kappa)[
            :, None
        ] * n
    # the quadratic's slope misses the arc's cubic term: ~kappa^2 L^2 / 20 rad over
    # L = 12 mm (4.5e-3 rad at 25 /m); plus 20 um noise: ~2e-3 rad. Bound 1e-2 rad.
    p = p + rng.normal(0, 2e-5, p.shape)
    z = initial_direction(s, p, 0.012, origin=np.zeros(3))
    assert np.arccos(np.clip(z @ t0, -1, 1)) < 1e-2
    assert initial_direction(s[:3], p[:3], 0.012, origin=np.zeros(3)) is None


def test_tip_pixel_finds_the_end_of_a_drawn_tube():
    mask = np.zeros((120, 160), np.uint8)
    cv2.line(mask, (20, 60), (120, 60), 1, 9)  # 9 px wide, ends at u = 120 (+ round cap)
    mask = mask.astype(bool)
    last_fg = np.flatnonzero(mask[60])[-1]
    uv = np.stack([np.arange(20.0, 115.0), np.full(95, 60.0)], 1)  # skeleton stops short
    tip = tip_pixel(uv, mask)
    # the mask's edge is half a pixel beyond its last pixel centre; 0.25 px search step.
    assert tip[0] == pytest.approx(last_fg + 0.5, abs=0.25)
    assert tip[1] == pytest.approx(60.0)
    line = polyline_px(uv)
    assert np.all(np.diff(line[:, 0]) >= 2.0 - 1e-9) and line[-1, 0] == uv[-1, 0]


def _cams():
    c1, c2, T2 = _rig()
    return c1, c2


def test_parse_base_forms_and_errors():
    c1, c2 = _cams()
    names = ["a", "b"]
    assert parse_base(None, "f", names, c1, c2).mode == "markers"
    T = np.eye(4)
    T[:3, 3] = [0.0, 0.0, 0.25]
    spec = parse_base({"T_cam_base": T.tolist()}, "f", names, c1, c2)
    np.testing.assert_array_equal(spec.T_cam1_base, T)
    X = np.array([0.01, 0.0, 0.25])
    e = {
        "a": _project(c1, np.eye(4), X).tolist(),
        "b": _project(c2, relative_pose(c1, c2), X).tolist(),
    }
    # another point 5 cm away across the epipolar lines (they run along the baseline, x)
    e_off = _project(c2, relative_pose(c1, c2), X + [0.0, 0.05, 0.0]).tolist()
    spec = parse_base({"entry_px": e}, "f", names, c1, c2)
    assert spec.mode == "entry_px" and spec.entry_px[1] == tuple(e["b"])
    bad = [
        ({"T_cam_base": T.tolist(), "entry_px": e}, "base"),
        ({"aruco": {}}, "base"),
        ({"T_cam_base": [[1, 0], [0, 1]]}, "base.T_cam_base"),
        ({"T_cam_base": (np.eye(4) * 2).tolist()}, "base.T_cam_base"),
        ({"T_cam_base": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 250.0], [0, 0, 0, 1]]},
         "base.T_cam_base"),  # 250 "m": millimetres
        ({"entry_px": {"a": e["a"]}}, "base.entry_px"),
        ({"entry_px": {"a": e["a"], "b": [1, "x"]}}, "base.entry_px.b"),
        ({"entry_px": {"a": [400.0, 10.0], "b": e["b"]}}, "base.entry_px.a"),
        ({"entry_px": {"a": e["a"], "b": e_off}}, "base.entry_px"),  # not one point
    ]  # fmt: skip
    for base, field in bad:
        with pytest.raises(InputError) as err:
            parse_base(base, "stereo.json", names, c1, c2)
        assert err.value.field == field, (base, err.value)
        assert "\n" not in str(err.value)
    with pytest.raises(InputError) as err:
        parse_base(None, "stereo.json", ["a"], c1, None)
    assert err.value.field == "base"


def test_stereo_json_base_errors_via_cli(tmp_path, capsys):
    """Bad base in stereo.json: exit 2, one line naming file and field."""
    from jaxcr.cli import main
    from jaxcr.io.calibration import save_stereo

    c1, c2 = _cams()
    (tmp_path / "calib").mkdir()
    save_stereo(c1, c2, tmp_path / "calib" / "stereo.yaml")
    meta = {"format": "jaxcr.stereo/1", "calibration": "calib/stereo.yaml",
            "cameras": ["a", "b"], "base": {"entry_px": {"a": [10, 10]}},
            "frames": [{"id": "0", "images": {"a": "a.png", "b": "b.png"}}]}  # fmt: skip
    (tmp_path / "stereo.json").write_text(json.dumps(meta))
    assert main(["stereo", str(tmp_path), "-o", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "stereo.json" in err[0] and "base.entry_px" in err[0]


def test_single_view_tail_follows_the_fitted_arc():
    """The tail appended beyond the last stereo sample lies on the chain's last arc
    (closed-form circle), attached at the last stereo point."""
    from jaxcr.stereo.pipeline import _single_view_tail

    kappa = 20.0  # 1/m, bending about the base x axis: circle in the y-z plane
    s = np.arange(0.0, 0.05 + 1e-12, 5e-4)

    def arc(t):
        return np.stack([0 * t, (1 - np.cos(kappa * t)) / kappa, np.sin(kappa * t) / kappa], 1)

    joint = {
        "fit": {"base": np.zeros(3), "R0": np.eye(3), "curvatures": np.array([[-kappa, 0.0]])},
        "seg_start": np.array([0.0]),
        "arc_length": np.array([0.062]),
    }
    st, pt = _single_view_tail(s, arc(s), joint, 5e-4)
    np.testing.assert_allclose(st, 0.05 + 5e-4 * np.arange(1, len(st) + 1), atol=1e-12)
    assert len(st) == 24  # 12 mm at 0.5 mm
    # float32 chain evaluation (~1e-7 x 0.06 m) and the 0.3 um arclength search: 2 um.
    np.testing.assert_allclose(pt, arc(st), atol=2e-6)
