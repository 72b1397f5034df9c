"""The ``real_like`` preset: a marker-free concentric-tube rig as real labs film it (issue 16
item 2), rendered by ray casting independently of the foreground estimator
(:mod:`jaxcr.segmentation.foreground` draws nothing here, and nothing here calls it).

Scene (base frame, metres; the stereo preset's geometry, :mod:`jaxcr.synth.stereo_ctr`):

* two webcams (default 1280x720; the focal length scales with the width), OpenCV lens
  distortion, webcam noise (optical blur, vignetting, read + shot noise, 8-bit);
* green cloth on the floor and two walls, with a weave, **dark creases** (soft folds that
  halve the brightness along random lines) and **static shadows** (large soft dark patches,
  down to 45 % brightness); both are in the plates too;
* on the wall behind the robot in camera 1, a **white circle-grid calibration board edged
  with black tape**, placed so that the tube crosses the board and its tape;
* the robot: a 2- or 3-tube CTR standing on the base (constant-curvature sections, exact
  ray-capsule intersections), the **outer tube dark and green-tinted**, the inner tubes
  grey metal; it casts a soft shadow on the cloth (directional light plus ambient);
* **no markers**; the **background plates** (empty scene) are rendered with the cameras
  at a slightly different orientation than the frames (a drift of ``drift_px`` pixels,
  sub-pixel to a few pixels, random direction per frame);
* an **occluder** (``occluder=True``, the default): a thin cable or tool shaft (a sagging
  chain of capsules, 0.6-1.6 mm radius, dark or grey) that crosses in front of the robot's
  middle part (20-70 % of its length) 8-30 mm nearer to one of the cameras. It is in the
  frames only, not in the plates (it moved into the scene), it casts no shadow, and it never
  covers the tip (the labelled tip is visible, as a human labeller needs);
* model error: the entry pixel handed to a method is the projection of the base through a
  camera pose perturbed by ``entry_error_px`` (the calibration/base-frame error of a rig);
  and each view's ``calib_camera`` (what a method may use as the rig's calibration) differs
  from the rendering camera by a calibration error: focal lengths by 0.15-0.3 %, the
  principal point by 0.75-1.5 px, the pose by 0.04-0.08 deg and 0.2-0.4 mm (each drawn as
  ``U(0.5, 1) x`` its limit, in a random direction or sign), the distortion unchanged.

Truth per view: the tip pixel (projection of the backbone's end point through the rendering
camera, OpenCV pixel convention), the visible robot mask at pixel centres (the occluder's
pixels excluded), the projected backbone.

The occluder and the calibration error are drawn from their own random stream
(``[seed, 18]``), so the rest of a seed's scene is the one rendered before they were added.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from jaxcr.stereo.aruco import MarkerLayout
from jaxcr.synth.raycast import ray_capsule
from jaxcr.synth.render import apply_camera_effects, pixel_rays, subpixel_rays
from jaxcr.synth.scene import RenderCamera
from jaxcr.synth.stereo_ctr import (
    WALL_OFFSET,
    _shadowed,
    cc_backbone,
    sample_robot,
    stereo_cameras,
    trace_rays,
)

__all__ = ["RealLikeView", "RealLikeFrame", "render_real_like_frame"]

CLOTH_RGB = np.array([0.16, 0.50, 0.20])
OUTER_RGB = np.array([0.10, 0.15, 0.11])  # dark, green-tinted outer tube
INNER_RGB = np.array([0.45, 0.46, 0.47])  # grey metal (darker than the white board)
_LIGHT = np.array([0.35, 0.25, 0.90])
BOARD_HALF = (0.045, 0.035)  # half width (y) and half height (z) of the board, metres
TAPE_W = 0.005  # black tape width, metres


@dataclass
class RealLikeView:
    """One camera's frame: ``image`` and ``plate`` uint8 (H, W, 3); ``tip_px`` (2,) true tip
    (u, v); ``entry_px`` (2,) the base pixel with model error; ``entry_true_px`` (2,);
    ``entry_dir_px`` (2,) unit image direction in which the robot leaves the base (the
    projected nominal base axis, turned by a random error of ``dir_error_deg`` rms);
    ``mask`` (H, W) bool true robot pixels; ``backbone_px`` (n, 2); ``drift_px`` (2,) the
    plate's image shift relative to the frame's camera (approximate, at the image
    centre); ``camera`` the frame's render camera; ``calib_camera`` the same camera with
    calibration error (what a method is given); ``occluder_px`` (m, 2) the projected
    centre line of the occluder (empty without one)."""

    image: np.ndarray
    plate: np.ndarray
    tip_px: np.ndarray
    entry_px: np.ndarray
    entry_true_px: np.ndarray
    entry_dir_px: np.ndarray
    mask: np.ndarray
    backbone_px: np.ndarray
    drift_px: np.ndarray
    camera: RenderCamera
    calib_camera: RenderCamera | None = None
    occluder_px: np.ndarray | None = None


@dataclass
class RealLikeFrame:
    views: list[RealLikeView]
    seed: int


class _RealScene:
    """Cloth planes with creases and static shadows, the taped board, robot capsules."""

    def __init__(self, layout: MarkerLayout, robot_p, robot_r, section, rng, occluder=None):
        self.p, self.r = robot_p, robot_r
        # occluder: None or (points (n, 3), radius, albedo (3,)), a capsule chain.
        self.occluder = occluder
        if robot_r is not None:
            r_next = np.r_[robot_r[1:], 0.0]
            self.flat_end = r_next < robot_r - 1e-12
            self.r_next = r_next
            self.section = section
        self.light = _LIGHT / np.linalg.norm(_LIGHT)
        bc = layout.base_centre
        self.bc = bc
        self.planes = [
            (np.array([0, 0, 0.0]), np.array([0, 0, 1.0])),
            (bc + np.array([-WALL_OFFSET, 0, 0]), np.array([1.0, 0, 0])),
            (bc + np.array([0, -WALL_OFFSET, 0]), np.array([0, 1.0, 0])),
        ]
        # Creases: per plane, lines (point, unit direction in the plane's 2-D coordinates).
        self.creases = [
            [(rng.uniform(-0.08, 0.08, 2), rng.uniform(0, np.pi), rng.uniform(0.001, 0.003))
             for _ in range(rng.integers(4, 8))]
            for _ in self.planes
        ]  # fmt: skip
        # Static shadows: a few soft elliptical patches per plane.
        self.patches = [
            [(rng.uniform(-0.08, 0.08, 2), rng.uniform(0.01, 0.03), rng.uniform(0.45, 0.75))
             for _ in range(rng.integers(2, 4))]
            for _ in self.planes
        ]  # fmt: skip
        self.weave = rng.normal(0, 1, (128, 128))
        # Board on the wall behind the robot in camera 1 (plane 1: x = const), centre
        # (y, z) near the robot's height so the tube crosses it.
        self.board_c = np.array([bc[1] + rng.uniform(-0.01, 0.01), rng.uniform(0.045, 0.06)])

    def plane_coords(self, k: int, P: np.ndarray) -> np.ndarray:
        """2-D coordinates (metres) on plane ``k`` relative to the base centre."""
        q = P - self.bc
        if k == 0:
            return q[:, [0, 1]]
        if k == 1:
            return np.stack([q[:, 1], P[:, 2]], 1)
        return np.stack([q[:, 0], P[:, 2]], 1)

    def cloth_albedo(self, k: int, P: np.ndarray) -> np.ndarray:
        xy = self.plane_coords(k, P)
        g = self.weave[
            (np.floor(xy[:, 1] * 3000).astype(np.int64)) % 128,
            (np.floor(xy[:, 0] * 3000).astype(np.int64)) % 128,
        ]
        f = 1.0 + 0.05 * g
        for c, ang, wid in self.creases[k]:
            n = np.array([-np.sin(ang), np.cos(ang)])
            dist = (xy - c) @ n
            f = f * (1.0 - 0.5 * np.exp(-0.5 * (dist / wid) ** 2))
        for c, rad, depth in self.patches[k]:
            r2 = np.sum((xy - c) ** 2, 1) / rad**2
            f = f * (1.0 - (1.0 - depth) * np.exp(-0.5 * r2))
        alb = CLOTH_RGB[None] * f[:, None]
        if k == 1:  # the board
            y, z = xy[:, 0], xy[:, 1]
            hy, hz = BOARD_HALF
            dy, dz = np.abs(y - self.board_c[0]), np.abs(z - self.board_c[1])
            on = (dy < hy) & (dz < hz)
            tape = on & ((dy > hy - TAPE_W) | (dz > hz - TAPE_W))
            # Circle grid: 4 mm dots on a 9 mm pitch inside the tape.
            gy = (y - self.board_c[0]) / 0.009
            gz = (z - self.board_c[1]) / 0.009
            dot = np.hypot(gy - np.round(gy), gz - np.round(gz)) * 0.009 < 0.002
            alb[on] = 0.95  # white paper: brighter than the steel tubes
            alb[on & dot] = 0.08
            alb[tape] = 0.04
        return alb


def _occluder_hits(scene: _RealScene, C: np.ndarray, d: np.ndarray):
    """First hits of base-frame rays from ``C`` with the occluder's capsule chain: distance
    (M,) (inf on a miss) and unit normal (M, 3)."""
    m = len(d)
    t_occ = np.full(m, np.inf)
    n_occ = np.zeros((m, 3))
    if scene.occluder is None:
        return t_occ, n_occ
    pts, rad, _ = scene.occluder
    o = np.broadcast_to(C, (m, 3))
    for a, b in zip(pts[:-1], pts[1:], strict=True):
        # Rays within the capsule's bounding sphere only (the exact test is per ray).
        cen, half = (a + b) / 2, np.linalg.norm(b - a) / 2 + rad
        oc = cen - C
        proj = d @ oc
        sel = np.nonzero(oc @ oc - proj**2 < half * half)[0]
        if not len(sel):
            continue
        tt, n = ray_capsule(o[sel], d[sel], a, b, rad)
        better = tt < t_occ[sel]
        t_occ[sel[better]] = tt[better]
        n_occ[sel[better]] = n[better]
    return t_occ, n_occ


def _shade_real(scene: _RealScene, cam: RenderCamera, d_cam: np.ndarray):
    C, d, tb, nb, pid, t_rob, n_rob, k_rob = trace_rays(scene, cam, d_cam)
    m = len(d)
    rgb = np.zeros((m, 3))
    t_occ, n_occ = _occluder_hits(scene, C, d)
    occ = t_occ < np.minimum(tb, t_rob)
    robot = (t_rob < tb) & ~occ
    cloth = ~robot & ~occ & np.isfinite(tb)
    ci = np.nonzero(cloth)[0]
    P = C + tb[ci, None] * d[ci]
    alb = np.zeros((len(ci), 3))
    for k in range(len(scene.planes)):
        sel = pid[ci] == k
        if sel.any():
            alb[sel] = scene.cloth_albedo(k, P[sel])
    shadow = _shadowed(scene, P) if scene.p is not None else np.zeros(len(ci), bool)
    ndl = np.clip(nb[ci] @ scene.light, 0, 1) * (~shadow)
    rgb[ci] = alb * (0.62 + 0.5 * ndl)[:, None]
    ri = np.nonzero(robot)[0]
    if len(ri):
        n = n_rob[ri]
        v = -d[ri]
        sec = scene.section[k_rob[ri]]
        base = np.where((sec == 0)[:, None], OUTER_RGB[None], INNER_RGB[None])
        ndl = np.clip(n @ scene.light, 0, 1)
        h = scene.light[None] + v
        h /= np.linalg.norm(h, axis=1, keepdims=True)
        ndh = np.clip(np.einsum("ij,ij->i", n, h), 0, 1)
        spec = np.where(sec == 0, 0.25, 0.6) * ndh**40
        refl = d[ri] - 2 * np.einsum("ij,ij->i", d[ri], n)[:, None] * n
        to_cloth = np.clip(0.5 - 0.8 * refl[:, 2], 0, 1)[:, None]
        env = to_cloth * CLOTH_RGB * 0.5 + (1 - to_cloth) * 0.35
        rgb[ri] = base * (0.55 + 0.6 * ndl)[:, None] + spec[:, None] + 0.15 * env
    oi = np.nonzero(occ)[0]
    if len(oi):
        n = n_occ[oi]
        ndl = np.clip(n @ scene.light, 0, 1)
        h = scene.light[None] - d[oi]
        h /= np.linalg.norm(h, axis=1, keepdims=True)
        spec = 0.3 * np.clip(np.einsum("ij,ij->i", n, h), 0, 1) ** 30
        rgb[oi] = scene.occluder[2][None] * (0.55 + 0.6 * ndl)[:, None] + spec[:, None]
    return rgb, robot


def _draw_occluder(rng: np.random.Generator, backbone: np.ndarray, cams) -> tuple:
    """A thin cable or tool shaft crossing in front of the robot (module docstring):
    (points (n, 3), radius, albedo (3,)), base frame, metres."""
    seg = np.linalg.norm(np.diff(backbone, axis=0), axis=1)
    s = np.r_[0.0, np.cumsum(seg)]
    k = int(np.searchsorted(s, rng.uniform(0.2, 0.7) * s[-1]))
    k = min(max(k, 1), len(backbone) - 2)
    Q = backbone[k]
    tangent = backbone[k + 1] - backbone[k - 1]
    tangent /= np.linalg.norm(tangent)
    cam = cams[int(rng.integers(len(cams)))]
    R, t = cam.T_cam_robot[:3, :3], cam.T_cam_robot[:3, 3]
    Cc = -R.T @ t
    to_cam = (Cc - Q) / np.linalg.norm(Cc - Q)
    centre = Q + rng.uniform(0.008, 0.03) * to_cam
    # Across the tube as the camera sees it: perpendicular to the viewing ray, at 35-90 deg
    # to the tube's tangent in that plane.
    t_perp = tangent - (tangent @ to_cam) * to_cam
    t_perp /= max(np.linalg.norm(t_perp), 1e-12)
    other = np.cross(to_cam, t_perp)
    ang = np.radians(rng.uniform(35, 90)) * rng.choice([-1.0, 1.0])
    axis = np.cos(ang) * t_perp + np.sin(ang) * other
    sag = rng.uniform(0.0, 0.01)  # a cable sags; a tool shaft is straight (sag 0)
    u = np.linspace(-0.15, 0.15, 13)
    pts = centre[None] + u[:, None] * axis[None]
    pts[:, 2] += sag * (u / 0.15) ** 2  # through ``centre``, its middle lowest
    radius = rng.uniform(0.6e-3, 1.6e-3)
    albedo = np.full(3, rng.uniform(0.03, 0.35)) * rng.uniform(0.9, 1.1, 3)
    return pts, radius, albedo


def _covers_tip(occ: tuple, tip: np.ndarray, cams) -> bool:
    """Whether the occluder passes within its own projected radius plus 8 px (at 1280 px
    width; scaled with the width) of the tip's pixel in some view."""
    pts, rad, _ = occ
    for cam in cams:
        uv = _project(cam, pts)
        t = _project(cam, tip[None])[0]
        depth = (cam.T_cam_robot[:3, :3] @ pts.T + cam.T_cam_robot[:3, 3:]).T[:, 2]
        r_px = cam.K[0, 0] * rad / max(float(depth.min()), 1e-6)
        a, b = uv[:-1], uv[1:]
        ab = b - a
        w = np.clip(np.einsum("ij,ij->i", t - a, ab) / np.maximum((ab**2).sum(1), 1e-12), 0, 1)
        dist = np.linalg.norm(a + w[:, None] * ab - t, axis=1).min()
        if dist < r_px + 8.0 * cam.width / 1280:
            return True
    return False


