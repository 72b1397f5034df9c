"""Tests of the synthetic scene generator (jaxcr.synth): exact ray casting against slow
references and closed forms, masks, model error, determinism, dataset output and the CLI."""

from __future__ import annotations

import json

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxcr.synth.generate import build_scene_data, generate, robot_shapes, tube_body
from jaxcr.synth.model_error import apply_tip_force, tip_force_curvature
from jaxcr.synth.presets import PRESETS
from jaxcr.synth.raycast import ray_box, ray_capsule, ray_plane, ray_sphere
from jaxcr.synth.render import (
    _edge_pixels,
    pixel_boxes,
    pixel_rays,
    render,
    render_static,
    robot_mask,
    undistort_to_rays,
)
from jaxcr.synth.scene import RenderCamera, TubeBody, look_at_pose
from tests.helpers.jitted import integrate_centreline  # compiled: input construction only

SMALL = (96, 72)
FRAMES = 2


# ----------------------------------------------------------------- references


def _seg_dist(x, a, b):
    ba = b - a
    h = np.clip(((x - a) @ ba) / (ba @ ba), 0.0, 1.0)
    return np.linalg.norm(x - (a + h[..., None] * ba), axis=-1)


def _first_hit_march(inside, o, d, t_max=3.0, n=60001):
    """Slow reference: march along the ray, then bisect the first inside sample."""
    ts = np.linspace(0.0, t_max, n)
    ins = inside(o[None] + ts[:, None] * d[None])
    if not ins.any():
        return np.inf
    k = int(np.argmax(ins))
    if k == 0:
        return np.nan  # starts inside
    lo, hi = ts[k - 1], ts[k]
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        if inside((o + mid * d)[None])[0]:
            hi = mid
        else:
            lo = mid
    return hi


def _random_rays(rng, m, target, spread):
    o = rng.normal(0, 0.3, (m, 3))
    aim = target + rng.normal(0, spread, (m, 3))
    d = aim - o
    return o, d / np.linalg.norm(d, axis=1, keepdims=True)


# ----------------------------------------------------------------- ray primitives


def test_ray_capsule_matches_marching_reference():
    rng = np.random.default_rng(0)
    a, b, r = np.array([0.01, -0.02, 0.03]), np.array([-0.05, 0.04, 0.08]), 0.012
    o, d = _random_rays(rng, 150, 0.5 * (a + b), 0.025)
    t, n = ray_capsule(o, d, a, b, r)
    hits = 0
    for i in range(len(o)):
        ref = _first_hit_march(lambda x: _seg_dist(x, a, b) <= r, o[i], d[i])
        if np.isnan(ref):
            continue
        if np.isinf(ref):
            assert np.isinf(t[i])
        else:
            hits += 1
            assert t[i] == pytest.approx(ref, abs=1e-7)
            p = o[i] + t[i] * d[i]
            assert _seg_dist(p[None], a, b)[0] == pytest.approx(r, abs=1e-9)
            assert np.linalg.norm(n[i]) == pytest.approx(1.0, abs=1e-9)
            assert n[i] @ d[i] < 0  # outward normal faces the incoming ray
    assert 30 < hits < 140  # both hits and misses were exercised


def test_ray_capsule_caps_parallel_and_degenerate():
    a, b, r = np.zeros(3), np.array([0.0, 0.0, 0.1]), 0.01
    # Along the axis: enters through the cap at a, at distance 1 - r.
    o = np.array([[0.0, 0.0, -1.0], [0.005, 0.0, 2.0]])
    d = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]])
    t, _ = ray_capsule(o, d, a, b, r)
    assert t[0] == pytest.approx(1.0 - r, abs=1e-12)
    assert t[1] == pytest.approx(2.0 - 0.1 - np.sqrt(r**2 - 0.005**2), abs=1e-12)
    # Zero-length segment = sphere.
    ts, _ = ray_capsule(o, d, a, a, r)
    tref, _ = ray_sphere(o, d, a, r)
    np.testing.assert_allclose(ts, tref)
    assert ts[0] == pytest.approx(1.0 - r)


