"""``jaxcr stereo --segmentation auto`` (the default, docs/decisions.md S32) and the one-camera
chroma-key check (:mod:`jaxcr.stereo.key_check`, audit r31 S18): the choice, its record, the
``--plate-...`` flags under it, and the WARNING on a real_like frame that the clean chroma
scenes do not get."""

import json

import cv2
import numpy as np
import pytest

from jaxcr.cli import main
from jaxcr.cli.stereo import RUN_FORMAT, segmentation_mode
from jaxcr.io.calibration import save_camera
from jaxcr.stereo.key_check import BORDER_FRACTION_MAX, ROBOT_FRACTION_MAX, key_mask_check


def test_segmentation_mode_choice_and_the_recorded_one(tmp_path):
    out = tmp_path / "o"
    assert segmentation_mode(None, True, out) == ("trace", "auto: background plates given")
    assert segmentation_mode("auto", False, out) == (
        "chroma",
        "auto: no background plates in stereo.json",
    )
    assert segmentation_mode("plate", True, out) == ("plate", "--segmentation plate")
    # an earlier run's run.json (written before `auto`: options only) decides; an explicit
    # mode does not read it; a shard's run.json counts as the job's
    (out / "shards" / "0-of-2").mkdir(parents=True)
    run = {"format": RUN_FORMAT, "dataset": "x", "options": {"segmentation": "chroma"}}
    (out / "shards" / "0-of-2" / "run.json").write_text(json.dumps(run))
    mode, why = segmentation_mode(None, True, out)
    assert mode == "chroma" and why.startswith("auto: recorded by the earlier run in "), why
    assert segmentation_mode("trace", True, out)[0] == "trace"
    (out / "shards" / "0-of-2" / "run.json").write_text("{not json")  # not a stereo run
    assert segmentation_mode(None, True, out)[0] == "trace"


def _border_loop(mask):
    """The reference border: every pixel (r, c) on the first/last row or column, once."""
    h, w = mask.shape
    return [mask[r, c] for r in range(h) for c in range(w) if r in (0, h - 1) or c in (0, w - 1)]


def test_key_mask_check_against_a_loop():
    rng = np.random.default_rng(0)
    for shape, p in (((7, 9), 0.1), ((20, 13), 0.3), ((5, 5), 0.6)):
        mask = rng.random(shape) < p
        robot = mask & (rng.random(shape) < 0.5)
        kc = key_mask_check(mask, robot)
        border = _border_loop(mask)
        assert len(border) == 2 * (shape[0] + shape[1]) - 4
        assert kc.border_fraction == pytest.approx(np.mean(border), abs=5e-5)  # rounded to 1e-4
        assert kc.robot_fraction == pytest.approx(robot.sum() / robot.size, abs=5e-5)
        assert kc.suspect == (
            robot.mean() > ROBOT_FRACTION_MAX or np.mean(border) > BORDER_FRACTION_MAX
        )
    # a thin tube on a key-coloured backdrop: not suspect; the same with a non-key edge: suspect
    tube = np.zeros((100, 200), bool)
    tube[50:52, 20:120] = True  # 200 px = 1 % of the frame, inside
    assert not key_mask_check(tube, tube).suspect
    blob = tube.copy()
    blob[40:60, 20:60] = True  # 1000 px = 5 %
    assert key_mask_check(blob, blob).suspect
    edge = tube.copy()
    edge[:, :40] = True  # non-key left fifth: 40 + 40 + 98 of the 596 border px (30 %)
    assert key_mask_check(edge, tube).suspect


@pytest.fixture(scope="module")
def real_like_one_camera(tmp_path_factory):
    """View 1 of a real_like frame (development seed 4000, 320x240) as a one-camera dataset
    with its background plate, its entry pixel and the rig's calibration."""
    from jaxcr.camera import Camera
    from jaxcr.synth.real_like import render_real_like_frame

    d = tmp_path_factory.mktemp("real_like_one")
    v = render_real_like_frame(4000, (320, 240)).views[0]
    c = v.calib_camera
    cam = Camera(K=c.K, dist=c.dist, T_cam_robot=c.T_cam_robot, width=c.width, height=c.height)
    save_camera(cam, d / "cam.yaml")
    for name, im in (("frame.png", v.image), ("plate.png", v.plate)):
        cv2.imwrite(str(d / name), cv2.cvtColor(im, cv2.COLOR_RGB2BGR))
    meta = {
        "format": "jaxcr.stereo/1",
        "calibration": "cam.yaml",
        "cameras": ["L"],
        "base": {"entry_px": {"L": [float(x) for x in v.entry_px]}},
        "background": {"key": "green"},
        "background_plates": {"L": "plate.png"},
        "frames": [{"id": f, "images": {"L": "frame.png"}} for f in ("a", "b")],
    }
    (d / "stereo.json").write_text(json.dumps(meta))
    return d, v


