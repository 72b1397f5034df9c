"""User-facing rough edges of the command line: exit codes of batch commands, exact problem
counts, quiet video reading, implausible distortion, plain-text --help."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from tests.helpers.datasets import H, W, edit_json, make_dataset


def _one_line_error(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "Traceback" not in err[0], err
    return err[0]


# ------------------------------------------------------------------ loader's problem count


def test_loader_counts_problems_as_validate_does(tmp_path, capsys):
    """One broken camera used by 5 frames said '(and 5 more problems)': the per-frame
    consequences were counted as problems. The count now equals `jaxcr validate`'s list."""
    from jaxcr.cli import main
    from jaxcr.errors import InputErrors
    from jaxcr.io.dataset import check_dataset, load_dataset

    root = make_dataset(tmp_path / "d", n_frames=5)

    def break_camera(d):
        d["cameras"]["main"]["K"][0][0] = -1.0

    edit_json(root, break_camera)
    with pytest.raises(InputErrors) as ei:
        load_dataset(root)
    assert len(ei.value.errors) == len(check_dataset(root).report_errors) == 2
    msg = str(ei.value)
    assert "focal lengths must be positive" in msg
    assert f"(and 1 more problem; jaxcr validate {root} lists them all)" in msg
    assert main(["segment", str(root), "-o", str(tmp_path / "o"), "--quiet"]) == 2
    assert "(and 1 more problem;" in _one_line_error(capsys)

    # two independent frame problems besides the camera: 4 problems, 3 more
    def break_frames(d):
        d["frames"][1]["q"] = [1.0]
        d["frames"][3]["q"] = "x"

    edit_json(root, break_frames)
    with pytest.raises(InputErrors) as ei:
        load_dataset(root)
    assert len(ei.value.errors) == len(check_dataset(root).report_errors) == 4
    assert "(and 3 more problems;" in str(ei.value)
    # a single problem has no count
    root2 = make_dataset(tmp_path / "d2", n_frames=1)
    edit_json(root2, lambda d: d.update(format="jaxcr.dataset/9"))
    with pytest.raises(InputErrors) as ei:
        load_dataset(root2)
    assert len(ei.value.errors) == 1 and "more problem" not in str(ei.value)


# ------------------------------------------------------------------ exit codes of batch commands


def _fake_run(root, out, oks):
    """A finished segment output folder: frame k ok (a full-size refined mask) or failed."""
    from jaxcr.io import results as R

    out.mkdir()
    (out / "run.json").write_text(
        json.dumps({"format": R.RUN_FORMAT, "dataset": str(root), "cameras": ["main"]})
    )
    lines = []
    for k, ok in enumerate(oks):
        fid = f"{k:06d}"
        rec = {"format": R.RESULTS_FORMAT, "frame": fid, "ok": ok}
        if ok:
            rel = f"masks/main/{fid}.png"
            R.atomic_write_png(out / rel, np.ones((H, W), bool))
            rec["files"] = {"masks": {"main": rel}}
        else:
            rec["reason"] = "kinematics failed"
        lines.append(json.dumps(rec))
    (out / "results.jsonl").write_text("\n".join(lines) + "\n")
    (out / "DONE").write_text("done\n")


def test_evaluate_exit_code_says_whether_frames_failed(tmp_path, capsys):
    """evaluate exited 0 whatever the report counted as failed; now 0 only when every frame
    is ok, 1 when some failed (in the run or in evaluation), with where they are listed."""
    from jaxcr.cli import main

    root = make_dataset(tmp_path / "d", n_frames=3)
    good = tmp_path / "good"
    _fake_run(root, good, [True, True, True])
    assert main(["evaluate", str(good), "--no-plot"]) == 0
    assert "failed" not in capsys.readouterr().err

    mixed = tmp_path / "mixed"
    _fake_run(root, mixed, [True, False, True])
    (mixed / "masks" / "main" / "000002.png").unlink()  # fails in evaluation
    assert main(["evaluate", str(mixed), "--no-plot"]) == 1
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert "2 of 3 frame(s) failed (1 in the segment run, 1 in evaluation)" in err
    assert str(mixed / "per_frame.csv") in err
    rows = {r["frame"]: r["ok"] for r in csv.DictReader(open(mixed / "per_frame.csv"))}
    assert rows == {"000000": "True", "000001": "False", "000002": "False"}
    # several runs: one failed frame anywhere makes it 1
    assert main(["evaluate", str(good), str(mixed), "-o", str(tmp_path / "r"), "--no-plot"]) == 1
    assert "2 of 6 frame(s) failed" in capsys.readouterr().err


