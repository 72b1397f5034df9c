"""Issue 17 item 3: every size, count and level has a ceiling (and floor) from jaxcr.limits,
refused with exit 2 and one line naming the flag (or file and field) and the limit, before
any work. "Before any work" is checked by replacing the work function with one that fails
the test if called (a run that started would hang, or end in a MemoryError traceback)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from jaxcr.cli import main
from jaxcr.errors import InputError
from tests.helpers.datasets import make_dataset


def _one_line(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "Traceback" not in err[0], err
    return err[0]


def _forbid(monkeypatch, module: str, name: str) -> None:
    def started(*a, **k):
        raise AssertionError(f"{module}.{name} was called: work started before the check")

    monkeypatch.setattr(f"{module}.{name}", started)


def test_limits_are_derived_from_the_stated_budget():
    """The ceilings follow from their documented derivations (recomputed here by hand)."""
    from jaxcr import limits as L

    for kind, bpp in L.RENDER_BYTES_PER_PIXEL.items():
        assert L.MAX_PIXELS[kind] == (4 << 30) // bpp
        # the default sizes of every renderer are inside their ceiling
    assert 640 * 480 <= min(L.MAX_PIXELS.values())
    assert 1024 * 768 <= L.MAX_PIXELS["manifold synth"]  # manifold synth's default
    # float32: 2^13 rad is where the spacing reaches 2^-10 rad
    assert np.spacing(np.float32(L.MAX_ANGLE)) == np.float32(2.0**-10)
    assert L.FLOAT32_MAX == np.finfo(np.float32).max
    with np.errstate(over="ignore"):
        assert np.isinf(np.float32(1e308)) and 1e308 > L.FLOAT32_MAX
    # pyramid levels: 320x240 -> 240 >> 4 = 15 >= 8 but 240 >> 5 = 7 < 8: 5 levels
    assert L.max_levels(240) == 5 and L.max_levels(8) == 1 and L.max_levels(15) == 1
    assert L.max_levels(16) == 2


@pytest.mark.parametrize(
    ("argv", "target", "field"),
    [
        (["stereo", "synth", "--size", "100000x100000"],
         ("jaxcr.synth.stereo_ctr", "generate_stereo_set"), "'--size'"),
        (["motion", "synth", "--size", "100000x100000"],
         ("jaxcr.synth.motion_scenes", "generate_motion_video"), "'--size'"),
        (["model-object", "synth", "--size", "100000x100000"],
         ("jaxcr.synth.rgbd_tasks", "generate_task"), "'size'"),
        (["synth", "--preset", "orthogonal", "--size", "100000x100000"],
         ("jaxcr.synth.generate", "generate"), "'size'"),
        (["synth", "--preset", "orthogonal", "--size", "4000x4000"],  # sides ok, pixels not
         ("jaxcr.synth.generate", "generate"), "'size'"),
        (["manifold", "synth", "--size", "8192x8192", "--split", "train"],
         ("jaxcr.synth.irep", "generate_irep"), "'size'"),
    ],
)  # fmt: skip
def test_huge_sizes_are_refused_before_work(tmp_path, monkeypatch, capsys, argv, target, field):
    """stereo/motion synth at 100000x100000 ended in a MemoryError traceback, model-object
    synth exited 0 with a scene no one can render."""
    _forbid(monkeypatch, *target)
    assert main([*argv, "-o", str(tmp_path / "o")]) == 2
    line = _one_line(capsys)
    assert f"field {field}" in line and "over the limit of 8192 pixels per side" in line, line
    assert "bytes per pixel" in line
    assert not (tmp_path / "o").exists()


def test_model_object_synth_floor_is_checked_before_out_is_created(tmp_path, monkeypatch, capsys):
    """The audit (experiments/contract_audit.py, item 3) found `model-object synth --size 8x8`
    refused only by the scene generator, after OUT had been created and claimed: an owned,
    empty folder was left behind. The 32x24 floor is now checked with the ceiling."""
    _forbid(monkeypatch, "jaxcr.synth.rgbd_tasks", "generate_task")
    assert main(["model-object", "synth", "--size", "8x8", "-o", str(tmp_path / "o")]) == 2
    line = _one_line(capsys)
    assert "field 'size'" in line and "the minimum is 32x24" in line, line
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize(
    ("argv", "target", "expect"),
    [
        (["synth", "--preset", "orthogonal", "--cameras", "100000"],
         ("jaxcr.synth.generate", "generate"), "field 'cameras': must be between 1 and 20"),
        (["synth", "--preset", "orthogonal", "--frames", "1000000"],
         ("jaxcr.synth.generate", "generate"), "field 'frames': must be between 1 and 999999"),
        (["stereo", "synth", "--frames", "10000000"],
         ("jaxcr.synth.stereo_ctr", "generate_stereo_set"), "'--frames': must be between 1"),
        (["motion", "synth", "--frames", "1000000"],
         ("jaxcr.synth.motion_scenes", "generate_motion_video"), "between 6 and 999999"),
        (["manifold", "synth", "--frames", "2000000", "--split", "train"],
         ("jaxcr.synth.irep", "generate_irep"), "field 'frames': must be between 1"),
    ],
)  # fmt: skip
def test_counts_are_refused_before_work(tmp_path, monkeypatch, capsys, argv, target, expect):
    """synth --cameras 100000 hung with no output (100000 views rendered per frame)."""
    _forbid(monkeypatch, *target)
    assert main([*argv, "-o", str(tmp_path / "o")]) == 2
    line = _one_line(capsys)
    assert expect in line, line


@pytest.mark.parametrize(
    ("extra", "expect"),
    [
        (["--levels", "30"], "field 'levels': must be between 1 and 4"),  # 72 >> 3 = 9 >= 8
        (["--levels", "0"], "field 'levels': must be between 1 and 4"),
        (["--max-steps", "1000000000"], "field 'max-steps': must be between 1 and 3000"),
        (["--basis", "100000"], "field 'basis': must be between 1 and"),
        (["--batch-size", "100000000"], "field 'batch-size': must be between 1 and"),
        (["--g-cam-rel", "nan"], "field 'g-cam-rel': must be a finite number >= 0, got nan"),
        (["--prior-weight", "inf"], "field 'prior-weight'"),
    ],
)
def test_segment_levels_and_counts_are_refused_before_work(tmp_path, monkeypatch, capsys,
                                                           extra, expect):  # fmt: skip
    """segment --levels 30 compiled and then hung with no output (a 1-pixel pyramid level)."""
    root = make_dataset(tmp_path / "d", n_frames=1)  # 96x72 images
    _forbid(monkeypatch, "jaxcr.segmentation.batch", "Segmenter")
    assert main(["segment", str(root), "-o", str(tmp_path / "o"), "--quiet", *extra]) == 2
    assert expect in _one_line(capsys)
    assert not (tmp_path / "o").exists()


@pytest.fixture(scope="module")
def motion_set(tmp_path_factory):
    from jaxcr.synth.motion_scenes import generate_motion_video

    d = tmp_path_factory.mktemp("motion") / "m"
    generate_motion_video(d, "pushed_static", seed=0, size=(64, 48), n_frames=8)
    return d


@pytest.mark.parametrize(
    ("edit", "expect"),
    [
        (lambda m: m["frames"][3]["x"].__setitem__(1, 1e308),
         "frame 3: field 'frames[3].x': 1 value(s) over 8192 in magnitude"),
        (lambda m: m["frames"][0]["x"].__setitem__(0, 1e5), "over 8192 in magnitude"),
        (lambda m: m["P"][0].__setitem__(3, 1e39), "field 'P': 1 value(s) over"),
        (lambda m: m["arm"].__setitem__("links", [0.3, 1e39, 0.1]), "field 'arm.links'"),
        (lambda m: m["arm"].__setitem__("base_height", 1e300), "field 'arm.base_height'"),
    ],
)  # fmt: skip
def test_motion_values_beyond_float32_are_refused(motion_set, tmp_path, monkeypatch, capsys,
                                                  edit, expect):  # fmt: skip
    """A joint value of 1e308 was accepted (finite in float64) and became inf in float32."""
    import shutil

    d = tmp_path / "m"
    shutil.copytree(motion_set, d)
    meta = json.loads((d / "motion.json").read_text())
    edit(meta)
    (d / "motion.json").write_text(json.dumps(meta))
    _forbid(monkeypatch, "jaxcr.motion.run", "run_motion")
    assert main(["motion", str(d), "-o", str(tmp_path / "o")]) == 2
    line = _one_line(capsys)
    assert "motion.json" in line and expect in line, line


@pytest.mark.parametrize("flag", ["--lambda", "--prior-frames", "--threshold"])
@pytest.mark.parametrize("value", ["nan", "inf"])
def test_motion_float_flags_refuse_nan_and_inf(motion_set, tmp_path, monkeypatch, capsys,
                                               flag, value):  # fmt: skip
    _forbid(monkeypatch, "jaxcr.motion.run", "run_motion")
    assert main(["motion", str(motion_set), "-o", str(tmp_path / "o"), flag, value]) == 2
    assert f"field '{flag}': must be a finite number" in _one_line(capsys)


@pytest.fixture(scope="module")
def rgbd_scene(tmp_path_factory):
    from jaxcr.synth.rgbd_tasks import generate_task

    d = tmp_path_factory.mktemp("rgbd") / "task1"
    generate_task(d, "1", 0, (64, 48))
    return d


@pytest.mark.parametrize("bad", ["nan", "some_nan", "inf", "huge"])
def test_model_object_refuses_non_finite_obstacles(rgbd_scene, tmp_path, capsys, bad):
    """An all-NaN obstacle cloud was accepted: the planner then avoided nothing."""
    import shutil

    from jaxcr.synth.rgbd_tasks import RgbdSimulator

    d = tmp_path / "s"
    shutil.copytree(rgbd_scene, d)
    pts = np.load(d / "obstacles.npy", allow_pickle=False).astype(np.float64)
    if bad == "nan":
        pts[:] = np.nan
    elif bad == "some_nan":
        pts[5, 1] = np.nan
    elif bad == "inf":
        pts[0, 0] = -np.inf
    else:
        pts[2, 2] = 1e39  # float32 would be inf
    np.save(d / "obstacles.npy", pts)
    with pytest.raises(InputError) as exc:
        RgbdSimulator(d)
    assert "obstacles.npy" in str(exc.value)
    assert main(["model-object", str(d), "-o", str(tmp_path / "o")]) == 2
    line = _one_line(capsys)
    assert "obstacles.npy" in line and "field 'points'" in line, line


def test_model_object_scene_size_is_limited(rgbd_scene, tmp_path, capsys):
    import shutil

    d = tmp_path / "s"
    shutil.copytree(rgbd_scene, d)
    meta = json.loads((d / "scene.json").read_text())
    meta["camera"]["width"] = meta["camera"]["height"] = 100000
    (d / "scene.json").write_text(json.dumps(meta))
    assert main(["model-object", str(d), "-o", str(tmp_path / "o")]) == 2
    line = _one_line(capsys)
    assert "scene.json" in line and "camera.width" in line and "over the limit" in line


@pytest.mark.parametrize(
    "argv",
    [
        ["--seed", str(2**32)],
        ["--seed", "99999999999999999999999"],
    ],
)
def test_seed_ceiling(argv, tmp_path, capsys):
    """Seeds beyond 32 bits collide in JAX's key (PRNGKey(2**40) == PRNGKey(0)) or overflow."""
    with pytest.raises(SystemExit) as exc:
        main(["synth", "--preset", "orthogonal", "-o", str(tmp_path / "o"), *argv])
    assert exc.value.code == 2
    assert "--seed: expected a non-negative integer <= 4294967295" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("kw", "field"),
    [({"smoothing": float("nan")}, "smoothing"), ({"smoothing": float("inf")}, "smoothing"),
     ({"step": float("nan")}, "step"), ({"step": 0.0}, "step"), ({"step": -1.0}, "step")],
)  # fmt: skip
def test_manifold_train_options_refuse_nan(kw, field):
    """manifold train --smoothing nan trained a model and exited 0."""
    from jaxcr.eigen.model import TrainConfig

    with pytest.raises(InputError) as exc:
        TrainConfig(**kw).check()
    assert exc.value.field == field


