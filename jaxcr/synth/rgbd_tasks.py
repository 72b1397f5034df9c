"""RGB-D scenes for progressive object modelling (issue 6; the paper's Task 1 and Task 2).

A target object stands on a table at the world origin (z up, metres) among obstacles; a
planar multi-section constant-curvature arm with a tip RGB-D camera moves around it. The
scene is *simulated in the loop*: the arm's motion is planned at run time, so the scene
stores geometry and textures and :class:`RgbdSimulator` renders a frame at whatever pose the
(true, perturbed) arm reaches, like the paper's augmented-reality set-up.

* Task 1: a textured box like a 1 l milk carton (7 x 7 x 19.5 cm) among four obstacles, a
  3-section arm, one winding direction (counter-clockwise) until the loop closes.
* Task 2: a textured can (r = 5 cm, h = 13 cm, top visible) on a table, with a clutter of
  obstacles; run 2-1 winds clockwise, run 2-2 counter-clockwise from a reset base, each
  until the arm reaches its length limit.

Frames contain the target object only (the paper's footnote 2: the close-range image shows
no obstacle); obstacles are sensed as the points of their (offline) point clouds inside the
camera frustum, as in the paper's Sec. V.A. Depth noise follows a consumer structured-light
camera (Nguyen et al. 2012, Kinect): sigma_z = 1.2 mm + 1.9e-3 (z - 0.4 m)^2 / m, depth
quantised to 1 mm steps of disparity-like resolution, grazing-angle dropout and 1 % random
holes. The real arm differs from the nominal one: curvature scale and a camera-mount error
(hidden from the estimator; recorded in scene.json under "truth" for evaluation only).

Scene format "jaxcr.rgbd_scene/1": see docs/rgbd-scene-format.md.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from jaxcr.errors import InputError
from jaxcr.synth.raycast import ray_box
from jaxcr.synth.texture import fractal_noise

FORMAT = "jaxcr.rgbd_scene/1"
TASKS = ("1", "2")


# --------------------------------------------------------------------------- textures
def _print_texture(rng: np.random.Generator, w: int, h: int) -> np.ndarray:
    """A packaging-like print: coloured fractal noise with random shapes and bars (plenty of
    SIFT corners), RGB float32 in [0, 1]."""
    base = rng.uniform(0.3, 0.9, 3)
    n = fractal_noise(rng, max(w, h), 4, 5)[:h, :w]
    img = (0.6 + 0.4 * n[..., None]) * base[None, None, :]
    img = (img * 255).astype(np.uint8).copy()
    for _ in range(int(w * h / 300)):
        c = tuple(int(v) for v in rng.integers(0, 256, 3))
        kind = rng.integers(0, 3)
        x, y = int(rng.integers(0, w)), int(rng.integers(0, h))
        s = int(rng.integers(4, max(6, w // 10)))
        if kind == 0:
            cv2.rectangle(img, (x, y), (x + s, y + int(s * rng.uniform(0.3, 1.5))), c, -1)
        elif kind == 1:
            cv2.circle(img, (x, y), s // 2, c, -1)
        else:
            cv2.putText(
                img,
                chr(int(rng.integers(65, 91))),
                (x, y),
                cv2.FONT_HERSHEY_SIMPLEX,
                s / 20.0,
                c,
                max(1, s // 10),
            )
    return img.astype(np.float32) / 255.0


def _sample(tex: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Bilinear lookup at texture coordinates u, v in [0, 1] (u along width)."""
    h, w = tex.shape[:2]
    n = u.size
    cols = 4096  # cv2.remap needs maps smaller than 32767 in each dimension
    rows = -(-n // cols)
    mu = np.zeros(rows * cols, np.float32)
    mv = np.zeros(rows * cols, np.float32)
    mu[:n] = np.clip(u * (w - 1), 0, w - 1)
    mv[:n] = np.clip(v * (h - 1), 0, h - 1)
    out = cv2.remap(
        tex,
        mu.reshape(rows, cols),
        mv.reshape(rows, cols),
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_REPLICATE,
    )
    return out.reshape(-1, 3)[:n]


# --------------------------------------------------------------------------- geometry
def _ray_cylinder(o, d, radius, height):
    """Upright cylinder about the world z axis, 0 <= z <= height, with a top cap; returns
    (t, normal, part) with part 0 = side, 1 = top, -1 = miss."""
    a = d[:, 0] ** 2 + d[:, 1] ** 2
    b = o[:, 0] * d[:, 0] + o[:, 1] * d[:, 1]
    c = o[:, 0] ** 2 + o[:, 1] ** 2 - radius**2
    h = b * b - a * c
    ok = (h >= 0) & (a > 1e-12)
    t_side = (-b - np.sqrt(np.where(ok, h, 0))) / np.where(a > 1e-12, a, 1)
    z = o[:, 2] + t_side * d[:, 2]
    side = ok & (t_side > 0) & (z >= 0) & (z <= height)
    t_top = (height - o[:, 2]) / np.where(np.abs(d[:, 2]) > 1e-12, d[:, 2], 1e-12)
    pt = o + t_top[:, None] * d
    top = (d[:, 2] < -1e-9) & (t_top > 0) & (pt[:, 0] ** 2 + pt[:, 1] ** 2 <= radius**2)
    t = np.where(side, t_side, np.inf)
    t = np.where(top & (t_top < t), t_top, t)
    part = np.where(np.isfinite(t), np.where(top & (t == t_top), 1, 0), -1)
    p = o + np.where(np.isfinite(t), t, 0)[:, None] * d
    n = np.zeros_like(p)
    n[part == 0, :2] = p[part == 0, :2] / radius
    n[part == 1] = (0.0, 0.0, 1.0)
    return t, n, part


def _obstacle_points(obstacles: list[dict[str, Any]], spacing: float = 0.006) -> np.ndarray:
    """Surface samples of box and cylinder obstacles (the offline obstacle point clouds)."""
    pts = []
    for ob in obstacles:
        cx, cy = ob["centre"]
        hgt = ob["height"]
        zs = np.arange(0.0, hgt + 1e-9, spacing)
        if ob["kind"] == "cylinder":
            r = ob["radius"]
            ang = np.arange(0, 2 * np.pi, spacing / r)
            A, Z = np.meshgrid(ang, zs)
            pts.append(
                np.stack([cx + r * np.cos(A).ravel(), cy + r * np.sin(A).ravel(), Z.ravel()], 1)
            )
        else:
            hx, hy = ob["half"]
            per = []
            for x in np.arange(-hx, hx + 1e-9, spacing):
                per += [(x, -hy), (x, hy)]
            for y in np.arange(-hy, hy + 1e-9, spacing):
                per += [(-hx, y), (hx, y)]
            per = np.asarray(per)
            P = np.repeat(per, len(zs), 0)
            Z = np.tile(zs, len(per))
            pts.append(np.stack([cx + P[:, 0], cy + P[:, 1], Z], 1))
    return np.concatenate(pts) if pts else np.zeros((0, 3))


# --------------------------------------------------------------------------- presets
def _task_config(task: str, rng: np.random.Generator) -> dict[str, Any]:
    if task == "1":
        return {
            "object": {
                "kind": "box",
                "half": [0.035, 0.035, 0.0975],
                "yaw": float(rng.uniform(0, 0.5)),
            },
            "obstacles": [
                {"kind": "cylinder", "centre": [0.42, 0.30], "radius": 0.05, "height": 0.22},
                {"kind": "box", "centre": [-0.08, 0.50], "half": [0.07, 0.04], "height": 0.15},
                {"kind": "cylinder", "centre": [0.10, -0.50], "radius": 0.05, "height": 0.18},
                {"kind": "box", "centre": [0.53, -0.20], "half": [0.04, 0.06], "height": 0.25},
                {"kind": "cylinder", "centre": [-0.45, 0.25], "radius": 0.05, "height": 0.2},
            ],
            "arm": {
                "n_sections": 3,
                "max_length": 0.8,
                "radius": 0.015,
                "height": 0.14,
                "max_kappa": 12.0,
            },
            "runs": [{"name": "1", "base": [-0.55, -0.30, 0.0], "direction": 1, "delta_s": 0.15}],
            "view_radius": 0.30,
            "tilt_target_z": 0.10,
        }
    if task == "2":
        return {
            "object": {
                "kind": "cylinder",
                "radius": 0.05,
                "height": 0.13,
                "yaw": float(rng.uniform(0, 6.28)),
            },
            "obstacles": [
                {"kind": "box", "centre": [0.36, 0.12], "half": [0.04, 0.06], "height": 0.2},
                {"kind": "cylinder", "centre": [0.30, -0.24], "radius": 0.045, "height": 0.16},
                {"kind": "box", "centre": [0.05, 0.37], "half": [0.07, 0.035], "height": 0.12},
                {"kind": "cylinder", "centre": [-0.02, -0.38], "radius": 0.04, "height": 0.2},
            ],
            "arm": {
                "n_sections": 3,
                "max_length": 0.45,
                "radius": 0.015,
                "height": 0.19,
                "max_kappa": 12.0,
            },
            "runs": [
                {"name": "2-1", "base": [-0.42, 0.19, 0.0], "direction": -1, "delta_s": 0.10},
                {"name": "2-2", "base": [-0.42, -0.19, 0.0], "direction": 1, "delta_s": 0.10},
            ],
            "view_radius": 0.19,
            "tilt_target_z": 0.08,
        }
    raise InputError(f"unknown task {task!r}; expected one of {TASKS}", field="task")


def generate_task(out, task: str = "1", seed: int = 0, size: tuple[int, int] = (320, 240)) -> Path:
    """Write an RGB-D modelling scene (format ``jaxcr.rgbd_scene/1``) to directory ``out``."""
    task = str(task)
    rng = np.random.default_rng([seed, int(task)])
    cfg = _task_config(task, rng)
    w, h = int(size[0]), int(size[1])
    if w < 32 or h < 24:
        raise InputError(f"image size {w}x{h} is too small (min 32x24)", field="size")
    out = Path(out)
    (out / "textures").mkdir(parents=True, exist_ok=True)
    f = 0.95 * w
    cfg["camera"] = {
        "K": [[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1]],
        "width": w,
        "height": h,
    }
    names = []
    if cfg["object"]["kind"] == "box":
        hx, hy, hz = cfg["object"]["half"]
        dims = [(2 * hx, 2 * hz)] * 4 + [(2 * hx, 2 * hy)]
    else:
        r, ht = cfg["object"]["radius"], cfg["object"]["height"]
        dims = [(2 * np.pi * r, ht), (2 * r, 2 * r)]
    for k, (a, b) in enumerate(dims):
        px = 1600  # texels per metre
        tex = _print_texture(rng, int(a * px), int(b * px))
        name = f"textures/face{k}.png"
        cv2.imwrite(str(out / name), cv2.cvtColor((tex * 255).astype(np.uint8), cv2.COLOR_RGB2BGR))
        names.append(name)
    cfg["object"]["textures"] = names
    np.save(out / "obstacles.npy", _obstacle_points(cfg["obstacles"]).astype(np.float32))
    cfg["format"] = FORMAT
    cfg["task"] = task
    cfg["seed"] = int(seed)
    cfg["depth_noise"] = {
        "sigma0": 0.0012,
        "sigma2": 0.0019,
        "z0": 0.4,
        "hole_rate": 0.01,
        "min_cos": 0.2,
        "colour_sigma": 0.01,
    }
    cfg["truth"] = {
        "kappa_scale": float(1.0 + rng.normal(0, 0.02)),
        "mount_rotvec": rng.normal(0, 0.01, 3).tolist(),
        "mount_t": rng.normal(0, 0.002, 3).tolist(),
    }
    tmp = out / "scene.json.tmp"
    tmp.write_text(json.dumps(cfg, indent=1))
    os.replace(tmp, out / "scene.json")
    return out


# --------------------------------------------------------------------------- simulator
def load_scene(path) -> dict[str, Any]:
    path = Path(path)
    f = path / "scene.json"
    if not f.is_file():
        raise InputError("not an RGB-D scene directory (no scene.json)", file=str(path))
    from jaxcr.io.jsonfile import read_json

    cfg = read_json(f)
    if not isinstance(cfg, dict):
        raise InputError("expected a JSON object at the top level", file=str(f))
    if cfg.get("format") != FORMAT:
        raise InputError(
            f"expected format {FORMAT!r}, got {cfg.get('format')!r}", file=str(f), field="format"
        )
    for key in ("object", "camera", "arm", "runs", "obstacles", "view_radius"):
        if key not in cfg:
            raise InputError("missing required key", file=str(f), field=key)
    _check_scene(cfg, str(f))
    return cfg


def _num(d, key, file, field, *, positive=False, integer=False, n=None):
    """``d[key]`` as a finite number (or a list of ``n``), else a one-line InputError."""
    v = d.get(key) if isinstance(d, dict) else None
    vals = v if n is not None else [v]
    ok = isinstance(vals, list) and (n is None or len(vals) == n)
    ok = ok and all(
        isinstance(x, int | float) and not isinstance(x, bool) and math.isfinite(x) for x in vals
    )
    ok = ok and (not integer or all(isinstance(x, int) for x in vals))
    ok = ok and (not positive or all(x > 0 for x in vals))
    if not ok:
        what = "integer" if integer else "number"
        what = f"{'positive ' if positive else 'finite '}{what}"
        what = f"a list of {n} {what}s" if n is not None else f"a {what}"
        raise InputError(f"expected {what}, got {v!r}", file=file, field=field)
    return v


def _check_scene(cfg: dict, file: str) -> None:
    """Types and ranges of the ``jaxcr.rgbd_scene/1`` fields the simulator reads
    (docs/rgbd-scene-format.md), so a foreign scene fails with one line naming the field."""

    def obj(key, parent=cfg, prefix=""):
        v = parent.get(key)
        if not isinstance(v, dict):
            raise InputError("expected an object", file=file, field=prefix + key)
        return v

    o = obj("object")
    if o.get("kind") == "box":
        _num(o, "half", file, "object.half", positive=True, n=3)
    elif o.get("kind") == "cylinder":
        _num(o, "radius", file, "object.radius", positive=True)
        _num(o, "height", file, "object.height", positive=True)
    else:
        raise InputError(
            f"expected 'box' or 'cylinder', got {o.get('kind')!r}", file=file, field="object.kind"
        )
    if "yaw" in o:
        _num(o, "yaw", file, "object.yaw")
    tex = o.get("textures")
    if not isinstance(tex, list) or not tex or not all(isinstance(t, str) for t in tex):
        raise InputError("expected a list of paths", file=file, field="object.textures")
    cam = obj("camera")
    K = cam.get("K")
    try:
        Ka = np.asarray(K, np.float64)
    except (TypeError, ValueError):
        Ka = None
    if Ka is None or Ka.shape != (3, 3) or not np.all(np.isfinite(Ka)):
        raise InputError("expected a finite 3x3 matrix", file=file, field="camera.K")
    if not (Ka[0, 0] > 0 and Ka[1, 1] > 0) or not np.allclose(Ka[2], [0, 0, 1]):
        raise InputError(
            "focal lengths must be positive and the last row [0, 0, 1]", file=file, field="camera.K"
        )
    for key in ("width", "height"):
        _num(cam, key, file, f"camera.{key}", positive=True, integer=True)
    from jaxcr.limits import check_size

    try:  # the simulator renders every view at this size
        check_size(cam["width"], cam["height"], "camera.width", "model-object", (32, 24))
    except InputError as err:
        raise InputError(err.message, file=file, field="camera.width") from None
    arm = obj("arm")
    _num(arm, "n_sections", file, "arm.n_sections", positive=True, integer=True)
    for key in ("max_length", "radius", "max_kappa"):
        _num(arm, key, file, f"arm.{key}", positive=True)
    _num(arm, "height", file, "arm.height")
    runs = cfg.get("runs")
    if not isinstance(runs, list) or not runs:
        raise InputError("expected a non-empty list of runs", file=file, field="runs")
    for i, r in enumerate(runs):
        if not isinstance(r, dict):
            raise InputError("expected an object", file=file, field=f"runs[{i}]")
        _num(r, "base", file, f"runs[{i}].base", n=3)
        _num(r, "delta_s", file, f"runs[{i}].delta_s", positive=True)
        if r.get("direction") not in (1, -1) or isinstance(r.get("direction"), bool):
            raise InputError("expected +1 or -1", file=file, field=f"runs[{i}].direction")
    if not isinstance(cfg.get("obstacles"), list):
        raise InputError("expected a list", file=file, field="obstacles")
    _num(cfg, "view_radius", file, "view_radius", positive=True)
    if "tilt_target_z" in cfg:
        _num(cfg, "tilt_target_z", file, "tilt_target_z")
    if "capture_frames" in cfg:
        from jaxcr.limits import MAX_CAPTURE_FRAMES

        _num(cfg, "capture_frames", file, "capture_frames", positive=True, integer=True)
        if cfg["capture_frames"] > MAX_CAPTURE_FRAMES:
            raise InputError(
                f"must be between 1 and {MAX_CAPTURE_FRAMES}, got {cfg['capture_frames']}",
                file=file,
                field="capture_frames",
            )
    noise = cfg.get("depth_noise", {})
    if not isinstance(noise, dict):
        raise InputError("expected an object", file=file, field="depth_noise")
    for key in noise:
        _num(noise, key, file, f"depth_noise.{key}")


class RgbdSimulator:
    """Renders noisy RGB-D frames of the scene's target and senses its obstacles."""

    def __init__(self, path, seed: int = 0, capture_frames: int | None = None):
        """``capture_frames``: depth frames averaged per capture (the camera held still, as
        a real RGB-D camera gives ~30 frames a second); None: the scene's
        ``capture_frames`` (default 1, the paper's single frame)."""
        self.path = Path(path)
        self.cfg = load_scene(path)
        frames = self.cfg.get("capture_frames", 1) if capture_frames is None else capture_frames
        from jaxcr.limits import MAX_CAPTURE_FRAMES, check_count

        self.capture_frames = check_count(int(frames), "capture_frames", 1, MAX_CAPTURE_FRAMES)
        self.K = np.asarray(self.cfg["camera"]["K"], np.float64)
        self.width = int(self.cfg["camera"]["width"])
        self.height = int(self.cfg["camera"]["height"])
        self.textures = []
        from jaxcr.io.images import read_image

        for name in self.cfg["object"]["textures"]:
            try:  # float32 RGB in [0, 1] (grey, RGBA, 16-bit accepted)
                self.textures.append(read_image(self.path / name))
            except InputError as err:
                raise InputError(
                    f"cannot read texture: {err.message}", file=err.file, field="object.textures"
                ) from None
        obs = self.path / "obstacles.npy"
        if not obs.is_file():
            raise InputError("missing obstacle cloud", file=str(obs))
        try:
            self.obstacles = np.load(obs, allow_pickle=False).astype(np.float64)
        except (ValueError, OSError, TypeError) as err:
            raise InputError(f"not a readable .npy point cloud ({err})", file=str(obs)) from None
        if self.obstacles.ndim != 2 or self.obstacles.shape[1] != 3:
            raise InputError(
                f"expected an (n, 3) point cloud, got shape {self.obstacles.shape}", file=str(obs)
            )
        from jaxcr.limits import check_finite_float32

        # a NaN/inf point is no obstacle the planner can avoid (an all-NaN cloud planned
        # through everything): refused, with the count
        check_finite_float32(self.obstacles, str(obs), "points")
        self.rng = np.random.default_rng(seed)
        yaw = float(self.cfg["object"].get("yaw", 0.0))
        c, s = np.cos(yaw), np.sin(yaw)
        self.R_obj = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])

    # ------------------------------------------------------------------ truth
    def surface_distance(self, points_world: np.ndarray) -> np.ndarray:
        """Unsigned distance (m) of world points to the object's true surface."""
        ob = self.cfg["object"]
        p = points_world @ self.R_obj  # object frame (rotation about z only)
        if ob["kind"] == "box":
            half = np.asarray(ob["half"])
            q = p - np.array([0, 0, half[2]])
            d = np.abs(q) - half
            outside = np.linalg.norm(np.maximum(d, 0), axis=1)
            inside = np.minimum(np.max(d, axis=1), 0)
            return np.abs(outside + inside)
        r, hgt = ob["radius"], ob["height"]
        rad = np.hypot(p[:, 0], p[:, 1]) - r
        dz = np.maximum(p[:, 2] - hgt, -p[:, 2])
        d = np.stack([rad, dz], 1)
        return np.abs(np.linalg.norm(np.maximum(d, 0), axis=1) + np.minimum(d.max(1), 0))

    # ------------------------------------------------------------------ rendering
    def _hit(self, o, d):
        ob = self.cfg["object"]
        if ob["kind"] == "box":
            half = np.asarray(ob["half"], np.float64)
            centre = np.array([0.0, 0.0, half[2]])
            t, n = ray_box(o, d, centre, self.R_obj, half)
            hit = np.isfinite(t)
            p = o + np.where(hit, t, 0)[:, None] * d
            q = (p - centre) @ self.R_obj  # box frame
            col = np.zeros((len(t), 3))
            nl = n @ self.R_obj
            # side faces 0..3 (+x, +y, -x, -y), top 4
            faces = [((0, 1.0), 1, 0), ((1, 1.0), 0, 0), ((0, -1.0), 1, 0), ((1, -1.0), 0, 0)]
            for k, ((ax, sg), uax, _) in enumerate(faces):
                sel = hit & (np.abs(nl[:, ax] - sg) < 1e-6)
                if sel.any():
                    u = (sg * (1 if k < 2 else -1) * q[sel, uax] * (-1 if ax == 0 else 1)) / (
                        2 * half[uax]
                    ) + 0.5
                    v = 0.5 - q[sel, 2] / (2 * half[2])
                    col[sel] = _sample(self.textures[k], u, v)
            sel = hit & (nl[:, 2] > 0.5)
            if sel.any():
                col[sel] = _sample(
                    self.textures[4],
                    q[sel, 0] / (2 * half[0]) + 0.5,
                    q[sel, 1] / (2 * half[1]) + 0.5,
                )
            return t, n, col
        r, hgt = ob["radius"], ob["height"]
        ol = o @ self.R_obj
        dl = d @ self.R_obj
        t, nl, part = _ray_cylinder(ol, dl, r, hgt)
        p = ol + np.where(np.isfinite(t), t, 0)[:, None] * dl
        col = np.zeros((len(t), 3))
        s = part == 0
        if s.any():
            ang = (np.arctan2(p[s, 1], p[s, 0]) + np.pi) / (2 * np.pi)
            col[s] = _sample(self.textures[0], ang, 1.0 - p[s, 2] / hgt)
        s = part == 1
        if s.any():
            col[s] = _sample(self.textures[1], p[s, 0] / (2 * r) + 0.5, p[s, 1] / (2 * r) + 0.5)
        return t, nl @ self.R_obj.T, col

    def capture(self, T_world_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Noisy (rgb (H, W, 3) in [0, 1], depth (H, W) metres, NaN = no return) seen by a
        camera at world pose ``T_world_cam`` (OpenCV camera frame)."""
        h, w = self.height, self.width
        v, u = np.mgrid[0:h, 0:w].astype(np.float64)
        dc = np.stack(
            [(u - self.K[0, 2]) / self.K[0, 0], (v - self.K[1, 2]) / self.K[1, 1], np.ones_like(u)],
            -1,
        ).reshape(-1, 3)
        dc /= np.linalg.norm(dc, axis=1, keepdims=True)
        R, c = T_world_cam[:3, :3], T_world_cam[:3, 3]
        d = dc @ R.T
        o = np.broadcast_to(c, d.shape).copy()
        t, n, col = self._hit(o, d)
        hit = np.isfinite(t)
        cosang = -np.sum(n * d, axis=1)
        nz = self.cfg["depth_noise"]
        z = np.where(hit, t * dc[:, 2], np.nan)
        sigma = nz["sigma0"] + nz["sigma2"] * (np.nan_to_num(z) - nz["z0"]) ** 2
        shade = 0.35 + 0.65 * np.clip(cosang, 0, 1)
        rgb0 = np.where(hit[:, None], col * shade[:, None], 0.0)
        # capture_frames frames of the still camera, each with its own noise, quantisation and
        # holes (frame 0 draws exactly what a single-frame capture draws); a pixel's depth is
        # the mean of its valid frames, valid when at least half of the frames are
        n = self.capture_frames
        zsum, count, rgbsum = np.zeros_like(z), np.zeros(z.shape), np.zeros_like(rgb0)
        for _ in range(n):
            zn = z + self.rng.normal(0, 1, z.shape) * sigma
            zn = np.round(zn * 2000.0) / 2000.0  # 0.5 mm depth quantisation
            holes = self.rng.random(z.shape) < nz["hole_rate"]
            valid = hit & (cosang > nz["min_cos"]) & ~holes
            zsum += np.where(valid, zn, 0.0)
            count += valid
            rgb = rgb0 + self.rng.normal(0, nz["colour_sigma"], rgb0.shape)
            rgbsum += np.clip(rgb, 0, 1)
        ok = count >= max(1, (n + 1) // 2)
        depth = np.where(ok, zsum / np.maximum(count, 1), np.nan).reshape(h, w)
        rgb = rgbsum / n
        return rgb.reshape(h, w, 3).astype(np.float32), depth.astype(np.float32)

    def sense_obstacles(
        self, T_world_cam: np.ndarray, fov: float = np.deg2rad(100.0), max_range: float = 0.8
    ) -> np.ndarray:
        """The obstacle points inside a viewing frustum (half-angle ``fov``/2) of the given
        camera pose and within ``max_range`` m (paper Sec. V.A: simulated sensing)."""
        P = (self.obstacles - T_world_cam[:3, 3]) @ T_world_cam[:3, :3]
        r = np.linalg.norm(P, axis=1)
        ang = np.arccos(np.clip(P[:, 2] / np.maximum(r, 1e-9), -1, 1))
        return self.obstacles[(ang < fov / 2) & (r < max_range)]

    def true_mount(self) -> np.ndarray:
        """Tip <- camera-mount error transform of the real arm (hidden from the estimator)."""
        tr = self.cfg["truth"]
        rv = np.asarray(tr["mount_rotvec"], np.float64)
        R, _ = cv2.Rodrigues(rv)
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = tr["mount_t"]
        return T