def _calibrated(cam: RenderCamera, rng: np.random.Generator) -> RenderCamera:
    """``cam`` with a calibration error (module docstring)."""
    K = cam.K.copy()
    K[0, 0] *= 1 + rng.choice([-1, 1]) * rng.uniform(0.5, 1) * 0.003
    K[1, 1] *= 1 + rng.choice([-1, 1]) * rng.uniform(0.5, 1) * 0.003
    pp = rng.normal(0, 1, 2)
    K[:2, 2] += pp / np.linalg.norm(pp) * rng.uniform(0.5, 1) * 1.5
    ax = rng.normal(0, 1, 3)
    ax /= np.linalg.norm(ax)
    ang = np.radians(rng.uniform(0.5, 1) * 0.08)
    Kx = np.array([[0, -ax[2], ax[1]], [ax[2], 0, -ax[0]], [-ax[1], ax[0], 0]])
    dR = np.eye(3) + np.sin(ang) * Kx + (1 - np.cos(ang)) * Kx @ Kx
    tr = rng.normal(0, 1, 3)
    T = cam.T_cam_robot.copy()
    T[:3, :3] = dR @ T[:3, :3]
    T[:3, 3] = dR @ T[:3, 3] + tr / np.linalg.norm(tr) * rng.uniform(0.5, 1) * 4e-4
    return RenderCamera(K, cam.dist.copy(), T, cam.width, cam.height)