def test_manifold_train_step_ceiling_is_checked_before_any_image(tmp_path, monkeypatch, capsys):
    """The audit (experiments/contract_audit.py, item 3) found `manifold train --step 1e-9`
    refused only after the colour model and every frame's contours were computed (a progress
    line, then the error: two lines, work done). The grid is now checked on the dataset's
    parameters before any image is read."""
    from jaxcr.synth.irep import generate_irep

    generate_irep(tmp_path / "d", 3, "train", 0, (32, 24), progress=False)
    _forbid(monkeypatch, "jaxcr.eigen.colour", "fit_colour_model")
    model = tmp_path / "m.npz"
    assert main(["manifold", "train", str(tmp_path / "d"), "-o", str(model), "--step", "1e-9"]) == 2
    line = _one_line(capsys)
    assert "field 'step'" in line and "over the limit of 5000000" in line, line
    assert not model.exists()
    # --neighbours over the grid's points (an upper bound of the manifold's) likewise
    assert main(["manifold", "train", str(tmp_path / "d"), "-o", str(model),
                 "--neighbours", "1000000000"]) == 2  # fmt: skip
    line = _one_line(capsys)
    assert "field 'neighbours': must be at most the manifold's points" in line, line
    assert not model.exists()
    # a model folder that cannot be written is refused first too (the audit's item 6: a
    # read-only folder failed after every frame's contours); a file stands in for the folder
    # (root ignores a read-only mode)
    (tmp_path / "file").write_text("")
    bad = tmp_path / "file" / "m.npz"
    assert main(["manifold", "train", str(tmp_path / "d"), "-o", str(bad)]) == 2
    line = _one_line(capsys)
    assert "model folder exists and is not a folder" in line and str(tmp_path / "file") in line