# ------------------------------------------------------------------ plain-text --help

_MARKUP = r"``|:[a-z]+:`|`[^`\n]+`|\*\*|::$"


def _command_paths():
    """Every (sub)command path of the CLI, nested ones included (manifold train, ...)."""
    import argparse

    from jaxcr.cli import build_parser

    def walk(parser, path):
        yield path
        for a in parser._actions:
            if isinstance(a, argparse._SubParsersAction):
                for name, sp in a.choices.items():
                    yield from walk(sp, [*path, name])

    return list(walk(build_parser(), []))


def test_every_help_is_plain_text(capsys):
    """Module docstrings became --help texts with their reST markup (``x``, :func:`x`, `x`,
    a trailing '::'); every command's and subcommand's --help is now plain text."""
    import re

    from jaxcr.cli import main

    paths = _command_paths()
    names = {" ".join(p) for p in paths}
    assert {"", "segment", "evaluate", "manifold train", "manifold query", "model-object"} <= names
    for path in paths:
        with pytest.raises(SystemExit) as exc:
            main([*path, "--help"])
        assert exc.value.code == 0, path
        out, err = capsys.readouterr()
        assert out.startswith("usage: jaxcr") and "Traceback" not in out + err, path
        bad = [m.group(0) for m in re.finditer(_MARKUP, out, re.M)]
        assert not bad, (path, bad)


# ------------------------------------------------------------------ video files


@pytest.fixture(scope="module")
def motion_video(tmp_path_factory):
    """A 64x48, 8-frame MJPG motion dataset (video.avi and the same frames as PNGs)."""
    from jaxcr.synth.motion_scenes import generate_motion_video

    d = tmp_path_factory.mktemp("mv") / "mv"
    generate_motion_video(d, "pushed_static", seed=0, size=(64, 48), n_frames=8, video=True)
    return d


_READ_FRAMES = (
    "import sys\n"
    "from jaxcr.errors import InputError\n"
    "from jaxcr.io.motion_dataset import load_motion_dataset\n"
    "for d in sys.argv[1:]:\n"
    "    print('DATASET', d, flush=True)\n"
    "    print('DATASET', d, file=sys.stderr, flush=True)\n"
    "    try:\n"
    "        ds = load_motion_dataset(d)\n"
    "    except InputError as e:\n"
    "        print('InputError:', e)\n"
    "        print('EXIT 2', flush=True)\n"
    "        continue\n"
    "    for i, img, why in ds.frames():\n"
    "        print(i, img is not None, why)\n"
    "    print('EXIT 0', flush=True)\n"
)


def _read_frames(*dirs):
    """Frames of the motion datasets ``dirs`` read in one fresh process (one Python start for
    all of them): per dataset (exit code as a one-dataset run gave it, stdout lines, what
    reached stderr while it was read: a marker line on both streams splits them)."""
    import subprocess
    import sys

    p = subprocess.run([sys.executable, "-c", _READ_FRAMES, *map(str, dirs)],
                       capture_output=True, text=True, timeout=900)  # fmt: skip
    assert p.returncode == 0, p.stderr
    out, lines = [], None
    for ln in p.stdout.splitlines():
        if ln.startswith("DATASET "):
            lines = []
        elif ln.startswith("EXIT "):
            out.append((int(ln[5:]), lines))
        else:
            lines.append(ln)
    errs = p.stderr.split("DATASET ")
    assert errs[0] == "" and len(out) == len(dirs) == len(errs) - 1, (p.stdout, p.stderr)
    # each part: "<dir>\n" then whatever that dataset's reading wrote to stderr
    return [(c, ln, e.split("\n", 1)[1]) for (c, ln), e in zip(out, errs[1:], strict=True)]


