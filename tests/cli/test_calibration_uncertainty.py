"""The calibration's uncertainty from ``jaxcr calibrate`` to ``jaxcr stereo`` (docs/decisions.md
S37, "The calibration's uncertainty from the CLI"): the standard deviations written are
OpenCV's own (``cv2.calibrateCameraExtended`` on the same rendered boards) and, for the rig's
R and T (which OpenCV does not report), the Monte-Carlo scatter of ``cv2.stereoCalibrate``;
the reader's units against closed forms; ``jaxcr stereo`` passes the block or
``--calibration-sigma`` to ``traced_stereo_tips``; bad values exit 2 naming file and field."""

from __future__ import annotations

import json
import shutil

import cv2
import numpy as np
import pytest

from jaxcr.cli import main
from jaxcr.io.calibration import (
    load_stereo,
    load_stereo_uncertainty,
    parse_calibration_sigma,
    read_raw,
)
from jaxcr.stereo.calibration import (
    IntrinsicConstraints,
    initial_camera_matrix,
    stereo_pose_std,
)
from tests.cli.test_calibrate_rig import COLS, OBJ, ROWS, SIZE, SQUARE, _poses, _write_pairs

# ------------------------------------------------------------------- jaxcr calibrate


@pytest.mark.slow  # renders and detects 10 boards, two calibrations (2-3 s)
def test_calibrate_writes_opencvs_standard_deviations(tmp_path):
    """Five rendered 320x240 pairs, fx fy cx cy free, no distortion: the file's
    ``std_intrinsics_1/_2`` are ``cv2.calibrateCameraExtended``'s stdDeviationsIntrinsics on
    OpenCV's own detections with the same flags and start (the same LM on the same points:
    agreement to its convergence, checked at 1e-6 relative); the summary is their closed
    form; read back with cv2.FileStorage itself."""
    _write_pairs(tmp_path, _poses(5, seed=7, tilt_sd=0.3))
    out = tmp_path / "s.yaml"
    args = ["calibrate", str(tmp_path / "L"), str(tmp_path / "R"), "-o", str(out), "--cols",
            str(COLS), "--rows", str(ROWS), "--pitch", str(SQUARE), "--no-distortion"]  # fmt: skip
    assert main(args) == 0
    c = IntrinsicConstraints(no_distortion=True)
    fs = cv2.FileStorage(str(out), cv2.FILE_STORAGE_READ)
    u = fs.getNode("uncertainty")
    written = {k: u.getNode(k).real() for k in ("focal_rel", "principal_px", "rotation_deg",
                                                "translation")}  # fmt: skip
    assert u.getNode("unit").string() == "m"
    arrays = {k: u.getNode(k).mat().ravel() for k in ("std_intrinsics_1", "std_intrinsics_2",
                                                      "std_rotation_deg", "std_translation")}  # fmt: skip
    fs.release()
    stds, Ks = [], []
    for i, side in ((1, "L"), (2, "R")):
        imgs = [cv2.imread(str(tmp_path / side / f"{k:02d}.png"), 0) for k in range(5)]
        pts = []
        for g in imgs:
            ok, corners = cv2.findChessboardCornersSB(g, (COLS, ROWS), flags=cv2.CALIB_CB_ACCURACY)
            assert ok
            pts.append(corners.reshape(-1, 2).astype(np.float32))
        cv = cv2.calibrateCameraExtended([OBJ] * 5, pts, SIZE, initial_camera_matrix(SIZE),
                                         np.zeros(5), flags=c.cv_flags())  # fmt: skip
        ref = np.asarray(cv[5], np.float64).ravel()[:9]
        got = arrays[f"std_intrinsics_{i}"]
        np.testing.assert_allclose(got, ref, rtol=1e-6, atol=1e-12)
        assert np.all(ref[:4] > 0) and np.all(ref[4:] == 0)  # fitted / fixed
        stds.append(ref)
        Ks.append(cv[1])
    focal = max(max(s[0] / K[0, 0], s[1] / K[1, 1]) for s, K in zip(stds, Ks, strict=True))
    assert written["focal_rel"] == pytest.approx(focal, rel=1e-6)
    assert written["principal_px"] == pytest.approx(max(np.max(s[2:4]) for s in stds),
                                                           rel=1e-6)  # fmt: skip
    rot, trans = arrays["std_rotation_deg"], arrays["std_translation"]
    assert written["rotation_deg"] == np.max(rot) > 0
    assert written["translation"] == np.max(trans) > 0
    # the reader: per camera, the rig's pose deviations shared by the two cameras
    unc = load_stereo_uncertainty(out)
    assert unc.focal_rel == pytest.approx(focal, rel=1e-6)
    assert unc.rotation_rad == pytest.approx(np.radians(np.max(rot)) / np.sqrt(2), rel=1e-12)
    assert unc.translation_m == pytest.approx(np.max(trans) / np.sqrt(2), rel=1e-12)
    load_stereo(out)  # the file with its block loads
    # JSON: the same block
    assert main([*args[:4], str(tmp_path / "s.json"), *args[5:]]) == 0
    assert load_stereo_uncertainty(tmp_path / "s.json") == unc


