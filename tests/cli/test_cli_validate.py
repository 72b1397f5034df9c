"""``jaxcr validate``: exit codes and one-line messages through ``jaxcr.cli.main``."""

from __future__ import annotations

import json

import numpy as np
import pytest

from jaxcr.cli import main
from tests.helpers.datasets import edit_json, make_dataset


@pytest.fixture
def ds(tmp_path):
    return make_dataset(tmp_path / "ds", n_frames=2)


def test_clean_dataset_exits_0(ds, capsys, tmp_path):
    code = main(["validate", str(ds), "-o", str(tmp_path / "rep" / "r.json")])
    out = capsys.readouterr().out
    assert code == 0
    assert (
        out.strip()
        .splitlines()[-1]
        .endswith("OK; robot constant_curvature; cameras main; frames 2 (2 OK, 0 with problems)")
    )
    rep = json.loads((tmp_path / "rep" / "r.json").read_text())
    assert rep["ok"] is True and rep["problems"] == [] and rep["n_frames"] == 2


def _run(argv, capsys):
    code = main(argv)
    cap = capsys.readouterr()
    assert "Traceback" not in cap.out + cap.err
    return code, cap.out.strip().splitlines()


@pytest.mark.parametrize(
    "mutate, expect",
    [
        (
            lambda d: d["frames"][0].update(q=[1.0]),
            "frame 000000: field 'q': expected 2 joint values",
        ),
        (lambda d: d["frames"][1].pop("id"), "frame #1: field 'id': missing frame id"),
        (lambda d: d.update(format="jaxcr.dataset/0"), "field 'format': unsupported format"),
        (
            lambda d: d["cameras"]["main"].update(K=[[1.0, 0.0], [0.0, 1.0]]),
            "field 'cameras.main.K': expected a 3x3 matrix",
        ),
        (lambda d: d.pop("robot"), "field 'robot': missing required key"),
    ],
)
def test_problem_lines_and_exit_2(ds, capsys, mutate, expect):
    edit_json(ds, mutate)
    code, lines = _run(["validate", str(ds)], capsys)
    assert code == 2
    assert any(expect in ln and str(ds) in ln for ln in lines), lines
    assert "problem(s)" in lines[-1]


def test_nan_joint_and_corrupt_png(ds, capsys, tmp_path):
    p = ds / "dataset.json"
    p.write_text(p.read_text().replace('"q": [5.0, 0.0]', '"q": [NaN, 0.0]'))
    (ds / "images" / "main" / "000001.png").write_bytes(b"not a png at all")
    code, lines = _run(["validate", str(ds), "-o", str(tmp_path / "r.json")], capsys)
    assert code == 2
    assert any(
        "frame 000000: field 'q': non-finite joint value(s) at index [0]" in ln for ln in lines
    ), lines
    bad = [ln for ln in lines if "000001.png: frame 000001: field 'images.main'" in ln]
    assert len(bad) == 1 and "not a readable image" in bad[0]
    assert lines[-1].endswith("frames 2 (0 OK, 2 with problems)")
    rep = json.loads((tmp_path / "r.json").read_text())
    assert rep["ok"] is False and rep["n_bad_frames"] == 2
    assert {(x["frame"], x["field"]) for x in rep["problems"]} == {
        ("000000", "q"),
        ("000001", "images.main"),
    }


def test_missing_dataset_exits_2(tmp_path, capsys):
    code, lines = _run(["validate", str(tmp_path)], capsys)
    assert code == 2
    assert lines[0] == f"{tmp_path}: missing dataset.json"


def test_camera_file_wrong_matrix_size(ds, capsys):
    import cv2

    fs = cv2.FileStorage(str(ds / "cam.yaml"), cv2.FILE_STORAGE_WRITE)
    fs.write("camera_matrix", np.eye(2))
    fs.write("image_width", 96)
    fs.write("image_height", 72)
    fs.release()
    edit_json(ds, lambda d: d["cameras"].update(main="cam.yaml"))
    code, lines = _run(["validate", str(ds)], capsys)
    assert code == 2
    assert (
        lines[0]
        == f"{ds / 'cam.yaml'}: field 'camera_matrix': expected a 3x3 matrix, got shape (2, 2)"
    )


def test_fast_mode_and_quiet(ds, capsys):
    edit_json(ds, lambda d: d["frames"][0].update(q=[1.0]))
    code, lines = _run(["validate", "--fast", "-q", str(ds / "dataset.json")], capsys)
    assert code == 2 and len(lines) == 1 and "1 problem(s)" in lines[0]