def test_truncated_video_is_quiet_and_fails_the_damaged_frames(motion_video, tmp_path, capfd):
    """A truncated AVI: FFmpeg printed '[mjpeg @ 0x...] overread 8' and OpenCV's AVI reader
    'Unexpected element. Expected: LIST. Got: <raw bytes>' on stderr, and the frame cut short
    was used with its missing part grey. Now stderr stays empty, the cut frame and the missing
    ones fail with a reason, and a file cut inside its header is one InputError (exit 2)."""
    import shutil

    data = (motion_video / "video.avi").read_bytes()
    d, d_head = tmp_path / "cut", tmp_path / "cut_header"
    shutil.copytree(motion_video, d)
    shutil.copytree(motion_video, d_head)
    # cut in the middle of frame 3's JPEG data: find frame 3's JPEG start marker
    starts = [k for k in range(len(data) - 2) if data[k : k + 3] == b"\xff\xd8\xff"]
    assert len(starts) == 8
    cut = (starts[3] + starts[4]) // 2
    (d / "video.avi").write_bytes(data[:cut])
    # a file cut inside its header
    (d_head / "video.avi").write_bytes(data[:300])
    # both read in one fresh process: its stderr (FFmpeg's and OpenCV's native writes) empty
    (code, lines, err), (code_head, lines_head, err_head) = _read_frames(d, d_head)
    assert code == 0 and err == "", err
    rows = [ln.split(" ", 2) for ln in lines]
    assert [r[1] for r in rows] == ["True"] * 3 + ["False"] * 5
    assert rows[3][2].startswith("corrupt video frame (decoder: ")
    assert rows[4][2] == (f"no such frame: the video ends after 4 frame(s) (file truncated: "
                          f"{cut} of {len(data)} bytes)")  # fmt: skip
    # the whole CLI: a file cut inside its header is bad input, one line, nothing else
    assert code_head == 2 and err_head == ""
    assert lines_head == [f"InputError: {d_head / 'video.avi'}: field 'source.video': not a "
                          f"readable video (the file is truncated (300 of {len(data)} bytes))"]  # fmt: skip
    # the command in this process (capfd: file descriptors 1 and 2, so FFmpeg's and OpenCV's
    # native writes would show too): exit 2, that line alone (a child cost a JAX start)
    from jaxcr.cli import main

    capfd.readouterr()
    assert main(["motion", str(d_head), "-o", str(tmp_path / "o")]) == 2
    err = capfd.readouterr().err
    assert err.splitlines() == [f"jaxcr motion: error: {lines_head[0][len('InputError: ') :]}"]


def test_video_extension_that_lies(motion_video, tmp_path):
    """The container is recognised by content: an MP4 renamed .avi decodes as its frames; a
    PNG/JPEG renamed .avi (FFmpeg read it as a one-frame video, the other frames failing
    as 'corrupt') and a text file are refused with one line naming the file."""
    import shutil

    import cv2
    import numpy as np

    d = tmp_path / "v"
    shutil.copytree(motion_video, d)
    pngs = sorted((d / "frames").glob("*.png"))
    w = cv2.VideoWriter(str(tmp_path / "x.mp4"), cv2.VideoWriter_fourcc(*"mp4v"), 10, (64, 48))
    for p in pngs:
        w.write(cv2.imread(str(p)))
    w.release()
    shutil.copy(tmp_path / "x.mp4", d / "video.avi")
    from jaxcr.io.motion_dataset import load_motion_dataset

    frames = [(img, why) for _, img, why in load_motion_dataset(d).frames()]
    assert [why for _, why in frames] == [""] * 8
    refs = [cv2.cvtColor(cv2.imread(str(p)), cv2.COLOR_BGR2RGB) / 255.0 for p in pngs]
    diff = np.array([[np.abs(img - ref).mean() for ref in refs] for img, _ in frames])
    # lossy MPEG-4 at 64x48: each frame is its own PNG up to compression noise (about 0.03)
    # and nearer to it than to any other frame
    assert np.all(np.diag(diff) < 0.05), np.diag(diff)
    assert np.all(np.argmin(diff, axis=1) == np.arange(8)), diff
    # a PNG, a text file and a JPEG renamed .avi: three copies read in one fresh process
    liars = {"png": tmp_path / "v_png", "text": tmp_path / "v_text", "jpeg": tmp_path / "v_jpeg"}
    for v in liars.values():
        shutil.copytree(d, v)
    shutil.copy(pngs[0], liars["png"] / "video.avi")
    (liars["text"] / "video.avi").write_text("not a video\n" * 50)
    jpg = liars["jpeg"] / "video.avi.jpg"
    cv2.imwrite(str(jpg), cv2.imread(str(pngs[0])))
    (liars["jpeg"] / "video.avi").write_bytes(jpg.read_bytes())
    read = dict(zip(liars, _read_frames(*liars.values()), strict=True))
    for name, kind in (("png", "a PNG image"), ("text", "not a readable video")):
        code, lines, err = read[name]
        v = liars[name]
        assert code == 2 and err == "" and len(lines) == 1, (lines, err)
        assert f"{v / 'video.avi'}: field 'source.video': " in lines[0] and kind in lines[0]
    code, lines, _ = read["jpeg"]
    assert code == 2 and "is a JPEG image, not a video" in lines[0]


