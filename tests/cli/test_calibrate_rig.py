"""``jaxcr calibrate`` for real rigs (issue 16 item 4, issue 17 item 3): the intrinsic
constraint flags against OpenCV's own calibrateCamera / stereoCalibrate with the same flags,
the predicted uncertainty against Monte-Carlo scatter, the refusal of views that do not
determine the fitted intrinsics (the real single-pose case), the circle-grid pitch, the
background plate, and the refused arguments."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from jaxcr.cli import main
from jaxcr.cli.calibrate import spacing_from_args
from jaxcr.errors import InputError
from jaxcr.io.calibration import load_stereo
from jaxcr.stereo.calibration import (
    IntrinsicConstraints,
    board_points,
    calibrate_camera,
    calibrate_stereo,
    fill_from_plate,
    find_pattern,
    identifiability_problems,
    initial_camera_matrix,
)

SIZE = (320, 240)
COLS, ROWS, SQUARE = 7, 6, 0.02  # 8 x 7 squares: no 180-degree ambiguity
OBJ = board_points("chessboard", COLS, ROWS, SQUARE)

CONSTRAINT_SETS = [
    IntrinsicConstraints(),
    IntrinsicConstraints(fix_principal_point=True),
    IntrinsicConstraints(fix_aspect_ratio=True),
    IntrinsicConstraints(zero_tangent_dist=True, fix_k=(3,)),
    IntrinsicConstraints(fix_k=(1, 2, 3)),
    IntrinsicConstraints(fix_principal_point=True, fix_aspect_ratio=True, no_distortion=True),
]


def _truth(c: IntrinsicConstraints):
    """Intrinsics the constrained model describes exactly (so the fit is unbiased)."""
    fx, fy = (300.0, 300.0) if c.fix_aspect_ratio else (302.0, 297.0)
    cx, cy = ((SIZE[0] - 1) / 2, (SIZE[1] - 1) / 2) if c.fix_principal_point else (163.0, 116.0)
    d = np.array([-0.12, 0.05, 0.002, -0.001, 0.01])
    ks = (1, 2, 3) if c.no_distortion else c.fix_k
    for k in ks:
        d[{1: 0, 2: 1, 3: 4}[k]] = 0.0
    if c.zero_tangent_dist or c.no_distortion:
        d[2:4] = 0.0
    return np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]]), d


def _poses(n, seed, tilt_sd=0.4):
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        r = rng.normal(0, tilt_sd, 3) + np.array([np.pi, 0, 0])
        t = np.array([-0.06, 0.04, 0.33]) + rng.normal(0, 0.02, 3)
        out.append((r, t))
    return out


def _points(K, d, poses, noise, seed):
    """Board detections rendered with cv2.projectPoints plus Gaussian pixel noise."""
    rng = np.random.default_rng(seed)
    img = []
    for r, t in poses:
        p, _ = cv2.projectPoints(OBJ, r, t, K, d)
        img.append((p.reshape(-1, 2) + rng.normal(0, noise, (len(OBJ), 2))).astype(np.float32))
    return [OBJ] * len(poses), img


@pytest.mark.parametrize("c", CONSTRAINT_SETS, ids=lambda c: c.describe())
def test_constraints_match_opencv_calibrate_camera(c):
    K, d = _truth(c)
    obj, img = _points(K, d, _poses(10, seed=1), noise=0.1, seed=2)
    cal = calibrate_camera(obj, img, SIZE, c)
    # OpenCV itself with the same flags and starting matrix: the same fit. Both run the same
    # LM from the same start on the same points, so they agree to its convergence (1e-9
    # relative here, checked at 1e-6)
    rms, K_cv, d_cv, _, _ = cv2.calibrateCamera(obj, img, SIZE, initial_camera_matrix(SIZE),
                                                np.zeros(5), flags=c.cv_flags())  # fmt: skip
    np.testing.assert_allclose(cal.K, K_cv, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(cal.dist, d_cv.ravel()[:5], rtol=1e-6, atol=1e-9)
    assert cal.rms == pytest.approx(rms, rel=1e-6)
    # the constraints hold exactly
    if c.fix_principal_point:
        assert (cal.K[0, 2], cal.K[1, 2]) == ((SIZE[0] - 1) / 2, (SIZE[1] - 1) / 2)
    if c.fix_aspect_ratio:
        assert cal.K[0, 0] == cal.K[1, 1]
    ks = (1, 2, 3) if c.no_distortion else c.fix_k
    for k in ks:
        assert cal.dist[{1: 0, 2: 1, 3: 4}[k]] == 0.0
    if c.zero_tangent_dist or c.no_distortion:
        assert np.all(cal.dist[2:4] == 0.0)
    # against the truth: within 5 predicted sigma (a Gaussian exceeds 5 sigma with
    # probability 6e-7 per parameter)
    idx = {"f": (0, 0), "fx": (0, 0), "fy": (1, 1), "cx": (0, 2), "cy": (1, 2)}
    for name, sd in cal.std.items():
        if name in idx:
            assert abs(cal.K[idx[name]] - K[idx[name]]) <= 5 * sd, (name, cal.K, sd)
    assert identifiability_problems(cal)[0] == []  # (corner extrapolation may warn)


def test_predicted_sigma_matches_monte_carlo_scatter():
    """The predicted 1-sigma of f, cx against the scatter of 40 fits over noise seeds. The
    sample std of 40 draws has a relative spread of 1/sqrt(2*39) = 11 %; 4 of those (45 %)
    bound the ratio."""
    c = IntrinsicConstraints(zero_tangent_dist=True, fix_k=(3,))
    K, d = _truth(c)
    poses = _poses(6, seed=5)
    fits, preds = [], []
    for seed in range(40):
        cal = calibrate_camera(*_points(K, d, poses, noise=0.2, seed=100 + seed), SIZE, c)
        fits.append([cal.K[0, 0], cal.K[0, 2]])
        preds.append([cal.std["fx"], cal.std["cx"]])
    ratio = np.std(fits, axis=0, ddof=1) / np.mean(preds, axis=0)
    assert np.all((ratio > 0.55) & (ratio < 1.45)), ratio


def test_single_pose_with_free_intrinsics_is_refused_and_the_fixed_fit_is_not():
    """The real rig's case: one board pose with fx, fy, cx, cy free gave fx/fy 1204/952 and
    exit 0. Now the views are found not to determine them. With the principal point and
    the aspect ratio fixed and no distortion, one tilted pose determines the focal length."""
    c_full = IntrinsicConstraints()
    c_rig = IntrinsicConstraints(fix_principal_point=True, fix_aspect_ratio=True,
                                 no_distortion=True)  # fmt: skip
    K, _ = _truth(c_rig)
    pose = [(np.array([np.pi + 0.5, 0.25, 0.0]), np.array([-0.06, 0.04, 0.33]))]
    obj, img = _points(K, np.zeros(5), pose * 3, noise=0.1, seed=3)
    refused, _ = identifiability_problems(calibrate_camera(obj, img, SIZE, c_full))
    assert any(r.startswith("fx =") for r in refused), refused
    cal = calibrate_camera(obj[:1], img[:1], SIZE, c_rig)
    assert identifiability_problems(cal)[0] == []
    assert abs(cal.K[0, 0] - 300.0) <= 5 * cal.std["f"]
    assert cal.orientations == 1 and 25 < cal.tilt_deg[0] < 40
    # a board facing the camera leaves even the one focal length free
    obj, img = _points(K, np.zeros(5), [(np.array([np.pi, 0, 0]), pose[0][1])] * 3, 0.1, 4)
    refused, _ = identifiability_problems(calibrate_camera(obj, img, SIZE, c_rig))
    assert refused and refused[0].startswith("f =")


# ------------------------------------------------------------------- rendered images


def _board_image(px):
    sq = np.indices((ROWS + 1, COLS + 1)).sum(axis=0) % 2
    img = np.kron(sq, np.ones((px, px))) * 255
    return np.pad(img, px, constant_values=255).astype(np.uint8)


def _render(K, R, t, px=24):
    """Perspective image of the chessboard (first inner corner = board origin), pinhole."""
    board = _board_image(px)
    S = np.array([[SQUARE / px, 0, -2 * SQUARE], [0, SQUARE / px, -2 * SQUARE], [0, 0, 1]])
    H = K @ np.c_[R[:, :2], t] @ S
    return cv2.warpPerspective(board, H, SIZE, flags=cv2.INTER_AREA, borderValue=160)


K_R = np.array([[300.0, 0, 159.5], [0, 300.0, 119.5], [0, 0, 1]])
R21 = cv2.Rodrigues(np.array([0.0, 0.3, 0.0]))[0]
T21 = np.array([-0.1, 0.0, 0.015])


def _write_pairs(root, poses, robot_in=()):
    (root / "L").mkdir(parents=True)
    (root / "R").mkdir()
    plates = None
    for k, (r, t) in enumerate(poses):
        Rb = cv2.Rodrigues(r)[0]
        a, b = _render(K_R, Rb, t), _render(K_R, R21 @ Rb, R21 @ t + T21)
        if k in robot_in:  # a dark tube crosses the board in the left view
            plates = (a.copy(), b.copy())
            a = a.copy()
            cv2.line(a, (40, 60), (300, 200), 100, 9)
        cv2.imwrite(str(root / "L" / f"{k:02d}.png"), a)
        cv2.imwrite(str(root / "R" / f"{k:02d}.png"), b)
    return plates


def test_stereo_with_flags_matches_opencv_stereo_calibrate(tmp_path):
    c = IntrinsicConstraints(fix_principal_point=True, fix_aspect_ratio=True, no_distortion=True)
    poses = _poses(5, seed=7, tilt_sd=0.3)
    _write_pairs(tmp_path, poses)
    left = [cv2.imread(str(tmp_path / "L" / f"{k:02d}.png"), 0) for k in range(5)]
    right = [cv2.imread(str(tmp_path / "R" / f"{k:02d}.png"), 0) for k in range(5)]
    res = calibrate_stereo(left, right, "chessboard", COLS, ROWS, SQUARE, c)
    assert res["used"] == list(range(5))
    # OpenCV alone: detections, calibrateCamera with the flags, stereoCalibrate FIX_INTRINSIC
    p1 = [find_pattern(g, "chessboard", COLS, ROWS) for g in left]
    p2 = [find_pattern(g, "chessboard", COLS, ROWS) for g in right]
    obj = [OBJ] * 5
    K0 = initial_camera_matrix(SIZE)
    _, K1, D1, _, _ = cv2.calibrateCamera(obj, p1, SIZE, K0.copy(), None, flags=c.cv_flags())
    _, K2, D2, _, _ = cv2.calibrateCamera(obj, p2, SIZE, K0.copy(), None, flags=c.cv_flags())
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-9)
    _, _, _, _, _, R, T, _, _ = cv2.stereoCalibrate(obj, p1, p2, K1, D1, K2, D2, SIZE,
                                                    flags=cv2.CALIB_FIX_INTRINSIC, criteria=crit)  # fmt: skip
    np.testing.assert_allclose(res["K1"], K1, rtol=1e-6)
    np.testing.assert_allclose(res["K2"], K2, rtol=1e-6)
    np.testing.assert_allclose(res["R"], R, atol=1e-7)
    np.testing.assert_allclose(res["T"], T.ravel(), atol=1e-7)
    # and the truth: f within 5 predicted sigma; the baseline to 1 % (a 1 % focal error
    # scales depth, hence the board poses and |T|, by 1 %; observed ~0.2 %)
    for i in (1, 2):
        cal = res[f"cal{i}"]
        assert abs(cal.K[0, 0] - 300.0) <= 5 * cal.std["f"]
    assert np.linalg.norm(res["T"]) == pytest.approx(np.linalg.norm(T21), rel=0.01)


def test_cli_refuses_one_board_pose_and_accepts_the_constrained_fit(tmp_path, capsys):
    pose = (np.array([np.pi + 0.45, 0.3, 0.05]), np.array([-0.06, 0.04, 0.33]))
    _write_pairs(tmp_path, [pose] * 3)
    out = tmp_path / "s.yaml"
    base = ["calibrate", str(tmp_path / "L"), str(tmp_path / "R"), "-o", str(out),
            "--cols", str(COLS), "--rows", str(ROWS), "--pitch", str(SQUARE)]  # fmt: skip
    assert main(base) == 1 and not out.exists()
    text = capsys.readouterr().out
    assert "the views do not determine the intrinsics being fitted" in text
    assert "1 distinct board orientation" in text and "--fix-principal-point" in text
    flags = ["--fix-principal-point", "--fix-aspect-ratio", "--no-distortion"]
    assert main(base + flags) == 0
    text = capsys.readouterr().out
    assert "pair  rms_1" in text and "tilt" in text
    c1, c2 = load_stereo(out)
    for cam in (c1, c2):
        K = np.asarray(cam.K, np.float64)
        assert K[0, 0] == K[1, 1] and (K[0, 2], K[1, 2]) == (159.5, 119.5)
        assert np.all(np.asarray(cam.dist) == 0)
        # one view, 42 corners at ~0.05 px: the predicted sigma of f is ~0.5-1 %; 3 % is
        # over 3 sigma
        assert K[0, 0] == pytest.approx(300.0, rel=0.03)
    fs = cv2.FileStorage(str(out), cv2.FILE_STORAGE_READ)
    assert (
        fs.getNode("calibrate_flags").string()
        == "fix_principal_point,fix_aspect_ratio,no_distortion"
    )
    assert fs.getNode("per_view_rms_1").mat().shape == (1, 3)
    fs.release()


def test_plate_finds_a_board_the_robot_crosses(tmp_path, capsys):
    poses = _poses(4, seed=11, tilt_sd=0.3)
    plates = _write_pairs(tmp_path, poses, robot_in=(2,))
    left = cv2.imread(str(tmp_path / "L" / "02.png"), 0)
    assert find_pattern(left, "chessboard", COLS, ROWS) is None  # the tube hides the board
    filled = fill_from_plate(left, plates[0])
    np.testing.assert_array_equal(filled, plates[0])  # the tube differs by >= 60 everywhere
    ref = find_pattern(plates[0], "chessboard", COLS, ROWS)
    np.testing.assert_array_equal(find_pattern(filled, "chessboard", COLS, ROWS), ref)
    cv2.imwrite(str(tmp_path / "plate_l.png"), plates[0])
    cv2.imwrite(str(tmp_path / "plate_r.png"), plates[1])
    argv = ["calibrate", str(tmp_path / "L"), str(tmp_path / "R"), "-o", str(tmp_path / "s.yaml"),
            "--cols", str(COLS), "--rows", str(ROWS), "--pitch", str(SQUARE),
            "--fix-principal-point", "--fix-aspect-ratio", "--no-distortion"]  # fmt: skip
    assert main(argv) == 0
    assert "skipped (pattern not found)" in capsys.readouterr().out
    argv += ["--plate-left", str(tmp_path / "plate_l.png"),
             "--plate-right", str(tmp_path / "plate_r.png")]  # fmt: skip
    assert main(argv) == 0
    text = capsys.readouterr().out
    assert "used 4 of 4 pairs" in text and "found after filling from the plate" in text


# ------------------------------------------------------------------- spacing, bad input


def test_acircles_pitch_is_twice_square():
    assert spacing_from_args("acircles", 0.04, None) == 0.02
    assert spacing_from_args("acircles", None, 0.02) == 0.02
    assert spacing_from_args("chessboard", 0.03, None) == 0.03
    # OpenCV's asymmetric grid: neighbours in one row are 2 * square apart, rows square apart
    pts = board_points("acircles", 4, 11, spacing_from_args("acircles", 0.04, None))
    assert np.allclose(np.diff(pts[:4, 0]), 0.04) and np.isclose(pts[4, 1] - pts[0, 1], 0.02)
    for bad in (float("nan"), float("inf"), 0.0, -1.0):
        with pytest.raises(InputError, match="finite number > 0"):
            spacing_from_args("chessboard", bad, None)


@pytest.mark.parametrize(
    "extra, message",
    [(["--max-rms", "nan"], "--max-rms must be a finite number > 0"),
     (["--max-rms", "inf"], "--max-rms must be a finite number > 0"),
     (["--max-std", "0"], "--max-std must be a finite number > 0"),
     (["--pitch", "nan"], "--pitch must be a finite number > 0")],
)  # fmt: skip
def test_refused_arguments_exit_2_one_line(tmp_path, capsys, extra, message):
    _write_pairs(tmp_path, _poses(1, seed=0))
    argv = ["calibrate", str(tmp_path / "L"), str(tmp_path / "R"), "-o", str(tmp_path / "s.yaml"),
            "--cols", str(COLS), "--rows", str(ROWS)]  # fmt: skip
    argv += extra if "--pitch" in extra else ["--pitch", str(SQUARE), *extra]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0], err


def test_same_images_for_both_cameras_are_refused(tmp_path, capsys):
    """Issue 17: the same folder as LEFT and RIGHT wrote a zero-baseline calibration with
    exit 0. The same folder (or glob) is bad input; the same pictures in two folders give a
    zero baseline, which is not written (exit 1)."""
    _write_pairs(tmp_path, _poses(3, seed=0, tilt_sd=0.3))
    out = tmp_path / "s.yaml"
    opts = ["-o", str(out), "--cols", str(COLS), "--rows", str(ROWS), "--pitch", str(SQUARE),
            "--fix-principal-point", "--fix-aspect-ratio", "--no-distortion"]  # fmt: skip
    L = str(tmp_path / "L")
    assert main(["calibrate", L, L, *opts]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "LEFT and RIGHT are the same images" in err[0]
    assert main(["calibrate", L, str(tmp_path / "L" / "*.png"), *opts]) == 2
    capsys.readouterr()
    import shutil

    shutil.copytree(tmp_path / "L", tmp_path / "L2")
    assert main(["calibrate", L, str(tmp_path / "L2"), *opts]) == 1 and not out.exists()
    assert "LEFT and RIGHT look like one camera" in capsys.readouterr().out


def _acircles_image(cols, rows, px):
    """An asymmetric circle grid, OpenCV layout, ``px`` board pixels per half-pitch; circle
    (c, r) at ((2c + r % 2), r) half-pitches from the first circle, 2 half-pitches margin."""
    w, h = (2 * (cols - 1) + 1 + 4) * px, (rows - 1 + 4) * px
    img = np.full((h, w), 255, np.uint8)
    for x, y, _ in board_points("acircles", cols, rows, 1.0):
        centre = (round((x + 2) * px * 16), round((y + 2) * px * 16))  # 4 fractional bits
        cv2.circle(img, centre, round(0.35 * px * 16), 0, -1, lineType=cv2.LINE_AA, shift=4)
    return img


def test_acircles_worked_example_pitch_vs_square(tmp_path, capsys):
    """The --help example at a small scale: circles 16 mm apart along a row (half-pitch 8 mm)
    are --pitch 0.016 or --square 0.008, and both give the true baseline; the row pitch
    passed as --square doubles it."""
    cols, rows, half, px = 4, 11, 0.008, 10
    board = _acircles_image(cols, rows, px)
    S = np.array([[half / px, 0, -2 * half], [0, half / px, -2 * half], [0, 0, 1]])
    (tmp_path / "L").mkdir()
    (tmp_path / "R").mkdir()
    for k, (r, t) in enumerate(_poses(6, seed=3, tilt_sd=0.3)):
        t = t * np.array([0.5, 1.0, 0.75])  # the grid is smaller than the chessboard
        Rb = cv2.Rodrigues(r)[0]
        for side, (R, tt) in (("L", (Rb, t)), ("R", (R21 @ Rb, R21 @ t + T21))):
            H = K_R @ np.c_[R[:, :2], tt] @ S
            img = cv2.warpPerspective(board, H, SIZE, flags=cv2.INTER_AREA, borderValue=160)
            cv2.imwrite(str(tmp_path / side / f"{k:02d}.png"), img)
    base = ["calibrate", str(tmp_path / "L"), str(tmp_path / "R"), "--pattern", "acircles",
            "--cols", str(cols), "--rows", str(rows), "--fix-principal-point",
            "--fix-aspect-ratio", "--no-distortion"]  # fmt: skip
    baselines = {}
    for name, spacing in (("pitch", ["--pitch", "0.016"]), ("square", ["--square", "0.008"]),
                          ("wrong", ["--square", "0.016"])):  # fmt: skip
        out = tmp_path / f"{name}.yaml"
        assert main([*base, "-o", str(out), *spacing]) == 0, capsys.readouterr().out
        c1, c2 = load_stereo(out)
        T = np.asarray(c2.T_cam_robot, np.float64) @ np.linalg.inv(np.asarray(c1.T_cam_robot))
        baselines[name] = np.linalg.norm(T[:3, 3])
    # identical inputs: identical fits (float32 storage of the cameras: 1e-6 relative)
    assert baselines["pitch"] == pytest.approx(baselines["square"], rel=1e-6)
    # the truth to 2 %: f is fitted from ~4 orientations at ~0.1 px (sigma ~0.5 %), and |T|
    # scales with the fitted depths
    assert baselines["pitch"] == pytest.approx(np.linalg.norm(T21), rel=0.02)
    # scaling every board point by 2 scales the whole rig by 2 (same LM path, to 1e-4)
    assert baselines["wrong"] == pytest.approx(2 * baselines["pitch"], rel=1e-4)
