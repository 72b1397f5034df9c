"""model-object CLI and the RGB-D task scenes: scene contract, rendering vs geometry, bad
inputs and degenerate registrations (clear failures, never garbage poses)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from jaxcr.cli import main
from jaxcr.errors import InputError
from jaxcr.registration.clouds import cloud_from_rgbd
from jaxcr.registration.pairwise import RegistrationFailed, make_frame, register_pair
from jaxcr.synth.rgbd_tasks import RgbdSimulator, generate_task, load_scene
from jaxcr.synth.scene import look_at_pose


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    # 160x120: register_pair's projective ICP / information programs then have the shapes
    # test_registration_pairwise compiles (4096-point sample, 120x160 target; run cache)
    return generate_task(tmp_path_factory.mktemp("t2") / "scene", "2", seed=1, size=(160, 120))


def _pose(r, ang, z=0.15):
    eye = np.array([r * np.cos(ang), r * np.sin(ang), z])
    return np.linalg.inv(look_at_pose(eye, [0, 0, 0.06], [0, 0, 1]))


def test_scene_contract_and_depth_on_true_surface(scene):
    cfg = load_scene(scene)
    assert cfg["format"] == "jaxcr.rgbd_scene/1" and len(cfg["runs"]) == 2
    sim = RgbdSimulator(scene, seed=0)
    sim.cfg["depth_noise"].update(sigma0=0.0, sigma2=0.0, hole_rate=0.0)
    T = _pose(0.25, 0.3)
    rgb, depth = sim.capture(T)
    assert rgb.shape == (120, 160, 3) and depth.shape == (120, 160)
    c = cloud_from_rgbd(rgb, depth, sim.K)
    world = c.points @ T[:3, :3].T + T[:3, 3]
    # depth quantisation is 0.5 mm
    assert np.max(sim.surface_distance(world)) < 6e-4
    # obstacle sensing returns only points inside the frustum
    pts = sim.sense_obstacles(T, fov=np.deg2rad(60), max_range=0.5)
    local = (pts - T[:3, 3]) @ T[:3, :3]
    assert np.all(local[:, 2] > 0) and np.all(np.linalg.norm(local, axis=1) < 0.5)


def test_bad_scene_inputs(tmp_path, scene):
    with pytest.raises(InputError, match="scene.json"):
        RgbdSimulator(tmp_path)
    d = tmp_path / "s"
    d.mkdir()
    (d / "scene.json").write_text(json.dumps({"format": "other"}))
    with pytest.raises(InputError, match="format"):
        load_scene(d)
    with pytest.raises(InputError, match="task"):
        generate_task(tmp_path / "x", "7")
    assert main(["model-object", str(tmp_path), "-o", str(tmp_path / "o")]) == 2
    assert main(["model-object", "synth", "--size", "big", "-o", str(tmp_path / "o")]) == 2


def test_degenerate_registration_fails_clearly(scene):
    sim = RgbdSimulator(scene, seed=0)
    K = sim.K
    rgb, depth = sim.capture(_pose(0.25, 0.0))
    a = make_frame(rgb, depth, K, size=256)
    # all-NaN depth: an input error before any pose exists
    with pytest.raises(InputError, match="no valid pixel"):
        make_frame(rgb, np.full_like(depth, np.nan), K)
    # no overlap (a view from the other side, no keypoints matched, nothing within reach)
    rgb2, depth2 = sim.capture(_pose(0.25, np.pi))
    b = make_frame(rgb2, depth2, K, size=256)
    far = np.eye(4)
    far[:3, 3] = (1.0, 0, 0)
    for assoc in ("projective", "nearest"):
        with pytest.raises(RegistrationFailed, match="no overlap"):
            register_pair(a, b, K, prior=far, association=assoc)
    with pytest.raises(ValueError, match="association"):
        register_pair(a, a, K, association="kdtree")
    # no keypoints (textureless grey image): falls back to the prior and still registers
    grey = np.full_like(rgb, 0.5)
    g = make_frame(grey, depth, K, size=256)
    res = register_pair(g, g, K)
    assert not res.seeded_by_keypoints and res.n_matches == 0
    np.testing.assert_allclose(res.T, np.eye(4), atol=1e-4)


def test_cli_synth_writes_scene(tmp_path):
    assert (
        main(["model-object", "synth", "--task", "1", "--size", "64x48", "-o", str(tmp_path / "s")])
        == 0
    )
    assert load_scene(tmp_path / "s")["task"] == "1"


def test_prior_gate_drops_a_keypoint_estimate_far_from_the_prior(scene):
    sim = RgbdSimulator(scene, seed=0)
    rgb, depth = sim.capture(_pose(0.25, 0.0))
    a = make_frame(rgb, depth, sim.K, size=256)
    c, s = np.cos(np.deg2rad(30)), np.sin(np.deg2rad(30))
    prior = np.array([[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]])
    free = register_pair(a, a, sim.K, prior=prior, min_fitness=0.0)
    gated = register_pair(a, a, sim.K, prior=prior, prior_gate=(10.0, 0.05), min_fitness=0.0)
    # the self-match keypoint estimate (identity) is 30 deg from the prior
    assert free.seeded_by_keypoints and free.n_inliers >= 3
    assert not gated.seeded_by_keypoints
    np.testing.assert_allclose(free.T, np.eye(4), atol=1e-3)


def test_cli_edge_weights_option():
    import argparse

    from jaxcr.cli import model_object
    from jaxcr.registration.pipeline import PipelineConfig

    p = argparse.ArgumentParser(prog="jaxcr")
    model_object.add_parser(p.add_subparsers())
    a = p.parse_args(["model-object", "synth", "-o", "x"])
    assert a.edge_weights == PipelineConfig().edge_weights == "calibrated"
    assert p.parse_args(["model-object", "synth", "-o", "x", "--edge-weights", "information"]
                        ).edge_weights == "information"  # fmt: skip
    with pytest.raises(SystemExit) as e:
        p.parse_args(["model-object", "synth", "-o", "x", "--edge-weights", "robust"])
    assert e.value.code == 2
