"""End-to-end tests of ``jaxcr segment`` and ``jaxcr evaluate`` on a tiny dataset (96x72, one
constant-curvature section, 4 good frames + 2 bad ones), run in-process so the compiled
refinement is shared by every test (one compile: same shapes, config and batch size).

The dataset is drawn independently of jaxcr's silhouette code: the true centreline (nominal q
plus a joint offset, i.e. a model error) is projected with ``cv2.projectPoints`` and drawn as
a thick polyline with ``cv2.polylines``.
"""

from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path

import cv2
import jax.numpy as jnp
import numpy as np
import pytest

from jaxcr.cli import main
from jaxcr.io import results as R
from jaxcr.io.dataset import DatasetWriter
from jaxcr.kinematics.robots import robot_from_dict
from tests.helpers.cli_scene import FAST as SCENE_FAST
from tests.helpers.cli_scene import ROBOT, H, W
from tests.helpers.cli_scene import camera as scene_camera
from tests.helpers.cli_scene import draw as _draw

#: the canonical CLI scene's options (tests/helpers/cli_scene.py: one pyramid level, a program
#: half the size of two levels' to compile): these tests check the command's plumbing
#: (records, files, resume, Ctrl-C, warm start, evaluate), not the refinement's accuracy
#: (tests/segmentation/test_refine*.py); test_cli_segment_plate.py, test_cli_contract.py's
#: Ctrl-C run and tests/scale/test_ray_fault.py run the same options on the same shapes, so
#: the same programs
FAST = [*SCENE_FAST, "--quiet"]


def make_dataset(root: Path) -> Path:
    rng = np.random.default_rng(0)
    robot = robot_from_dict(ROBOT)
    cam = scene_camera()
    qs = [(5.0, 0.0), (-4.0, 0.2), (3.0, -0.3), (-6.0, 0.1), (2.0, 0.0), (4.0, 0.0), (1.0, 0.0)]
    with DatasetWriter(root, "tiny", ROBOT, {"main": cam}) as w:
        for k, q in enumerate(qs):
            q_true = np.array(q) + np.array([1.5, 0.05])
            p = np.asarray(robot.forward(jnp.asarray(q_true, jnp.float32)).centreline.p)
            full = _draw(cam, p, 0.003)
            occ = np.zeros((H, W), bool)
            if k == 1:
                occ[:, 40:52] = True
            visible = full & ~occ
            img = np.empty((H, W, 3), np.float32)
            img[...] = [0.55, 0.2, 0.2]
            img += 0.05 * rng.standard_normal((H, W, 3)).astype(np.float32)
            img[visible] = [0.7, 0.7, 0.72]
            img[occ] = [0.1, 0.5, 0.1]
            if k == 6:  # saturated red everywhere: the colour mask leaves nothing
                img[...] = [0.8, 0.1, 0.1]
            w.add_frame(
                k, q, {"main": np.clip(img, 0, 1)}, masks={"main": visible},
                full_masks={"main": full}, occluders={"main": occ},
                tags=["tiny"], truth={"centreline": p},
            )  # fmt: skip
    # frame 4: NaN joint values; frame 5: image file missing
    path = root / "dataset.json"
    text = path.read_text().replace('"q": [2.0, 0.0]', '"q": [NaN, 0.0]')
    path.write_text(text)
    (root / "images" / "main" / "000005.png").unlink()
    return root


GOOD = ["000000", "000001", "000002", "000003"]
BAD = ["000004", "000005", "000006"]


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    return make_dataset(tmp_path_factory.mktemp("tiny"))


@pytest.fixture(scope="module")
def full_run(dataset, tmp_path_factory):
    out = tmp_path_factory.mktemp("seg") / "out"
    code = main(["segment", str(dataset), "-o", str(out), *FAST])
    return code, out


def _records(out):
    return {r["frame"]: r for r in R.read_results(out / "results.jsonl")}