# ------------------------------------------------------------------ distortion plausibility


def _first_fold_dense(k1, k2, k3, r_max=20.0, n=400_001):
    """Reference for radial_fold: r_d sampled densely, the first sample where it decreases."""
    import numpy as np

    r = np.linspace(0.0, r_max, n)
    rd = r * (1 + k1 * r**2 + k2 * r**4 + k3 * r**6)
    down = np.flatnonzero(np.diff(rd) < 0)
    return None if down.size == 0 else (r[down[0]], rd[down[0]])


def test_radial_fold_against_dense_sampling():
    import numpy as np

    from jaxcr.io.calibration import radial_fold

    # k1 only: closed form r_c = 1/sqrt(-3 k1), r_d(r_c) = 2/3 r_c
    rc, rdc = radial_fold([-0.5, 0, 0, 0, 0])
    assert rc == pytest.approx(1 / np.sqrt(1.5), rel=1e-12) and rdc == pytest.approx(2 / 3 * rc)
    rng = np.random.default_rng(0)
    cases = [(-0.12, 0.08, -0.01), (-0.3, 0.1, 0.04), (0.1, -0.05, 0.001), (0.2, 0.0, 0.0),
             (-5.0, 0.0, 0.0), (0.0, 0.0, -0.3)] + [tuple(rng.normal(0, 0.5, 3)) for _ in range(20)]  # fmt: skip
    n_fold = 0
    for k1, k2, k3 in cases:
        got = radial_fold([k1, k2, 1e-3, -1e-3, k3])  # tangential terms do not enter
        ref = _first_fold_dense(k1, k2, k3)
        if ref is None:  # monotone up to r = 20 (87 deg off-axis)
            assert got is None or got[0] > 19.99, (k1, k2, k3, got)
            continue
        n_fold += 1
        assert got is not None and got[0] == pytest.approx(ref[0], abs=1e-4), (k1, k2, k3)
        assert got[1] == pytest.approx(ref[1], abs=1e-4)
    assert n_fold >= 5


def _camera_yaml(path, dist, fx=500.0, size=(640, 480)):
    import cv2
    import numpy as np

    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    fs.write("camera_matrix", np.array([[fx, 0, (size[0] - 1) / 2], [0, fx, (size[1] - 1) / 2],
                                        [0, 0, 1.0]]))  # fmt: skip
    fs.write("distortion_coefficients", np.asarray(dist, float).reshape(1, -1))
    fs.write("image_width", size[0])
    fs.write("image_height", size[1])
    fs.release()
    return path


