"""Video presets for motion-likelihood object segmentation (M-L paper sections 5-6).

A cluttered textured table, five objects (a book, a mug, a uniform-yellow spirit level, a
bottle and a toy rabbit, seen as their flat top faces), and the 5-DOF arm of
:mod:`jaxcr.motion.arm` whose tip moves in a straight line, touches one object and pushes it
("pushed" set), or grips an object and carries it with out-of-plane rotation ("held" set, the
homography model's case). Joint values x_i come from the closed-form inverse kinematics; the
tip position g(x_i) is forward kinematics. Everything is ray cast in the robot frame (exact
plane and capsule hits, :mod:`jaxcr.synth.raycast`), textured with :mod:`jaxcr.synth.texture`
noise and finished with :func:`jaxcr.synth.render.apply_camera_effects`.

Changing backgrounds add any of: ``distractor`` (two textured "hands" moving over the
background in their own directions), ``shake`` (the rendering camera jitters each frame by
about 0.4 deg while the calibrated P stays nominal), ``lighting`` (a global illumination gain
varying by +-20 % over the video).

Output (format ``jaxcr.motion/1``, docs/motion-format.md): ``motion.json``, ``frames/NNNNNN.png``
(or ``video.avi`` with ``video=True``), ground-truth object masks ``masks/NNNNNN.png`` for every
frame.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import cv2
import jax
import numpy as np

from jaxcr.motion.arm import ArmModel, arm_inverse, joint_positions
from jaxcr.synth.raycast import ray_capsule
from jaxcr.synth.render import apply_camera_effects
from jaxcr.synth.texture import fractal_noise, value_noise

OBJECTS = ("book", "mug", "spirit_level", "bottle", "rabbit")
CHANGES = ("distractor", "shake", "lighting")
PRESETS = ("pushed_static", "pushed_changing", "held_static", "held_changing")
ARM = ArmModel(base_height=0.20, upper=0.25, forearm=0.22, hand=0.10)
_TABLE_HALF = 0.40  # table texture covers x in [0, 0.8], y in [-0.4, 0.4] m
_TABLE_C = np.array([0.40, 0.0])
_ARM_RADII = (0.030, 0.024, 0.019, 0.013)


@dataclass
class Planar:
    """A flat textured shape: origin (3,), in-plane axes u, v (3,), half extents (m), shape
    ("rect" | "ellipse" | "rabbit"), texture (T, T, 3) over [-hu, hu] x [-hv, hv]."""

    origin: np.ndarray
    u: np.ndarray
    v: np.ndarray
    hu: float
    hv: float
    shape: str
    texture: np.ndarray

    def moved(self, T: np.ndarray) -> Planar:
        R, t = T[:3, :3], T[:3, 3]
        return Planar(
            R @ self.origin + t, R @ self.u, R @ self.v, self.hu, self.hv, self.shape, self.texture
        )


def _inside(shape: str, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a, b: normalised local coordinates in [-1, 1]."""
    if shape == "rect":
        return (np.abs(a) <= 1) & (np.abs(b) <= 1)
    if shape == "ellipse":
        return a * a + b * b <= 1
    # rabbit: body, head and two ears
    body = ((a + 0.25) / 0.75) ** 2 + (b / 0.85) ** 2 <= 1
    head = ((a - 0.55) / 0.32) ** 2 + (b / 0.4) ** 2 <= 1
    ear1 = ((a - 0.85) / 0.18) ** 2 + ((b - 0.45) / 0.5) ** 2 <= 1
    ear2 = ((a - 0.85) / 0.18) ** 2 + ((b + 0.45) / 0.5) ** 2 <= 1
    return (body | head | ear1 | ear2) & (np.abs(a) <= 1) & (np.abs(b) <= 1)


