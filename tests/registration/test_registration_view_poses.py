"""Views left out of the ring get a pose and an error (issue 17 item 10): a view captured
before the loop's closing view is chained from the nearest ring view through the forward
registrations. Checked on a hand-built result against closed forms: exact registrations
reproduce the true poses; one registration rotated by a known angle gives exactly that error
to the views it chains."""

from types import SimpleNamespace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from jaxcr.registration.evaluation import view_errors, view_poses
from jaxcr.registration.pipeline import Capture, ModelResult, RunLog


def _pose(rotvec, t):
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = t
    return T


@pytest.fixture
def scene():
    rng = np.random.default_rng(3)
    n, k0 = 8, 3  # views 0-2 precede the ring (closing view 3)
    truth = [_pose(rng.normal(scale=0.5, size=3), rng.normal(scale=0.3, size=3)) for _ in range(n)]
    caps = [Capture("1", i, None, truth[i], truth[i], None) for i in range(n)]
    pairs = [SimpleNamespace(T=np.linalg.inv(truth[i + 1]) @ truth[i]) for i in range(n - 1)]
    log = RunLog("1", 1, 0.1, captures=caps, pairs=pairs, ring_start=k0)
    ring = [(0, i) for i in range(k0, n)]
    result = ModelResult([log], ring, pairs[k0:], None, 0.0, {}, [])
    anchor = truth[-1]
    ring_poses = [np.linalg.inv(anchor) @ truth[i] for i in range(k0, n)]
    return result, truth, ring_poses, k0


def test_exact_registrations_reproduce_the_truth_outside_the_ring(scene):
    result, truth, ring_poses, k0 = scene
    views = view_poses(result, ring_poses)
    assert [v["ring_position"] for v in views] == [None] * k0 + list(range(len(ring_poses)))
    for i, v in enumerate(views):
        expect = np.linalg.inv(truth[-1]) @ truth[i]
        # a chain of <= 3 float64 4x4 products and one inverse: ~1e-15; 1e-12 leaves margin
        np.testing.assert_allclose(v["T"], expect, atol=1e-12)
        np.testing.assert_allclose(v["T_true"], expect, atol=1e-12)


def test_error_of_a_perturbed_registration_reaches_the_chained_views(scene):
    result, truth, ring_poses, k0 = scene
    theta = np.radians(0.02)  # below arccos' float32 resolution: needs the atan2 form too
    R = Rotation.from_rotvec(theta * np.array([0.0, 0.6, 0.8])).as_matrix()
    D = np.eye(4)
    D[:3, :3] = R
    p = result.runs[0].pairs[k0 - 1]  # T_{k0 <- k0-1}: views 0..k0-1 chain through it
    p.T = p.T @ D
    errs = view_errors(result, ring_poses)
    for v in errs[:k0]:
        # T_O,i = T_O,k0 T_{k0<-k0-1} D T_{k0-1<-i}: R_true^T R_est = R_chain^T R R_chain,
        # a conjugate of R, so the angle is theta exactly
        assert np.radians(v["rot_deg"]) == pytest.approx(theta, rel=1e-9)
    for v in errs[k0:]:
        assert v["rot_deg"] == pytest.approx(0.0, abs=1e-10)
        assert v["trans_m"] == pytest.approx(0.0, abs=1e-12)


def test_poses_files_hold_every_view_as_4x4_matrices(scene, tmp_path):
    import csv
    import json

    from jaxcr.cli.model_object import POSES_FORMAT, write_poses

    result, truth, ring_poses, k0 = scene
    ev = {
        "views": {
            "before": view_errors(result, ring_poses),
            "after": view_errors(result, ring_poses),
        }
    }
    write_poses(tmp_path, None, result, ev)
    doc = json.loads((tmp_path / "poses.json").read_text())
    assert doc["format"] == POSES_FORMAT == "jaxcr.model_poses/1"
    assert doc["anchor"] == {"run": "1", "index": len(truth) - 1}
    np.testing.assert_allclose(doc["T_world_O_true"], truth[-1], atol=1e-9)
    assert len(doc["views"]) == len(truth)
    for i, v in enumerate(doc["views"]):
        expect = np.linalg.inv(truth[-1]) @ truth[i]
        # written rounded to 1e-9
        np.testing.assert_allclose(v["T_O_cam"], expect, atol=2e-9)
        np.testing.assert_allclose(v["T_O_cam_true"], expect, atol=2e-9)
        assert (v["ring_position"] is None) == (i < k0)
    rows = list(csv.DictReader(open(tmp_path / "poses.csv")))
    assert len(rows) == len(truth)
    assert [r["ring_position"] for r in rows[:k0]] == [""] * k0
    assert all(r["trans_after_mm"] != "" for r in rows)  # outside-ring views have errors too