def test_implausible_distortion_is_refused_naming_file_and_field(tmp_path, capsys):
    """Any finite distortion was accepted; k1 = -5 (e.g. a coefficient in the wrong unit)
    folds the image onto itself 14 deg off-axis. Refused when the radial model is not monotone
    over the image's own field of view: the same k1 = -0.5 is fine for a narrow camera and
    refused for a wide one; a typical strong barrel lens passes."""
    import math

    from jaxcr.cli import main
    from jaxcr.errors import InputError
    from jaxcr.io.calibration import load_camera

    # k1 = -0.5 folds at r_d = 0.544: inside a 640x480 fx=500 image (corner radius 0.8),
    # outside a fx=1000 one (corner radius 0.4)
    load_camera(_camera_yaml(tmp_path / "narrow.yaml", [-0.5, 0, 0, 0, 0], fx=1000.0))
    with pytest.raises(InputError) as ei:
        load_camera(_camera_yaml(tmp_path / "wide.yaml", [-0.5, 0, 0, 0, 0], fx=500.0))
    e = ei.value
    assert e.file.endswith("wide.yaml") and e.field == "distortion_coefficients"
    assert "not monotone over the 640x480 image" in e.message and "peaks at 0.544" in e.message
    # a typical strong barrel lens: monotone over its image
    load_camera(_camera_yaml(tmp_path / "real.yaml", [-0.29, 0.11, 1e-3, 0.0, 0.04], fx=535.0))
    # non-finite: always refused
    bad = _camera_yaml(tmp_path / "nan.yaml", [math.nan, 0, 0, 0, 0])
    with pytest.raises(InputError, match="NaN or infinite") as ei:
        load_camera(bad)
    assert ei.value.field == "distortion_coefficients"
    # in a dataset (inline camera): validate names dataset.json and the field, exit 2
    root = make_dataset(tmp_path / "d", n_frames=2)
    edit_json(root, lambda d: d["cameras"]["main"].update(dist=[-5.0, 0, 0, 0, 0]))
    capsys.readouterr()
    assert main(["validate", str(root)]) == 2
    out = capsys.readouterr().out.splitlines()
    assert out[0].startswith(f"{root / 'dataset.json'}: field 'cameras.main.dist': radial "
                             "distortion (k1=-5, k2=0, k3=0) is not monotone")  # fmt: skip
    # a stereo calibration names D1/D2
    import cv2
    import numpy as np

    from jaxcr.io.calibration import load_stereo

    fs = cv2.FileStorage(str(tmp_path / "st.yaml"), cv2.FILE_STORAGE_WRITE)
    K = np.array([[500.0, 0, 319.5], [0, 500.0, 239.5], [0, 0, 1]])
    for k, v in (("K1", K), ("D1", np.zeros((1, 5))), ("K2", K),
                 ("D2", np.array([[0.0, -3.0, 0, 0, 0]])), ("R", np.eye(3)),
                 ("T", np.array([[0.1], [0], [0]]))):  # fmt: skip
        fs.write(k, v)
    fs.write("image_width", 640)
    fs.write("image_height", 480)
    fs.release()
    with pytest.raises(InputError) as ei:
        load_stereo(tmp_path / "st.yaml")
    assert ei.value.field == "D2" and "k2=-3" in ei.value.message


def test_calibrate_does_not_write_a_folding_distortion(tmp_path, monkeypatch, capsys):
    """A calibration whose distortion folds inside the image would be written and then refused
    by every loader; calibrate now says so and writes nothing (exit 1)."""
    import cv2
    import numpy as np

    from jaxcr.cli import calibrate, main

    K = np.array([[150.0, 0, (W - 1) / 2], [0, 150.0, (H - 1) / 2], [0, 0, 1]])
    res = {"K1": K, "D1": np.zeros((1, 5)), "K2": K, "D2": np.array([[-3.0, 0, 0, 0, 0]]),
           "R": np.eye(3), "T": np.array([-0.1, 0, 0]), "E": np.eye(3), "F": np.eye(3),
           "size1": (W, H), "size2": (W, H), "rms_1": 0.2, "rms_2": 0.2, "rms_stereo": 0.3,
           "used": [0, 1, 2]}  # fmt: skip
    monkeypatch.setattr(calibrate, "calibrate_stereo", lambda *a, **k: res)
    for side in ("L", "R"):
        (tmp_path / side).mkdir()
        for k in range(3):
            cv2.imwrite(str(tmp_path / side / f"{k}.png"), np.zeros((H, W), np.uint8))
    out = tmp_path / "s.yaml"
    argv = ["calibrate", str(tmp_path / "L"), str(tmp_path / "R"), "-o", str(out),
            "--cols", "8", "--rows", "6", "--square", "0.02"]  # fmt: skip
    assert main(argv) == 1
    msg = capsys.readouterr().out
    assert "field 'D2': radial distortion (k1=-3, k2=0, k3=0) is not monotone" in msg
    assert "nothing written" in msg and not out.exists()
    res["D2"] = np.array([[-0.1, 0.01, 0, 0, 0]])
    assert main(argv) == 0 and out.exists()