def _render(scene: _RealScene, cam: RenderCamera, rays) -> tuple[np.ndarray, np.ndarray]:
    """Linear RGB (H, W, 3) with edge supersampling (3x3), and the robot mask; ``rays`` the
    camera's :func:`pixel_rays` (they depend on the intrinsics only)."""
    h, w = cam.height, cam.width
    rgb, robot = _shade_real(scene, cam, rays.d)
    rgb = rgb.reshape(h, w, 3)
    robot = robot.reshape(h, w)
    lum = rgb.mean(axis=2)
    pad = np.pad(lum, 1, mode="edge")
    win = np.stack([pad[i : i + h, j : j + w] for i in range(3) for j in range(3)])
    # Edges of the board, tape, dots and plane seams (the weave varies by < 0.1 over 3x3).
    edge = (win.max(0) - win.min(0)) > 0.15
    if robot.any():
        rp = np.pad(robot, 2)
        near = np.zeros_like(robot)
        for i in range(5):
            for j in range(5):
                near |= rp[i : i + h, j : j + w]
        edge |= near
    rr, cc = np.nonzero(edge)
    if len(rr):
        sub = subpixel_rays(cam, rr, cc, 3)
        srgb, _ = _shade_real(scene, cam, sub.d)
        rgb[rr, cc] = srgb.reshape(len(rr), 9, 3).mean(axis=1)
    return rgb, robot