@pytest.mark.slow  # 100 stereo calibrations (~1 s)
def test_rig_pose_std_matches_monte_carlo_scatter():
    """R's and T's predicted 1-sigma (``stereo_pose_std``, the fit's Jacobian) against the
    scatter of ``cv2.stereoCalibrateExtended`` (intrinsics fixed) over 100 noise seeds at
    0.2 px: the sample std of 100 draws has a relative spread of 1/sqrt(198) = 7 %, and the
    prediction is first order (400 seeds: ratios 0.97-1.06); 0.7-1.3 bound it."""
    K = np.array([[300.0, 0, 159.5], [0, 300.0, 119.5], [0, 0, 1]])
    D = np.zeros(5)
    R21 = cv2.Rodrigues(np.array([0.0, 0.3, 0.0]))[0]
    T21 = np.array([-0.1, 0.0, 0.015])
    poses = _poses(5, seed=5, tilt_sd=0.3)
    obj = [OBJ] * len(poses)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-9)
    fits, preds = [], []
    for seed in range(100):
        rng = np.random.default_rng(100 + seed)
        a, b = [], []
        for r, t in poses:
            Rb = cv2.Rodrigues(r)[0]
            for out, (rv, tv) in ((a, (r, t)), (b, (cv2.Rodrigues(R21 @ Rb)[0], R21 @ t + T21))):
                p, _ = cv2.projectPoints(OBJ, rv, tv, K, D)
                noisy = p.reshape(-1, 2) + rng.normal(0, 0.2, (len(OBJ), 2))
                out.append(noisy.astype(np.float32))
        res = cv2.stereoCalibrateExtended(obj, a, b, K, D, K, D, SIZE, None, None,
                                          flags=cv2.CALIB_FIX_INTRINSIC, criteria=crit)  # fmt: skip
        R, T = res[5], res[6]
        sr, st = stereo_pose_std(obj, a, b, K, D, K, D, R, T, res[9], res[10])
        fits.append(np.r_[cv2.Rodrigues(R)[0].ravel(), T.ravel()])
        preds.append(np.r_[sr, st])
    ratio = np.std(fits, axis=0, ddof=1) / np.mean(preds, axis=0)
    assert np.all((ratio > 0.7) & (ratio < 1.3)), ratio


def test_no_block_when_a_deviation_is_not_finite_or_implausible():
    """The writer never writes a block the reader refuses: a focal deviation of 20 % of f
    (--max-std raised), an infinite T deviation (a free direction) give no block."""
    from types import SimpleNamespace

    from jaxcr.io.calibration import uncertainty_block, uncertainty_from_dict

    K = np.array([[300.0, 0, 159.5], [0, 300.0, 119.5], [0, 0, 1]])
    sd = np.array([0.6, 0.6, 0.8, 0.5, 0, 0, 0, 0, 0.0])
    res = {"K1": K, "K2": K, "cal1": SimpleNamespace(std_intrinsics_cv=sd),
           "cal2": SimpleNamespace(std_intrinsics_cv=sd), "std_R_rad": np.full(3, 1e-4),
           "std_T": np.full(3, 2e-4)}  # fmt: skip
    block = uncertainty_block(res)
    assert block["focal_rel"] == 0.002 and block["principal_px"] == 0.8
    assert block["rotation_deg"] == pytest.approx(np.degrees(1e-4), rel=1e-12)
    assert uncertainty_from_dict(block).translation_m == pytest.approx(2e-4 / np.sqrt(2))
    big = sd.copy()
    big[0] = 60.0
    assert uncertainty_block({**res, "cal2": SimpleNamespace(std_intrinsics_cv=big)}) is None
    assert uncertainty_block({**res, "std_T": np.array([2e-4, np.inf, 2e-4])}) is None
    assert uncertainty_block({k: v for k, v in res.items() if k != "std_T"}) is None


# ------------------------------------------------------------------------- the reader