def test_one_camera_chroma_on_a_real_background_warns_once(real_like_one_camera, tmp_path, capsys):
    """The chroma key on a real_like view, one camera (audit r31 S18: exit 0, tips 337 / 664 px
    off, no word): one WARNING line for the run naming both frames; the default (auto: plates
    given) is trace, accepts a --plate-... flag, and gets no warning."""
    d, v = real_like_one_camera
    out = tmp_path / "chroma"
    code = main(["stereo", str(d), "-o", str(out), "--segmentation", "chroma", "--no-overlays"])
    printed = capsys.readouterr().out.splitlines()
    assert code in (0, 1), printed
    recs = [json.loads(x) for x in (out / "results.jsonl").read_text().splitlines()]
    assert all(r["segmentation"] == "chroma" for r in recs)
    ok = [r for r in recs if r["ok"]]
    assert ok and all(r["key_check"]["suspect"] for r in ok), recs
    warn = [x for x in printed if x.startswith("WARNING")]
    assert len(warn) == 1, printed  # one line per run, not per frame
    assert all(f"{r['id']}" in warn[0] for r in ok) and "--segmentation trace" in warn[0]
    out = tmp_path / "auto"
    code = main(["stereo", str(d), "-o", str(out), "--plate-max-gap", "60", "--no-overlays"])
    printed = capsys.readouterr().out.splitlines()
    assert printed[0] == "segmentation: trace (auto: background plates given)", printed
    assert not [x for x in printed if x.startswith("WARNING")], printed
    run = json.loads((out / "run.json").read_text())
    assert run["options"]["segmentation"] == "trace"
    assert run["options"]["plate"]["max_gap_px"] == 60.0
    recs = [json.loads(x) for x in (out / "results.jsonl").read_text().splitlines()]
    assert all(r["segmentation"] == "trace" and "key_check" not in r for r in recs)
    # S33: one camera, traced: each record's trace_check; the tips nothing checks are said
    # to be unchecked, in one line for the run
    ok = [r for r in recs if r["ok"]]
    assert ok and all(not r["trace_check"]["suspect"] for r in ok), recs
    note = [x for x in printed if x.startswith("NOTE: one camera")]
    assert len(note) == 1 and f"of {len(ok)} frame(s) is unchecked" in note[0], printed


def test_plate_flags_refused_when_auto_chooses_chroma(real_like_one_camera, tmp_path, capsys):
    """Without background plates auto is chroma: a --plate-... flag is the existing one-line
    error (exit 2), which now says why the mode is chroma."""
    d, _ = real_like_one_camera
    meta = json.loads((d / "stereo.json").read_text())
    del meta["background_plates"]
    for name in ("cam.yaml", "frame.png"):
        (tmp_path / name).write_bytes((d / name).read_bytes())
    (tmp_path / "stereo.json").write_text(json.dumps(meta))
    assert main(["stereo", str(tmp_path), "-o", str(tmp_path / "o"), "--plate-dark", "0.3"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--plate-dark needs --segmentation trace" in err[0], err
    assert "auto: no background plates" in err[0], err
    assert not (tmp_path / "o" / "results.jsonl").exists()


def test_trace_check_flags_a_trace_that_stopped_at_the_entry_or_left_the_image():
    """S33 (one camera, traced; real_like seeds 4005: the trace stopped at the entry, and
    4010: it ran out of the image; tips 386 / 392 px off, no word). Closed form: the length
    of a polyline along a 3-4-5 triangle and its end's distance to the border."""
    from jaxcr.stereo.trace_check import STUB_WIDTHS, trace_check

    line = np.array([[100.0, 100.0], [130.0, 140.0], [160.0, 180.0]])  # 100 px
    res = trace_check(line, 15.0, (320, 240))
    assert res.length_px == pytest.approx(100.0, abs=0.05) and res.width_px == 15.0
    assert res.edge_px == pytest.approx(240 - 1 - 180.0, abs=0.05)  # 59 px to the bottom
    assert res.suspect == (100.0 < STUB_WIDTHS * 15.0)  # 60 px: not suspect
    assert trace_check(line, 30.0, (320, 240)).suspect  # 100 px < 4 widths of 30 px
    assert trace_check(line[:1], 15.0, (320, 240)).suspect  # a single point: length 0
    # the same line ending 9 px from the bottom border (under one tube width): suspect
    assert trace_check(line, 15.0, (320, 190)).suspect
    assert trace_check(line + [150.0, 0.0], 15.0, (320, 240)).edge_px == pytest.approx(9.0)