def test_ray_box_and_plane_against_references():
    rng = np.random.default_rng(1)
    ang = 0.4
    axes = np.array([[np.cos(ang), -np.sin(ang), 0], [np.sin(ang), np.cos(ang), 0], [0, 0, 1.0]])
    centre, half = np.array([0.02, 0.01, 0.05]), np.array([0.01, 0.004, 0.02])
    o, d = _random_rays(rng, 120, centre, 0.02)
    t, n = ray_box(o, d, centre, axes, half)

    def inside(x):
        return np.all(np.abs((x - centre) @ axes) <= half, axis=-1)

    n_hit = 0
    for i in range(len(o)):
        ref = _first_hit_march(inside, o[i], d[i])
        if np.isnan(ref):
            continue
        if np.isinf(ref):
            assert np.isinf(t[i])
        else:
            n_hit += 1
            assert t[i] == pytest.approx(ref, abs=1e-7)
            assert n[i] @ d[i] < 0
    assert n_hit > 20
    tp, _ = ray_plane(o, d, np.array([0, 0, 0.5]), np.array([0, 0, -1.0]))
    front = d[:, 2] > 0
    np.testing.assert_allclose(tp[front], ((0.5 - o[:, 2]) / d[:, 2])[front])
    assert np.all(np.isinf(tp[~front]))


# ----------------------------------------------------------------- camera rays and bounds


def _camera(w=160, h=120, dist=(0.0, 0.0, 0.0, 0.0, 0.0), T=None):
    K = np.array([[150.0, 0, (w - 1) / 2 + 0.3], [0, 150.0, (h - 1) / 2 - 0.2], [0, 0, 1]])
    return RenderCamera(K, np.asarray(dist, float), np.eye(4) if T is None else T, w, h)


def test_undistorted_rays_round_trip_through_opencv():
    cam = _camera(dist=(-0.12, 0.08, 3e-4, -2e-4, -0.01))
    rng = np.random.default_rng(2)
    uv = rng.uniform([0, 0], [cam.width - 1, cam.height - 1], (200, 2))
    d = undistort_to_rays(cam, uv)
    back, _ = cv2.projectPoints(d, np.zeros(3), np.zeros(3), cam.K, cam.dist)
    np.testing.assert_allclose(back.reshape(-1, 2), uv, atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-12)


def test_pixel_boxes_contain_every_hit_pixel():
    cam = _camera(dist=(-0.12, 0.08, 3e-4, -2e-4, -0.01))
    rays = pixel_rays(cam)
    rng = np.random.default_rng(3)
    for _ in range(6):
        a = np.array([rng.uniform(-0.06, 0.06), rng.uniform(-0.05, 0.05), rng.uniform(0.08, 0.2)])
        b = a + rng.normal(0, 0.03, 3)
        r = rng.uniform(0.001, 0.006)
        t, _ = ray_capsule(np.zeros((len(rays.row), 3)), rays.d, a, b, r)
        box = pixel_boxes(cam, np.minimum(a, b)[None] - r, np.maximum(a, b)[None] + r)[0]
        hit = np.isfinite(t)
        sel = np.zeros(len(hit), bool)
        sel[rays.select(box)] = True
        assert not np.any(hit & ~sel)


def test_straight_cylinder_mask_width_matches_analytic_projection():
    """A straight tube of radius r crossing the optical axis at depth D: pixel centres are
    inside its silhouette iff |u - cx| <= f r / sqrt(D^2 - r^2) (tangent lines)."""
    cam = _camera()
    r, D = 0.004, 0.1
    body = TubeBody(
        np.array([[0.0, -0.2, D], [0.0, 0.0, D], [0.0, 0.2, D]]), np.array([r, r]), np.array([0, 0])
    )
    mask = robot_mask(cam, body)
    half = cam.K[0, 0] * r / np.sqrt(D**2 - r**2)
    u = np.arange(cam.width) - cam.K[0, 2]
    expected = np.abs(u) <= half
    assert expected.sum() >= 8
    for row in mask:
        np.testing.assert_array_equal(row, expected)