def _stereo_file(tmp_path, name="s.json", unit="m", block=None):
    """A stereo calibration JSON (baseline 0.1 m) in ``unit``, with ``block``."""
    scale = {"m": 1.0, "cm": 100.0, "mm": 1000.0}[unit]
    K = [[300.0, 0.0, 159.5], [0.0, 300.0, 119.5], [0.0, 0.0, 1.0]]
    R = cv2.Rodrigues(np.array([0.0, 0.3, 0.0]))[0].tolist()
    d = {"K1": K, "D1": [0.0] * 5, "K2": K, "D2": [0.0] * 5, "image_width": 320,
         "image_height": 240, "R": R, "T": [-0.1 * scale, 0.0, 0.015 * scale], "unit": unit}  # fmt: skip
    if block is not None:
        d["uncertainty"] = block
    path = tmp_path / name
    path.write_text(json.dumps(d))
    return path


@pytest.mark.parametrize(
    "file_unit, block",
    [
        ("m", {"translation": 3e-4}),
        ("mm", {"translation": 0.3}),
        ("cm", {"translation": 0.03}),
        ("m", {"translation": 0.3, "unit": "mm"}),  # the block's own unit
        ("mm", {"translation": 3e-4, "unit": "m"}),
    ],
)
def test_reader_units_closed_form(tmp_path, file_unit, block):
    """0.3 mm of T's deviation in any unit: 0.3e-3 / sqrt(2) m per camera; 0.05 deg of R's:
    radians(0.05) / sqrt(2) rad; focal_rel and principal_px as written."""
    block = {"focal_rel": 0.002, "principal_px": 1.0, "rotation_deg": 0.05, **block}
    unc = load_stereo_uncertainty(_stereo_file(tmp_path, unit=file_unit, block=block))
    assert unc.translation_m == pytest.approx(3e-4 / np.sqrt(2), rel=1e-12)
    assert unc.rotation_rad == pytest.approx(np.radians(0.05) / np.sqrt(2), rel=1e-12)
    assert (unc.focal_rel, unc.principal_px, unc.tip_px) == (0.002, 1.0, 0.5)
    # the same by hand
    flag = "focal_rel=0.002,principal_px=1,rotation_deg=0.05,translation_mm=0.3"
    hand = parse_calibration_sigma(flag)
    for k in ("focal_rel", "principal_px", "rotation_rad", "translation_m", "tip_px"):
        assert getattr(hand, k) == pytest.approx(getattr(unc, k), rel=1e-12), k
    assert load_stereo_uncertainty(_stereo_file(tmp_path, "none.json")) is None
    assert parse_calibration_sigma("none") is None


GOOD = {"focal_rel": 0.002, "principal_px": 1.0, "rotation_deg": 0.05, "translation": 3e-4}
BAD_BLOCKS = [
    ({**GOOD, "focal": 0.1}, "uncertainty.focal", "did you mean 'focal_rel'?"),
    ({**GOOD, "focal_rel": -0.001}, "uncertainty.focal_rel", "finite standard deviation >= 0"),
    ({**GOOD, "focal_rel": 0.2}, "uncertainty.focal_rel", "0.002 is 0.2 %"),
    ({**GOOD, "translation": 0.3}, "uncertainty.translation", 'set "unit": "mm"'),
    ({**GOOD, "principal_px": "one"}, "uncertainty.principal_px", "expected a number"),
    ({k: v for k, v in GOOD.items() if k != "rotation_deg"}, "uncertainty.rotation_deg",
     "missing required key"),
    ({**GOOD, "std_translation": [1e-4, -1e-4, 0.0]}, "uncertainty.std_translation", ">= 0"),
    ({**GOOD, "unit": "inch"}, "uncertainty.unit", "expected one of"),
]  # fmt: skip


@pytest.fixture(scope="module")
def synth_set(tmp_path_factory):
    """One 320x240 pair (the size of tests/stereo/test_stereo_cli.py's, whose compiled
    programs the run's cache holds)."""
    d = tmp_path_factory.mktemp("unc") / "set"
    assert main(["stereo", "synth", "-o", str(d), "--frames", "1", "--size", "320x240",
                 "--seed", "4"]) == 0  # fmt: skip
    return d


def _with_block(synth_set, tmp_path, block):
    """A copy of the synth set whose calibration (as JSON) carries ``block``."""
    d = tmp_path / "set"
    shutil.copytree(synth_set, d)
    raw = read_raw(d / "calib" / "stereo.yaml")
    raw = {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in raw.items()}
    if block is not None:
        raw["uncertainty"] = block
    (d / "calib" / "stereo.json").write_text(json.dumps(raw))
    meta = json.loads((d / "stereo.json").read_text())
    meta["calibration"] = "calib/stereo.json"
    (d / "stereo.json").write_text(json.dumps(meta))
    return d


