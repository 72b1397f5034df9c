"""M-L end to end on a tiny synthetic video (128x96, 12 frames): the object gets the highest
probability, per-frame reporting of skipped/corrupt frames, video vs image-folder input, the
baseline, dataset errors and the CLI."""

from __future__ import annotations

import json
import shutil
from dataclasses import astuple

import numpy as np
import pytest

from jaxcr.cli import main as cli
from jaxcr.errors import InputError
from jaxcr.io.motion_dataset import load_motion_dataset
from jaxcr.motion.baseline import fitzpatrick_segment
from jaxcr.motion.flow import FlowConfig
from jaxcr.motion.pipeline import MotionConfig, MotionTracker, frame_update, resolve_steps
from jaxcr.motion.run import end_effector_pixels, run_baseline, run_motion
from jaxcr.synth.motion_scenes import generate_motion_video

# (the default 6 first SLIC iterations: the segment_first program of the translation-only
# runs below and of test_motion_cli_baseline / _batch / _superpixels, one compile in all)
CFG = MotionConfig(superpixel_step=8, flow=FlowConfig(step=4))


@pytest.fixture(scope="module")
def video(tmp_path_factory):
    d = tmp_path_factory.mktemp("mv") / "push"
    generate_motion_video(
        d, "pushed_static", seed=0, size=(128, 96), n_frames=12, video=True, speed_px=10
    )
    return d


@pytest.fixture(scope="module")
def result(video):
    return run_motion(load_motion_dataset(video), CFG)


def test_generated_dataset_is_consistent(video):
    ds = load_motion_dataset(video)
    meta = json.loads((video / "motion.json").read_text())
    assert meta["format"] == "jaxcr.motion/1" and len(ds) == 12
    assert ds.touch.sum() > 0 and not ds.touch[0]
    uv, vis = end_effector_pixels(ds)
    assert vis.all()
    # h(x) = pi(P g(x)) moves about speed_px * 128/320 px per frame
    step = np.linalg.norm(np.diff(uv, axis=0), axis=1)
    assert np.median(step) == pytest.approx(4.0, rel=0.05)
    # ground truth: the target is visible and moves after the touch
    m0, m1 = ds.mask(0), ds.mask(11)
    assert m0.sum() > 50 and m1.sum() > 50 and (m0 != m1).sum() > 20


def test_object_is_most_probable(video, result):
    ds = load_motion_dataset(video)
    gt = ds.mask(result.eval_frame)
    for m in CFG.models:
        pm = result.maps[m]
        assert pm[gt].mean() > pm[~gt].mean() + 0.1, m
    assert all(r.used for r in result.records[1:])
    assert result.warnings == []


def test_video_input_matches_image_folder(video, tmp_path):
    d = tmp_path / "v"
    shutil.copytree(video, d)
    ds_video = load_motion_dataset(d)  # the generator points motion.json at video.avi
    assert ds_video._video is not None
    meta = json.loads((d / "motion.json").read_text())
    meta["source"] = {"images": "frames"}
    (d / "motion.json").write_text(json.dumps(meta))
    ds_img = load_motion_dataset(d)
    fv = [f for _, f, _ in ds_video.frames()]
    fi = [f for _, f, _ in ds_img.frames()]
    assert len(fv) == len(fi) == 12 and all(f is not None and f.shape == (96, 128, 3) for f in fv)
    # MJPG is lossy: same frames up to compression noise
    assert np.mean([np.abs(a - b).mean() for a, b in zip(fv, fi, strict=True)]) < 0.03
    # a subset of frames (what the baseline and the P-R evaluation read) is exactly those
    # frames of the full pass, in increasing order, from either source (same decoder, same bytes)
    for ds, full in ((ds_video, fv), (ds_img, fi)):
        sub = list(ds.frames(indices=[7, 2, 7]))
        assert [i for i, _, _ in sub] == [2, 7]
        for i, rgb, why in sub:
            assert why == "" and np.array_equal(rgb, full[i])
        assert list(ds.frames(indices=[])) == []
        with pytest.raises(ValueError, match="frame index 12"):
            list(ds.frames(indices=[3, 12]))


