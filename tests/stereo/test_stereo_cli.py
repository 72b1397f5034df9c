"""End to end: ``jaxcr stereo synth``, ``jaxcr stereo DATASET -o OUT`` (outputs, accuracy
against the truth, per-frame failures that do not stop the batch, resume, bad input) and
``jaxcr calibrate`` on rendered chessboard pairs."""

import json
import shutil

import cv2
import numpy as np
import pytest

from jaxcr.cli import main
from jaxcr.io.calibration import load_stereo
from jaxcr.stereo.evaluate import evaluate_frame


@pytest.fixture(scope="module")
def synth_set(tmp_path_factory):
    """One pair at 320x240, seed 4: the pair of examples/stereo.py (tests/core/test_examples.py)
    and the size of test_ray_equality.py's and the tutorial's stereo runs, so the stereo
    programs compiled there are loaded from the run's compilation cache (480x360 before)."""
    d = tmp_path_factory.mktemp("stereo") / "set"
    code = main(
        ["stereo", "synth", "-o", str(d), "--frames", "1", "--size", "320x240", "--seed", "4"]
    )
    assert code == 0
    return d


@pytest.mark.parametrize(
    "flags, mode, why",
    [
        (["--segmentation", "chroma"], "chroma", "--segmentation chroma"),
        # the default (docs/decisions.md S32): the synth set gives background plates
        ([], "trace", "auto: background plates given"),
    ],
)
def test_stereo_cli_outputs_and_accuracy(synth_set, tmp_path, capsys, flags, mode, why):
    out = tmp_path / "out"
    assert main(["stereo", str(synth_set), "-o", str(out), *flags]) == 0
    printed = capsys.readouterr().out.splitlines()
    assert printed[0] == f"segmentation: {mode} ({why})", printed  # the first line
    assert not [x for x in printed if x.startswith("WARNING")], printed  # two views: no key check
    run = json.loads((out / "run.json").read_text())
    assert run["options"]["segmentation"] == mode and run["segmentation_choice"] == why
    rec = [json.loads(x) for x in (out / "results.jsonl").read_text().splitlines()]
    assert len(rec) == 1 and rec[0]["ok"] and rec[0]["segmentation"] == mode
    assert "key_check" not in rec[0]  # two views check each other (tip_epipolar_px)
    assert rec[0]["camera_order_suspect"] is False  # the right order (markers) is not flagged
    fj = json.loads((out / "frames" / "000.json").read_text())
    assert fj["format"] == "jaxcr.stereo-frame/2" and len(fj["segments"]) >= 1
    npz = np.load(out / "frames" / "000.npz")
    assert npz["p"].shape[1] == 3
    for cam in ("cam1", "cam2"):
        assert cv2.imread(str(out / "overlays" / f"000_{cam}.png")) is not None
    assert (out / "segments.csv").read_text().startswith("frame,segment,")
    assert (out / "segments.md").read_text().startswith("| frame |")
    truth = dict(np.load(synth_set / "truth" / "000.npz"))
    res = {
        "p": npz["p"],
        "s": npz["s"],
        "segments": fj["segments"],
        "boundary_p": npz["boundary_p"],
    }
    ev = evaluate_frame(res, truth)
    # the bound was 0.5 mm at 480x360; at 320x240 (same field of view) a pixel covers
    # 480/320 = 1.5x more, so 0.75 mm, as tests/core/test_examples.py::test_stereo derives
    # for this very pair (measured there: 0.49 mm; coverage 0.974, 0.975-0.995 over seeds 0-5;
    # the trace default on this pair: 0.33 mm, coverage 0.971)
    assert ev["backbone_rms_mm"] < 0.75
    assert ev["coverage"] > 0.95
    if mode != "chroma":
        return
    # An earlier run written before `auto` (no segmentation_choice in run.json, no
    # segmentation in its records, chroma by the old default) continues with its recorded
    # mode when rerun without the flag: nothing redone, not refused for other options.
    del run["segmentation_choice"]
    (out / "run.json").write_text(json.dumps(run))
    lines = (out / "results.jsonl").read_text().splitlines()
    old = [json.loads(x) for x in lines]
    for r in old:
        del r["segmentation"]
    (out / "results.jsonl").write_text("".join(json.dumps(r) + "\n" for r in old))
    assert main(["stereo", str(synth_set), "-o", str(out)]) == 0
    printed = capsys.readouterr().out.splitlines()
    assert (
        printed[0]
        == f"segmentation: chroma (auto: recorded by the earlier run in {out / 'run.json'})"
    )
    assert len((out / "results.jsonl").read_text().splitlines()) == len(lines)
    # --segmentation auto given explicitly is the default: the same choice
    assert main(["stereo", str(synth_set), "-o", str(out), "--segmentation", "auto"]) == 0
    assert capsys.readouterr().out.startswith("segmentation: chroma (auto: recorded")
    # an explicit other mode is a different run: refused, one line
    assert main(["stereo", str(synth_set), "-o", str(out), "--segmentation", "trace"]) == 2
    assert "different options" in capsys.readouterr().err