# ----------------------------------------------------------------- rendering


@pytest.fixture(scope="module")
def occluded_scene():
    cfg = PRESETS["orthogonal_occluded"]
    sd = build_scene_data(cfg, 0, FRAMES, (160, 120), 1)
    return sd


def test_masks_consistent_and_static_layer_equals_full_render(occluded_scene):
    sd = occluded_scene
    cam = sd.cameras_true["main"]
    static = render_static(cam, sd.scene(None, []))
    for k in range(FRAMES):
        scene = sd.scene(sd.bodies[k], sd.instruments[k])
        full = render(cam, scene)
        fast = render(cam, scene, static=static)
        np.testing.assert_array_equal(full.visible, fast.visible)
        np.testing.assert_array_equal(full.full, fast.full)
        np.testing.assert_array_equal(full.occluder, fast.occluder)
        np.testing.assert_allclose(full.image, fast.image, atol=1e-6)
        assert not np.any(full.visible & ~full.full)  # visible is part of the full projection
        assert not np.any(full.visible & full.occluder)
        assert full.visible.sum() > 20
        # Full mask ignores occluders: it equals the robot rendered alone.
        np.testing.assert_array_equal(full.full, robot_mask(cam, sd.bodies[k]))
        # Anti-aliasing only changes pixels next to an edge, and does change robot edges.
        plain = render(cam, scene, antialias=False)
        changed = np.any(np.abs(plain.image - full.image) > 1e-6, axis=2)
        # (edges = material changes or depth jumps, dilated by one pixel)
        near_edge = _edge_pixels(full.mat, full.depth)
        assert near_edge.mean() < 0.3
        assert not np.any(changed & ~near_edge)
        robot_edge = full.full & ~cv2.erode(
            full.full.astype(np.uint8), np.ones((3, 3), np.uint8)
        ).astype(bool)
        assert changed[robot_edge].mean() > 0.5


def test_model_error_moves_the_robot_and_zero_error_is_exact(occluded_scene):
    sd = occluded_scene
    cfg = sd.cfg
    nominal = robot_shapes(cfg.robot, sd.q_nominal)
    tip = np.linalg.norm(nominal.p[:, -1] - sd.shapes_true.p[:, -1], axis=1)
    assert np.all(tip > 1e-3)
    assert sd.error.kappa_factor and all(abs(f - 1) > 0.01 for f in sd.error.kappa_factor)
    assert not np.allclose(
        sd.cameras_true["main"].T_cam_robot, sd.cameras_nominal["main"].T_cam_robot
    )
    exact = build_scene_data(cfg, 0, FRAMES, (160, 120), 1, cfg.model_error.scaled(0.0))
    np.testing.assert_allclose(exact.shapes_true.p, nominal.p, atol=1e-9)
    cam = exact.cameras_nominal["main"]
    np.testing.assert_array_equal(cam.T_cam_robot, exact.cameras_true["main"].T_cam_robot)
    for k in range(FRAMES):
        nom = robot_mask(cam, tube_body(cfg.robot, nominal.p[k], nominal.rho[k]))
        np.testing.assert_array_equal(nom, robot_mask(exact.cameras_true["main"], exact.bodies[k]))


