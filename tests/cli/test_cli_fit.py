"""``jaxcr fit`` end to end: backbone files in mm and m give the same q, bad files give one
line on stderr and exit 2, tip pixels fit through a dataset's camera and update its frame."""

from __future__ import annotations

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxcr.camera import project_points
from jaxcr.cli import main
from jaxcr.io.dataset import load_dataset
from jaxcr.io.robot import load_robot
from jaxcr.kinematics.fit import _cold_forward
from tests.helpers.datasets import edit_json, make_dataset

SS = {"kind": "single_segment", "length": 0.1, "radius": 0.003, "n_points": 24}
Q_TRUE = [0.55, 0.8]


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("fit")
    (d / "ss.json").write_text(json.dumps(SS))
    model = load_robot(d / "ss.json")
    p = np.asarray(_cold_forward(model, jnp.asarray(Q_TRUE)).centreline.p, np.float64)
    rng = np.random.default_rng(3)
    pts = p[np.r_[0 : len(p) : 3, len(p) - 1]] + rng.normal(scale=1e-4, size=(9, 3))
    with open(d / "bb_mm.csv", "w") as fh:
        fh.write("# unit: mm\nx,y,z\n")
        np.savetxt(fh, pts * 1000.0, delimiter=",", fmt="%.6f")
    with open(d / "bb_m.txt", "w") as fh:
        np.savetxt(fh, pts, fmt="%.9f")  # whitespace-separated, unit from --unit
    (d / "bb.json").write_text(json.dumps({"unit": "cm", "points": (pts * 100).tolist()}))
    return d


def _fit(files, out, *args):
    return main(["fit", str(files / "ss.json"), *args, "-o", str(files / out)])


def test_mm_and_m_give_the_same_q(files, capsys):
    assert _fit(files, "a", "--backbone", str(files / "bb_mm.csv")) == 0
    assert _fit(files, "b", "--backbone", str(files / "bb_m.txt"), "--unit", "m") == 0
    assert _fit(files, "c", "--backbone", str(files / "bb.json")) == 0
    fits = [json.loads((files / o / "fit.json").read_text()) for o in "abc"]
    assert all(f["format"] == "jaxcr.fit/1" and f["ok"] for f in fits)
    # The files hold the same points rounded to 1e-6 mm / 1e-9 m: the LM optimum moves by
    # (J^T J)^-1 J^T dr ~ 1e-9 m / 0.1 m lever ~ 1e-8 rad, far under the float32 solver's
    # resolution (rtol 1e-6 on unit-scale q; 1e-5 with margin).
    for f in fits[1:]:
        np.testing.assert_allclose(f["q"], fits[0]["q"], atol=1e-5)
    # Noise 0.1 mm: q near the truth (the library test checks against the covariance)
    np.testing.assert_allclose(fits[0]["q"], Q_TRUE, atol=0.05)
    assert len(fits[0]["errors"]) == 9 and fits[0]["error_unit"] == "m"
    assert fits[0]["rms"] < 5e-4
    # q.csv is readable by jaxcr fk, and gives the fitted tip
    out = files / "fk"
    assert main(["fk", str(files / "ss.json"), str(files / "a" / "q.csv"), "-o", str(out)]) == 0
    tips = np.loadtxt(out / "tips.csv", delimiter=",", skiprows=2)
    model = load_robot(files / "ss.json")
    fk = _cold_forward(model, jnp.asarray(fits[0]["q"], jnp.float32))
    tip = np.asarray(fk.centreline.p[-1])
    np.testing.assert_allclose(tips[2:5], tip, atol=1e-6)  # float32 on 0.1 m: ~1e-8, margin
    assert "rms" in capsys.readouterr().out


