"""Dataset validation, loading and writing (format jaxcr.dataset/1)."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

from jaxcr.errors import InputError, InputErrors
from jaxcr.io.calibration import save_camera
from jaxcr.io.dataset import FORMAT, DatasetWriter, load_dataset, validate_dataset
from jaxcr.io.images import read_image, read_mask, write_png
from tests.helpers.datasets import ROBOT, H, W, camera, edit_json, make_dataset


@pytest.fixture
def ds(tmp_path):
    return make_dataset(tmp_path / "ds")


def test_writer_then_load_round_trip(tmp_path):
    rng = np.random.default_rng(3)
    imgs = [rng.random((H, W, 3)) for _ in range(2)]
    masks = [im[..., 1] > 0.4 for im in imgs]
    cl = rng.normal(size=(8, 3))
    with DatasetWriter(tmp_path / "d", "rt", ROBOT, {"main": camera()}, meta={"seed": 7}) as w:
        assert not (tmp_path / "d" / "dataset.json").exists()  # written last
        ids = [
            w.add_frame(
                "a0",
                [1.0, 2.0],
                {"main": imgs[0]},
                masks={"main": masks[0]},
                full_masks={"main": masks[0]},
                occluders={"main": ~masks[0]},
                tags=["x", "y"],
                truth={"centreline": cl, "tip_error_mm": 0.5},
            ),
            w.add_frame(12, [3.0, 4.0], {"main": imgs[1]}),
        ]
    assert ids == ["a0", "000012"]
    d = load_dataset(tmp_path / "d")
    assert d.name == "rt" and d.meta == {"seed": 7} and d.bad_frames == {}
    assert d.robot is not None and d.robot.n_joints == 2
    assert [f.id for f in d.frames] == ids
    f0 = d.frame("a0")
    np.testing.assert_array_equal(f0.q, [1.0, 2.0])
    np.testing.assert_allclose(f0.load_image("main"), imgs[0], atol=0.5 / 255 + 1e-6)
    np.testing.assert_array_equal(f0.load_mask("main"), masks[0])
    np.testing.assert_array_equal(f0.load_full_mask("main"), masks[0])
    np.testing.assert_array_equal(f0.load_occluder("main"), ~masks[0])
    np.testing.assert_array_equal(f0.load_truth(), cl)
    assert f0.load_truth("tip_error_mm") == 0.5 and f0.tags == ["x", "y"]
    assert d.frames[1].load_mask("main") is None
    cam = d.cameras["main"]
    np.testing.assert_allclose(
        np.asarray(cam.T_cam_robot), np.asarray(camera().T_cam_robot), atol=1e-7
    )
    with pytest.raises(InputError, match="no image for camera"):
        f0.load_image("other")
    assert validate_dataset(tmp_path / "d") == []
    assert validate_dataset(tmp_path / "d" / "dataset.json") == []


def test_writer_rejects_bad_calls(tmp_path):
    w = DatasetWriter(tmp_path / "d", "x", ROBOT, {"main": camera()})
    img = np.zeros((H, W, 3))
    with pytest.raises(ValueError, match="does not match camera size"):
        w.add_frame(0, [0, 0], {"main": np.zeros((H + 1, W, 3))})
    with pytest.raises(ValueError, match="unknown camera"):
        w.add_frame(0, [0, 0], {"side": img})
    with pytest.raises(ValueError, match="NaN"):
        w.add_frame(0, [np.nan, 0], {"main": img})
    w.add_frame(0, [0, 0], {"main": img})
    with pytest.raises(ValueError, match="duplicate"):
        w.add_frame("000000", [0, 0], {"main": img})
    with pytest.raises(ValueError, match="invalid frame id"):
        w.add_frame("a/b", [0, 0], {"main": img})
    w.close()
    with pytest.raises(FileExistsError):
        DatasetWriter(tmp_path / "d", "x", ROBOT, {"main": camera()})
    # overwrite removes the old dataset.json first: an interrupted rewrite is not "complete"
    w2 = DatasetWriter(tmp_path / "d", "x", ROBOT, {"main": camera()}, overwrite=True)
    assert not (tmp_path / "d" / "dataset.json").exists()
    del w2


def test_interrupted_writer_leaves_no_dataset_json(tmp_path):
    with pytest.raises(RuntimeError):
        with DatasetWriter(tmp_path / "d", "x", ROBOT, {"main": camera()}) as w:
            w.add_frame(0, [0, 0], {"main": np.zeros((H, W, 3))})
            raise RuntimeError("crash")
    assert not (tmp_path / "d" / "dataset.json").exists()
    assert (tmp_path / "d" / "images" / "main" / "000000.png").exists()
    errs = validate_dataset(tmp_path / "d")
    assert len(errs) == 1 and "missing dataset.json" in str(errs[0])


def test_camera_file_reference(tmp_path):
    root = tmp_path / "d"
    root.mkdir()
    save_camera(camera(), root / "calib.yaml")
    with DatasetWriter(root, "x", ROBOT, {"main": "calib.yaml"}) as w:
        w.add_frame(0, [0, 0], {"main": np.zeros((H, W, 3))})
    assert json.loads((root / "dataset.json").read_text())["cameras"]["main"] == "calib.yaml"
    d = load_dataset(root)
    np.testing.assert_allclose(np.asarray(d.cameras["main"].K), np.asarray(camera().K), atol=1e-6)


def test_robot_file_reference(ds):
    (ds / "robot.json").write_text(json.dumps(ROBOT))
    edit_json(ds, lambda d: d.update(robot="robot.json"))
    assert validate_dataset(ds) == []
    assert load_dataset(ds).robot.n_joints == 2


# ------------------------------------------------------------------------------ bad inputs


def _one(errs, **expect):
    """The single error in ``errs``, checking its attributes and that it is one line."""
    assert len(errs) == 1, [str(e) for e in errs]
    e = errs[0]
    for k, v in expect.items():
        got = getattr(e, k)
        if k == "message":
            assert v in got, (got, v)
        else:
            assert got == v, (k, got, v)
    assert "\n" not in str(e)
    return e


def test_missing_dataset_json_and_folder(tmp_path):
    _one(validate_dataset(tmp_path), message="missing dataset.json", file=str(tmp_path))
    _one(validate_dataset(tmp_path / "nope"), message="not found")
    with pytest.raises(InputErrors, match="missing dataset.json"):
        load_dataset(tmp_path)


@pytest.mark.parametrize(
    "mutate, field, message",
    [
        (lambda d: d.pop("format"), "format", "missing required key"),
        (lambda d: d.update(format="jaxcr.dataset/2"), "format", "unsupported format"),
        (lambda d: d.pop("robot"), "robot", "missing"),
        (lambda d: d.update(robot={"kind": "tentacle"}), "robot.kind", "unknown robot kind"),
        (lambda d: d.update(robot={"sections": []}), "robot.kind", "missing"),
        (lambda d: d.update(robot="nothere.json"), "robot", "robot file not found"),
        (lambda d: d.pop("cameras"), "cameras", "missing"),
        (lambda d: d.update(cameras={}), "cameras", "non-empty"),
        (lambda d: d.pop("frames"), "frames", "missing"),
        (lambda d: d.update(frams=[]), "frams", "unknown key"),
        (lambda d: d["cameras"]["main"]["K"].pop(), "cameras.main.K", "3x3"),
        (lambda d: d["cameras"]["main"].pop("size"), "cameras.main.image_width", "missing"),
        (lambda d: d["cameras"]["main"]["K"][0].__setitem__(0, 0.0), "cameras.main.K", "positive"),
        (
            lambda d: d["cameras"].update(main="calib/none.yaml"),
            "cameras.main",
            "camera file not found",
        ),
        (
            lambda d: d["background_images"].update(side=["x.png"]),
            "background_images.side",
            "unknown camera",
        ),
        (
            lambda d: d["background_images"].update(main=["x.png"]),
            "background_images.main",
            "file not found",
        ),
    ],
)
def test_dataset_level_problems(ds, mutate, field, message):
    edit_json(ds, mutate)
    errs = validate_dataset(ds)
    # a broken camera also flags every frame that uses it; the dataset-level error comes first
    e = errs[0]
    assert e.field == field, [str(x) for x in errs]
    assert message in e.message
    assert e.frame is None
    assert "\n" not in str(e)
    with pytest.raises(InputErrors):
        load_dataset(ds)


def test_wrong_format_version_message(ds):
    edit_json(ds, lambda d: d.update(format="jaxcr.dataset/9"))
    e = _one(validate_dataset(ds), field="format")
    assert str(e) == (
        f"{ds / 'dataset.json'}: field 'format': unsupported format 'jaxcr.dataset/9'; "
        f"this jaxcr reads '{FORMAT}'"
    )


def _edit_frame(i, fn):
    return lambda d: fn(d["frames"][i])


@pytest.mark.parametrize(
    "mutate, frame, field, message",
    [
        (_edit_frame(1, lambda f: f.pop("id")), "#1", "id", "missing frame id"),
        (
            _edit_frame(1, lambda f: f.update(id="000000")),
            "000000 (#1)",
            "id",
            "duplicate frame id",
        ),
        (_edit_frame(1, lambda f: f.pop("q")), "000001", "q", "missing required key"),
        (_edit_frame(1, lambda f: f.update(q=[1.0])), "000001", "q", "expected 2 joint values"),
        (_edit_frame(1, lambda f: f.update(q=[1.0, 2.0, 3.0])), "000001", "q", "got 3"),
        (_edit_frame(1, lambda f: f.update(q=[1.0, "a"])), "000001", "q", "list of numbers"),
        (_edit_frame(1, lambda f: f.pop("images")), "000001", "images", "missing required key"),
        (_edit_frame(1, lambda f: f.update(images={})), "000001", "images", "non-empty"),
        (
            _edit_frame(1, lambda f: f["images"].update(main="images/main/zzz.png")),
            "000001",
            "images.main",
            "file not found",
        ),
        (
            _edit_frame(1, lambda f: f["images"].update(side="images/main/000001.png")),
            "000001",
            "images.side",
            "unknown camera",
        ),
        (
            _edit_frame(1, lambda f: f["masks"].update(side="masks/main/000001.png")),
            "000001",
            "masks.side",
            "unknown camera",
        ),
        (_edit_frame(1, lambda f: f.update(tags="a")), "000001", "tags", "list of strings"),
        (
            _edit_frame(1, lambda f: f["truth"].update(centreline="truth/nope.npy")),
            "000001",
            "truth.centreline",
            "file not found",
        ),
        (_edit_frame(1, lambda f: f.update(qq=[])), "000001", "qq", "unknown key"),
    ],
)
def test_frame_level_problems(ds, mutate, frame, field, message):
    edit_json(ds, mutate)
    _one(
        validate_dataset(ds),
        frame=frame,
        field=field,
        message=message,
        file=str(ds / "dataset.json"),
    )
    d = load_dataset(ds)
    assert frame in d.bad_frames and message in d.bad_frames[frame]
    assert len(d.frames) == 2  # the others are still usable
    with pytest.raises(InputErrors) as ei:
        load_dataset(ds, strict=True)
    assert len(ei.value.errors) == 1


def test_nan_joint_written_by_hand(ds):
    # JSON has no NaN, but Python's json writes/reads it; labs' scripts produce it.
    p = ds / "dataset.json"
    p.write_text(p.read_text().replace('"q": [6.0, 0.1]', '"q": [NaN, 0.1]'))
    e = _one(validate_dataset(ds), frame="000001", field="q")
    assert "non-finite" in e.message and "[0]" in e.message


def test_corrupt_png_and_size_mismatch(ds):
    # a truncated PNG: valid header (the fast path sees the right size), broken data
    p = ds / "images" / "main" / "000001.png"
    p.write_bytes(p.read_bytes()[:200])
    write_png(ds / "masks" / "main" / "000002.png", np.zeros((H, W + 4), bool))
    write_png(ds / "images" / "main" / "000000.png", np.zeros((H - 2, W, 3), np.uint8))
    errs = validate_dataset(ds)
    assert len(errs) == 3, [str(e) for e in errs]
    by_frame = {e.frame: e for e in errs}
    e = by_frame["000001"]
    assert e.field == "images.main" and e.file == str(ds / "images/main/000001.png")
    assert "not a readable image" in e.message
    e = by_frame["000002"]
    assert (
        e.field == "masks.main"
        and f"{W + 4}x{H} does not match camera 'main' ({W}x{H})" in e.message
    )
    e = by_frame["000000"]
    assert e.field == "images.main" and "does not match" in e.message
    d = load_dataset(ds)
    assert sorted(d.bad_frames) == ["000000", "000002"]  # the fast path reads PNG headers only
    with pytest.raises(InputError, match="not a readable image") as ei:
        d.frame("000001").load_image("main")  # found lazily, naming file, frame and field
    assert (ei.value.file, ei.value.frame, ei.value.field) == (str(p), "000001", "images.main")
    d = load_dataset(ds, decode_images=True)
    assert sorted(d.bad_frames) == ["000000", "000001", "000002"] and d.frames == []


def test_every_problem_reported_at_once(ds):
    def mutate(d):
        d["format"] = "old"
        d["frames"][0]["q"] = [1.0]
        d["frames"][1]["images"]["main"] = "missing.png"
        d["frames"][2].pop("id")

    edit_json(ds, mutate)
    errs = validate_dataset(ds)
    assert [(e.frame, e.field) for e in errs] == [
        (None, "format"),
        ("000000", "q"),
        ("000001", "images.main"),
        ("#2", "id"),
    ]


def test_invalid_json(ds):
    (ds / "dataset.json").write_text("{ not json")
    _one(validate_dataset(ds), file=str(ds / "dataset.json"), message="not valid JSON")


def test_lazy_loading_does_not_read_images(ds, monkeypatch):
    import jaxcr.io.dataset as mod

    calls = []
    monkeypatch.setattr(mod, "read_image", lambda p: calls.append(p))
    load_dataset(ds)
    assert calls == []
    assert len(os.listdir(ds / "images" / "main")) == 3


def test_truth_shape_checked(ds):
    np.save(ds / "truth" / "000001.npy", np.zeros((5, 2)))
    _one(validate_dataset(ds), frame="000001", field="truth.centreline", message="(N, 3)")


def test_read_back_matches_independent_reader(ds):
    d = load_dataset(ds)
    f = d.frames[0]
    np.testing.assert_array_equal(read_image(f.images["main"]), f.load_image("main"))
    np.testing.assert_array_equal(read_mask(f.masks["main"]), f.load_mask("main"))


def _ctr_dataset(tmp_path, q):
    from jaxcr.kinematics.ctr import TEST_CTR

    with DatasetWriter(tmp_path / "c", "ctr", TEST_CTR, {"main": camera()}) as w:
        w.add_frame(0, q, {"main": np.zeros((H, W, 3))})
    return tmp_path / "c"


def test_ctr_robot_joint_count(tmp_path):
    root = _ctr_dataset(tmp_path, [0.0] * 5)
    e = _one(validate_dataset(root), frame="000000", field="q")
    assert "expected 6 joint values" in e.message  # 3 tubes: 3 rotations + 3 translations
    root2 = _ctr_dataset(tmp_path / "ok", [0.0, 0.1, 0.2, -0.01, -0.02, -0.03])
    assert validate_dataset(root2) == []
    assert load_dataset(root2).robot.n_joints == 6


def test_robot_kind_only_when_model_module_missing(tmp_path, monkeypatch):
    """If a kind's module is absent from the build, only 'kind' is checked (robot=None)."""
    import jaxcr.kinematics.robots as robots

    def missing(kind):
        raise ModuleNotFoundError(f"No module named 'jaxcr.kinematics.{kind}'")

    monkeypatch.setattr(robots, "_model_class", missing)
    root = _ctr_dataset(tmp_path, [0.0] * 5)
    assert validate_dataset(root) == []  # joint count cannot be checked without the model
    assert load_dataset(root).robot is None
    edit_json(root, lambda d: d["robot"].update(kind="ctrx"))
    _one(validate_dataset(root), field="robot.kind", message="unknown robot kind")
