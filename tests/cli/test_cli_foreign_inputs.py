"""Command-line tools on inputs we did not generate (foreign or damaged files): every problem is
one line naming file/frame/field with exit code 2, or a failed-frame record in a batch; never
a traceback, a write outside the output folder, or a partial output that looks complete."""

from __future__ import annotations

from pathlib import Path

import pytest

from jaxcr.io.dataset import load_dataset, validate_dataset
from tests.helpers.datasets import edit_json, make_dataset


def test_frame_id_that_is_a_path_is_a_bad_frame(tmp_path):
    """Frame ids name output files (segment's masks/<cam>/<id>.png, centrelines/<id>.npy);
    before, an id '../../evil' passed validation and segment wrote outside OUT."""
    root = make_dataset(tmp_path / "d", n_frames=4)

    def ids(d):
        d["frames"][1]["id"] = "../../evil"
        d["frames"][2]["id"] = "a\\b"
        d["frames"][3]["id"] = ".."

    edit_json(root, ids)
    ds = load_dataset(root)
    assert [f.id for f in ds.frames] == ["000000"]
    assert sorted(ds.bad_frames) == ["#1", "#2", "#3"]
    assert all("not usable as a file name" in m for m in ds.bad_frames.values())
    errs = validate_dataset(root)
    assert len(errs) == 3 and all(e.field == "id" for e in errs)
    assert all("\n" not in str(e) for e in errs)
    # an id with spaces and unicode is a fine file name
    edit_json(root, lambda d: d["frames"][1].update(id="frame ü 1"))
    assert "frame ü 1" in [f.id for f in load_dataset(root).frames]
    assert not any(p.name.startswith("evil") for p in Path(tmp_path).rglob("*"))