def test_manifold_step_grid_ceiling(monkeypatch):
    """A tiny --step resampled a grid of billions of points; refused before the spline fit."""
    from jaxcr.eigen import manifold as M
    from jaxcr.limits import MAX_MANIFOLD_POINTS

    _forbid(monkeypatch, "jaxcr.eigen.manifold", "fit_tps")
    psi = np.array([[0.0, 0.0], [1.0, 3.0], [0.5, 1.0]])
    # grid (floor(1 / s) + 1) * (floor(3 / s) + 1) points: s = 1e-3 gives 1001 * 3001 = 3.0e6
    # (under the ceiling, so the forbidden fit is reached), s = 1e-4 gives 3.0e8 (refused)
    assert 1001 * 3001 < MAX_MANIFOLD_POINTS < 10001 * 30001
    with pytest.raises(AssertionError, match="work started"):
        M.build_manifold(psi, np.zeros((3, 2)), 1e-3)
    with pytest.raises(InputError) as exc:
        M.build_manifold(psi, np.zeros((3, 2)), 1e-4)
    assert exc.value.field == "step" and f"over the limit of {MAX_MANIFOLD_POINTS}" in str(
        exc.value
    )


def test_bench_repeats_ceiling(tmp_path, monkeypatch, capsys):
    """bench fk --repeats 1000000000 ran silently for days."""
    _forbid(monkeypatch, "jaxcr.cli.bench", "find_provider")
    assert main(["bench", "fk", "--repeats", "1000000000", "-o", str(tmp_path / "b.md")]) == 2
    assert "field 'repeats': must be between 1 and 1000" in _one_line(capsys)