def _rotated(cam: RenderCamera, shift_px: np.ndarray) -> RenderCamera:
    """The camera turned about its centre so the image moves by about ``shift_px``."""
    f = cam.K[0, 0]
    ay, ax = shift_px[0] / f, shift_px[1] / f  # small rotations about camera y and x
    Ry = np.array([[np.cos(ay), 0, np.sin(ay)], [0, 1, 0], [-np.sin(ay), 0, np.cos(ay)]])
    Rx = np.array([[1, 0, 0], [0, np.cos(ax), -np.sin(ax)], [0, np.sin(ax), np.cos(ax)]])
    T = cam.T_cam_robot.copy()
    Rd = Rx.T @ Ry  # x' = x + f*ay ... (sign fixed below by construction)
    T2 = np.eye(4)
    T2[:3, :3] = Rd
    return cam.with_pose(T2 @ T)


def _project(cam: RenderCamera, P: np.ndarray) -> np.ndarray:
    import cv2

    T = cam.T_cam_robot
    uv, _ = cv2.projectPoints(
        np.ascontiguousarray(P, np.float64).reshape(-1, 3),
        cv2.Rodrigues(T[:3, :3])[0], T[:3, 3], cam.K, cam.dist,
    )  # fmt: skip
    return uv.reshape(-1, 2)