# ------------------------------------------------------------------ confusing messages


@pytest.mark.parametrize(
    "marker, what",
    [("stereo.json", "jaxcr stereo"), ("motion.json", "jaxcr motion"),
     ("scene.json", "jaxcr model-object"), ("run.json", "jaxcr evaluate")],
)  # fmt: skip
def test_another_format_folder_says_what_it_is(tmp_path, capsys, marker, what):
    """Giving a stereo/motion/RGB-D/segment-output folder to a dataset command said only
    'missing dataset.json'; it now says which format the folder holds and which command
    reads it."""
    from jaxcr.cli import main

    d = tmp_path / "x"
    d.mkdir()
    (d / marker).write_text("{}")
    hint = f"(this folder has {marker}: "
    assert main(["segment", str(d), "-o", str(tmp_path / "o")]) == 2
    msg = _one_line_error(capsys)
    assert f"{d}: missing dataset.json {hint}" in msg and msg.endswith(f"read by {what})")
    (tmp_path / "q.csv").write_text("0,0\n")
    assert main(["fk", str(d), str(tmp_path / "q.csv"), "-o", str(tmp_path / "f")]) == 2
    assert f"folder has no dataset.json {hint}" in _one_line_error(capsys)
    assert main(["validate", str(d)]) == 2
    assert hint in capsys.readouterr().out


def test_manifold_query_with_a_folder_as_model(tmp_path, capsys):
    """A folder given as MODEL said 'model file not found' although it exists."""
    from jaxcr.cli import main

    root = make_dataset(tmp_path / "d", n_frames=1)
    assert main(["manifold", "query", str(root), str(root), "-o", str(tmp_path / "o")]) == 2
    assert "is a folder, expected a model file" in _one_line_error(capsys)


def test_motion_report_times_are_rounded():
    """report.md said 'flow 46.62798000208568 ms' (and 'None ms' without used frames)."""
    from jaxcr.cli.motion import timing_line

    t = {"flow_ms": 46.62798000208568, "segmentation_ms": 2.134474, "likelihood_ms": 21.902257}
    assert timing_line(t) == (
        "Median per-frame time: flow 46.6 ms, segmentation 2.1 ms, likelihood 21.9 ms."
    )
    none = dict.fromkeys(t)
    assert timing_line(none) == "Median per-frame time: flow -, segmentation -, likelihood -."


def test_fk_says_why_rows_failed(tmp_path, capsys):
    """'jaxcr fk: 0/2 rows ok, 2 failed (rows 0, 1)' gave no reason; a CTR row outside its
    joint limits looked like a solver failure. Now each failed row has its reason."""
    import numpy as np

    from jaxcr.cli import main
    from jaxcr.cli.fk import failure_reasons
    from jaxcr.kinematics.ctr import make_test_ctr

    ctr = make_test_ctr()
    n = len(ctr.length)
    good = np.concatenate([-0.5 * np.asarray(ctr.length) * [0.9, 0.6, 0.3], np.zeros(n)])
    q = np.stack([good, good, good, good, good])
    q[1, 0] = np.nan
    q[2, :n] = [0.01, 0.02, 0.03]  # beta > 0: tubes pulled behind the actuation unit
    out = {"ok": np.array([True, False, False, False, False]),
           "residual": np.array([0.0, np.nan, 0.0, 1.0, 0.0]),
           "p": np.zeros((5, 4, 3))}  # fmt: skip
    out["p"][4, 2] = np.nan
    reasons = failure_reasons(ctr, q, out)
    assert sorted(reasons) == [1, 2, 3, 4]
    assert reasons[1] == "non-finite joint values"
    assert reasons[2].startswith("outside the joint limits (beta_1 <= ... <= beta_n <= 0")
    assert reasons[3] == f"no converged solution (residual 1 > tolerance {ctr.tol:g})"
    assert reasons[4] == "non-finite centreline"
    # through the command: the 9-sample single-segment robot and 2 rows of
    # tests/scale/test_ray_equality.py's `jaxcr fk --chunk 2` (and tests/cli/test_cli_fk.py),
    # so the compiled batch is loaded from the run's cache, not compiled again
    robot = tmp_path / "robot.json"
    robot.write_text(json.dumps({"kind": "single_segment", "length": 0.04, "radius": 0.002,
                                 "n_points": 9}))  # fmt: skip
    (tmp_path / "q.csv").write_text("0.3,-2.0\nnan,0.1\n")
    assert main(["fk", str(robot), str(tmp_path / "q.csv"), "-o", str(tmp_path / "o")]) == 1
    assert ("1/2 rows ok, 1 failed (row 1: non-finite joint values; ok = 0 in tips.csv)"
            in capsys.readouterr().out)  # fmt: skip