@pytest.mark.parametrize("rgb", ["nan,0,0", "5,0,0", "0,-1,0"])
def test_manifold_marker_rgb_must_be_a_colour(tmp_path, monkeypatch, capsys, rgb):
    """--marker-rgb nan,0,0 trained a model on a colour no pixel has and exited 0."""
    root = make_dataset(tmp_path / "d", n_frames=1)
    _forbid(monkeypatch, "jaxcr.eigen.colour", "fit_colour_model")
    argv = ["manifold", "train", str(root), "-o", str(tmp_path / "m.npz"), "--cameras"]
    assert main([*argv, "main,main", "--marker-rgb", rgb]) == 2
    assert "field 'marker-rgb': marker colour must be r,g,b in [0, 1]" in _one_line(capsys)


@pytest.mark.parametrize("flag", ["--superpixel-step", "--flow-step"])
def test_motion_grid_steps_at_most_the_frame(motion_set, tmp_path, monkeypatch, capsys, flag):
    """A grid step over the frame's shorter side (48 px here) leaves one cell."""
    _forbid(monkeypatch, "jaxcr.motion.run", "run_motion")
    assert main(["motion", str(motion_set), "-o", str(tmp_path / "o"), flag, "1000000000"]) == 2
    assert f"field '{flag}': must be between 0 and 48" in _one_line(capsys)