BAD = [
    ("nounit.csv", "1,2,3\n4,5,6\n", [], "no unit declared"),
    ("badunit.csv", "# unit: inch\n1,2,3\n4,5,6\n", [], "unknown unit 'inch'"),
    ("clash.csv", "# unit: mm\n1,2,3\n4,5,6\n", ["--unit", "m"], "declares unit 'mm'"),
    ("text.csv", "# unit: mm\n1,2,3\n4,x,6\n", [], "line 3: non-numeric"),
    ("cols.csv", "# unit: mm\n1,2,3\n4,5\n", [], "expected 3 values"),
    ("one.csv", "# unit: mm\n1,2,3\n", [], "at least 2 points"),
    ("nan.csv", "# unit: mm\n1,2,3\nnan,5,6\n", [], "point 1 is not finite"),
    ("key.json", '{"unit": "mm", "point": [[1,2,3]]}', [], "unknown key(s) ['point']"),
    ("empty.csv", "# unit: mm\n", [], "no points found"),
]


@pytest.mark.parametrize("name,text,extra,message", BAD)
def test_bad_backbone_files_give_one_line(files, capsys, name, text, extra, message):
    (files / name).write_text(text)
    assert _fit(files, "bad", "--backbone", str(files / name), *extra) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err
    assert message in err and name in err


def test_bad_options_give_one_line(files, capsys):
    bb = str(files / "bb_mm.csv")
    assert _fit(files, "bad", "--backbone", bb, "--q0", "1,2,3") == 2
    assert "--q0" in capsys.readouterr().err
    assert _fit(files, "bad", "--backbone", bb, "--frame", "0") == 2
    assert "--frame needs ROBOT to be a dataset" in capsys.readouterr().err
    assert _fit(files, "bad", "--tips", bb) == 2
    assert "--tips needs ROBOT to be a dataset" in capsys.readouterr().err
    assert _fit(files, "bad", "--backbone", str(files / "missing.csv")) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "missing.csv" in err


def test_tip_pixels_fit_updates_the_dataset_frame(tmp_path, capsys):
    root = make_dataset(tmp_path / "ds", n_frames=2)
    ds = load_dataset(root)
    cam = ds.cameras["main"]
    q_true = jnp.asarray([9.0, 0.6])  # kappa (1/m), phi (rad) of the 5 cm section
    # compiled FK and projection (run eagerly, ~50 operations were compiled one by one)
    project = jax.jit(project_points)
    tip = _cold_forward(ds.robot, q_true).centreline.p[-1:]
    uv = np.asarray(project(cam, tip)[0][0], np.float64)
    tips = tmp_path / "tips.json"
    tips.write_text(json.dumps({"tips": {"main": uv.tolist()}}))
    code = main(
        ["fit", str(root), "--tips", str(tips), "--q0", "5,0.3", "--frame", "000001",
         "-o", str(tmp_path / "out")]
    )  # fmt: skip
    assert code == 0, capsys.readouterr().err
    rec = json.loads((tmp_path / "out" / "fit.json").read_text())
    # one view, two unknowns, two equations: an exact fit (float32 projection of ~100 px
    # coordinates: eps32 x 100 ~ 1e-5 px; LM stops at rtol 1e-6 -> 1e-3 px with margin)
    assert rec["max"] < 1e-3 and rec["error_unit"] == "px"
    # the fitted q reprojects onto the pixel (q itself is determined up to one view's depth)
    again = load_dataset(root)
    fr = again.frame("000001")
    np.testing.assert_allclose(fr.q, rec["q"])
    assert fr.meta["fit"]["mode"] == "tips"
    p = _cold_forward(again.robot, jnp.asarray(fr.q, jnp.float32)).centreline.p[-1:]
    np.testing.assert_allclose(np.asarray(project(cam, p)[0][0]), uv, atol=1e-2)
    # unknown camera in the tips file: one line, exit 2
    tips.write_text(json.dumps({"tips": {"left": [1, 2]}}))
    assert main(["fit", str(root), "--tips", str(tips), "-o", str(tmp_path / "o2")]) == 2
    assert "unknown camera 'left'" in capsys.readouterr().err
    # a robot never placed in the camera (audit r31: 100 steps, then 322 px and the solver's
    # generic text): exit 2, one line naming the field and the way to place it
    tips.write_text(json.dumps({"tips": {"main": uv.tolist()}}))
    edit_json(root, lambda j: j["cameras"]["main"].update(T_cam_robot=np.eye(4).tolist()))
    assert main(["fit", str(root), "--tips", str(tips), "-o", str(tmp_path / "o3")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "cameras.main.T_cam_robot" in err[0] and "--fit-pose" in err[0]