def render_real_like_frame(
    seed: int,
    size: tuple[int, int] = (1280, 720),
    *,
    max_drift_px: float = 3.0,
    entry_error_px: float = 3.0,
    dir_error_deg: float = 8.0,
    noise: float = 0.02,
    occluder: bool = True,
) -> RealLikeFrame:
    """One frame of the ``real_like`` preset (both views), deterministic for ``seed``;
    ``occluder=False`` leaves the occluder out (the scene is otherwise the same)."""
    rng = np.random.default_rng([seed, 16])
    layout = MarkerLayout()
    cams = stereo_cameras(size, layout, rng)
    # "general" configurations only: a tip curled back over its own shaft (the stereo
    # preset's "curled" kind) cannot be told from the shaft in one view by any method.
    robot = sample_robot(rng, "general", layout, cams)
    fine = cc_backbone(robot, 1e-3)
    radius = fine["diameter"][1:] / 2
    section = fine["section"][1:]
    rng_err = np.random.default_rng([seed, 18])
    for _ in range(50):  # redraw an occluder that would cover the tip in a view
        occ = _draw_occluder(rng_err, fine["p"], cams)
        if not _covers_tip(occ, fine["p"][-1], cams):
            break
    calib = [_calibrated(c, rng_err) for c in cams]
    scene = _RealScene(layout, fine["p"], radius, section, np.random.default_rng([seed, 17]),
                       occ if occluder else None)  # fmt: skip
    empty = _RealScene(layout, None, None, None, np.random.default_rng([seed, 17]))
    views = []
    for k, cam in enumerate(cams):
        rays = pixel_rays(cam)
        rgb, mask = _render(scene, cam, rays)
        drift = rng.uniform(-1, 1, 2)
        drift = drift / np.linalg.norm(drift) * rng.uniform(0.2, max_drift_px)
        pcam = _rotated(cam, drift)
        prgb, _ = _render(empty, pcam, rays)
        img = apply_camera_effects(rgb, np.random.default_rng([seed, k, 1]), 0.7, noise)
        plate = apply_camera_effects(prgb, np.random.default_rng([seed, k, 2]), 0.7, noise)
        bb_px = _project(cam, fine["p"])
        centre = np.array([[cam.width / 2, cam.height / 2]])
        ray = np.linalg.solve(cam.K, np.array([cam.width / 2, cam.height / 2, 1.0]))
        Pc = np.linalg.inv(cam.T_cam_robot) @ np.r_[ray * 0.25, 1.0]
        drift_meas = _project(pcam, Pc[None, :3])[0] - centre[0]
        entry_true = _project(cam, layout.base_centre[None])[0]
        e = rng.normal(0, 1, 2)
        entry = entry_true + e / max(np.linalg.norm(e), 1e-9) * rng.uniform(0, entry_error_px)
        axis = _project(cam, layout.base_centre[None] + np.array([[0.0, 0.0, 0.005]]))[0]
        a = np.arctan2(*(axis - entry_true)[::-1]) + np.radians(rng.normal(0, dir_error_deg))
        direction = np.array([np.cos(a), np.sin(a)])
        occ_px = _project(cam, occ[0]) if occluder else np.zeros((0, 2))
        views.append(
            RealLikeView(
                img,
                plate,
                bb_px[-1],
                entry,
                entry_true,
                direction,
                mask,
                bb_px,
                drift_meas,
                cam,
                calib[k],
                occ_px,
            )  # fmt: skip
        )
    return RealLikeFrame(views, seed)
