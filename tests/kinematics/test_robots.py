"""robot_from_dict / robot_to_dict / load_robot: round trips and every bad input."""

import json
import math

import jax.numpy as jnp
import numpy as np
import pytest

from jaxcr.errors import InputError
from jaxcr.io.robot import load_robot, save_robot
from jaxcr.kinematics.base import RobotModel, piecewise_arclength, steps_per_piece
from jaxcr.kinematics.constant_curvature import ConstantCurvature
from jaxcr.kinematics.robots import robot_from_dict, robot_to_dict
from jaxcr.kinematics.single_segment import SingleSegment

CC = {
    "kind": "constant_curvature",
    "sections": [
        {"length": 0.05, "radius": 0.003, "phi": 0.2, "bending_stiffness": 0.002},
        {"length": 0.04, "radius": 0.002, "phi": -0.4},
    ],
    "joints": ["kappa", "length"],
    "n_points": 21,
}
SS = {"kind": "single_segment", "length": 0.04, "radius": 0.002}


def test_steps_per_piece_and_grid():
    assert steps_per_piece(3, 31) == (10, 10, 10)
    assert steps_per_piece(3, 12) == (4, 4, 3)
    with pytest.raises(ValueError):
        steps_per_piece(3, 3)
    s = piecewise_arclength(jnp.array([0.1, 0.3, 0.05]), (4, 4, 3))
    np.testing.assert_allclose(np.asarray(s)[[0, 4, 8, 11]], [0.0, 0.1, 0.4, 0.45], atol=1e-7)
    assert np.all(np.diff(np.asarray(s)) > 0)
    np.testing.assert_allclose(np.diff(np.asarray(s))[4:8], 0.075, rtol=1e-5)


@pytest.mark.parametrize("kind", ["constant_curvature", "single_segment", "ctr"])
def test_every_builtin_model_is_a_pytree_satisfying_the_protocol(kind):
    """docs/ARCHITECTURE.md: RobotModel is a Protocol, and every built-in model is an
    eqx.Module satisfying it with static structural ints (a change of n_points changes the
    pytree structure, so jit retraces; the leaves are arrays only, never Python numbers that
    would be traced or hashed)."""
    import equinox as eqx
    import jax

    from jaxcr.kinematics.ctr import TEST_CTR

    d = {"constant_curvature": CC, "single_segment": SS, "ctr": TEST_CTR}[kind]
    model = robot_from_dict(d)
    assert isinstance(model, eqx.Module) and isinstance(model, RobotModel)
    assert model.kind == kind and isinstance(model.n_joints, int)
    other = robot_from_dict({**d, "n_points": model.n_points + 2})
    assert jax.tree.structure(other) != jax.tree.structure(model)
    assert all(isinstance(x, jax.Array | np.ndarray) for x in jax.tree.leaves(model))


@pytest.mark.parametrize("d", [CC, SS])
def test_round_trip(d):
    model = robot_from_dict(d)
    assert isinstance(model, RobotModel)
    d2 = robot_to_dict(model)
    model2 = robot_from_dict(json.loads(json.dumps(d2)))
    assert type(model2) is type(model) and model2.n_points == model.n_points
    q = jnp.linspace(0.1, 0.5, model.n_joints)
    np.testing.assert_allclose(model.forward(q).centreline.p, model2.forward(q).centreline.p)


def test_parsed_values():
    m = robot_from_dict(CC)
    assert isinstance(m, ConstantCurvature)
    assert m.joints == ("kappa", "length") and m.n_joints == 4 and m.n_points == 21
    np.testing.assert_allclose(m.phi, [0.2, -0.4])
    np.testing.assert_allclose(m.bending_stiffness, [0.002, 0.0])
    s = robot_from_dict(SS)
    assert isinstance(s, SingleSegment) and s.n_joints == 2 and s.n_points == 64
    assert float(s.length) == pytest.approx(0.04)


def _cc(**changes):
    d = json.loads(json.dumps(CC))
    for k, v in changes.items():
        if k.startswith("s0_"):
            d["sections"][0][k[3:]] = v
        elif v is None:
            del d[k]
        else:
            d[k] = v
    return d


