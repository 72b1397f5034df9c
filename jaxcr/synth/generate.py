"""Generate one synthetic dataset (format ``jaxcr.dataset/1``) from a preset.

Per preset: a procedural tissue texture, the nominal robot and camera(s) written to
``dataset.json``, a drawn model error giving the *true* robot and camera(s) used to render
(:mod:`jaxcr.synth.model_error`), a joint trajectory (nominal q = what the joint sensors
read; true q = nominal + offsets), the true centrelines (CTR forward kinematics of the true
robot, then the linearised tip load), occluders (actuation unit; laparoscopic scissors in
``*_occluded`` presets) and per frame and camera: the ray-cast image with camera noise, the
visible / full / occluder masks and the true centreline.

Random streams are derived from ``(seed, preset_index, stream)`` with
``numpy.random.SeedSequence``, so a preset's output depends only on the seed, the preset and
the requested frame count and size.
"""

from __future__ import annotations

import copy
import dataclasses
import os
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxcr.errors import InputError
from jaxcr.io.exported import FAST_COMPILE, cached_call
from jaxcr.kinematics.batch import forward_batch
from jaxcr.synth.model_error import (
    ModelError,
    apply_tip_force,
    bending_stiffness_along,
    draw_model_error,
    perturbed_camera_pose,
    perturbed_robot,
)
from jaxcr.synth.occluders import actuation_unit, laparoscopic_instrument
from jaxcr.synth.presets import PRESETS, PresetConfig, ctr_trajectory, generic_trajectory
from jaxcr.synth.render import apply_camera_effects, render, render_static
from jaxcr.synth.scene import RenderCamera, Scene, Tissue, TubeBody, look_at_pose
from jaxcr.synth.texture import make_tissue_texture

GENERATOR_VERSION = "jaxcr-synth/1"
#: ``jaxcr segment``'s default ``--batch-size``: the kinematics batch of :func:`robot_shapes`
SEGMENT_BATCH = 4
N_BACKGROUND_IMAGES = 3
_STREAM_TEXTURE, _STREAM_TRAJ, _STREAM_ERROR, _STREAM_OCC, _STREAM_NOISE = range(5)


def _rng(seed: int, cfg: PresetConfig, *stream: int) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence([int(seed), cfg.preset_index, *stream]))


def camera_names(n: int) -> list[str]:
    """``main`` for one camera, ``left``/``right`` for two, ``cam0..`` otherwise."""
    if n == 1:
        return ["main"]
    if n == 2:
        return ["left", "right"]
    return [f"cam{i}" for i in range(n)]


def nominal_cameras(
    cfg: PresetConfig, size: tuple[int, int], n_cameras: int
) -> dict[str, RenderCamera]:
    """The calibrated (nominal) cameras of a preset at image ``size`` = (width, height).

    Several cameras form a rig with parallel optical axes spread along the image x axis of
    the preset's view over ``baseline`` (metres)."""
    v = cfg.camera
    w, h = int(size[0]), int(size[1])
    # Same field of view at any size (square pixels at 4:3).
    K = np.array(
        [
            [v.fx * w / 640.0, 0.0, (w - 1) / 2.0],
            [0.0, v.fx * h / 480.0, (h - 1) / 2.0],
            [0, 0, 1.0],
        ]
    )
    T0 = look_at_pose(v.eye, v.target, v.up)
    x_axis = T0[0, :3]  # camera x axis in the robot frame
    out = {}
    names = camera_names(n_cameras)
    offsets = [0.0] if n_cameras == 1 else list(np.linspace(-0.5, 0.5, n_cameras) * v.baseline)
    for name, off in zip(names, offsets, strict=True):
        eye = np.asarray(v.eye) + off * x_axis
        target = np.asarray(v.target) + off * x_axis
        out[name] = RenderCamera(
            K.copy(), np.asarray(v.dist, float), look_at_pose(eye, target, v.up), w, h
        )
    return out


def tissue_for(cfg: PresetConfig, texture) -> Tissue:
    n = np.asarray(cfg.tissue.normal, float)
    n /= np.linalg.norm(n)
    helper = np.array([0.0, 1.0, 0.0]) if abs(n[1]) < 0.9 else np.array([0.0, 0.0, 1.0])
    ev = helper - (helper @ n) * n
    ev /= np.linalg.norm(ev)
    eu = np.cross(ev, n)  # eu x ev = n
    return Tissue(np.asarray(cfg.tissue.origin, float), eu, ev, texture)