def test_corrupt_frame_no_touch_and_out_of_view_are_reported(video, tmp_path):
    d = tmp_path / "bad"
    shutil.copytree(video, d)
    (d / "frames" / "000005.png").write_bytes(b"not a png")
    meta = json.loads((d / "motion.json").read_text())
    meta["source"] = {"images": "frames"}
    for fr in meta["frames"]:
        fr["touch"] = False
    meta["frames"][8]["x"][1] += 1.5  # shoulder up 1.5 rad: the tip leaves the view (v < 0)
    (d / "motion.json").write_text(json.dumps(meta))
    res = run_motion(
        load_motion_dataset(d),
        MotionConfig(superpixel_step=8, models=("translation",), flow=FlowConfig(step=4)),
    )
    reasons = {r.index: r.reason for r in res.records}
    assert "unreadable" in reasons[5]
    # the reader's failures are data of the result (the CLI's failed frames), nothing else is
    assert res.failed == {5: reasons[5]}
    assert reasons[8] == "end-effector out of view" and reasons[9] == "end-effector out of view"
    assert reasons[6] == ""  # tracking resumed from frame 4
    assert any("no frame has touch" in w for w in res.warnings)


def test_baseline_masks(video):
    ds = load_motion_dataset(video)
    masks = run_baseline(ds, [5, 20])
    assert set(masks) == {5.0, 20.0}
    assert all(m.shape == (96, 128) and m.dtype == bool for m in masks.values())
    # identical frames: nothing changes, nothing is segmented
    f = np.full((20, 30, 3), 120, np.uint8)
    assert not fitzpatrick_segment(f, f, f, threshold=5).any()


@pytest.mark.parametrize(
    "edit,field",
    [
        (lambda m: m.update(format="other"), "format"),
        (lambda m: m.update(P=[[1, 2, 3]]), "P"),
        (lambda m: m["frames"][2].update(x=[1, 2]), "frames[2].x"),
        (lambda m: m["frames"][1].update(touch="yes"), "touch"),
        (
            lambda m: m.update(arm={"kind": "chain5", "base_height": 0.2, "links": [1, -1, 1]}),
            "arm.links",
        ),
        (lambda m: m.update(source={"video": "missing.avi"}), "source.video"),
        (lambda m: m.update(eval_frame=99), "eval_frame"),
    ],
)
def test_bad_metadata_is_one_line_input_error(video, tmp_path, edit, field):
    d = tmp_path / "m"
    shutil.copytree(video, d)
    meta = json.loads((d / "motion.json").read_text())
    edit(meta)
    (d / "motion.json").write_text(json.dumps(meta))
    with pytest.raises(InputError) as e:
        load_motion_dataset(d)
    assert field in str(e.value) and "\n" not in str(e.value)


def test_cli_outputs_and_exit_codes(video, tmp_path, capsys):
    out = tmp_path / "out"
    code = cli(["motion", str(video), "-o", str(out), "--superpixel-step", "8", "--flow-step", "4"])
    assert code == 0
    for name in (
        "frames.jsonl",
        "report.md",
        "summary.json",
        "prob_translation.png",
        "prob_homography.npy",
        "mask_translation.png",
        "pr_homography.csv",
        "baseline_pr.csv",
    ):
        assert (out / name).exists(), name
    lines = (out / "frames.jsonl").read_text().splitlines()
    assert len(lines) == 12
    s = json.loads((out / "summary.json").read_text())
    assert 0 <= s["models"]["translation"]["tanimoto"] <= 1
    assert cli(["motion", str(tmp_path / "nope"), "-o", str(out)]) == 2
    assert s["settings"]["superpixel_step_px"] == 8 and s["settings"]["flow_step_px"] == 4
    assert cli(["motion", str(video), "-o", str(out), "--lambda", "-1"]) == 2
    assert cli(["motion", str(video), "-o", str(out), "--flow-step", "-1"]) == 2
    assert cli(["motion", str(video), "-o", str(out), "--superpixel-step", "3"]) == 2
    assert cli(["motion", "synth", "-o", str(tmp_path / "s"), "--preset", "nope"]) == 2