def test_segment_writes_everything_and_fails_bad_frames(full_run):
    code, out = full_run
    assert code == 1  # three bad frames
    recs = _records(out)
    assert sorted(recs) == sorted(GOOD + BAD)
    for fid in BAD:
        assert recs[fid]["ok"] is False and recs[fid]["reason"]
    assert "NaN" in recs["000004"]["reason"] or "finite" in recs["000004"]["reason"]
    assert "000005.png" in recs["000005"]["reason"]
    assert "background" in recs["000006"]["reason"]
    assert "files" not in recs["000006"]
    for fid in GOOD:
        r = recs[fid]
        assert r["format"] == "jaxcr.segment/2"
        assert r["ok"] is True, r
        # the tip covariance (docs/uncertainty.md): present, self-consistent and positive
        u = r["uncertainty"]
        assert u["model"] == "laplace-gauss-newton/1" and u["depth_factor"] == 3.0
        c = u["cameras"]["main"]
        assert c["sigma_image_mm"] > 0 and c["sigma_image_px"] > 0 and c["noise_std"] > 0
        cov = np.asarray(u["tip_cov_m2"])
        assert cov.shape == (3, 3) and np.allclose(cov, cov.T, atol=1e-12)
        depth = c["sigma_depth_mm"]
        assert u["depth_ambiguous"] == (depth is None or depth > 3.0 * c["sigma_image_mm"])
        assert r["num_steps"] >= 1 and r["time_s"] > 0
        assert set(r["energy"]) >= {"e_in", "e_out", "e_reg", "e_pen", "total"}
        assert np.asarray(r["coeffs"]).shape == (2, 4)
        for kind in ("masks", "nominal", "background", "overlays"):
            f = out / r["files"][kind]["main"]
            assert f.exists()
        m = R.read_mask_png(out / r["files"]["masks"]["main"])
        assert m.shape == (H, W) and m.any()
        ov = cv2.imread(str(out / r["files"]["overlays"]["main"]))
        assert ov.shape == (2 * H, 2 * W, 3)
        cl = np.load(out / r["files"]["centreline"])
        assert cl.shape == (24, 3) and np.all(np.isfinite(cl))
    summary = json.loads((out / "summary.json").read_text())
    assert summary["frames"] == 7 and summary["failed"] == 3
    flagged = sorted(f for f in GOOD if recs[f]["uncertainty"]["depth_ambiguous"])
    assert sorted(summary["depth_ambiguous"]) == flagged
    assert (out / "DONE").exists()
    run = json.loads((out / "run.json").read_text())
    assert run["format"] == "jaxcr.segment-run/1" and run["cameras"] == ["main"]
    from jaxcr.segmentation.refine import RefineConfig

    assert run["config"]["levels"] == list(RefineConfig().levels[-1:])  # --levels 1
    assert "jax" in run["versions"]
    assert not list(out.rglob("*.tmp"))


def _compare_runs(a: Path, b: Path):
    ra, rb = _records(a), _records(b)
    assert sorted(ra) == sorted(rb)
    for fid in ra:
        assert ra[fid]["ok"] == rb[fid]["ok"]
        if ra[fid]["ok"]:
            np.testing.assert_allclose(ra[fid]["coeffs"], rb[fid]["coeffs"], atol=1e-5)
            for kind in ("masks", "nominal"):
                ma = R.read_mask_png(a / ra[fid]["files"][kind]["main"])
                mb = R.read_mask_png(b / rb[fid]["files"][kind]["main"])
                assert (ma != mb).sum() <= 2  # float32 reassociation at the boundary


def test_limit_then_resume_equals_uninterrupted(full_run, dataset, tmp_path):
    _, ref = full_run
    out = tmp_path / "out"
    code = main(["segment", str(dataset), "-o", str(out), *FAST, "--limit", "3"])
    assert code == 1  # a bad frame is among the first three
    assert len(_records(out)) == 3 and not (out / "DONE").exists()
    assert not (out / "summary.json").exists()
    # without --resume an existing run is refused
    assert main(["segment", str(dataset), "-o", str(out), *FAST]) == 2
    code = main(["segment", str(dataset), "-o", str(out), *FAST, "--resume"])
    assert code == 1 and (out / "DONE").exists()
    _compare_runs(ref, out)
    lines = (out / "results.jsonl").read_text().splitlines()
    assert len(lines) == 7  # no frame processed twice