@dataclass
class Shapes:
    """Centrelines of a batch of joint vectors (numpy, robot frame, metres)."""

    s: np.ndarray  # (F, N)
    p: np.ndarray  # (F, N, 3)
    rho: np.ndarray  # (F, N)
    ok: np.ndarray  # (F,)


def robot_shapes(
    robot: dict[str, Any], q: np.ndarray, tip_force: np.ndarray | None = None
) -> Shapes:
    """Forward kinematics of ``robot`` (a description dict) at each row of ``q``, optionally
    with the linearised tip load (:func:`jaxcr.synth.model_error.apply_tip_force`)."""
    from jaxcr.kinematics.robots import robot_from_dict

    model = robot_from_dict(robot)
    # segment's nominal-kinematics program (jaxcr.segmentation.batch): the same function,
    # stored traced program and XLA options, and its batch shape (chunks of `jaxcr segment`'s
    # default --batch-size 4, or of all frames when fewer, as `jaxcr demo` runs segment; the
    # last chunk padded by repeating a row), so synth and a later segment (or demo's) compile
    # one CTR program, any frame count the same one, and a second process loads it instead of
    # tracing it (rows bit-identical to one plain jit of all frames: docs/decisions.md S22, S25)
    q32 = np.asarray(q, np.float32)
    n = len(q32)
    b = min(n, SEGMENT_BATCH)
    n_pad = -(-n // b) * b
    qp = np.concatenate([q32, np.repeat(q32[-1:], n_pad - n, 0)])
    chunks = [cached_call(forward_batch, model, jnp.asarray(qp[i : i + b]),
                          compiler_options=FAST_COMPILE)  # fmt: skip
              for i in range(0, n_pad, b)]  # fmt: skip
    # on the host: jnp.concatenate and slicing would compile a program per frame count
    res = jax.tree.map(lambda *a: np.concatenate([np.asarray(x) for x in a])[:n], *chunks)
    cl = res.centreline
    p = np.asarray(cl.p, np.float64)
    if tip_force is not None and np.any(tip_force):
        s_np = np.asarray(cl.s, np.float64)
        ei = np.stack(
            [
                bending_stiffness_along(robot, np.asarray(q[k]), 0.5 * (s_np[k, :-1] + s_np[k, 1:]))
                for k in range(len(q))
            ]
        )
        forces = np.repeat(np.asarray(tip_force, float)[None], len(q), axis=0)
        p = np.asarray(apply_tip_force(cl, forces, ei).p, np.float64)
    return Shapes(
        np.asarray(cl.s, np.float64), p, np.asarray(cl.rho, np.float64), np.asarray(res.ok)
    )


def tube_body(robot: dict[str, Any], p: np.ndarray, rho: np.ndarray) -> TubeBody:
    """Capsule chain of one centreline: segment k (samples k..k+1) has the outer radius
    ``rho[k+1]`` (the step convention of the kinematics) and is drawn in the material of the
    tube of that outer diameter."""
    radius = rho[1:]
    if robot["kind"] == "ctr":
        od = np.array([t["od"] for t in robot["tubes"]]) / 2.0
        tube = np.argmin(np.abs(radius[:, None] - od[None, :]), axis=1)
    else:
        tube = np.zeros(len(radius), int)
    return TubeBody(p, radius, tube)


def instrument_for_frame(
    cfg: PresetConfig,
    rng: np.random.Generator,
    base_angle: float,
    p: np.ndarray,
    eye: np.ndarray,
    T_cam: np.ndarray,
):
    """Laparoscopic scissors crossing the robot between it and the camera: the shaft passes
    ``instrument_depth`` in front of a centreline sample (a fraction in ``instrument_span`` of
    the samples from the base), at an image-plane
    angle near ``base_angle``, its jaws ending 5-25 mm past the crossing."""
    n = len(p)
    c = p[int(rng.uniform(*cfg.instrument_span) * (n - 1))]
    to_cam = eye - c
    to_cam /= np.linalg.norm(to_cam)
    c_front = c + cfg.instrument_depth * to_cam
    ang = base_angle + rng.normal(0.0, 0.15)
    ex, ey = T_cam[0, :3], T_cam[1, :3]
    direction = np.cos(ang) * ex + np.sin(ang) * ey - 0.25 * to_cam
    direction /= np.linalg.norm(direction)
    tip = c_front + rng.uniform(0.005, 0.025) * direction
    return laparoscopic_instrument(
        tip, direction, roll=rng.uniform(0, np.pi), open_angle=rng.uniform(0.1, 0.6)
    )


def parse_size(text: str, kind: str = "synth") -> tuple[int, int]:
    """``"640x480"`` -> (640, 480) within the limits of renderer ``kind`` (a key of
    :data:`jaxcr.limits.MAX_PIXELS`); raises :class:`InputError` on anything else."""
    from jaxcr.limits import parse_size as parse_limited

    return parse_limited(text, "size", kind)


def generate(
    preset: str | PresetConfig,
    out: str | os.PathLike,
    seed: int = 0,
    frames: int | None = None,
    size: tuple[int, int] | None = None,
    progress: bool = True,
    model_error_scale: float | None = None,
    n_cameras: int | None = None,
    robot: dict[str, Any] | None = None,
) -> Path:
    """Write the dataset of ``preset`` (a name in :data:`PRESETS` or a config) to folder
    ``out``; returns the path of its ``dataset.json`` (written last, atomically).

    ``robot`` (a robot description dict, any kind of docs/dataset-format.md) replaces the
    preset's CTR; the scene (cameras, tissue, occluders) stays that of the preset.

    ``frames``/``size``/``n_cameras`` override the preset (20 frames, 640x480, 1 camera);
    ``model_error_scale`` multiplies every model-error magnitude (0 gives a perfect model).
    """
    cfg = _resolve(preset)
    if robot is not None:
        from jaxcr.kinematics.robots import robot_from_dict, robot_to_dict

        cfg = dataclasses.replace(cfg, robot=robot_to_dict(robot_from_dict(robot)))
    frames = cfg.frames if frames is None else int(frames)
    if frames < 1:
        raise InputError(f"need at least one frame, got {frames}", field="frames")
    size = cfg.size if size is None else (int(size[0]), int(size[1]))
    n_cameras = cfg.n_cameras if n_cameras is None else int(n_cameras)
    if n_cameras < 1:
        raise InputError(f"need at least one camera, got {n_cameras}", field="cameras")
    spec = (
        cfg.model_error if model_error_scale is None else cfg.model_error.scaled(model_error_scale)
    )
    if spec.scale < 0:
        raise InputError(f"model error scale must be >= 0, got {spec.scale}", field="model_error")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)

    scene_data = build_scene_data(cfg, seed, frames, size, n_cameras, spec)
    names = list(scene_data.cameras_nominal)
    it = range(frames)
    if progress:
        from jaxcr.progress import progress as progress_bar

        it = progress_bar(it, desc=f"synth {cfg.name}", unit="frame", leave=False)
    statics = {
        name: render_static(scene_data.cameras_true[name], scene_data.scene(None, []))
        for name in names
    }
    from jaxcr.camera import camera_from_arrays
    from jaxcr.io.dataset import DatasetWriter

    cameras = {
        n: camera_from_arrays(c.K, c.dist, c.T_cam_robot, c.width, c.height)
        for n, c in scene_data.cameras_nominal.items()
    }
    meta = {
        "generator": "jaxcr synth",
        "generator_version": GENERATOR_VERSION,
        "preset": cfg.name,
        "seed": int(seed),
        "frames": frames,
        "size": list(size),
        "model_error": scene_data.error.to_dict(),
        "true_robot": scene_data.robot_true,
        "true_cameras": {n: c.T_cam_robot.tolist() for n, c in scene_data.cameras_true.items()},
        "tip_load_model": "linearised: du(s) = R(s)^T ((p(L)-p(s)) x F) / EI(s), re-integrated",
    }
    if not np.all(scene_data.shapes_true.ok):
        bad = np.nonzero(~scene_data.shapes_true.ok)[0].tolist()
        warnings.warn(
            f"{cfg.name}: true-robot kinematics did not converge for frames {bad}", stacklevel=2
        )
    writer = DatasetWriter(out, cfg.name, cfg.robot, cameras, meta=meta, overwrite=True)
    for k in it:
        scene = scene_data.scene(scene_data.bodies[k], scene_data.instruments[k])
        images, masks, full, occ = {}, {}, {}, {}
        for ci, name in enumerate(names):
            r = render(scene_data.cameras_true[name], scene, static=statics[name])
            images[name] = apply_camera_effects(r.image, _rng(seed, cfg, _STREAM_NOISE, k, ci))
            masks[name], full[name], occ[name] = r.visible, r.full, r.occluder
        writer.add_frame(
            f"{k:03d}",
            scene_data.q_nominal[k],
            images,
            masks=masks,
            full_masks=full,
            occluders=occ,
            tags=cfg.tags,
            truth={"centreline": scene_data.shapes_true.p[k]},
            meta={
                "q_true": [float(x) for x in scene_data.q_true[k]],
                "fk_ok_true": bool(scene_data.shapes_true.ok[k]),
            },
        )
    for ci, name in enumerate(names):
        for b in range(N_BACKGROUND_IMAGES):
            img = apply_camera_effects(
                statics[name].image, _rng(seed, cfg, _STREAM_NOISE, 10_000 + b, ci)
            )
            writer.add_background(name, img)
    return writer.close()