def _one_line_error(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "Traceback" not in err[0], err
    return err[0]


def test_segment_refuses_to_write_into_the_dataset_or_a_foreign_folder(tmp_path, capsys):
    """Before, `jaxcr segment D -o D` replaced D's ground-truth masks/<cam>/<id>.png with its
    predictions (exit 0), and --overwrite deleted D/masks and D/background."""
    from jaxcr.cli import main
    from jaxcr.cli.segment import prepare_output

    root = make_dataset(tmp_path / "d", n_frames=2)
    before = {p: p.read_bytes() for p in root.rglob("*") if p.is_file()}
    for extra in ([], ["--overwrite"], ["--resume"]):
        assert main(["segment", str(root), "-o", str(root), "--quiet", *extra]) == 2
        assert "holds a dataset" in _one_line_error(capsys)
    assert {p: p.read_bytes() for p in root.rglob("*") if p.is_file()} == before
    other = tmp_path / "other"
    other.mkdir()
    (other / "notes.txt").write_text("mine")
    assert main(["segment", str(root), "-o", str(other), "--quiet", "--overwrite"]) == 2
    assert "other files" in _one_line_error(capsys)
    assert (other / "notes.txt").read_text() == "mine"
    # an empty existing folder is fine
    (tmp_path / "empty").mkdir()
    assert prepare_output(tmp_path / "empty", False, False, {"format": "x"}) == []
    assert (tmp_path / "empty" / "run.json").exists()


def test_unwritable_output_is_one_line_exit_2(tmp_path, capsys):
    """An output under a regular file (as for a read-only folder: OSError) was a traceback;
    now one line naming the path, exit 2, and fk fails before compiling."""
    import json

    from jaxcr.cli import main
    from tests.helpers.datasets import ROBOT

    robot = tmp_path / "robot.json"
    robot.write_text(json.dumps(ROBOT))
    q = tmp_path / "q.csv"
    q.write_text("5.0,0.1\n")
    blocker = tmp_path / "a file"
    blocker.write_text("")
    assert main(["fk", str(robot), str(q), "-o", str(blocker / "out")]) == 2
    line = _one_line_error(capsys)
    assert line.startswith("jaxcr fk: error: ") and str(blocker) in line
    root = make_dataset(tmp_path / "d", n_frames=1)
    assert main(["segment", str(root), "-o", str(blocker / "out"), "--quiet"]) == 2
    assert str(blocker) in _one_line_error(capsys)


def test_absurd_centreline_samples_are_refused(tmp_path, capsys):
    """`jaxcr fk --points 100000000` asked XLA for 61 GB (a traceback, or the shared machine
    out of memory); a robot file with such an n_points validated. Now both are input errors."""
    import json

    import pytest

    from jaxcr.cli import main
    from jaxcr.errors import InputError
    from jaxcr.kinematics.robots import robot_from_dict
    from tests.helpers.datasets import ROBOT

    for kind in (ROBOT, {"kind": "single_segment", "length": 0.05, "radius": 0.001}):
        with pytest.raises(InputError, match="n_points.*<= 10000"):
            robot_from_dict({**kind, "n_points": 100_000_000})
        assert robot_from_dict({**kind, "n_points": 10_000}).n_points == 10_000
    robot = tmp_path / "robot.json"
    robot.write_text(json.dumps(ROBOT))
    q = tmp_path / "q.csv"
    q.write_text("5.0,0.1\n")
    assert main(["fk", str(robot), str(q), "-o", str(tmp_path / "o"), "--points", "100000000"]) == 2
    assert "--points must be in [2, 10000]" in _one_line_error(capsys)


def test_negative_seed_and_infinite_model_error_are_usage_errors(capsys):
    """--seed -5 was a numpy traceback (synth; every command shares the argparse type now);
    synth --model-error inf blamed 'tubes[0].E'."""
    import pytest

    from jaxcr.cli import main

    for argv in (
        ["synth", "--preset", "orthogonal", "-o", "x"],
        ["segment", "d", "-o", "x"],
        ["stereo", "synth", "-o", "x"],
        ["manifold", "synth", "-o", "x"],
        ["model-object", "synth", "-o", "x"],
    ):
        with pytest.raises(SystemExit) as exc:
            main([*argv, "--seed", "-5"])
        assert exc.value.code == 2
        assert "--seed: expected a non-negative integer, got -5" in capsys.readouterr().err
    assert main(["synth", "--preset", "orthogonal", "-o", "x", "--model-error", "inf"]) == 2
    assert "field 'model-error': model-error scale must be finite" in _one_line_error(capsys)


def test_truncated_or_foreign_run_json_is_one_line(tmp_path, capsys):
    """A truncated run.json (a run killed by the OS while the folder was copied, a hand edit)
    was a JSONDecodeError traceback in evaluate and in segment --resume."""
    import json

    from jaxcr.cli import main

    root = make_dataset(tmp_path / "d", n_frames=1)
    out = tmp_path / "run"
    out.mkdir()
    (out / "results.jsonl").write_text('{"frame": "000000", "ok": false, "reason": "x"}\n')
    good = {"format": "jaxcr.segment-run/1", "dataset": str(root)}
    for text in (json.dumps(good)[:30], "[1, 2]", json.dumps({**good, "format": "other/9"})):
        (out / "run.json").write_text(text)
        assert main(["evaluate", str(out), "--no-plot"]) == 2
        assert "run.json" in _one_line_error(capsys)
        assert main(["segment", str(root), "-o", str(out), "--resume", "--quiet"]) == 2
        assert "run.json" in _one_line_error(capsys)


def test_evaluate_marks_an_incomplete_run_in_the_report(tmp_path, capsys):
    """An interrupted run's table2.md read exactly like a complete one (only a stderr warning)."""
    import json

    from jaxcr.cli import main

    root = make_dataset(tmp_path / "d", n_frames=2)
    out = tmp_path / "run"
    out.mkdir()
    (out / "run.json").write_text(
        json.dumps({"format": "jaxcr.segment-run/1", "dataset": str(root), "cameras": ["main"]})
    )
    rec = {"format": "jaxcr.segment/1", "frame": "000000", "ok": False, "reason": "x"}
    (out / "results.jsonl").write_text(json.dumps(rec) + "\n")
    assert main(["evaluate", str(out), "--no-plot"]) == 1  # its one frame failed
    assert "is incomplete" in capsys.readouterr().err
    md = (out / "table2.md").read_text()
    assert "**INCOMPLETE RUN**" in md and "only its 1 processed frames" in md
    (out / "DONE").write_text("now\n")
    assert main(["evaluate", str(out), "--no-plot"]) == 1
    assert "INCOMPLETE" not in (out / "table2.md").read_text()


def test_help_texts_do_not_repeat_themselves():
    """stereo/calibrate --help printed the first paragraph twice (description, then again as
    the start of the epilog); every subcommand's help is checked."""
    import collections

    from jaxcr.cli import build_parser

    parser = build_parser()
    (sub,) = [a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction"]
    assert {"segment", "evaluate", "stereo", "calibrate", "fk", "validate"} <= set(sub.choices)
    for name, p in sub.choices.items():
        lines = [ln.strip() for ln in p.format_help().splitlines() if len(ln.strip()) > 25]
        repeated = [ln for ln, c in collections.Counter(lines).items() if c > 1]
        assert not repeated, (name, repeated)


def test_non_finite_truth_centreline_is_a_bad_frame(tmp_path):
    """A NaN truth centreline validated; evaluate then dropped that frame's errors from the
    means without a word (nanmean)."""
    import numpy as np

    root = make_dataset(tmp_path / "d", n_frames=3)
    np.save(root / "truth" / "000001.npy", np.full((8, 3), np.nan))
    np.save(root / "truth" / "000002.npy", np.zeros((1, 3)))
    ds = load_dataset(root)
    assert [f.id for f in ds.frames] == ["000000"]
    assert all("truth.centreline" in m and "finite" in m for m in ds.bad_frames.values())


# ----------------------------------------------------------------------------- stereo


@pytest.fixture(scope="module")
def stereo_set(tmp_path_factory):
    from jaxcr.synth.stereo_ctr import generate_stereo_set

    d = tmp_path_factory.mktemp("stereo") / "set"
    generate_stereo_set(d, 1, 0, (320, 240), "green", progress=False)
    return d


def _stereo_variant(src, dst, fn):
    import json
    import shutil

    shutil.copytree(src, dst)
    meta = json.loads((dst / "stereo.json").read_text())
    meta = fn(meta, dst) or meta
    (dst / "stereo.json").write_text(json.dumps(meta))
    return dst


def test_stereo_json_with_foreign_content_is_one_line(stereo_set, tmp_path, capsys):
    """Each of these was an AttributeError/ValueError/KeyError traceback (or, for the id, a
    write outside OUT/frames) in `jaxcr stereo`."""
    import cv2

    from jaxcr.cli import main

    def plate_small(m, d):
        p = d / m["background_plates"]["cam1"]
        cv2.imwrite(str(p), cv2.resize(cv2.imread(str(p)), (100, 80)))

    def dup(m, d):
        m["frames"].append(dict(m["frames"][0]))

    cases = {
        "top": (lambda m, d: [1], "top level"),
        "bg": (lambda m, d: m.update(background=["green"]), "field 'background'"),
        "key": (
            lambda m, d: m["background"].update(key_rgb=["a", 1, 2]),
            "field 'background.key_rgb': expected 3 finite numbers",
        ),
        "base": (lambda m, d: m.update(robot_base="origin"), "field 'robot_base'"),
        "plates": (
            lambda m, d: m.update(background_plates={"cam1": "background/cam1.png"}),
            "field 'background_plates'",
        ),
        "plate_size": (plate_small, "image is 100x80, the calibration is 320x240"),
        "id": (lambda m, d: m["frames"][0].update(id="../x"), "not usable as a file name"),
        "dup": (dup, "duplicate frame id"),
        "cams": (lambda m, d: m.update(cameras=["a", "a"]), "field 'cameras'"),
    }
    for name, (fn, expect) in cases.items():
        d = _stereo_variant(stereo_set, tmp_path / name, fn)
        assert main(["stereo", str(d), "-o", str(tmp_path / f"o_{name}")]) == 2, name
        assert expect in _one_line_error(capsys), name
    assert not (tmp_path / "x.json").exists() and not list(tmp_path.glob("o_*/frames"))


def test_stereo_black_view_is_a_failed_frame_not_a_shape(stereo_set):
    """A black first view (foreground everywhere under the chroma key) was 'reconstructed'
    into a 1-segment backbone 7 cm from the true one, ok=true."""
    import numpy as np

    from jaxcr.cli.stereo import _read_rgb, load_stereo_dataset
    from jaxcr.stereo.pipeline import StereoFailure, reconstruct_pair

    ds = load_stereo_dataset(stereo_set)
    fr = ds["frames"][0]
    im1, im2 = (_read_rgb(ds["root"] / fr["images"][n]) for n in ds["names"])
    with pytest.raises(StereoFailure, match="covers .* of view 1"):
        reconstruct_pair(np.zeros_like(im1), im2, ds["cam1"], ds["cam2"], ds["config"], None)


def test_stereo_rerun_with_other_options_is_refused(stereo_set, tmp_path):
    """A rerun into the same OUT skipped the frames already in results.jsonl whatever the
    options, so e.g. --segmentation plate silently mixed with earlier chroma results."""
    from jaxcr.cli.stereo import _check_run, load_stereo_dataset
    from jaxcr.errors import InputError

    ds = load_stereo_dataset(stereo_set)
    out = tmp_path / "o"
    out.mkdir()
    _check_run(out, ds)
    _check_run(out, ds)  # same options: continue
    ds["config"].segmentation = "plate"
    with pytest.raises(InputError, match="different options"):
        _check_run(out, ds)
    other = tmp_path / "old"
    (other / "frames").mkdir(parents=True)
    with pytest.raises(InputError, match="without run.json"):
        _check_run(other, ds)


# ----------------------------------------------------------------------------- motion


def test_motion_json_mistyped_fields_are_one_line(tmp_path, capsys):
    """frames[i].x given as a string raised IndexError while formatting its own error message;
    eval_frame true was read as frame 1."""
    import json
    import shutil

    from jaxcr.cli import main
    from jaxcr.errors import InputError
    from jaxcr.io.motion_dataset import load_motion_dataset

    src = tmp_path / "mo"
    assert main(["motion", "synth", "-o", str(src), "--size", "64x48", "--frames", "6"]) == 0
    capsys.readouterr()
    for name, edit, expect in (
        ("x", lambda m: m["frames"][2].update(x="abc"), "field 'frames[2].x': must be a 5 number"),
        ("ev", lambda m: m.update(eval_frame=True), "field 'eval_frame'"),
    ):
        d = tmp_path / name
        shutil.copytree(src, d)
        meta = json.loads((d / "motion.json").read_text())
        edit(meta)
        (d / "motion.json").write_text(json.dumps(meta))
        with pytest.raises(InputError, match=expect.replace("[", r"\[").replace("]", r"\]")):
            load_motion_dataset(d)


# ----------------------------------------------------------------------------- model-object


def test_rgbd_scene_foreign_content_is_one_line(tmp_path, capsys):
    """Each of these was a traceback (ValueError, KeyError, IndexError, AttributeError) in
    `jaxcr model-object SCENE`, or (negative focal length) a 30 s run ending in exit 0."""
    import json
    import shutil

    from jaxcr.cli import main
    from jaxcr.synth.rgbd_tasks import RgbdSimulator, generate_task

    for task in ("1", "2"):  # the generator's own scenes still load
        RgbdSimulator(generate_task(tmp_path / f"t{task}", task, 0, (64, 48)))
    src = tmp_path / "t1"

    def edit(fn):
        def apply(d):
            meta = json.loads((d / "scene.json").read_text())
            meta = fn(meta) or meta
            (d / "scene.json").write_text(json.dumps(meta))

        return apply

    cases = {
        "top": (edit(lambda m: [1]), "top level"),
        "K": (edit(lambda m: m["camera"].update(K="eye")), "field 'camera.K'"),
        "fx": (edit(lambda m: m["camera"]["K"][0].__setitem__(0, -10.0)), "focal lengths"),
        "runs": (edit(lambda m: m.update(runs=[])), "field 'runs'"),
        "kind": (edit(lambda m: m["object"].update(kind="sphere")), "field 'object.kind'"),
        "arm": (edit(lambda m: m["arm"].update(n_sections="three")), "field 'arm.n_sections'"),
        "dir": (edit(lambda m: m["runs"][0].update(direction=0)), "field 'runs[0].direction'"),
        "obs": (lambda d: (d / "obstacles.npy").write_bytes(b"junk"), "obstacles.npy"),
        "tex": (lambda d: (d / "textures" / "face0.png").write_bytes(b""), "image file is empty"),
    }
    for name, (fn, expect) in cases.items():
        d = tmp_path / name
        shutil.copytree(src, d)
        fn(d)
        assert main(["model-object", str(d), "-o", str(tmp_path / f"o_{name}")]) == 2, name
        assert expect in _one_line_error(capsys), name


def test_implausible_intrinsics_are_reported_by_validate(tmp_path):
    """fx = 1e-30 or 1e30 and cx = 1e6 validated as OK; segment then failed every frame with
    'robot out of view' instead of naming the calibration."""
    from jaxcr.io.calibration import check_intrinsics_range

    root = make_dataset(tmp_path / "d", n_frames=1)
    for k, (r, c, v) in enumerate([(0, 0, 1e-30), (1, 1, 1e30), (0, 2, 1e6), (1, 2, -500.0)]):
        d = make_dataset(tmp_path / f"d{k}", n_frames=1)
        edit_json(d, lambda j, r=r, c=c, v=v: j["cameras"]["main"]["K"][r].__setitem__(c, v))
        (err,) = [e for e in validate_dataset(d) if e.frame is None]
        assert err.field == "cameras.main.K" and ("field of view" in str(err) or "far" in str(err))
    assert validate_dataset(root) == []
    # the bounds: 0.1..179 degrees, principal point within one image size
    K = [[100.0, 0, 50], [0, 100.0, 40], [0, 0, 1]]
    check_intrinsics_range(K, 100, 80)
    check_intrinsics_range([[100.0, 0, -99], [0, 100.0, 159], [0, 0, 1]], 100, 80)
    with pytest.raises(Exception, match="field of view"):
        check_intrinsics_range([[0.3, 0, 50], [0, 100.0, 40], [0, 0, 1]], 100, 80)


def test_dataset_json_with_byte_order_mark_or_deep_nesting(tmp_path):
    """A dataset.json saved with a UTF-8 byte-order mark (Notepad) was 'not valid JSON';
    a pathologically nested one was a RecursionError traceback."""
    root = make_dataset(tmp_path / "d", n_frames=1)
    p = root / "dataset.json"
    p.write_bytes(b"\xef\xbb\xbf" + p.read_bytes())
    assert validate_dataset(root) == []
    p.write_text("[" * 100_000 + "]" * 100_000)
    (err,) = validate_dataset(root)
    assert "nested too deeply" in str(err)


def test_segment_joint_values_beyond_float32_fail_the_frame_cleanly(tmp_path):
    """q = 1e300 is finite in float64 but inf in float32: it reached the kinematics (numpy
    overflow warning, then 'kinematics failed'); now the frame fails with the reason."""
    from jaxcr.segmentation.batch import Segmenter
    from jaxcr.segmentation.refine import RefineConfig

    root = make_dataset(tmp_path / "d", n_frames=1)
    edit_json(root, lambda j: j["frames"][0]["q"].__setitem__(0, 1e300))
    ds = load_dataset(root)
    seg = Segmenter(ds, ["main"], RefineConfig(), "none", tmp_path / "o", batch_size=1)
    images, reason = seg._check_frame("000000")
    assert images is None and "float32 range" in reason


def test_bench_counts_are_checked_before_running(capsys):
    """bench fk --batch 0 and bench segment --frames 0 were numpy 'need at least one array to
    stack' tracebacks after the compile; --batch 10000000 ran into the machine's memory."""
    from jaxcr.cli import main

    for argv, expect in (
        (["fk", "--batch", "0"], "--batch must be >= 1"),
        (["fk", "--batch", "10000000"], "--batch must be <= 65536"),
        (["fk", "--repeats", "0"], "--repeats must be >= 1"),
        (["segment", "--frames", "0"], "--frames must be >= 1"),
        (["segment", "--size", "5x5"], "image size must be between"),
    ):
        assert main(["bench", *argv, "-o", "unused.md"]) == 2
        assert expect in _one_line_error(capsys)


def test_synth_never_overwrites_a_foreign_dataset_or_a_run(tmp_path, capsys):
    """`jaxcr synth -o X` replaced X's dataset.json and images/<cam>/<id>.png whatever X
    held (a real dataset, or a segment output whose masks/ it overwrote), exit 0."""
    import json

    from jaxcr.cli import main

    root = make_dataset(tmp_path / "d", n_frames=1)  # meta has no 'generator'
    before = (root / "dataset.json").read_bytes()
    argv = ["synth", "--preset", "orthogonal", "--frames", "1", "--size", "64x48", "--quiet"]
    assert main([*argv, "-o", str(root)]) == 2
    assert "not written by jaxcr synth" in _one_line_error(capsys)
    assert (root / "dataset.json").read_bytes() == before
    run = tmp_path / "run"
    run.mkdir()
    (run / "run.json").write_text(json.dumps({"format": "jaxcr.segment-run/1"}))
    assert main([*argv, "-o", str(run)]) == 2
    assert "run's output" in _one_line_error(capsys)


def test_resume_with_other_config_names_only_the_differing_keys(tmp_path):
    """The refusal printed both whole RefineConfig dicts (~1500 characters) on one line."""
    import json

    from jaxcr.cli.segment import prepare_output
    from jaxcr.errors import InputError

    out = tmp_path / "o"
    out.mkdir()
    info = {"format": "jaxcr.segment-run/1", "dataset": "/d", "cameras": ["main"]}
    cfg = {f"k{i}": i for i in range(30)}
    (out / "run.json").write_text(json.dumps({**info, "config": cfg}))
    (out / "results.jsonl").write_text('{"frame": "a", "ok": true}\n')
    new = {**info, "config": {**cfg, "k3": 4, "new_field": "x"}}
    with pytest.raises(InputError) as exc:
        prepare_output(out, True, False, new)
    msg = str(exc.value)
    assert "k3: 3 -> 4" in msg and "new_field: '(absent)' -> 'x'" in msg
    assert "k4" not in msg and len(msg) < 300
    assert prepare_output(out, True, False, {**info, "config": cfg}) == [{"frame": "a", "ok": True}]


def test_motion_rerun_stopped_early_leaves_no_earlier_report(tmp_path, monkeypatch, capsys):
    """A rerun into the same OUT truncated frames.jsonl but left the earlier run's
    summary.json/report.md/probability maps, which then read as this run's results."""
    from jaxcr.cli import main
    from jaxcr.motion import run as motion_run

    src = tmp_path / "mo"
    assert main(["motion", "synth", "-o", str(src), "--size", "64x48", "--frames", "6"]) == 0
    out = tmp_path / "out"
    out.mkdir()
    (out / "frames.jsonl").write_text("")  # an earlier motion run (OUT must be one)
    stale = ["summary.json", "report.md", "prob_translation.npy", "mask_homography.png"]
    for name in stale:
        (out / name).write_text("earlier run")

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(motion_run, "run_motion", interrupted)
    assert main(["motion", str(src), "-o", str(out), "--no-baseline"]) == 130
    assert not any((out / name).exists() for name in stale)


def test_model_object_rerun_stopped_early_leaves_no_earlier_model(tmp_path, monkeypatch):
    """A rerun that failed or was stopped left the earlier run's model.ply and report.md."""
    from jaxcr.cli import main
    from jaxcr.registration import pipeline
    from jaxcr.synth.rgbd_tasks import generate_task

    scene = generate_task(tmp_path / "s", "1", 0, (64, 48))
    out = tmp_path / "out"
    out.mkdir()
    stale = ["report.md", "report.json", "model.ply", "poses.csv", "partial_1.ply"]
    for name in stale:
        (out / name).write_text("earlier run")

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(pipeline, "build_model", interrupted)
    assert main(["model-object", str(scene), "-o", str(out)]) == 130
    assert not any((out / name).exists() for name in stale)


def test_truncated_png_is_one_line_without_libpng_noise(tmp_path, capfd):
    """A PNG cut short was reported, but libpng also printed 'libpng error: PNG input buffer
    is incomplete' on stderr (a second line); a PNG with data after IEND still reads."""
    import numpy as np

    from jaxcr.errors import InputError
    from jaxcr.io.images import read_image, write_png

    img = np.random.default_rng(0).random((24, 32, 3))
    p = write_png(tmp_path / "a.png", img)
    full = p.read_bytes()
    (tmp_path / "extra.png").write_bytes(full + b"\0" * 2048)
    assert read_image(tmp_path / "extra.png").shape == (24, 32, 3)
    p.write_bytes(full[: len(full) // 2])
    with pytest.raises(InputError, match="truncated PNG: no IEND"):
        read_image(p)
    assert "libpng" not in capfd.readouterr().err


def test_broken_calibration_file_messages_say_what_is_wrong(tmp_path):
    """A truncated FileStorage file was reported as '(<class 'cv2.FileStorage'> returned a
    result with an exception set)'; an empty one likewise."""
    import cv2
    import numpy as np

    from jaxcr.errors import InputError
    from jaxcr.io.calibration import load_camera

    p = tmp_path / "cam.yaml"
    fs = cv2.FileStorage(str(p), cv2.FILE_STORAGE_WRITE)
    fs.write("camera_matrix", np.array([[100.0, 0, 50], [0, 100.0, 40], [0, 0, 1]]))
    fs.write("image_width", 100)
    fs.write("image_height", 80)
    fs.release()
    assert load_camera(p).width == 100
    text = p.read_bytes()
    p.write_bytes(text[: len(text) // 2])
    with pytest.raises(InputError) as exc:
        load_camera(p)
    assert "exception set" not in str(exc.value) and "Parsing error" in str(exc.value)
    p.write_bytes(b"")
    with pytest.raises(InputError, match="calibration file is empty"):
        load_camera(p)


def _png_bomb(path, w, h):
    """A valid 8-bit grey PNG of w x h zero pixels, streamed (never held in memory)."""
    import struct
    import zlib

    def chunk(kind, data):
        return (
            struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
        )

    z = zlib.compressobj(9)
    row = b"\0" * (w + 1)
    idat = b"".join(z.compress(row) for _ in range(h)) + z.flush()
    ihdr = struct.pack(">IIBBBBB", w, h, 8, 0, 0, 0, 0)
    data = b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", idat)
    path.write_bytes(data + chunk(b"IEND", b""))


def test_huge_declared_images_are_never_decoded(tmp_path):
    """A 12000x12000 PNG of zeros is 140 kB on disk; validate decoded it (and would decode
    a 30000x30000 one into ~11 GB of float32). JPEG sizes are now read from the header too."""
    import cv2
    import numpy as np

    from jaxcr.errors import InputError
    from jaxcr.io.images import MAX_PIXELS, header_size, read_image

    bomb = tmp_path / "bomb.png"
    _png_bomb(bomb, 12000, 12000)
    assert bomb.stat().st_size < 1_000_000 and 12000**2 > MAX_PIXELS
    with pytest.raises(InputError, match="exceeds the 134217728 pixel limit"):
        read_image(bomb)
    root = make_dataset(tmp_path / "d", n_frames=1)
    img = root / "images" / "main" / "000000.png"
    _png_bomb(img, 4000, 3000)  # under the limit, but not the camera's size
    (err,) = validate_dataset(root)
    assert "size 4000x3000 does not match camera 'main' (96x72)" in str(err)
    # JPEG headers (baseline and progressive) agree with OpenCV's decoded size
    im = (np.random.default_rng(0).random((37, 53, 3)) * 255).astype(np.uint8)
    for flags in ([], [cv2.IMWRITE_JPEG_PROGRESSIVE, 1]):
        ok, buf = cv2.imencode(".jpg", im, flags)
        assert header_size(buf.tobytes()) == (53, 37)


def test_manifold_train_reports_frames_the_loader_rejected(tmp_path, capsys):
    """A training frame with a missing image vanished: the summary said '23/23 frames' for
    a 24-frame dataset and nothing named the frame."""
    from jaxcr.cli import main

    # test_cli_rough_edges.py's manifold size and training options (160x120, --bins 24 --step
    # 0.05): its programs and examples/eigen.py's colour k-means (160x120), loaded from the
    # run's cache instead of compiled for 256x192 here
    d = tmp_path / "train"
    argv = ["manifold", "synth", "-o", str(d), "--frames", "12", "--size", "160x120"]
    assert main(argv) == 0
    (d / "images" / "left" / "000003.png").unlink()
    capsys.readouterr()
    args = ["manifold", "train", str(d), "-o", str(tmp_path / "m.npz"), "--bins", "24", "--step",
            "0.05"]  # fmt: skip
    assert main(args) == 1
    out, err = capsys.readouterr()
    assert "/12 frames" in out
    assert "1 bad frame(s) not used" in err and "000003" in err