@pytest.mark.parametrize("block, field, message", BAD_BLOCKS)
def test_bad_block_exits_2_naming_file_and_field(synth_set, tmp_path, capsys, block, field,
                                                 message):  # fmt: skip
    d = _with_block(synth_set, tmp_path, block)
    assert main(["stereo", str(d), "-o", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert "stereo.json" in err[0] and f"field '{field}'" in err[0] and message in err[0], err


SIGMA = "focal_rel=0.002,principal_px=1,rotation_deg=0.05,translation_mm=0.3"
BAD_FLAGS = [
    (["--calibration-sigma", SIGMA.replace("0.002", "abc")], "--calibration-sigma.focal_rel",
     "expected a number"),
    (["--calibration-sigma", SIGMA.replace("focal_rel", "focal")], "--calibration-sigma.focal",
     "did you mean 'focal_rel'?"),
    (["--calibration-sigma", SIGMA.replace(",translation_mm=0.3", "")],
     "--calibration-sigma.translation_mm", "missing"),
    (["--calibration-sigma", SIGMA.replace("translation_mm=0.3", "translation_m=0.3")],
     "--calibration-sigma.translation_m", 'set "unit": "mm"'),
    (["--calibration-sigma", SIGMA + ",rotation_deg=1"], "--calibration-sigma.rotation_deg",
     "given twice"),
    (["--calibration-sigma", "0.3"], "--calibration-sigma", "expected key=value"),
    (["--calibration-sigma", SIGMA, "--segmentation", "chroma"], "--calibration-sigma",
     "needs --segmentation trace"),
]  # fmt: skip


@pytest.mark.parametrize("flags, field, message", BAD_FLAGS)
def test_bad_flag_exits_2_naming_the_field(synth_set, tmp_path, capsys, flags, field, message):
    assert main(["stereo", str(synth_set), "-o", str(tmp_path / "out"), *flags]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"field '{field}'" in err[0] and message in err[0], err


# ------------------------------------------------------------------ passed through


class _Recorded(Exception):
    pass


@pytest.mark.parametrize(
    "block, flags, expect",
    [
        (None, [], None),  # no block, no flag: the fixed 5 px
        (GOOD, [], "block"),
        (GOOD, ["--calibration-sigma", "none"], None),
        (GOOD, ["--calibration-sigma", SIGMA.replace("0.002", "0.004")], "flag"),
        (None, ["--calibration-sigma", SIGMA], "flag0"),
    ],
)
def test_cli_passes_the_uncertainty_to_traced_stereo_tips(
    synth_set, tmp_path, capsys, monkeypatch, block, flags, expect
):
    """A recording ``traced_stereo_tips`` (it stops the frame once called, so the rest of
    the pipeline is not run): the ``calibration=`` it gets is the file's block, the flag's
    value or None; run.json records it."""
    import jaxcr.stereo.pipeline as pipeline

    seen = []

    def record(cams, traces, *, calibration=None, **kw):
        seen.append(calibration)
        raise pipeline.StereoFailure("correspondence", "recorded")

    monkeypatch.setattr(pipeline, "traced_stereo_tips", record)
    d = _with_block(synth_set, tmp_path, block)
    out = tmp_path / "out"
    assert main(["stereo", str(d), "-o", str(out), "--no-overlays", *flags]) == 1
    printed = capsys.readouterr().out.splitlines()
    assert printed[0].startswith("segmentation: trace") and len(seen) == 1
    run = json.loads((out / "run.json").read_text())["options"]
    if expect is None:
        assert seen[0] is None and "calibration_sigma" not in run
        assert printed[1].startswith("tips' re-search: fixed 5 px")
        return
    want = {
        "block": load_stereo_uncertainty(d / "calib" / "stereo.json"),
        "flag": parse_calibration_sigma(SIGMA.replace("0.002", "0.004")),
        "flag0": parse_calibration_sigma(SIGMA),
    }[expect]
    assert seen[0] == want and want.focal_rel == (0.004 if expect == "flag" else 0.002)
    assert want.translation_m == pytest.approx(3e-4 / np.sqrt(2), rel=1e-12)
    assert run["calibration_sigma"]["focal_rel"] == want.focal_rel
    source = "--calibration-sigma" if expect.startswith("flag") else "uncertainty block"
    assert printed[1].startswith("tips' re-search: 3 sigma") and source in printed[1]