def test_kill_mid_run_then_resume(full_run, dataset, tmp_path, monkeypatch):
    """Interrupt (KeyboardInterrupt) while writing the 2nd good frame's files: its record must
    not exist, the earlier ones must; --resume completes to the uninterrupted result."""
    _, ref = full_run
    out = tmp_path / "out"
    calls = {"n": 0}
    real = R.atomic_write_npy

    def flaky(path, array):
        if "centrelines_nominal" in str(path):
            calls["n"] += 1
            if calls["n"] == 2:
                raise KeyboardInterrupt
        return real(path, array)

    monkeypatch.setattr(R, "atomic_write_npy", flaky)
    assert main(["segment", str(dataset), "-o", str(out), *FAST]) == 130
    monkeypatch.setattr(R, "atomic_write_npy", real)
    recs = _records(out)
    assert set(recs) == {BAD[0], BAD[1], GOOD[0]}  # bad frames are recorded first
    assert not (out / "DONE").exists()
    assert main(["segment", str(dataset), "-o", str(out), *FAST, "--resume"]) == 1
    _compare_runs(ref, out)


def test_overwrite_and_bad_inputs(dataset, tmp_path, capsys):
    assert main(["segment", str(tmp_path / "nope"), "-o", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "nope" in err[0] and "not found" in err[0]
    assert main(["segment", str(dataset), "-o", str(tmp_path / "o"), "--camera", "left"]) == 2
    assert "no camera 'left'" in capsys.readouterr().err
    assert main(["evaluate", str(tmp_path / "nothing")]) == 2


def test_resume_refuses_changed_config(full_run, dataset, tmp_path):
    _, ref = full_run
    out = tmp_path / "out"
    shutil.copytree(ref, out)
    (out / "DONE").unlink()
    args = ["segment", str(dataset), "-o", str(out), "--resume", "--basis", "3", "--quiet"]
    assert main(args) == 2


def test_roi_choice_recorded_and_kept_by_a_resume(full_run, dataset, tmp_path):
    """--roi is part of the job (run.json "roi"): a resume keeps the recorded choice and
    refuses another one; a run.json written before the option (no "roi") resumes as "off"
    (the behaviour it was written with). Every frame is recorded: no refinement runs."""
    _, ref = full_run
    assert json.loads((ref / "run.json").read_text())["roi"] == "auto"
    _check_resume_keeps_choice(ref, dataset, tmp_path, "roi", "auto")


def test_shape_buckets_recorded_kept_by_a_resume_and_outputs_at_the_real_size(
    full_run, dataset, tmp_path
):
    """--shape-buckets (decisions S29) is part of the job (run.json "shape_buckets", default
    "on"): a resume keeps it and refuses another choice; a run.json written before the option
    resumes as "off". The default run padded the 96x72 frames to the 96x80 bucket: its masks,
    overlays and pixel coordinates keep 96x72 (asserted in the test above; here the
    background PNG and the record's pixel fields). No refinement runs."""
    from jaxcr.segmentation.buckets import bucket_shape

    _, ref = full_run
    assert bucket_shape(H, W) != (H, W)  # the default run was padded
    assert json.loads((ref / "run.json").read_text())["shape_buckets"] == "on"
    for fid in GOOD:
        r = _records(ref)[fid]
        assert R.read_mask_png(ref / r["files"]["background"]["main"]).shape == (H, W)
        assert R.read_mask_png(ref / r["files"]["nominal"]["main"]).shape == (H, W)
    _check_resume_keeps_choice(ref, dataset, tmp_path, "shape_buckets", "on")


@pytest.mark.slow
def test_shape_buckets_off_gives_the_same_answer(full_run, dataset, tmp_path):
    """The same run with --shape-buckets off (the unpadded program): the same frames ok and
    the same tube. Tolerance as tests/segmentation/test_shape_buckets.py's end-to-end test
    (the energies agree to float rounding; the solves amplify it): IoU between the two
    runs' masks >= 0.97, tips within 0.5 mm (a third of the tube's radius here).
    ``--no-uncertainty``: nothing here reads the covariance, which is computed after the
    refinement from its answer (its padded-vs-unpadded equality is
    tests/segmentation/test_shape_buckets.py's), so the unpadded covariance program is not
    compiled for this run (only this test runs `jaxcr segment` unpadded)."""
    _, ref = full_run
    out = tmp_path / "off"
    off = ["--shape-buckets", "off", "--no-uncertainty", *FAST]
    assert main(["segment", str(dataset), "-o", str(out), *off]) == 1
    a, b = _records(ref), _records(out)
    for fid in GOOD:
        assert b[fid]["ok"]
        ma = R.read_mask_png(ref / a[fid]["files"]["masks"]["main"])
        mb = R.read_mask_png(out / b[fid]["files"]["masks"]["main"])
        assert _iou(ma, mb) >= 0.97
        ca = np.load(ref / a[fid]["files"]["centreline"])
        cb = np.load(out / b[fid]["files"]["centreline"])
        assert np.linalg.norm(ca[-1] - cb[-1]) < 5e-4


def _check_resume_keeps_choice(ref, dataset, tmp_path, key, default):
    """A resume of ``ref`` (run with the default ``default`` of option ``--KEY``, recorded as
    run.json ``key``) keeps the recorded choice and refuses ``off``; a run.json written
    before the option (no ``key``) resumes as ``off``, refusing ``default``. Every frame is
    recorded, so no refinement runs; the bad frames make each accepted resume exit 1."""
    flag = "--" + key.replace("_", "-")
    base = ["segment", str(dataset), "-o"]
    out = tmp_path / "new"
    shutil.copytree(ref, out)
    (out / "DONE").unlink()
    assert main([*base, str(out), "--resume", flag, "off", *FAST]) == 2
    assert main([*base, str(out), "--resume", *FAST]) == 1  # the bad frames, as ref
    old = tmp_path / "old"
    shutil.copytree(ref, old)
    (old / "DONE").unlink()
    info = json.loads((old / "run.json").read_text())
    del info[key]
    (old / "run.json").write_text(json.dumps(info))
    assert main([*base, str(old), "--resume", flag, default, *FAST]) == 2
    assert main([*base, str(old), "--resume", *FAST]) == 1
    assert main([*base, str(old), "--resume", flag, "off", *FAST]) == 1
    assert key not in json.loads((old / "run.json").read_text())


def _iou(a, b):
    u = np.logical_or(a, b).sum()
    return np.logical_and(a, b).sum() / u if u else 1.0


def test_evaluate_matches_numpy(full_run, dataset, tmp_path, capsys):
    _, out = full_run
    rep = tmp_path / "rep"
    assert main(["evaluate", str(out), "-o", str(rep)]) == 1  # the run has 3 failed frames
    assert "Optimised projection" in capsys.readouterr().out
    for f in ("table2.md", "table2.csv", "per_frame.csv", "iou.png"):
        assert (rep / f).exists()
    recs = _records(out)
    want = {k: [] for k in ("iou_background", "iou_nominal", "iou_refined", "adj_iou_refined",
                            "tip_refined_mm")}  # fmt: skip
    for fid in GOOD:
        r = recs[fid]
        truth = cv2.imread(str(dataset / "masks" / "main" / f"{fid}.png"), 0) > 127
        occ = cv2.imread(str(dataset / "occluders" / "main" / f"{fid}.png"), 0) > 127
        ref = cv2.imread(str(out / r["files"]["masks"]["main"]), 0) > 127
        nom = cv2.imread(str(out / r["files"]["nominal"]["main"]), 0) > 127
        fg = cv2.imread(str(out / r["files"]["background"]["main"]), 0) > 127
        want["iou_background"].append(_iou(fg, truth))
        want["iou_nominal"].append(_iou(nom, truth))
        want["iou_refined"].append(_iou(ref, truth))
        want["adj_iou_refined"].append(_iou(ref & ~occ, truth))
        p = np.load(out / r["files"]["centreline"])
        t = np.load(dataset / "truth" / f"{fid}.npy")
        want["tip_refined_mm"].append(1e3 * np.linalg.norm(p[-1] - t[-1]))
    rows = {(r["column"], r["metric"]): r for r in csv.DictReader(open(rep / "table2.csv"))}
    for k, v in want.items():
        got = rows[("tiny", k)]
        assert float(got["mean"]) == pytest.approx(np.mean(v), abs=1e-5), k
        assert float(got["std"]) == pytest.approx(np.std(v), abs=1e-5), k
        assert int(got["n"]) == 4
    assert rows[("tiny", "failed")]["mean"] == "3"
    md = (rep / "table2.md").read_text()
    m, s = np.mean(want["iou_refined"]), np.std(want["iou_refined"])
    assert f"{m:.3f} ± {s:.3f} \\| " in md


def test_evaluate_several_runs_one_column_each(full_run, tmp_path):
    _, out = full_run
    other = tmp_path / "again"
    shutil.copytree(out, other)
    rep = tmp_path / "rep"
    assert main(["evaluate", str(out), str(other), "-o", str(rep), "--no-plot"]) == 1
    rows = list(csv.DictReader(open(rep / "table2.csv")))
    cols = list(dict.fromkeys(r["column"] for r in rows))
    assert cols == ["tiny", "tiny (again)", "all"]
    get = {(r["column"], r["metric"]): r for r in rows}
    assert get[("tiny", "iou_refined")]["mean"] == get[("tiny (again)", "iou_refined")]["mean"]
    assert int(get[("all", "iou_refined")]["n"]) == 8
    assert not (rep / "iou.png").exists()


def test_warm_start_carries_coefficients_and_camera_correction(dataset, tmp_path, monkeypatch):
    """--warm-start: each chunk's refine_sequence starts from the previous chunk's last good
    frame, both its delta-u coefficients and its camera-pose correction (physical units)."""
    import jaxcr.segmentation.refine as refine_mod
    from jaxcr.io import exported

    calls = []
    real = refine_mod.refine_sequence

    def spy(*args, **kw):
        res = real(*args, **kw)
        if not exported.in_compile_ahead():  # not the first chunk's dry run (zeros)
            calls.append((kw.get("init"), kw.get("init_cam"), res, kw.get("roi")))
        return res

    monkeypatch.setattr(refine_mod, "refine_sequence", spy)
    out = tmp_path / "warm"
    code = main(["segment", str(dataset), "-o", str(out), "--warm-start", *FAST])
    assert code == 1  # the three bad frames
    recs = _records(out)
    assert all(recs[f]["ok"] for f in GOOD)
    assert len(calls) >= 2
    assert calls[0][0] is None and calls[0][1] is None
    # --roi auto (the default) at 96x72: no region (below ROI_AUTO_MIN_PIXELS), recorded
    assert json.loads((out / "run.json").read_text())["roi"] == "auto"
    assert all(c[3] is None for c in calls)
    first = calls[0][2]
    last_ok = max(i for i in range(len(first.ok)) if bool(first.ok[i]))
    np.testing.assert_array_equal(np.asarray(calls[1][0]), np.asarray(first.coeffs[last_ok]))
    np.testing.assert_array_equal(
        np.asarray(calls[1][1]), np.asarray(first.camera_correction[last_ok])
    )


def test_robot_never_placed_is_refused_before_compiling(tmp_path, capsys):
    """A camera whose T_cam_robot has no translation puts the robot's base at its optical
    centre (audit r31: a lab dataset before jaxcr fit --fit-pose failed its frame after a
    minute with "no data (every pixel is background)"): exit 2, one line naming the field."""
    from tests.helpers.datasets import edit_json
    from tests.helpers.datasets import make_dataset as tiny_dataset

    root = tiny_dataset(tmp_path / "d", n_frames=1)
    edit_json(root, lambda j: j["cameras"]["main"].update(T_cam_robot=np.eye(4).tolist()))
    assert main(["segment", str(root), "-o", str(tmp_path / "o"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "cameras.main.T_cam_robot" in err[0] and "--fit-pose" in err[0]
