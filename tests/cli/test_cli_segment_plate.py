"""``jaxcr segment --background plate`` end to end on a tiny dataset (96x72): a grey tube
drawn with ``cv2.polylines`` (independent of jaxcr's code) over a textured red background,
with a background plate of the empty scene shifted by a sub-pixel drift."""

from __future__ import annotations

import json

import cv2
import jax.numpy as jnp
import numpy as np
from scipy import ndimage as ndi

from jaxcr.cli import main
from jaxcr.io.dataset import DatasetWriter
from jaxcr.kinematics.robots import robot_from_dict
from tests.helpers import cli_scene

#: tests/helpers/cli_scene.py's scene and options (one refinement program with test_cli_segment)
FAST = [*cli_scene.FAST, "--quiet"]
W, H, ROBOT, _cam = cli_scene.W, cli_scene.H, cli_scene.ROBOT, cli_scene.camera


def _draw(camera, p):
    K = np.asarray(camera.K, np.float64)
    T = np.asarray(camera.T_cam_robot, np.float64)
    uv, _ = cv2.projectPoints(p, cv2.Rodrigues(T[:3, :3])[0], T[:3, 3], K, np.zeros(5))
    mask = np.zeros((H, W), np.uint8)
    pts = np.round(uv.reshape(-1, 1, 2) * 8).astype(np.int32)
    cv2.polylines(mask, [pts], False, 255, 4, cv2.LINE_8, shift=3)
    return mask > 0, uv.reshape(-1, 2)


def _make(root, with_plate=True):
    rng = np.random.default_rng(1)
    robot = robot_from_dict(ROBOT)
    cam = _cam()
    bg = np.empty((H, W, 3), np.float32)
    bg[...] = [0.55, 0.2, 0.2]
    bg += ndi.gaussian_filter(rng.normal(0, 0.08, (H, W, 3)), (2, 2, 0)).astype(np.float32)
    tips = []
    with DatasetWriter(root, "plate", ROBOT, {"main": cam}) as w:
        for k, q in enumerate([(5.0, 0.0), (-4.0, 0.2)]):
            q_true = np.array(q) + np.array([1.5, 0.05])
            p = np.asarray(robot.forward(jnp.asarray(q_true, jnp.float32)).centreline.p)
            full, uv = _draw(cam, p)
            img = bg.copy()
            img[full] = [0.7, 0.7, 0.72]
            img += 0.01 * rng.standard_normal(img.shape).astype(np.float32)
            w.add_frame(k, q, {"main": np.clip(img, 0, 1)}, masks={"main": full})
            tips.append(uv[-1])
        if with_plate:
            # The plate drifted by (0.4, -0.3) px (camera moved between plate and frames).
            plate = ndi.shift(bg, (-0.3, 0.4, 0), order=1, mode="nearest")
            w.add_background("main", np.clip(plate, 0, 1))
    return root, tips


def test_segment_plate_records_tip(tmp_path):
    root, tips = _make(tmp_path / "ds")
    out = tmp_path / "out"
    assert main(["segment", str(root), "-o", str(out), "--background", "plate", *FAST]) == 0
    recs = [json.loads(x) for x in (out / "results.jsonl").read_text().splitlines()]
    assert len(recs) == 2
    for rec, tip in zip(recs, tips, strict=True):
        fg = rec["foreground"]["main"]
        # The drawn line ends at the projected tip plus up to half its 4-px thickness
        # (polylines' round-ish cap) plus the tracer's 1.5 px sampling error.
        assert np.linalg.norm(np.array(fg["tip_px"]) - tip) <= 2.0 + 1.5
        assert len(fg["backbone_px"]) >= 5
        assert abs(fg["plate_shift_px"][0] + 0.4) < 0.2  # the plate moved by (0.4, -0.3)
    run = json.loads((out / "run.json").read_text())
    assert run["plate"]["max_gap_px"] == 80.0


def test_segment_plate_needs_a_plate(tmp_path, capsys):
    root, _ = _make(tmp_path / "ds", with_plate=False)
    code = main(["segment", str(root), "-o", str(tmp_path / "o"), "--background", "plate"])
    assert code == 2
    err = capsys.readouterr().err
    assert "--background plate needs a background image" in err and "Traceback" not in err


def test_segment_gmm_background_with_shape_buckets(tmp_path):
    """--background gmm fits a per-pixel model of the plate's (real) size: with shape buckets
    (the default; 96x72 pads to 96x80) its mask is computed at the real size and padded, and
    every output keeps 96x72 (decisions S29)."""
    from jaxcr.io import results as R
    from jaxcr.segmentation.buckets import bucket_shape

    assert bucket_shape(H, W) != (H, W)
    root, _ = _make(tmp_path / "ds")
    out = tmp_path / "out"
    assert main(["segment", str(root), "-o", str(out), "--background", "gmm", *FAST]) in (0, 1)
    recs = [json.loads(x) for x in (out / "results.jsonl").read_text().splitlines()]
    assert len(recs) == 2 and any(r["ok"] for r in recs)
    for rec in recs:
        for kind in ("masks", "nominal", "background"):
            if rec["ok"]:
                assert R.read_mask_png(out / rec["files"][kind]["main"]).shape == (H, W)