def test_defaults_are_the_validated_setting_at_any_width():
    """Superpixel step W / 16 and LK grid W / 80 (window 15, 3 levels): 20 / 4 px on the
    320x240 experiment videos, 40 / 8 px at 640x480 (SLIC on the half-size frame), the flow
    step a multiple of the working scale; explicit values are kept."""
    cfg = MotionConfig()
    assert (cfg.superpixel_step, cfg.flow.step, cfg.flow.window, cfg.flow.levels) == (0, 0, 15, 3)
    assert resolve_steps(cfg, 320) == (20, 1, 4)
    assert resolve_steps(cfg, 640) == (40, 2, 8)
    sp, scale, step = resolve_steps(cfg, 1024)
    assert (sp, scale) == (64, 3) and step % scale == 0 and abs(step - 1024 / 80) <= scale / 2
    assert resolve_steps(MotionConfig(superpixel_step=8, flow=FlowConfig(step=4)), 128) == (8, 1, 4)
    # an explicit flow step that is not a multiple of the working scale: SLIC at full size
    assert resolve_steps(MotionConfig(flow=FlowConfig(step=5)), 640) == (40, 1, 5)
    frame = np.zeros((120, 160, 3), np.float32)
    tr = MotionTracker(MotionConfig(slic_iters_first=1), frame)
    assert (tr.sp_step, tr.scale, tr.flow_cfg.step, tr.n_segments) == (10, 1, 2, 16 * 12)


def test_frame_update_compiles_once_per_shape(video, result):
    """The per-frame jitted call does not retrace from frame to frame: a second run of the
    same configuration adds no compiled entry, and gives the same maps."""
    before = frame_update._cache_size()
    again = run_motion(load_motion_dataset(video), CFG)
    assert frame_update._cache_size() == before
    for m in CFG.models:
        np.testing.assert_array_equal(again.maps[m], result.maps[m])


def _untimed(rec):
    # StepRecord: index, used, reason, touch, flow_ms, segmentation_ms, likelihood_ms, valid
    t = astuple(rec)
    return t[:4] + t[7:]


def test_overlapped_flow_equals_sequential(video, tmp_path):
    """run_motion's default overlaps the next pair's OpenCV flow (a second thread) with the
    JAX steps of the current pair; the sequential path runs the same functions on the same
    inputs, so every output must be bit-identical (tolerance 0), also around unreadable
    frames, where the flow must start from the last readable frame."""
    d = tmp_path / "gaps"
    shutil.copytree(video, d)
    for k in (4, 5):  # the pair after them is (3, 6)
        (d / "frames" / f"{k:06d}.png").write_bytes(b"not a png")
    meta = json.loads((d / "motion.json").read_text())
    meta["source"] = {"images": "frames"}
    (d / "motion.json").write_text(json.dumps(meta))
    ds = load_motion_dataset(d)
    seq = run_motion(ds, CFG, overlap_flow=False)
    seen = []
    par = run_motion(ds, CFG, overlap_flow=True, on_step=lambda r: seen.append(r.index))
    assert seen == list(range(12))  # every frame reported once, in order
    assert seq.failed == par.failed and sorted(par.failed) == [4, 5]
    assert [_untimed(r) for r in seq.records] == [_untimed(r) for r in par.records]
    assert par.records[6].used  # tracking resumed from frame 3
    np.testing.assert_array_equal(seq.labels_eval, par.labels_eval)
    np.testing.assert_array_equal(seq.window_sums, par.window_sums)
    np.testing.assert_array_equal(seq.window_counts, par.window_counts)
    for m in CFG.models:
        np.testing.assert_array_equal(seq.maps[m], par.maps[m])
        np.testing.assert_array_equal(seq.final_maps[m], par.final_maps[m])
    assert all(r.flow_ms > 0 for r in par.records if r.used)  # the flow's own wall time


def test_flow_error_in_the_thread_reaches_the_caller(video, monkeypatch):
    """A failure inside the flow thread is raised by run_motion, not lost with the thread."""
    import jaxcr.motion.run as run_mod

    def broken(*a, **k):
        raise RuntimeError("flow broke")

    monkeypatch.setattr(run_mod, "pair_flow", broken)
    with pytest.raises(RuntimeError, match="flow broke"):
        run_motion(load_motion_dataset(video), CFG, overlap_flow=True)