def test_bench_report_path_is_checked_before_benchmarking(tmp_path, monkeypatch, capsys):
    """'jaxcr bench fk -o bfk.md' ran the whole benchmark (2 min) and then failed with
    'jaxcr bench: error: : No such file or directory' (the script's makedirs of dirname('bfk.md')
    = ''). Now scripts get an absolute path, and an unusable report folder is refused before
    anything runs."""
    import os

    from jaxcr.cli import bench, main

    calls = []

    def script_main(argv):  # writes its report as experiments/kinematics/bench_fk.py does
        out = argv[argv.index("-o") + 1]
        calls.append(out)
        os.makedirs(os.path.dirname(out), exist_ok=True)
        with open(out, "w") as fh:
            fh.write("# report\n")
        return 0

    monkeypatch.setattr(bench, "find_provider",
                        lambda what: (bench._ScriptProvider(script_main), "fake:main"))  # fmt: skip
    monkeypatch.chdir(tmp_path)
    assert main(["bench", "fk", "-o", "bfk.md"]) == 0
    assert (tmp_path / "bfk.md").read_text() == "# report\n" and calls == [str(tmp_path / "bfk.md")]
    (tmp_path / "afile").write_text("x")
    capsys.readouterr()
    assert main(["bench", "fk", "-o", "afile/r.md"]) == 2
    assert "afile" in _one_line_error(capsys) and len(calls) == 1  # nothing was run


def test_manifold_query_says_which_frames_failed(tmp_path, capsys):
    """'manifold query: 11/12 frames estimated' (exit 1) named neither the failed frame nor
    where the reasons are; the loader's message also said 'frame X' twice in stereo/manifold."""
    from jaxcr.cli import main

    d = tmp_path / "tr"
    assert main(["manifold", "synth", "-o", str(d), "--frames", "12", "--size", "160x120"]) == 0
    model = tmp_path / "m.npz"
    assert main(["manifold", "train", str(d), "-o", str(model), "--bins", "24", "--step",
                 "0.05"]) == 0  # fmt: skip
    (d / "images" / "left" / "000003.png").unlink()
    capsys.readouterr()
    assert main(["manifold", "query", str(model), str(d), "-o", str(tmp_path / "q")]) == 1
    out, err = capsys.readouterr()
    assert "11/12 frames estimated" in out
    (line,) = [ln for ln in err.splitlines() if ln.startswith("jaxcr")]  # besides progress
    assert line.startswith(f"jaxcr manifold: 1 frame(s) failed: {d / 'dataset.json'}: frame "
                           "000003: field 'images.left': file not found")  # fmt: skip
    assert line.count("frame 000003") == 1
    assert line.endswith(f"; all listed in {tmp_path / 'q' / 'estimates.jsonl'}")


def test_stereo_failure_line_names_the_frame_once():
    """'frame 000: ST2/images/cam1/000.png: frame 000: field ...' named the frame twice."""
    from jaxcr.cli.stereo import failure_line

    img = {"id": "000", "message": "S/images/cam1/000.png: frame 000: field 'images.cam1': x"}
    assert failure_line(img) == img["message"]
    assert failure_line({"id": "007", "message": "4 of 4 markers not found in cam2"}) == (
        "frame 007: 4 of 4 markers not found in cam2"
    )
