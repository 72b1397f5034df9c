"""The examples/ notebooks (Jupytext percent .py files) run top to bottom, and what they show
is checked against independent references."""

import runpy
from pathlib import Path

import cv2
import numpy as np
import pytest

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"


@pytest.fixture
def run_example(tmp_path, monkeypatch):
    def run(name):
        monkeypatch.setenv("JAXCR_EXAMPLES_OUT", str(tmp_path))
        monkeypatch.setenv("MPLBACKEND", "Agg")
        import matplotlib

        matplotlib.use("Agg")
        return runpy.run_path(str(EXAMPLES / name)), tmp_path

    return run


@pytest.mark.slow  # two CTR solver compiles: ~4 min at load 15
def test_kinematics_projection(run_example):
    ns, out = run_example("kinematics_projection.py")
    fk, uv, cam = ns["fk"], np.asarray(ns["uv"]), ns["camera"]
    assert np.asarray(fk.ok).all() and all(r == "" for r in ns["batch"].reasons)
    # jcr.forward == the hand-written jit(vmap(forward)) (same kernels per row; float32
    # rounding of batched vs unbatched reductions: 1e-6 m on a 0.2 m robot)
    np.testing.assert_allclose(ns["batch"].p, np.asarray(fk.centreline.p), atol=1e-6)
    # projection against OpenCV (float64) on the same points: float32 rounding of ~0.7 m
    # camera-frame coordinates (4e-8 m) times fx / Z <= 120 / 0.5 px/m is < 1e-5 px; 1e-3 px
    # leaves room for the float32 camera pose
    p = np.asarray(fk.centreline.p, np.float64).reshape(-1, 3)
    T = np.asarray(cam.T_cam_robot, np.float64)
    ref, _ = cv2.projectPoints(
        p, cv2.Rodrigues(T[:3, :3])[0], T[:3, 3], np.asarray(cam.K, np.float64),
        np.asarray(cam.dist, np.float64),
    )  # fmt: skip
    np.testing.assert_allclose(uv.reshape(-1, 2), ref[:, 0], atol=1e-3)
    # the figure: every centreline inside the 160x120 image, and drawn
    assert np.asarray(ns["valid"]).all()
    assert (uv[..., 0] > 0).all() and (uv[..., 0] < 160).all()
    assert (uv[..., 1] > 0).all() and (uv[..., 1] < 120).all()
    ax = ns["ax"]
    assert len(ax.lines) == 4
    np.testing.assert_allclose(ax.lines[2].get_xydata(), uv[2], atol=1e-6)
    img = cv2.imread(str(out / "kinematics_projection.png"))
    assert img is not None and img.shape[0] > 100 and img.std() > 1.0  # a non-blank figure


# The example's scene (three tubes, kinds=("general",), 320x240) is the one of
# docs/make_example_rig.py: its reconstruction has three segments and 256 chain observations,
# as tests/cli/test_tutorial.py's `jaxcr stereo` run, so the chain fit, the view profiles and
# diameters, the segment fits, the reparametrisation and the thinning are the same programs,
# loaded instead of compiled (tests/conftest.py LONGEST_FIRST runs the tutorial first).
# `jaxcr stereo` calls those stages through jaxcr.io.exported.cached_call (stored traced
# programs, decisions S23), the library's reconstruct calls them directly: the two lowered
# programs differ, so the run's cache served neither from the other (stop 36: five misses
# here, 6.3 s of XLA compilation, with the tutorial in the same process). The notebook runs
# here with the CLI's call (the library's module default `_direct` replaced by
# `cached_call`), so the tutorial's stored programs serve it; what the notebook computes is
# the same function of the same arguments (test_io_exported pins stored == direct), and the
# direct path stays run by tests/stereo (reconstruct_pair without jit_call).
@pytest.fixture
def stereo_through_stored_programs(monkeypatch):
    import jaxcr.stereo.pipeline
    from jaxcr.io.exported import cached_call

    monkeypatch.setattr(jaxcr.stereo.pipeline, "_direct", cached_call)