def test_per_frame_failures_and_resume(synth_set, tmp_path):
    d = tmp_path / "bad"
    shutil.copytree(synth_set, d)
    meta = json.loads((d / "stereo.json").read_text())
    good = meta["frames"][0]
    img1 = cv2.imread(str(d / good["images"]["cam1"]))
    img2 = cv2.imread(str(d / good["images"]["cam2"]))
    (d / "bad").mkdir()
    # Markers unreadable in both views.
    cv2.imwrite(str(d / "bad" / "blur1.png"), cv2.GaussianBlur(img1, (0, 0), 6))
    cv2.imwrite(str(d / "bad" / "blur2.png"), cv2.GaussianBlur(img2, (0, 0), 6))
    # Calibration does not match the image size.
    cv2.imwrite(str(d / "bad" / "small1.png"), cv2.resize(img1, (400, 300)))
    # Empty scene: no robot.
    frames = [
        good,
        {"id": "nomarkers", "images": {"cam1": "bad/blur1.png", "cam2": "bad/blur2.png"}},
        {"id": "size", "images": {"cam1": "bad/small1.png", "cam2": good["images"]["cam2"]}},
        {"id": "norobot", "images": {"cam1": "background/cam1.png", "cam2": "background/cam2.png"}},
        {"id": "missing", "images": {"cam1": "bad/none.png", "cam2": "bad/none.png"}},
    ]
    meta["frames"] = frames
    (d / "stereo.json").write_text(json.dumps(meta))
    out = tmp_path / "out"
    assert main(["stereo", str(d), "-o", str(out), "--no-overlays"]) == 1
    recs = {r["id"]: r for r in map(json.loads, (out / "results.jsonl").read_text().splitlines())}
    assert recs["000"]["ok"]
    assert recs["nomarkers"]["reason"] == "markers"
    assert '"base": {"entry_px"' in recs["nomarkers"]["message"]  # the marker-free way out
    assert recs["size"]["reason"] == "calibration_size"
    assert recs["norobot"]["reason"] == "robot_not_found"
    assert recs["missing"]["reason"] == "image"
    # Resume: nothing is redone.
    n = len((out / "results.jsonl").read_text().splitlines())
    assert main(["stereo", str(d), "-o", str(out), "--no-overlays"]) == 1
    assert len((out / "results.jsonl").read_text().splitlines()) == n