def test_linearised_tip_load_matches_cantilever_deflection():
    """Straight uniform rod, small tip force F perpendicular: deflection F L^3 / (3 EI)."""
    L, ei, F = 0.1, 0.01, 1e-3
    # 97 samples and a batch of 2 (the scenes' centrelines: apply_tip_force's compiled
    # re-integration is the one the rendering tests above load). The moment is linear in
    # s, so each step's midpoint curvature integrates the bending angle exactly; the
    # positions' error is O((h / L)^2) ~ 1e-5 relative, and the linearisation's
    # (deflection / L)^2 ~ 1e-7: far inside 1 %.
    n = 97
    s = jnp.linspace(0.0, L, n)
    base = integrate_centreline(s, jnp.zeros((n - 1, 3)), jnp.full(n, 1e-3))
    cl = jax.tree.map(lambda a: jnp.stack([a, a]), base)
    forces = np.array([[F, 0.0, 0.0], [0.0, F, 0.0]])  # the same load along x and along y
    out = apply_tip_force(cl, forces, np.full((2, n - 1), ei))
    for k in range(2):
        defl = float(out.p[k, -1, k])
        assert defl == pytest.approx(F * L**3 / (3 * ei), rel=0.01)
    du = tip_force_curvature(
        np.asarray(base.p), np.asarray(base.R), np.array([F, 0, 0]), np.full(n - 1, ei)
    )
    # Moment about +y grows linearly towards the base: F (L - s) / EI.
    mid = 0.5 * (np.asarray(s)[:-1] + np.asarray(s)[1:])
    np.testing.assert_allclose(du[:, 1], F * (L - mid) / ei, rtol=1e-5, atol=1e-9)


# ----------------------------------------------------------------- datasets and CLI


@pytest.fixture(scope="module")
def small_dataset(tmp_path_factory):
    out = tmp_path_factory.mktemp("synth") / "endo"
    generate("endoscopic_occluded", out, seed=5, frames=FRAMES, size=SMALL, progress=False)
    return out


def test_dataset_written_completely(small_dataset):
    doc = json.loads((small_dataset / "dataset.json").read_text())
    assert doc["format"] == "jaxcr.dataset/1"
    assert doc["meta"]["seed"] == 5 and doc["meta"]["preset"] == "endoscopic_occluded"
    assert len(doc["frames"]) == FRAMES
    cam = doc["cameras"]["main"]
    assert cam["size"] == list(SMALL)
    for fr in doc["frames"]:
        assert fr["tags"] == ["endoscopic", "occluded"]
        img = cv2.imread(str(small_dataset / fr["images"]["main"]))
        assert img.shape == (SMALL[1], SMALL[0], 3)
        vis = cv2.imread(str(small_dataset / fr["masks"]["main"]), cv2.IMREAD_UNCHANGED)
        full = cv2.imread(str(small_dataset / fr["full_masks"]["main"]), cv2.IMREAD_UNCHANGED)
        occ = cv2.imread(str(small_dataset / fr["occluders"]["main"]), cv2.IMREAD_UNCHANGED)
        assert set(np.unique(vis)) <= {0, 255} and vis.ndim == 2
        assert not np.any((vis > 0) & (full == 0))
        assert not np.any((vis > 0) & (occ > 0))
        assert occ.any()  # the actuation unit hides the base in endoscopic views
        assert np.any((full > 0) & (occ > 0))
        truth = np.load(small_dataset / fr["truth"]["centreline"])
        assert truth.shape[1] == 3 and np.all(np.isfinite(truth))
    assert len(doc["background_images"]["main"]) == 3
    from jaxcr.io.dataset import load_dataset, validate_dataset

    assert validate_dataset(small_dataset) == []
    ds = load_dataset(small_dataset)
    assert len(ds.frames) == FRAMES and not ds.bad_frames


def test_generation_is_deterministic(small_dataset, tmp_path):
    out = tmp_path / "again"
    generate("endoscopic_occluded", out, seed=5, frames=FRAMES, size=SMALL, progress=False)
    a = json.loads((small_dataset / "dataset.json").read_text())
    b = json.loads((out / "dataset.json").read_text())
    assert a == b
    for fr in a["frames"]:
        for key in ("images", "masks", "full_masks", "occluders"):
            rel = fr[key]["main"]
            assert (small_dataset / rel).read_bytes() == (out / rel).read_bytes()
        rel = fr["truth"]["centreline"]
        np.testing.assert_array_equal(np.load(small_dataset / rel), np.load(out / rel))