def _ray_planar(o: np.ndarray, d: np.ndarray, p: Planar):
    """Two-sided hit of rays with a planar shape: (t (M,), texture coordinates (M, 2))."""
    n = np.cross(p.u, p.v)
    denom = d @ n
    ok = np.abs(denom) > 1e-9
    t = ((p.origin - o) @ n) / np.where(ok, denom, 1.0)
    hit = o + t[:, None] * d
    a = ((hit - p.origin) @ p.u) / p.hu
    b = ((hit - p.origin) @ p.v) / p.hv
    inside = ok & (t > 0) & _inside(p.shape, a, b)
    T = p.texture.shape[0]
    tex = np.stack([(a + 1) * 0.5 * (T - 1), (b + 1) * 0.5 * (T - 1)], axis=1)
    return np.where(inside, t, np.inf), tex


def _sample(texture: np.ndarray, uv: np.ndarray) -> np.ndarray:
    n = len(uv)
    cols = 1024
    rows = -(-n // cols)
    m = np.zeros((rows * cols, 2), np.float32)
    m[:n] = np.nan_to_num(uv, nan=0.0, posinf=0.0, neginf=0.0)
    m = m.reshape(rows, cols, 2)
    out = cv2.remap(texture, m[..., 0], m[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    return out.reshape(-1, 3)[:n]


def _colour_noise(rng, size, cells, c0, c1, octaves=4) -> np.ndarray:
    n = fractal_noise(rng, size, cells, octaves)[..., None]
    return (np.asarray(c0, np.float32) * (1 - n) + np.asarray(c1, np.float32) * n).astype(
        np.float32
    )


def _object_texture(rng, kind: str, size: int = 256) -> np.ndarray:
    if kind == "spirit_level":
        return np.tile(np.array([0.92, 0.78, 0.10], np.float32), (size, size, 1))
    if kind == "book":
        tex = _colour_noise(rng, size, 4, (0.10, 0.25, 0.60), (0.85, 0.25, 0.20))
        tex[size // 3 : size // 3 + size // 10] = (0.95, 0.95, 0.85)
        tex[:, : size // 12] *= 0.4
        return tex
    if kind == "mug":
        n = fractal_noise(rng, size, 8, 3)
        stripes = (np.sin(np.linspace(0, 10 * np.pi, size))[None, :] > 0).astype(np.float32)
        return np.stack(
            [
                0.9 - 0.5 * stripes * n,
                0.9 - 0.2 * n,
                np.broadcast_to(0.95 - 0.7 * stripes, n.shape),
            ],
            -1,
        ).astype(np.float32)
    if kind == "bottle":
        tex = _colour_noise(rng, size, 6, (0.10, 0.45, 0.20), (0.55, 0.85, 0.55))
        tex[:, size // 3 : 2 * size // 3] = _colour_noise(
            rng, size, 12, (0.9, 0.9, 0.9), (0.8, 0.1, 0.1)
        )[:, size // 3 : 2 * size // 3]
        return tex
    return _colour_noise(rng, size, 16, (0.45, 0.30, 0.18), (0.85, 0.75, 0.60), octaves=5)


_OBJ_SIZE = {  # half extents (m) and shape
    "book": (0.075, 0.055, "rect"),
    "mug": (0.045, 0.045, "ellipse"),
    "spirit_level": (0.11, 0.018, "rect"),
    "bottle": (0.09, 0.03, "ellipse"),
    "rabbit": (0.06, 0.045, "rabbit"),
}


def _table_texture(rng, size: int = 1024) -> np.ndarray:
    tex = _colour_noise(rng, size, 6, (0.55, 0.42, 0.30), (0.80, 0.70, 0.55))
    grain = value_noise(rng, size, size // 8)[..., None]
    tex = tex * (0.85 + 0.3 * grain)
    # clutter: random patches of other materials painted into the table
    for _ in range(40):
        c = rng.integers(0, size, 2)
        r = rng.integers(size // 60, size // 18)
        col = rng.random(3).astype(np.float32)
        patch = _colour_noise(rng, 64, 4, col * 0.6, np.minimum(col * 1.3 + 0.1, 1.0), 3)
        patch = cv2.resize(patch, (2 * r, 2 * r))
        y0, x0 = max(c[0] - r, 0), max(c[1] - r, 0)
        y1, x1 = min(c[0] + r, size), min(c[1] + r, size)
        sub = patch[y0 - (c[0] - r) : y1 - (c[0] - r), x0 - (c[1] - r) : x1 - (c[1] - r)]
        if rng.random() < 0.5:
            yy, xx = np.mgrid[y0:y1, x0:x1]
            m = ((yy - c[0]) ** 2 + (xx - c[1]) ** 2) <= r * r
            tex[y0:y1, x0:x1][m] = sub[m]
        else:
            tex[y0:y1, x0:x1] = sub
    return np.clip(tex, 0, 1).astype(np.float32)


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """4x4 robot-frame -> camera-frame transform (OpenCV camera: z forward, y down)."""
    eye, target, up = (np.asarray(a, float) for a in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, -R @ eye
    return T


def _rotvec(w) -> np.ndarray:
    return cv2.Rodrigues(np.asarray(w, np.float64).reshape(3, 1))[0]


def _rays(K: np.ndarray, T_cam_robot: np.ndarray, width: int, height: int):
    uu, vv = np.meshgrid(np.arange(width, dtype=float), np.arange(height, dtype=float))
    pix = np.stack([uu.ravel(), vv.ravel(), np.ones(uu.size)], 1)
    dc = pix @ np.linalg.inv(K).T
    R, t = T_cam_robot[:3, :3], T_cam_robot[:3, 3]
    d = dc @ R  # R^T dc
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = np.broadcast_to(-R.T @ t, d.shape)
    return o, d


@dataclass
class _Surface:
    t: np.ndarray
    colour: np.ndarray
    ident: int


def _render_frame(o, d, table_tex, planars, idents, joints, light_dir, gain):
    """Colour (M, 3) float and surface id (M,) (-1 table, -2 arm, else the planar's id)."""
    # table: z = 0 plane
    dz = np.where(np.abs(d[:, 2]) > 1e-9, d[:, 2], -1e-9)
    t_tab = -o[:, 2] / dz
    t_tab = np.where(t_tab > 0, t_tab, np.inf)
    hit = o + np.where(np.isfinite(t_tab), t_tab, 0)[:, None] * d
    S = table_tex.shape[0]
    tuv = np.stack(
        [
            (hit[:, 1] + _TABLE_HALF - _TABLE_C[1]) / (2 * _TABLE_HALF) * (S - 1),
            (hit[:, 0] + _TABLE_HALF - _TABLE_C[0]) / (2 * _TABLE_HALF) * (S - 1),
        ],
        1,
    )
    best_t = t_tab.copy()
    colour = _sample(table_tex, tuv) * 0.95
    colour = np.where(np.isfinite(t_tab)[:, None], colour, 0.25)
    ident = np.full(len(o), -1, np.int32)
    for p, k in zip(planars, idents, strict=True):
        t, uv = _ray_planar(o, d, p)
        better = t < best_t
        if better.any():
            colour[better] = _sample(p.texture, uv[better])
            best_t = np.where(better, t, best_t)
            ident[better] = k
    # arm: capsules base-shoulder-elbow-wrist-tip, grey metal with bands along each link
    for k in range(4):
        a, b = joints[k], joints[k + 1]
        t, n = ray_capsule(o, d, a, b, _ARM_RADII[k])
        better = t < best_t
        if better.any():
            pt = o[better] + t[better, None] * d[better]
            w = np.clip(((pt - a) @ (b - a)) / max(float((b - a) @ (b - a)), 1e-12), 0, 1)
            band = 0.5 + 0.5 * np.sin(w * 2 * np.pi * (3 + 2 * k) + 1.3 * k)
            lam = 0.35 + 0.65 * np.clip(n[better] @ light_dir, 0, 1)
            base = np.array([0.55, 0.55, 0.6]) * (0.6 + 0.4 * band[:, None])
            base[:, 0] += 0.25 * (k % 2)  # alternate reddish links
            colour[better] = np.clip(base * lam[:, None], 0, 1)
            best_t = np.where(better, t, best_t)
            ident[better] = -2
    return np.clip(colour * gain, 0, 1), ident


def _layout(rng, target: str):
    """Object centres (x, y) and yaw: the target sits in front of the arm, the others around."""
    spots = [(0.46, 0.15), (0.48, -0.03), (0.45, -0.21), (0.16, 0.13), (0.16, -0.15)]
    spots = [np.array(s) + rng.normal(0, 0.01, 2) for s in spots]
    others = [k for k in OBJECTS if k != target]
    rng.shuffle(others)
    centres = {target: np.array([0.31, 0.0]) + rng.normal(0, 0.01, 2)}
    # the push corridor (x ~ 0.31, along y) is kept clear
    for k, s in zip(others, spots, strict=False):
        centres[k] = s
    yaw = {k: float(rng.uniform(-0.4, 0.4)) for k in OBJECTS}
    yaw[target] = float(rng.uniform(-0.25, 0.25))
    return centres, yaw


def _flat(kind, centre, yaw, height, tex) -> Planar:
    hu, hv, shape = _OBJ_SIZE[kind]
    c, s = np.cos(yaw), np.sin(yaw)
    return Planar(
        np.array([centre[0], centre[1], height]),
        np.array([c, s, 0.0]),
        np.array([-s, c, 0.0]),
        hu,
        hv,
        shape,
        tex,
    )


def _write_png(path: Path, bgr: np.ndarray) -> None:
    """``cv2.imwrite``'s bytes, written atomically: imwrite on a full disk printed libpng's
    "Write Error" on stderr and returned False unchecked (the audit, item 6)."""
    from jaxcr.io.results import atomic_write_bytes

    ok, buf = cv2.imencode(".png", bgr)
    if not ok:
        raise OSError(f"{path}: PNG encoding failed")
    atomic_write_bytes(path, buf.tobytes())


def generate_motion_video(
    out: str | os.PathLike,
    preset: str = "pushed_static",
    seed: int = 0,
    size: tuple[int, int] = (320, 240),
    n_frames: int = 24,
    changing_background: bool | None = None,
    target: str | None = None,
    changes: tuple[str, ...] | None = None,
    touch_frame: int | None = None,
    video: bool = False,
    speed_px: float = 6.0,
) -> Path:
    """Write one synthetic video dataset (format ``jaxcr.motion/1``) to ``out``.

    Args:
        preset: "pushed_static" | "pushed_changing" | "held_static" | "held_changing" (the
            held set is the 3-D motion set: the arm grips the object and rotates it out of
            plane).
        seed: everything random (layout, textures, distractors, shake) derives from it.
        size: (width, height) pixels.
        n_frames: frames in the video (>= 6).
        changing_background: overrides the preset's static/changing choice.
        target: the object moved (default: ``OBJECTS[seed % 5]``).
        changes: subset of ("distractor", "shake", "lighting") for changing backgrounds
            (default: cycles through each alone and all together with the seed).
        touch_frame: first frame with contact (default 40 % of the video).
        video: also encode the frames as ``video.avi`` (MJPG) and point motion.json at it.
        speed_px: tip speed in image pixels per frame at 320 px width (scaled with width).
    Returns the dataset folder.
    """
    if preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r}; choose from {PRESETS}")
    if n_frames < 6:
        raise ValueError("n_frames must be >= 6")
    width, height = size
    held = preset.startswith("held")
    changing = preset.endswith("changing") if changing_background is None else changing_background
    rng = np.random.default_rng([seed, PRESETS.index(preset)])
    target = target or (
        ("book", "spirit_level")[seed % 2] if held else OBJECTS[seed % len(OBJECTS)]
    )
    if changing and changes is None:
        cyc = [("distractor",), ("shake",), ("lighting",), CHANGES]
        changes = cyc[seed % 4]
    changes = tuple(changes or ()) if changing else ()
    t_touch = int(round(0.4 * n_frames)) if touch_frame is None else int(touch_frame)

    # camera (robot frame): in front of the arm, looking back and down at the table
    f = 0.95 * width
    K = np.array([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1.0]])
    T_cam = look_at([0.80, 0.02, 0.48], [0.30, 0.0, 0.0])
    P = K @ T_cam[:3]

    table_tex = _table_texture(rng)
    textures = {k: _object_texture(rng, k) for k in OBJECTS}
    centres, yaws = _layout(rng, target)
    heights = {k: 0.012 + 0.004 * i for i, k in enumerate(OBJECTS)}
    statics = {k: _flat(k, centres[k], yaws[k], heights[k], textures[k]) for k in centres}
    tgt0 = statics[target]

    # tip trajectory and joints; touch[i] means the object moved between frames i-1 and i
    def trajectory(step_m):
        xs, touch, obj_T = [], [], []
        if not held:
            for i in range(n_frames):
                k = i - t_touch + 1  # steps past the contact (reached at frame t_touch - 1)
                tip = contact + k * step_m * dirn
                xs.append(arm_inverse(ARM, tip, -1.2))
                touch.append(i >= t_touch)
                T = np.eye(4)
                T[:3, 3] = max(k, 0) * step_m * dirn
                obj_T.append(T)
        else:
            n_move = max(n_frames - t_touch, 1)
            for i in range(n_frames):
                k = i - t_touch + 1
                if k <= 0:
                    x = arm_inverse(ARM, grip - k * step_m * approach, elev0)
                    T = np.eye(4)
                else:
                    sfrac = k / n_move
                    tip = grip + k * step_m * 0.8 * lift_dir
                    x = arm_inverse(ARM, tip, elev0 + elev_amp * sfrac, roll=roll_amp * sfrac)
                    T = np.asarray(_ee_frame(x)) @ np.linalg.inv(T_ee_grip)
                xs.append(x)
                touch.append(i >= t_touch)
                obj_T.append(T)
        return np.asarray(xs), touch, obj_T

    if not held:
        ang = float(rng.choice([-1.0, 1.0]) * np.pi / 2 + rng.uniform(-0.3, 0.3))
        dirn = np.array([np.cos(ang), np.sin(ang), 0.0])  # sideways push across the image
        # contact point: where the tip path enters the target's footprint (search along dirn)
        start_c = tgt0.origin - dirn * 0.25
        s = np.linspace(0, 0.25, 500)
        pts = start_c[None] + s[:, None] * dirn
        a = ((pts - tgt0.origin) @ tgt0.u) / tgt0.hu
        b = ((pts - tgt0.origin) @ tgt0.v) / tgt0.hv
        inside = _inside(tgt0.shape, a, b)
        contact = pts[int(np.argmax(inside))] - dirn * 0.004
        contact[2] = heights[target] * 0.6
    else:
        grip = tgt0.origin - tgt0.u * tgt0.hu * 0.8  # far edge: the hand does not cover it
        approach = np.array([-0.6, 0.0, 0.8])
        approach /= np.linalg.norm(approach)
        elev0 = -1.2
        T_ee_grip = np.asarray(_ee_frame(arm_inverse(ARM, grip, elev0)))
        lift_dir = np.array([rng.uniform(-0.3, 0.3), rng.choice([-1.0, 1.0]), 0.6])
        lift_dir /= np.linalg.norm(lift_dir)
        roll_amp = float(rng.uniform(0.9, 1.2)) * rng.choice([-1, 1])
        elev_amp = float(rng.uniform(0.15, 0.3))
    # scale the step so that the tip moves ``speed_px`` (x width / 320) pixels per frame
    xs, touch, obj_T = trajectory(0.01)
    uv = np.asarray(_tip_pixels(P, xs))
    measured = float(np.median(np.linalg.norm(np.diff(uv, axis=0), axis=1)))
    xs, touch, obj_T = trajectory(0.01 * speed_px * (width / 320.0) / max(measured, 1e-6))
    xs = np.asarray(xs)
    joints = np.asarray(_joint_positions_batch(xs))

    # changing-background elements
    distractors = []
    if "distractor" in changes:
        for _ in range(2):
            c0 = np.array(
                [rng.uniform(0.15, 0.6), rng.choice([-1, 1]) * rng.uniform(0.2, 0.3), 0.06]
            )
            v = rng.normal(0, 1, 3) * np.array([1, 1, 0])
            v = v / np.linalg.norm(v) * 0.012 * rng.uniform(0.8, 1.5)
            tex = _colour_noise(rng, 128, 6, (0.75, 0.5, 0.4), (0.95, 0.78, 0.65))
            distractors.append(
                (
                    Planar(
                        c0, np.array([1.0, 0, 0]), np.array([0, 1.0, 0]), 0.06, 0.04, "ellipse", tex
                    ),
                    v,
                )
            )
    shake = (
        rng.normal(0, np.deg2rad(0.4), (n_frames, 3))
        if "shake" in changes
        else np.zeros((n_frames, 3))
    )
    gain = (
        (
            1.0
            + 0.2
            * np.sin(
                2 * np.pi * np.arange(n_frames) / n_frames * rng.uniform(1.0, 2.0)
                + rng.uniform(0, 2 * np.pi)
            )
        )
        if "lighting" in changes
        else np.ones(n_frames)
    )
    light = np.array([0.3, -0.4, 0.87])
    light /= np.linalg.norm(light)

    out = Path(out)
    (out / "frames").mkdir(parents=True, exist_ok=True)
    (out / "masks").mkdir(parents=True, exist_ok=True)
    frames_meta = []
    writer = None
    if video:
        writer = cv2.VideoWriter(
            str(out / "video.avi"), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (width, height)
        )
    ids = list(statics)
    for i in range(n_frames):
        Tc = T_cam.copy()
        Tc[:3, :3] = _rotvec(shake[i]) @ Tc[:3, :3]
        Tc[:3, 3] = _rotvec(shake[i]) @ Tc[:3, 3]
        o, d = _rays(K, Tc, width, height)
        planars = [statics[k] if k != target else statics[k].moved(obj_T[i]) for k in ids]
        pid = list(range(len(ids)))
        for j, (p, v) in enumerate(distractors):
            T = np.eye(4)
            T[:3, 3] = v * i
            planars.append(p.moved(T))
            pid.append(100 + j)
        colour, ident = _render_frame(o, d, table_tex, planars, pid, joints[i], light, gain[i])
        img = apply_camera_effects(colour.reshape(height, width, 3).astype(np.float32), rng)
        mask = (ident == ids.index(target)).reshape(height, width)
        name = f"{i:06d}.png"
        _write_png(out / "frames" / name, cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
        _write_png(out / "masks" / name, mask.astype(np.uint8) * 255)
        if writer is not None:
            writer.write(cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
        frames_meta.append(
            {
                "index": i,
                "x": [float(v) for v in xs[i]],
                "touch": bool(touch[i]),
                "mask": f"masks/{name}",
            }
        )
    if writer is not None:
        writer.release()
    meta = {
        "format": "jaxcr.motion/1",
        "source": {"video": "video.avi"} if video else {"images": "frames"},
        "width": width,
        "height": height,
        "P": P.tolist(),
        "arm": ARM.to_dict(),
        "frames": frames_meta,
        "eval_frame": t_touch if not held else (t_touch + n_frames) // 2,
        "scene": {
            "preset": preset,
            "seed": seed,
            "object": target,
            "set": "held" if held else "pushed",
            "background": "changing" if changing else "static",
            "changes": list(changes),
            "K": K.tolist(),
            "T_cam_robot": T_cam.tolist(),
        },
    }
    tmp = out / "motion.json.tmp"
    tmp.write_text(json.dumps(meta, indent=1))
    os.replace(tmp, out / "motion.json")
    return out


_joint_positions_batch = jax.jit(jax.vmap(lambda x: joint_positions(ARM, x)))


def _tip_pixels(P, xs):
    from jaxcr.motion.arm import end_effector

    X = np.stack([np.asarray(end_effector(ARM, np.asarray(x))) for x in xs])
    Xh = np.concatenate([X, np.ones((len(X), 1))], 1) @ P.T
    return Xh[:, :2] / Xh[:, 2:]


def _ee_frame(x):
    from jaxcr.motion.arm import end_effector_frame

    return end_effector_frame(ARM, np.asarray(x, np.float64))