def test_shards_together_equal_one_run(synth_set, tmp_path):
    """--shard 0/2 and 1/2 into one OUT: every frame recorded once across the shards, each
    record the unsharded run's (timings apart), frame files in OUT; the reference is the
    unsharded run of the same dataset."""
    d = tmp_path / "set"
    shutil.copytree(synth_set, d)
    meta = json.loads((d / "stereo.json").read_text())
    good = meta["frames"][0]
    meta["frames"] = [good] + [
        {"id": f"miss{k}", "images": {"cam1": "none.png", "cam2": "none.png"}} for k in range(3)
    ]
    (d / "stereo.json").write_text(json.dumps(meta))
    ref, out = tmp_path / "ref", tmp_path / "out"
    assert main(["stereo", str(d), "-o", str(ref), "--no-overlays"]) == 1
    assert main(["stereo", str(d), "-o", str(out), "--no-overlays", "--shard", "1/2"]) == 1
    assert main(["stereo", str(d), "-o", str(out), "--no-overlays", "--shard", "0/2"]) == 1

    def recs(path):
        out = {}
        for line in path.read_text().splitlines():
            r = json.loads(line)
            r.pop("timings", None)
            out[r["id"]] = r
        return out

    a = recs(out / "shards" / "0-of-2" / "results.jsonl")
    b = recs(out / "shards" / "1-of-2" / "results.jsonl")
    assert sorted(a) == ["000", "miss0"] and sorted(b) == ["miss1", "miss2"]  # contiguous
    assert {**a, **b} == recs(ref / "results.jsonl")
    assert (out / "frames" / "000.json").read_bytes() == (ref / "frames" / "000.json").read_bytes()
    # another option set into the same job is refused
    assert main(["stereo", str(d), "-o", str(out), "--segments", "2", "--shard", "0/2"]) == 2


def test_summary_warns_when_the_two_tips_disagree():
    """A frame reconstructed with tips far from each other's epipolar lines (audit r31: the
    chroma key on a real_like frame, ok with one view's tip 664 px off and
    tip_epipolar_px 394) gets a WARNING line naming it; a consistent one does not."""
    from jaxcr.cli.stereo import TIP_EPIPOLAR_WARN_PX, summary_lines

    recs = [
        {"id": "a", "ok": True, "tip_epipolar_px": 394.4},
        {"id": "b", "ok": True, "tip_epipolar_px": TIP_EPIPOLAR_WARN_PX - 0.5},
        {"id": "c", "ok": True, "views": {}},  # one camera: no epipolar check
        {"id": "d", "ok": False, "reason": "correspondence", "message": "correspondence: x"},
    ]
    lines = summary_lines(recs, "OUT")
    assert lines[0].startswith("3/4 frames reconstructed")
    warn = [x for x in lines if x.startswith("WARNING")]
    assert len(warn) == 1 and "frame a:" in warn[0] and "394 px" in warn[0], lines
    assert "try --segmentation trace" in warn[0]  # a record without the field: the hint
    # a traced frame is not told to try trace (S32: real_like seed 4005, a trace that
    # followed the occluding cable, was told so)
    traced = summary_lines([{**recs[0], "segmentation": "trace"}], "OUT")
    assert "--segmentation trace" not in traced[1] and "crossing" in traced[1], traced
    chroma = summary_lines([{**recs[0], "segmentation": "chroma"}], "OUT")
    assert "try --segmentation trace" in chroma[1], chroma
    assert any("frame d" in x and "correspondence" in x for x in lines), lines
    # a frame whose backbones the exchanged camera order explains (audit r31 S19)
    recs[1].update(camera_order_suspect=True, camera_order_px=[306.0, 0.0, 1159.1])
    warn = [x for x in summary_lines(recs, "OUT") if x.startswith("WARNING")]
    assert len(warn) == 2 and "frame b:" in warn[1] and "swapped" in warn[1], warn
    assert '"cameras"' in warn[1] and "306 of" in warn[1], warn


def test_summary_one_camera_traced_frames():
    """S33: one camera, traced: a trace that stopped at the entry is named in one WARNING
    line; the other traced frames are counted in one NOTE line (their tips are unchecked)."""
    from jaxcr.cli.stereo import summary_lines

    tc = {"length_px": 480.0, "width_px": 15.0, "edge_px": 150.0, "suspect": False}
    recs = [{"id": f"f{k}", "ok": True, "views": {"L": {}}, "segmentation": "trace",
             "trace_check": dict(tc)} for k in range(3)]  # fmt: skip
    recs[1]["trace_check"].update(length_px=2.2, suspect=True)
    lines = summary_lines(recs, "OUT")
    warn = [x for x in lines if x.startswith("WARNING")]
    assert len(warn) == 1 and "(f1)" in warn[0] and "stopped" in warn[0], lines
    note = [x for x in lines if x.startswith("NOTE")]
    assert len(note) == 1 and "of 2 frame(s) is unchecked" in note[0], lines
    # two cameras or the chroma key (no trace_check): no such lines
    assert len(summary_lines([{"id": "a", "ok": True, "views": {}}], "OUT")) == 1