@pytest.mark.slow  # one stereo synth + reconstruction at 320x240: ~1 min at load 5
def test_stereo(run_example, stereo_through_stored_programs):
    ns, out = run_example("stereo.py")
    rec, truth = ns["rec"], ns["truth"]
    tp, p = np.asarray(truth["p"]), np.asarray(rec.p)
    # distance of every reconstructed point to the dense true backbone (brute force, float64)
    d = np.sqrt(((p[:, None, :] - tp[None, :, :]) ** 2).sum(-1)).min(1)
    rms_mm = 1e3 * np.sqrt(np.mean(d**2))
    # tests/stereo/test_stereo_cli.py bounds the RMS by 0.5 mm at 480x360; at 320x240 (same
    # field of view) a pixel covers 480/320 = 1.5x more, so 0.75 mm. Measured: 0.32 mm on this
    # seed (4); 0.18-0.67 mm over seeds 1-5 of this three-tube general scene, and 2.1 mm on
    # seed 0 (the seed is fixed, so deterministic; the default two-tube scene gave 0.49 mm on
    # seed 4, 0.10-0.77 mm over seeds 0-5)
    assert rms_mm < 0.75
    # coverage of the true length: 0.980 here, 0.967-1.042 over seeds 0-5; the tip (last
    # ~2 mm, a few pixels) is where the skeleton ends early
    assert rec.s[-1] / truth["s"][-1] > 0.95
    assert len(rec.segments) == len(truth["seg_diameter"])
    # the figure shows exactly these arrays
    ax1 = ns["ax1"]
    np.testing.assert_allclose(ax1.lines[1].get_xydata(), 1e3 * p[:, [0, 2]])
    img = cv2.imread(str(out / "stereo.png"))
    assert img is not None and img.std() > 1.0


# The example's synth writes two frames and runs forward_batch on both: TEST_CTR's tubes at 97
# samples for 2 frames, the batched cold solve tests/kinematics/test_ctr.py and tests/synth
# compile (one program in the run instead of a B = 1 copy here); frame 0 is the same frame
# as with frames=1 (IoU 0.704 -> 0.842, 23 steps, as measured before)
@pytest.mark.slow  # synth + one one-level refinement compile at 320x240
def test_refine_frame(run_example):
    ns, out = run_example("refine_frame.py")
    res, truth = ns["result"], np.asarray(ns["truth"], bool)
    assert bool(res.ok) and int(res.failure) == 0

    def iou(a):  # numpy, against the ray-cast truth (an independent renderer)
        a = np.asarray(a, bool)
        return (a & truth).sum() / (a | truth).sum()

    nominal, refined = iou(res.nominal_masks[0]), iou(res.masks[0])
    assert nominal == pytest.approx(ns["iou_nominal"]) and refined == pytest.approx(
        ns["iou_refined"]
    )
    # measured here: 0.704 -> 0.842 (+0.138, one pyramid level, 23 steps; the earlier
    # two-level config gained +0.087; at 160x120 the 2-3 px wide tube gained only +0.009,
    # hence 320x240). Required: under half the measured gain, +0.06: the other half covers
    # a different solver path on another CPU (float32 rounding of the energy changes BFGS
    # steps, not the optimum's basin on this seed); a refinement that does nothing fails
    assert refined > nominal + 0.06
    img = cv2.imread(str(out / "refine_frame.png"))
    assert img is not None and img.std() > 1.0


@pytest.mark.slow  # two 160x120 IREP sets (28 pairs) + contours + training: ~25 s CPU
def test_eigen(run_example):
    ns, out = run_example("eigen.py")
    model, est, truth = ns["model"], np.asarray(ns["estimates"]), ns["psi_test"][ns["ok_test"]]
    assert ns["ok"].all() and ns["ok_test"].all() and est.shape == truth.shape == (4, 2)
    # jcr.eigen.query against a numpy reference of Reiter et al. eqs. 7-8 (brute-force
    # nearest neighbours in float64, inverse-distance weights): the same neighbours, so equal
    # up to float32 rounding of the features (1e-5 rad on values ~1 rad)
    F = np.asarray(model.manifold.features, np.float64)
    P = np.asarray(model.manifold.psi, np.float64)
    x = np.asarray(ns["features"][0], np.float64)
    d = np.linalg.norm(F - x, axis=1)
    nn = np.argsort(d)[: model.config.b]
    w = (1 / d[nn]) / (1 / d[nn]).sum()
    np.testing.assert_allclose(np.asarray(ns["one"]), w @ P[nn], atol=1e-5)
    # the batch estimate (exact pruned k-NN search) agrees with the single query
    np.testing.assert_allclose(est[0], np.asarray(ns["one"]), atol=1e-5)
    # unseen configurations are recovered: measured errors 0.9-4.5 deg (theta_L) and
    # 1.3-6.5 deg (delta) on this seed with 24 training pairs; 15 deg is twice the worst
    # plus margin for a different k-means/float32 path on another CPU, and far below what
    # an uninformed guess gives (uniform over the workspace: ~20 deg theta_L, ~60 deg delta)
    assert np.degrees(np.abs(est - truth)).max() < 15.0
    # the figure shows exactly these arrays
    ax = ns["ax"]
    np.testing.assert_allclose(ax.lines[3].get_xydata(), np.degrees(est[:, ::-1]))
    img = cv2.imread(str(out / "eigen.png"))
    assert img is not None and img.std() > 1.0
