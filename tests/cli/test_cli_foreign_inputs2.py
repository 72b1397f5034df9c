"""Command-line tools on foreign or damaged inputs, continued (see test_cli_foreign_inputs.py):
one bad frame is a failed frame and the batch goes on; bad input is one line, exit 2; a run
can be resumed and re-tried; no output looks complete when it is not."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from tests.helpers import cli_scene
from tests.helpers.datasets import H, W, make_dataset


def _one_line_error(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "Traceback" not in err[0], err
    return err[0]


def _fake_run(root, out, frames, sizes):
    """A segment output folder for ``frames`` whose refined masks have the given (h, w)."""
    from jaxcr.io import results as R

    out.mkdir()
    (out / "run.json").write_text(
        json.dumps({"format": R.RUN_FORMAT, "dataset": str(root), "cameras": ["main"]})
    )
    lines = []
    for fid, (h, w) in zip(frames, sizes, strict=True):
        rel = f"masks/main/{fid}.png"
        R.atomic_write_png(out / rel, np.ones((h, w), bool))
        lines.append(json.dumps({"format": R.RESULTS_FORMAT, "frame": fid, "ok": True,
                                 "files": {"masks": {"main": rel}}}))  # fmt: skip
    (out / "results.jsonl").write_text("\n".join(lines) + "\n")
    (out / "DONE").write_text("done\n")


def test_evaluate_counts_a_frame_with_a_wrong_mask_size_as_failed(tmp_path, capsys):
    """One frame whose predicted mask had another size than its ground truth aborted the
    whole report (exit 2, no table); now that frame is failed with the reason, the rest go on."""
    from jaxcr.cli import main

    root = make_dataset(tmp_path / "d", n_frames=3)
    out = tmp_path / "run"
    _fake_run(root, out, ["000000", "000001", "000002"], [(H, W), (H // 2, W), (H, W)])
    assert main(["evaluate", str(out), "--no-plot"]) == 1
    err = capsys.readouterr().err
    assert "1 frame(s) counted as failed: frame 000001" in err and "(36, 96)" in err
    rows = {r["frame"]: r for r in csv.DictReader(open(out / "per_frame.csv"))}
    assert rows["000001"]["ok"] == "False" and "(36, 96)" in rows["000001"]["reason"]
    assert rows["000001"]["iou_refined"] == ""
    assert rows["000000"]["ok"] == "True" and float(rows["000000"]["iou_refined"]) > 0
    assert "3 (1)" in (out / "table2.md").read_text()  # Frames (failed)


def test_evaluate_counts_a_frame_with_damaged_outputs_as_failed(tmp_path, capsys):
    """A missing or corrupt mask PNG aborted the report (exit 2); a corrupt centreline .npy
    was a numpy traceback. Now each fails its own frame, with the file named."""
    from jaxcr.cli import main

    root = make_dataset(tmp_path / "d", n_frames=4)
    out = tmp_path / "run"
    _fake_run(root, out, ["000000", "000001", "000002", "000003"], [(H, W)] * 4)
    (out / "masks" / "main" / "000001.png").unlink()
    (out / "masks" / "main" / "000002.png").write_bytes(b"\x89PNG\r\n\x1a\n garbage")
    lines = [json.loads(x) for x in (out / "results.jsonl").read_text().splitlines()]
    lines[3]["files"]["centreline"] = "centrelines/000003.npy"
    (out / "centrelines").mkdir()
    (out / "centrelines" / "000003.npy").write_bytes(b"\x93NUMPY truncated")
    (out / "results.jsonl").write_text("".join(json.dumps(r) + "\n" for r in lines))
    assert main(["evaluate", str(out), "--no-plot"]) == 1
    assert "3 frame(s) counted as failed" in capsys.readouterr().err
    rows = {r["frame"]: r for r in csv.DictReader(open(out / "per_frame.csv"))}
    assert rows["000000"]["ok"] == "True" and float(rows["000000"]["iou_refined"]) > 0
    assert "missing output file masks/main/000001.png" in rows["000001"]["reason"]
    assert (
        "000002.png" in rows["000002"]["reason"]
        and "not a readable image" in rows["000002"]["reason"]
    )
    assert (
        "000003.npy" in rows["000003"]["reason"]
        and "not a readable .npy" in rows["000003"]["reason"]
    )
    assert all(rows[f]["ok"] == "False" for f in ("000001", "000002", "000003"))


#: tests/helpers/cli_scene.py's options: the refinement program test_cli_segment compiles,
#: loaded from the run's compilation cache
FAST = [*cli_scene.FAST, "--no-overlays", "--quiet"]


def test_segment_retry_failed_reruns_a_frame_whose_image_was_fixed(tmp_path, capsys):
    """--resume treats failed records as done, so a frame whose image was later repaired was
    never re-run; --retry-failed re-runs it and its new record supersedes the failed one."""
    from jaxcr.cli import main
    from jaxcr.io import results as R

    root = cli_scene.make_frames(tmp_path / "d", n_frames=2)
    img = root / "images" / "main" / "000001.png"
    good = img.read_bytes()
    img.write_bytes(b"not a png")
    out = tmp_path / "run"
    assert main(["segment", str(root), "-o", str(out), *FAST]) == 1
    (rec,) = [r for r in R.read_results(out / "results.jsonl") if r["frame"] == "000001"]
    assert not rec["ok"]
    img.write_bytes(good)
    assert main(["segment", str(root), "-o", str(out), "--resume", *FAST]) == 1  # unchanged
    assert len((out / "results.jsonl").read_text().splitlines()) == 2
    assert main(["segment", str(root), "-o", str(out), "--retry-failed", *FAST]) == 0
    lines = (out / "results.jsonl").read_text().splitlines()
    assert [json.loads(x)["frame"] for x in lines] == ["000001", "000000", "000001"]
    recs = R.read_results(out / "results.jsonl")  # readers: the last record per frame
    assert [(r["frame"], r["ok"]) for r in recs] == [("000001", True), ("000000", True)]
    assert json.loads((out / "summary.json").read_text())["failed"] == 0
    assert (out / "DONE").exists() and (out / "masks" / "main" / "000001.png").exists()
    capsys.readouterr()
    argv = ["segment", str(root), "-o", str(out), "--retry-failed", "--overwrite", *FAST]
    assert main(argv) == 2
    assert "exclude each other" in _one_line_error(capsys)


def test_motion_exits_1_when_a_frame_could_not_be_read(tmp_path, capsys):
    """An unreadable frame was skipped (used: false) and the run exited 0, though the README's
    exit codes say 1 when some frames fail; pairs the method does not use are no failures."""
    from jaxcr.cli import main

    # tests/motion/test_motion_batch.py's video v1 and options (FAST there): the same motion
    # programs (image size, superpixel and flow steps, model), compiled once in the run and
    # loaded by the later module (a 64x48 run of the default options compiled its own, ~9 s)
    src = tmp_path / "mo"
    assert main(["motion", "synth", "--preset", "pushed_static", "--seed", "1", "--size",
                 "128x96", "--frames", "6", "-o", str(src)]) == 0  # fmt: skip
    (src / "frames" / "000003.png").write_bytes(b"not a png")
    capsys.readouterr()
    fast = ["--no-baseline", "--model", "translation", "--superpixel-step", "8", "--flow-step", "4"]
    assert main(["motion", str(src), "-o", str(tmp_path / "b"), *fast]) == 1
    assert "1 frame(s) failed: frame 3: unreadable image 000003.png" in capsys.readouterr().err
    summary = json.loads((tmp_path / "b" / "summary.json").read_text())
    assert list(summary["failed"]) == ["3"] and summary["used"] >= 3
    assert summary["failed"]["3"].startswith("unreadable image 000003.png")
    assert (tmp_path / "b" / "report.md").exists()
    lines = [json.loads(x) for x in (tmp_path / "b" / "frames.jsonl").read_text().splitlines()]
    assert lines[0]["reason"] == "first frame" and not lines[0]["used"]  # not a failure


def test_empty_dataset_is_said_by_validate_and_refused_by_segment(tmp_path, capsys):
    """A dataset with "frames": [] validated as a bare OK and segment wrote DONE with 0/0 frames, exit 0."""
    from jaxcr.cli import main
    from tests.helpers.datasets import edit_json

    root = make_dataset(tmp_path / "d", n_frames=1)
    edit_json(root, lambda d: d.__setitem__("frames", []))
    assert main(["validate", str(root), "-o", str(tmp_path / "v.json")]) == 0
    out = capsys.readouterr().out.strip().splitlines()
    assert len(out) == 1 and "OK but empty (no frames: nothing to process)" in out[0]
    assert json.loads((tmp_path / "v.json").read_text())["warnings"] != []
    assert main(["segment", str(root), "-o", str(tmp_path / "o"), "--quiet"]) == 2
    msg = _one_line_error(capsys)
    assert "dataset.json" in msg and "'frames'" in msg and "no frames" in msg
    assert not (tmp_path / "o").exists()


def _stereo_result():
    K = np.array([[100.0, 0, 47.5], [0, 100.0, 35.5], [0, 0, 1]])
    return {"K1": K, "D1": np.zeros(5), "K2": K, "D2": np.zeros(5), "R": np.eye(3),
            "T": np.array([-0.1, 0.0, 0.0]), "size1": (W, H), "size2": (W, H),
            "rms_1": 0.1, "rms_2": 0.2, "rms_stereo": 0.3, "used": [0, 1, 2]}  # fmt: skip


def _rms_stereo(path) -> float:
    if path.suffix == ".json":
        return json.loads(path.read_text())["rms_stereo"]
    import cv2

    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    try:
        return fs.getNode("rms_stereo").real()
    finally:
        fs.release()


@pytest.mark.parametrize("suffix", [".yaml", ".json"])
def test_calibrate_output_is_written_atomically(tmp_path, monkeypatch, suffix):
    """save_stereo wrote the file, then the RMS values were appended in a second write: an
    interruption between (or in) them left a file that reads as a complete calibration."""
    from jaxcr.io import calibration as calibrate
    from jaxcr.io.calibration import load_stereo

    out = tmp_path / "sub" / f"stereo{suffix}"
    calibrate.save_calibration(_stereo_result(), str(out))
    c1, c2 = load_stereo(out)
    assert c1.width == W and np.isclose(float(c2.T_cam_robot[0, 3]), -0.1)
    text = out.read_text()
    assert abs(_rms_stereo(out) - 0.3) < 1e-9
    real = calibrate._write_calibration

    def interrupted(res, path):
        real(res, path)  # the temporary file is complete, then the run stops before the rename
        raise KeyboardInterrupt

    monkeypatch.setattr(calibrate, "_write_calibration", interrupted)
    with pytest.raises(KeyboardInterrupt):
        calibrate.save_calibration({**_stereo_result(), "rms_stereo": 9.0}, str(out))
    assert out.read_text() == text  # the earlier file is untouched
    fresh = tmp_path / f"new{suffix}"
    with pytest.raises(KeyboardInterrupt):
        calibrate.save_calibration(_stereo_result(), str(fresh))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["sub"]  # nothing, no temporaries
    assert [p.name for p in (tmp_path / "sub").iterdir()] == [out.name]


def test_calibrate_names_the_image_of_another_size(tmp_path, capsys):
    """'images of one camera differ in size' named no file."""
    import cv2

    from jaxcr.cli import main

    for side in ("L", "R"):
        (tmp_path / side).mkdir()
        for k in range(3):
            cv2.imwrite(str(tmp_path / side / f"{k}.png"), np.zeros((H, W), np.uint8))
    cv2.imwrite(str(tmp_path / "R" / "1.png"), np.zeros((H, W + 2), np.uint8))
    argv = ["calibrate", str(tmp_path / "L"), str(tmp_path / "R"), "-o", str(tmp_path / "s.yaml"),
            "--cols", "8", "--rows", "6", "--square", "0.02"]  # fmt: skip
    assert main(argv) == 2
    msg = _one_line_error(capsys)
    assert "R/1.png" in msg and "98x72 differs from 96x72" in msg and "R/0.png" in msg
    assert not (tmp_path / "s.yaml").exists()
    # an output folder that cannot be written is refused before any image is read (the
    # audit, experiments/contract_audit.py item 6); a file stands in for it (root ignores modes)
    (tmp_path / "file").write_text("")
    argv[4] = str(tmp_path / "file" / "s.yaml")
    assert main(argv) == 2
    msg = _one_line_error(capsys)
    assert "output folder exists and is not a folder" in msg and str(tmp_path / "file") in msg
    # --cols/--rows have a ceiling (the audit's item 3: --cols 100000 ran the detection)
    assert main([*argv[:5], "--cols", "100000", "--rows", "6", "--square", "0.02"]) == 2
    msg = _one_line_error(capsys)
    assert "field 'cols': must be between 2 and 2047" in msg, msg


def test_motion_results_and_calibrate_readers_respect_the_pixel_limit(
    tmp_path, monkeypatch, capsys
):
    """motion's frame and mask reader, results.read_mask_png and calibrate called cv2.imread
    directly: a 140 kB PNG declaring 12000x12000 pixels was decoded (and 30000x30000 would be
    ~11 GB). Now they go through jaxcr.io.images' checked reader; a motion frame whose header
    has another size than motion.json is not decoded at all."""
    from jaxcr.cli import main
    from jaxcr.errors import InputError
    from jaxcr.io import images
    from jaxcr.io.motion_dataset import load_motion_dataset
    from jaxcr.io.results import read_mask_png
    from tests.cli.test_cli_foreign_inputs import _png_bomb

    bomb = tmp_path / "bomb.png"
    _png_bomb(bomb, 12000, 12000)
    with pytest.raises(InputError, match="exceeds the 134217728 pixel limit"):
        read_mask_png(bomb)
    with pytest.raises(FileNotFoundError):
        read_mask_png(tmp_path / "missing.png")

    src = tmp_path / "mo"
    assert main(["motion", "synth", "-o", str(src), "--size", "64x48", "--frames", "6"]) == 0
    (src / "frames" / "000001.png").write_bytes(bomb.read_bytes())
    _png_bomb(src / "frames" / "000002.png", 4000, 3000)
    meta = json.loads((src / "motion.json").read_text())
    mask_rel = next(fr["mask"] for fr in meta["frames"] if fr.get("mask"))
    (src / mask_rel).write_bytes(bomb.read_bytes())
    ds = load_motion_dataset(src)

    real_decode = images._quiet_decode

    def no_decode(data, flags):
        size = images.header_size(data[:64].tobytes())
        assert size == (64, 48), f"decoded a {size} file the header check should have refused"
        return real_decode(data, flags)

    reasons = {}
    with monkeypatch.context() as m:
        m.setattr(images, "_quiet_decode", no_decode)
        for i, rgb, why in ds.frames():
            reasons[i] = why
            assert (rgb is None) == (i in (1, 2))
        with pytest.raises(InputError, match="ground-truth mask: image of 12000x12000"):
            ds.mask(next(i for i, p in enumerate(ds.masks) if p is not None))
    assert reasons[1] == "image size 12000x12000 != 64x48" and reasons[3] == ""
    assert reasons[2] == "image size 4000x3000 != 64x48"
    meta["width"], meta["height"] = 20000, 10000
    (src / "motion.json").write_text(json.dumps(meta))
    with pytest.raises(InputError, match="exceeds the 134217728 pixel limit"):
        load_motion_dataset(src)

    for side in ("L", "R"):
        (tmp_path / side).mkdir()
        for k in range(3):
            _png_bomb(tmp_path / side / f"{k}.png", 32, 24)
    (tmp_path / "R" / "2.png").write_bytes(bomb.read_bytes())
    argv = ["calibrate", str(tmp_path / "L"), str(tmp_path / "R"), "-o", str(tmp_path / "s.yaml"),
            "--cols", "8", "--rows", "6", "--square", "0.02"]  # fmt: skip
    capsys.readouterr()
    assert main(argv) == 2
    msg = _one_line_error(capsys)
    assert "R/2.png" in msg and "exceeds the 134217728 pixel limit" in msg


def test_motion_video_declaring_too_many_pixels_is_not_decoded(tmp_path, monkeypatch):
    """The container's declared frame size is checked against the pixel limit before any
    frame is decoded (the limit is lowered here to the synthetic video's size)."""
    from jaxcr.cli import main
    from jaxcr.io import motion_dataset as mds

    src = tmp_path / "mo"
    argv = ["motion", "synth", "-o", str(src), "--size", "64x48", "--frames", "6", "--video"]
    assert main(argv) == 0
    ds = mds.load_motion_dataset(src)
    assert ds._video is not None
    assert [rgb is not None for _, rgb, _ in ds.frames()] == [True] * 6
    monkeypatch.setattr(mds, "MAX_PIXELS", 64 * 48 - 1)
    reasons = [why for _, rgb, why in ds.frames() if rgb is None]
    assert reasons == [f"video frame size 64x48 exceeds the {64 * 48 - 1} pixel limit"] * 6


def test_validate_reports_a_broken_camera_once(tmp_path, capsys):
    """One broken camera file gave one 'camera has an invalid calibration' line per frame and
    per image kind (2 x frames lines); now one line for the camera's own error and one naming
    the frames that use it. The frames still count as bad."""
    from jaxcr.cli import main
    from jaxcr.io.dataset import check_dataset
    from tests.helpers.datasets import edit_json

    root = make_dataset(tmp_path / "d", n_frames=7)
    (root / "cam.yaml").write_text("garbage: [")
    edit_json(root, lambda d: d["cameras"].__setitem__("main", "cam.yaml"))
    edit_json(root, lambda d: d["frames"][2].__setitem__("q", [1.0]))  # an unrelated problem
    assert main(["validate", str(root), "-o", str(tmp_path / "v.json")]) == 2
    out = capsys.readouterr().out.strip().splitlines()
    assert len(out) == 4, out  # camera file, its frames, frame 000002's q, summary
    assert "cam.yaml" in out[0] and "Parsing error" in out[0]
    assert sum("invalid calibration" in ln for ln in out) == 1
    assert "field 'cameras.main'" in out[1] and "7 frame(s) use it" in out[1]
    assert "(000000, 000001, 000002, 000003, 000004 and 2 more)" in out[1]
    assert "frame 000002: field 'q'" in out[2] and "3 problem(s)" in out[3]
    assert len(json.loads((tmp_path / "v.json").read_text())["problems"]) == 3
    check = check_dataset(root)
    assert len(check.frame_errors) == 7 and check.n_bad_frames == 7  # no frame reads as OK
    for errs in check.frame_errors.values():
        assert sum("invalid calibration" in str(e) for e in errs) == 1