def test_bad_input_exit_2(tmp_path, capsys):
    assert main(["stereo", str(tmp_path), "-o", str(tmp_path / "o")]) == 2
    (tmp_path / "stereo.json").write_text('{"format": "other"}')
    assert main(["stereo", str(tmp_path), "-o", str(tmp_path / "o")]) == 2
    assert "format" in capsys.readouterr().err


# ----------------------------------------------------------------------------- calibrate


def _board_image(cols, rows, px):
    sq = np.indices((rows + 1, cols + 1)).sum(axis=0) % 2
    img = np.kron(sq, np.ones((px, px))) * 255
    return np.pad(img, px, constant_values=255).astype(np.uint8)


def _render_board(K, R, t, cols, rows, square, size, px=40):
    """Perspective image of a chessboard (inner corners cols x rows, spacing square) whose
    first inner corner is the board origin; homography from board pixels to the image."""
    board = _board_image(cols, rows, px)
    # Board pixel (x, y) -> board metres: first inner corner at pixel (2 px, 2 px) (pad + 1 sq)
    S = np.array([[square / px, 0, -2 * square], [0, square / px, -2 * square], [0, 0, 1]])
    H = K @ np.c_[R[:, :2], t] @ S
    return cv2.warpPerspective(board, H, size, flags=cv2.INTER_AREA, borderValue=255)


def test_calibrate_on_rendered_chessboards(tmp_path):
    cols, rows, square, size = 8, 6, 0.02, (480, 360)
    K = np.array([[420.0, 0, 239.5], [0, 420.0, 179.5], [0, 0, 1]])
    R21 = cv2.Rodrigues(np.array([0.0, 0.35, 0.0]))[0]
    t21 = np.array([-0.12, 0.0, 0.02])
    rng = np.random.default_rng(0)
    (tmp_path / "L").mkdir()
    (tmp_path / "R").mkdir()
    for k in range(8):
        Rb = cv2.Rodrigues(rng.normal(0, 0.25, 3) + np.array([np.pi, 0, 0]))[0]
        tb = np.array([-0.07, -0.05, 0.45]) + rng.normal(0, 0.02, 3)
        cv2.imwrite(
            str(tmp_path / "L" / f"{k:02d}.png"), _render_board(K, Rb, tb, cols, rows, square, size)
        )
        cv2.imwrite(
            str(tmp_path / "R" / f"{k:02d}.png"),
            _render_board(K, R21 @ Rb, R21 @ tb + t21, cols, rows, square, size),
        )
    out = str(tmp_path / "stereo.yaml")
    code = main(["calibrate", str(tmp_path / "L"), str(tmp_path / "R"), "-o", out,
                 "--cols", str(cols), "--rows", str(rows), "--square", str(square)])  # fmt: skip
    assert code == 0
    c1, c2 = load_stereo(out)
    np.testing.assert_allclose(np.asarray(c1.K), K, rtol=0.01, atol=1.5)
    T21 = np.asarray(c2.T_cam_robot) @ np.linalg.inv(np.asarray(c1.T_cam_robot))
    np.testing.assert_allclose(T21[:3, 3], t21, atol=2e-3)
    fs = cv2.FileStorage(out, cv2.FILE_STORAGE_READ)
    assert fs.getNode("rms_stereo").real() < 0.5 and fs.getNode("rms_1").real() < 0.5
    # Too few usable pairs: exit 1; bad arguments: exit 2.
    assert main(["calibrate", str(tmp_path / "L"), str(tmp_path / "R"), "-o", out,
                 "--cols", "10", "--rows", "8", "--square", "0.02"]) == 1  # fmt: skip
    assert main(["calibrate", str(tmp_path / "L"), str(tmp_path / "R"), "-o", out,
                 "--cols", "8", "--rows", "6", "--square", "-1"]) == 2  # fmt: skip