def _resolve(preset: str | PresetConfig) -> PresetConfig:
    if isinstance(preset, PresetConfig):
        return preset
    if preset not in PRESETS:
        raise InputError(
            f"unknown preset {preset!r}; choose from {sorted(PRESETS)}", field="preset"
        )
    return PRESETS[preset]


@dataclass
class SceneData:
    """Everything drawn for one preset before rendering (used by :func:`generate` and by the
    nominal-IoU experiment)."""

    cfg: PresetConfig
    tissue: Tissue
    cameras_nominal: dict[str, RenderCamera]
    cameras_true: dict[str, RenderCamera]
    error: ModelError
    robot_true: dict[str, Any]
    q_nominal: np.ndarray
    q_true: np.ndarray
    shapes_true: Shapes
    bodies: list[TubeBody]
    instruments: list[list]
    static_occluders: list

    def scene(self, body: TubeBody | None, instrument: list) -> Scene:
        return Scene(self.tissue, body, list(instrument), self.static_occluders)


def build_scene_data(
    cfg: PresetConfig, seed: int, frames: int, size: tuple[int, int], n_cameras: int, spec=None
) -> SceneData:
    """Draw texture, trajectory, model error, true shapes and occluders of a preset."""
    spec = cfg.model_error if spec is None else spec
    texture = make_tissue_texture(_rng(seed, cfg, _STREAM_TEXTURE))
    tissue = tissue_for(cfg, texture)
    cams = nominal_cameras(cfg, size, n_cameras)
    if cfg.robot["kind"] == "ctr":
        q_nom = ctr_trajectory(cfg, _rng(seed, cfg, _STREAM_TRAJ), frames)
        ranges = None
    elif cfg.robot["kind"] in ("constant_curvature", "single_segment"):
        q_nom, ranges = generic_trajectory(cfg.robot, _rng(seed, cfg, _STREAM_TRAJ), frames)
    else:
        raise InputError(f"unsupported robot kind {cfg.robot['kind']!r}", field="robot.kind")
    err = draw_model_error(
        _rng(seed, cfg, _STREAM_ERROR), spec, cfg.robot, q_nom.shape[1], list(cams), ranges
    )
    robot_true = perturbed_robot(copy.deepcopy(cfg.robot), err)
    q_true = q_nom + np.asarray(err.joint_offset)[None, :]
    shapes = robot_shapes(robot_true, q_true, np.asarray(err.tip_force))
    cams_true = {
        n: c.with_pose(perturbed_camera_pose(c.T_cam_robot, err, n)) for n, c in cams.items()
    }
    bodies = [tube_body(robot_true, shapes.p[k], shapes.rho[k]) for k in range(frames)]
    instruments: list[list] = [[] for _ in range(frames)]
    if cfg.occluded:
        orng = _rng(seed, cfg, _STREAM_OCC)
        base_angle = orng.uniform(0.0, np.pi)
        ref = cams[camera_names(n_cameras)[0]]
        eye = -ref.T_cam_robot[:3, :3].T @ ref.T_cam_robot[:3, 3]
        for k in range(frames):
            instruments[k] = instrument_for_frame(
                cfg, orng, base_angle, shapes.p[k], eye, ref.T_cam_robot
            )
    return SceneData(
        cfg,
        tissue,
        cams,
        cams_true,
        err,
        robot_true,
        q_nom,
        q_true,
        shapes,
        bodies,
        instruments,
        actuation_unit(),
    )
