"""``jaxcr motion`` and the baseline (issue 17 item 9): the baseline's mask is written
(mask_baseline.png, at --baseline-threshold, default the validated 40), the report gives the
baseline at that threshold, at the paper's 5 and at its per-video best, and --help states
the default --model."""

import json

import cv2
import numpy as np
import pytest

from jaxcr.cli import main as cli
from jaxcr.io.motion_dataset import load_motion_dataset
from jaxcr.motion.baseline import fitzpatrick_segment
from jaxcr.motion.run import first_touch, touch_frames_u8
from jaxcr.synth.motion_scenes import generate_motion_video


@pytest.fixture(scope="module")
def video(tmp_path_factory):
    d = tmp_path_factory.mktemp("mvb") / "push"
    # 128x96 with the flags below: the programs test_motion_pipeline compiles (run cache)
    generate_motion_video(d, "pushed_static", seed=0, size=(128, 96), n_frames=12, speed_px=10)
    return d


def _cli_run(video, out, *extra):
    return cli(
        ["motion", str(video), "-o", str(out), "--model", "translation", "--superpixel-step", "8",
         "--flow-step", "4", *extra]
    )  # fmt: skip


def test_baseline_mask_written_and_reported(video, tmp_path):
    out = tmp_path / "out"
    assert _cli_run(video, out) == 0
    png = cv2.imread(str(out / "mask_baseline.png"), cv2.IMREAD_UNCHANGED)
    assert png is not None
    # reference: the baseline called directly on the first touch frames at 40 grey levels
    ds = load_motion_dataset(video)
    ref = fitzpatrick_segment(*touch_frames_u8(ds, first_touch(ds)), threshold=40.0)
    assert ref.any()
    np.testing.assert_array_equal(png > 0, ref)
    s = json.loads((out / "summary.json").read_text())
    b = s["baseline"]
    assert b["threshold"] == 40.0 and b["mask_pixels"] == int(ref.sum())
    assert b["best_tanimoto"] <= min(b["tanimoto"], b["tanimoto_at_5"])
    report = (out / "report.md").read_text()
    assert "diff > 40 + grabCut" in report and "paper's threshold 5" in report
    assert "best threshold for this video" in report


def test_baseline_threshold_option_and_bad_value(video, tmp_path):
    out = tmp_path / "out20"
    assert _cli_run(video, out, "--baseline-threshold", "20") == 0
    ds = load_motion_dataset(video)
    ref = fitzpatrick_segment(*touch_frames_u8(ds, first_touch(ds)), threshold=20.0)
    png = cv2.imread(str(out / "mask_baseline.png"), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(png > 0, ref)
    assert _cli_run(video, tmp_path / "bad", "--baseline-threshold", "300") == 2


def test_help_states_the_default_model(capsys):
    with pytest.raises(SystemExit):
        cli(["motion", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "default: both" in text


def test_missing_truth_mask_is_refused_before_any_frame(video, tmp_path, capsys):
    """Issue 17 (audit r31): a motion.json whose scored frame's ground-truth mask is missing
    ran every frame and then exited 2. It is bad input found first: one line naming the file
    and the field, exit 2, no OUT written (the check precedes claiming OUT)."""
    import shutil

    d = tmp_path / "push"
    shutil.copytree(video, d)
    meta = json.loads((d / "motion.json").read_text())
    ds = load_motion_dataset(d)
    ev = ds.eval_frame if ds.eval_frame is not None else first_touch(ds)
    assert meta["frames"][ev].get("mask"), "the synth video scores a frame with a mask"
    meta["frames"][ev]["mask"] = "masks/renamed.png"
    (d / "motion.json").write_text(json.dumps(meta))
    capsys.readouterr()
    out = tmp_path / "out"
    assert _cli_run(d, out) == 2
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(err) == 1 and "renamed.png" in err[0] and f"frames[{ev}].mask" in err[0], err
    assert not out.exists()