def test_cli_stereo_and_bad_input(tmp_path, capsys):
    from jaxcr.cli import main

    out = tmp_path / "stereo"
    code = main(
        [
            "synth",
            "--preset",
            "endoscopic_occluded",
            "--seed",
            "5",
            "--frames",
            str(FRAMES),
            "--size",
            "96x72",
            "--stereo",
            "--quiet",
            "-o",
            str(out),
        ]
    )
    assert code == 0
    doc = json.loads((out / "dataset.json").read_text())
    assert sorted(doc["cameras"]) == ["left", "right"]
    T = [np.asarray(doc["cameras"][c]["T_cam_robot"]) for c in ("left", "right")]
    base = np.linalg.norm(T[0][:3, :3].T @ T[0][:3, 3] - T[1][:3, :3].T @ T[1][:3, 3])
    assert base == pytest.approx(PRESETS["endoscopic_occluded"].camera.baseline, rel=1e-4)
    assert (
        main(["synth", "--preset", "orthogonal", "--size", "big", "-o", str(tmp_path / "x")]) == 2
    )
    assert main(["synth", "-o", str(tmp_path / "y")]) == 2
    assert (
        main(["synth", "--preset", "orthogonal", "--frames", "0", "-o", str(tmp_path / "z")]) == 2
    )
    err = capsys.readouterr().err
    assert "WIDTHxHEIGHT" in err and "--preset" in err


def test_look_at_pose_is_a_rigid_transform():
    T = look_at_pose((0.1, -0.2, 0.05), (0.0, 0.0, 0.06), (0.0, -1.0, 0.0))
    R = T[:3, :3]
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    eye = -R.T @ T[:3, 3]
    np.testing.assert_allclose(eye, [0.1, -0.2, 0.05], atol=1e-12)
    target_cam = R @ np.array([0.0, 0.0, 0.06]) + T[:3, 3]
    assert target_cam[0] == pytest.approx(0.0, abs=1e-12) and target_cam[2] > 0
    from jaxcr.camera import Camera

    ref = Camera.look_at((0.1, -0.2, 0.05), (0.0, 0.0, 0.06), (0.0, -1.0, 0.0), 100.0, (64, 48))
    np.testing.assert_allclose(np.asarray(ref.T_cam_robot), T, atol=1e-6)


def test_other_robot_kinds_via_cli(tmp_path):
    """A two-section constant-curvature robot in the orthogonal scene: valid dataset, robot
    visible, nominal joint readings differ from the rendered ones (joint offsets)."""
    from jaxcr.cli import main
    from jaxcr.io.dataset import validate_dataset

    robot = {
        "kind": "constant_curvature",
        "sections": [{"length": 0.05, "radius": 1.5e-3}, {"length": 0.04, "radius": 1.0e-3}],
        "joints": ["kappa", "phi"],
    }
    path = tmp_path / "cc.json"
    path.write_text(json.dumps(robot))
    out = tmp_path / "cc"
    code = main(
        [
            "synth",
            "--preset",
            "orthogonal",
            "--robot",
            str(path),
            "--frames",
            "2",
            "--size",
            "96x72",
            "--quiet",
            "-o",
            str(out),
        ]
    )
    assert code == 0
    assert validate_dataset(out) == []
    doc = json.loads((out / "dataset.json").read_text())
    assert doc["robot"]["kind"] == "constant_curvature"
    for fr in doc["frames"]:
        assert len(fr["q"]) == 4
        assert not np.allclose(fr["q"], fr["meta"]["q_true"])
        vis = cv2.imread(str(out / fr["masks"]["main"]), cv2.IMREAD_GRAYSCALE)
        assert (vis > 0).sum() > 5
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"kind": "nope"}))
    assert (
        main(["synth", "--preset", "orthogonal", "--robot", str(bad), "-o", str(tmp_path / "b")])
        == 2
    )