@pytest.mark.parametrize(
    "d, field, words",
    [
        ({"length": 0.04}, "kind", "missing"),
        ({"kind": "tendon"}, "kind", "unknown robot kind"),
        ({"kind": 3}, "kind", "unknown robot kind"),
        ([1, 2], "robot", "expected an object"),
        ({"kind": "single_segment", "radius": 0.002}, "length", "missing"),
        ({"kind": "single_segment", "length": -0.04, "radius": 0.002}, "length", "> 0"),
        ({"kind": "single_segment", "length": 0.0, "radius": 0.002}, "length", "> 0"),
        ({"kind": "single_segment", "length": math.nan, "radius": 0.002}, "length", "finite"),
        ({"kind": "single_segment", "length": math.inf, "radius": 0.002}, "length", "finite"),
        (
            {"kind": "single_segment", "length": "0.04", "radius": 0.002},
            "length",
            "expected a number",
        ),
        (
            {"kind": "single_segment", "length": True, "radius": 0.002},
            "length",
            "expected a number",
        ),
        (
            {"kind": "single_segment", "length": 0.04, "radius": 0.002, "lenght": 1},
            "lenght",
            "unknown key",
        ),
        (
            {"kind": "single_segment", "length": 0.04, "radius": 0.002, "n_points": 1},
            "n_points",
            ">= 2",
        ),
        (
            {"kind": "single_segment", "length": 0.04, "radius": 0.002, "n_points": 3.5},
            "n_points",
            "integer",
        ),
        (_cc(sections=None), "sections", "missing"),
        (_cc(sections=[]), "sections", "non-empty"),
        (_cc(sections=[1.0]), "sections[0]", "expected an object"),
        (_cc(s0_length=-1.0), "sections[0].length", "> 0"),
        (_cc(s0_radius=None), "sections[0].radius", "expected a number"),
        (_cc(s0_kappa=math.nan), "sections[0].kappa", "finite"),
        (_cc(joints=["kappa", "twist"]), "joints", "distinct names"),
        (_cc(joints=["kappa", "kappa"]), "joints", "distinct names"),
        (_cc(joints="kappa"), "joints", "list of names"),
        (_cc(n_points=2), "n_points", ">= 3"),
    ],
)
def test_bad_descriptions_raise_one_line_input_error(d, field, words):
    with pytest.raises(InputError) as err:
        robot_from_dict(d, file="robot.json")
    assert err.value.field == field
    assert words in str(err.value)
    assert str(err.value).startswith("robot.json")
    assert "\n" not in str(err.value)


def test_load_robot_from_files(tmp_path):
    (tmp_path / "robot.json").write_text(json.dumps(SS))
    assert isinstance(load_robot(tmp_path / "robot.json"), SingleSegment)
    # Dataset folder with the robot inline.
    ds = tmp_path / "ds1"
    ds.mkdir()
    (ds / "dataset.json").write_text(
        json.dumps({"format": "jaxcr.dataset/1", "robot": CC, "frames": []})
    )
    assert isinstance(load_robot(ds), ConstantCurvature)
    assert isinstance(load_robot(ds / "dataset.json"), ConstantCurvature)
    # Dataset folder whose robot entry is a relative path.
    ds2 = tmp_path / "ds2"
    ds2.mkdir()
    (ds2 / "robot.json").write_text(json.dumps(SS))
    (ds2 / "dataset.json").write_text(
        json.dumps({"format": "jaxcr.dataset/1", "robot": "robot.json"})
    )
    assert isinstance(load_robot(ds2), SingleSegment)
    # save_robot writes a loadable file.
    m = robot_from_dict(CC)
    save_robot(m, tmp_path / "saved.json")
    assert robot_to_dict(load_robot(tmp_path / "saved.json")) == robot_to_dict(m)


def test_load_robot_bad_files(tmp_path):
    with pytest.raises(InputError, match="file not found"):
        load_robot(tmp_path / "missing.json")
    with pytest.raises(InputError, match="no dataset.json"):
        load_robot(tmp_path)
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    with pytest.raises(InputError, match="not valid JSON"):
        load_robot(bad)
    bad.write_text(json.dumps({"kind": "single_segment", "length": 0.04}))
    with pytest.raises(InputError) as err:
        load_robot(bad)
    assert err.value.file == str(bad) and err.value.field == "radius"


def test_ctr_dispatch():
    ctr = pytest.importorskip("jaxcr.kinematics.ctr")
    if not hasattr(ctr.ConcentricTubeRobot, "from_dict"):
        pytest.skip("ConcentricTubeRobot.from_dict not available yet")
    with pytest.raises(InputError) as err:
        robot_from_dict({"kind": "ctr", "tubes": []}, file="robot.json")
    assert err.value.field == "tubes" and err.value.file == "robot.json"
    model = robot_from_dict(ctr.TEST_CTR)
    assert isinstance(model, ctr.ConcentricTubeRobot) and model.n_joints == 6
    d = robot_to_dict(model)
    assert d["kind"] == "ctr"
    assert robot_to_dict(robot_from_dict(json.loads(json.dumps(d)))) == d
