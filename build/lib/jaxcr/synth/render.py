"""Ray-casting renderer for synthetic continuum-robot scenes (numpy + OpenCV).

Independent of jaxcr's estimators by construction: each pixel becomes a ray
(``cv2.undistortPoints`` inverts the lens distortion), the ray is intersected exactly with
every surface (capsule chain of the robot, occluder capsules and boxes, the tissue plane; see
:mod:`jaxcr.synth.raycast`) and the nearest hit wins. Model points are projected only to
bound which pixels can possibly hit a primitive (a conservative box with a margin), never
to draw.

Outputs per camera and frame:
* the shaded RGB image, anti-aliased by 3x3 supersampling of the pixels on object edges
  (pixels whose first-hit surface or depth differs from a neighbour, dilated by one pixel),
  then blurred and corrupted by camera noise;
* binary masks evaluated at pixel centres: ``visible`` (the centre ray hits the robot
  first), ``full`` (the centre ray hits the robot when occluders and tissue are ignored),
  ``occluder`` (the centre ray hits an occluder first).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from jaxcr.synth.raycast import ray_box, ray_capsule, ray_plane
from jaxcr.synth.scene import Box, Capsule, Material, RenderCamera, Scene, TubeBody

KIND_NONE, KIND_TISSUE, KIND_ROBOT, KIND_OCCLUDER = 0, 1, 2, 3
_BBOX_MARGIN_PX = 2.0
_SUPERSAMPLE = 3
_VOID_RGB = np.array([0.04, 0.035, 0.035])
_ROOM_RGB = np.array([0.42, 0.42, 0.45])
_TISSUE_MEAN_RGB = np.array([0.80, 0.50, 0.48])


@dataclass
class RaySet:
    """Rays from the camera centre: ``d`` (M, 3) unit directions in the camera frame, with
    the pixel (``row``, ``col``) each belongs to; sorted by row so that a pixel box can be
    selected with a binary search."""

    row: np.ndarray
    col: np.ndarray
    d: np.ndarray

    def select(self, box: tuple[int, int, int, int] | None) -> np.ndarray:
        """Indices of rays whose pixel lies in ``box = (r0, r1, c0, c1)`` (inclusive)."""
        if box is None:
            return np.arange(len(self.row))
        r0, r1, c0, c1 = box
        i0 = np.searchsorted(self.row, r0, "left")
        i1 = np.searchsorted(self.row, r1, "right")
        c = self.col[i0:i1]
        return i0 + np.nonzero((c >= c0) & (c <= c1))[0]


def undistort_to_rays(cam: RenderCamera, uv: np.ndarray) -> np.ndarray:
    """Unit ray directions (M, 3) in the camera frame through distorted pixels ``uv`` (M, 2).

    Uses ``cv2.undistortPoints`` with a tight iteration criterion (round trip through
    ``cv2.projectPoints`` below 1e-6 px for ordinary lenses).
    """
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-12)
    xy = cv2.undistortPoints(
        np.ascontiguousarray(uv, np.float64).reshape(-1, 1, 2),
        cam.K,
        cam.dist,
        None,
        None,
        None,
        crit,
    ).reshape(-1, 2)
    d = np.concatenate([xy, np.ones((len(xy), 1))], axis=1)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


_GRID_CACHE: dict[tuple, RaySet] = {}


def pixel_rays(cam: RenderCamera) -> RaySet:
    """Rays through all pixel centres (row-major), cached per intrinsics and size."""
    key = (cam.width, cam.height, cam.K.tobytes(), cam.dist.tobytes())
    if key not in _GRID_CACHE:
        rows, cols = np.mgrid[0 : cam.height, 0 : cam.width]
        uv = np.stack([cols.ravel(), rows.ravel()], axis=1).astype(np.float64)
        _GRID_CACHE.clear()
        _GRID_CACHE[key] = RaySet(rows.ravel(), cols.ravel(), undistort_to_rays(cam, uv))
    return _GRID_CACHE[key]


def subpixel_rays(cam: RenderCamera, rows: np.ndarray, cols: np.ndarray, n: int) -> RaySet:
    """``n`` x ``n`` stratified sub-pixel rays for each listed pixel (rows sorted), grouped
    per pixel (n*n consecutive rays each)."""
    off = (np.arange(n) + 0.5) / n - 0.5
    ou, ov = np.meshgrid(off, off)
    u = cols[:, None] + ou.ravel()[None, :]
    v = rows[:, None] + ov.ravel()[None, :]
    uv = np.stack([u.ravel(), v.ravel()], axis=1)
    return RaySet(np.repeat(rows, n * n), np.repeat(cols, n * n), undistort_to_rays(cam, uv))


def _normalised_limits(cam: RenderCamera) -> tuple[float, float, float, float]:
    """Normalised-coordinate box (x0, x1, y0, y1) covering the image with 25% spare."""
    w, h = cam.width, cam.height
    border = np.array(
        [[u, v] for u in np.linspace(-0.5, w - 0.5, 9) for v in (-0.5, h - 0.5)]
        + [[u, v] for v in np.linspace(-0.5, h - 0.5, 9) for u in (-0.5, w - 0.5)]
    )
    d = undistort_to_rays(cam, border)
    x, y = d[:, 0] / d[:, 2], d[:, 1] / d[:, 2]
    sx, sy = 0.25 * (x.max() - x.min()), 0.25 * (y.max() - y.min())
    return x.min() - sx, x.max() + sx, y.min() - sy, y.max() + sy


def pixel_boxes(
    cam: RenderCamera, lo: np.ndarray, hi: np.ndarray
) -> list[tuple[int, int, int, int] | None]:
    """Conservative pixel boxes of axis-aligned 3D boxes [lo, hi] (K, 3) in the camera frame.

    The perspective image of a box lies inside the box spanned by its corners' normalised
    coordinates; that box (clipped to the image's neighbourhood) is pushed through the lens
    distortion along its sampled boundary, and a margin is added. Boxes reaching behind the
    camera get ``None`` (all pixels). Empty boxes (entirely off-image) get ``(1, 0, 1, 0)``.
    """
    nk = len(lo)
    corners = np.stack(
        [
            np.stack(
                [
                    lo[:, 0] if i else hi[:, 0],
                    lo[:, 1] if j else hi[:, 1],
                    lo[:, 2] if k else hi[:, 2],
                ],
                1,
            )
            for i in (0, 1)
            for j in (0, 1)
            for k in (0, 1)
        ],
        axis=1,
    )  # (K, 8, 3)
    z = corners[..., 2]
    behind = (z <= 1e-4).any(axis=1)
    zs = np.where(z > 1e-4, z, 1.0)
    xn, yn = corners[..., 0] / zs, corners[..., 1] / zs
    x0, x1, y0, y1 = _normalised_limits(cam)
    bx0 = np.clip(xn.min(1), x0, x1)
    bx1 = np.clip(xn.max(1), x0, x1)
    by0 = np.clip(yn.min(1), y0, y1)
    by1 = np.clip(yn.max(1), y0, y1)
    s = np.linspace(0.0, 1.0, 7)
    # Boundary samples of each normalised box: (K, 28, 2).
    top = np.stack([bx0[:, None] + s * (bx1 - bx0)[:, None], np.repeat(by0[:, None], 7, 1)], -1)
    bot = np.stack([bx0[:, None] + s * (bx1 - bx0)[:, None], np.repeat(by1[:, None], 7, 1)], -1)
    lef = np.stack([np.repeat(bx0[:, None], 7, 1), by0[:, None] + s * (by1 - by0)[:, None]], -1)
    rig = np.stack([np.repeat(bx1[:, None], 7, 1), by0[:, None] + s * (by1 - by0)[:, None]], -1)
    pts = np.concatenate([top, bot, lef, rig], axis=1).reshape(-1, 2)
    obj = np.concatenate([pts, np.ones((len(pts), 1))], axis=1)
    uv, _ = cv2.projectPoints(obj, np.zeros(3), np.zeros(3), cam.K, cam.dist)
    uv = uv.reshape(nk, -1, 2)
    out: list[tuple[int, int, int, int] | None] = []
    for k in range(nk):
        if behind[k]:
            out.append(None)
            continue
        c0 = int(np.floor(uv[k, :, 0].min() - _BBOX_MARGIN_PX))
        c1 = int(np.ceil(uv[k, :, 0].max() + _BBOX_MARGIN_PX))
        r0 = int(np.floor(uv[k, :, 1].min() - _BBOX_MARGIN_PX))
        r1 = int(np.ceil(uv[k, :, 1].max() + _BBOX_MARGIN_PX))
        c0, r0 = max(c0, 0), max(r0, 0)
        c1, r1 = min(c1, cam.width - 1), min(r1, cam.height - 1)
        out.append((r0, r1, c0, c1) if (r0 <= r1 and c0 <= c1) else (1, 0, 1, 0))
    return out


@dataclass
class _CamPrims:
    """Scene primitives moved into one camera frame, with their materials indexed.

    Capsules are ordered robot first (``n_robot_caps`` of them); ``caps_static`` and the
    boxes' flags mark primitives of the static layer (cached per camera)."""

    caps_a: np.ndarray  # (C, 3)
    caps_b: np.ndarray
    caps_r: np.ndarray
    caps_mat: np.ndarray  # (C,) material index
    caps_static: np.ndarray  # (C,) bool
    boxes: list[tuple[np.ndarray, np.ndarray, np.ndarray, int, bool]]
    n_robot_caps: int
    materials: list[Material]
    kinds: np.ndarray  # (n_materials,) KIND_* per material
    plane_point: np.ndarray
    plane_normal: np.ndarray


def _to_cam(T: np.ndarray, p: np.ndarray) -> np.ndarray:
    return p @ T[:3, :3].T + T[:3, 3]


def _prepare(cam: RenderCamera, scene: Scene) -> _CamPrims:
    T = cam.T_cam_robot
    materials: list[Material] = [Material("tissue", (0.0, 0.0, 0.0))]
    kinds = [KIND_TISSUE]

    def mat_index(m: Material, kind: int) -> int:
        for i, existing in enumerate(materials):
            if existing == m and kinds[i] == kind:
                return i
        materials.append(m)
        kinds.append(kind)
        return len(materials) - 1

    caps: list[Capsule] = []
    cap_kind: list[int] = []
    cap_static: list[bool] = []
    if scene.robot is not None:
        caps += scene.robot.capsules()
        cap_kind += [KIND_ROBOT] * len(scene.robot.radius)
        cap_static += [False] * len(scene.robot.radius)
    n_robot = len(caps)
    boxes = []
    for static, group in ((False, scene.occluders), (True, scene.static_occluders)):
        for occ in group:
            if isinstance(occ, Capsule):
                caps.append(occ)
                cap_kind.append(KIND_OCCLUDER)
                cap_static.append(static)
            elif isinstance(occ, Box):
                boxes.append(
                    (
                        _to_cam(T, occ.centre[None])[0],
                        T[:3, :3] @ occ.axes,
                        np.asarray(occ.half, float),
                        mat_index(occ.material, KIND_OCCLUDER),
                        static,
                    )
                )
            else:
                raise TypeError(f"unknown occluder type {type(occ).__name__}")
    if caps:
        a = _to_cam(T, np.stack([c.a for c in caps]))
        b = _to_cam(T, np.stack([c.b for c in caps]))
        r = np.array([c.radius for c in caps])
        m = np.array([mat_index(c.material, k) for c, k in zip(caps, cap_kind, strict=True)])
    else:
        a = b = np.zeros((0, 3))
        r = np.zeros(0)
        m = np.zeros(0, int)
    if scene.tissue is not None:
        plane_point = _to_cam(T, scene.tissue.origin[None])[0]
        plane_normal = T[:3, :3] @ scene.tissue.normal
    else:
        plane_point, plane_normal = np.zeros(3), np.zeros(3)
    return _CamPrims(
        caps_a=a,
        caps_b=b,
        caps_r=r,
        caps_mat=m,
        caps_static=np.array(cap_static, bool),
        boxes=boxes,
        n_robot_caps=n_robot,
        materials=materials,
        kinds=np.array(kinds),
        plane_point=plane_point,
        plane_normal=plane_normal,
    )


@dataclass
class Trace:
    """Per-ray results: first-hit distance ``t``, material index ``mat`` (-1: nothing),
    kind (KIND_*), unit normal, and the robot's own first hit ``t_robot`` (ignoring every
    other surface; ``inf`` where the ray misses the robot)."""

    t: np.ndarray
    mat: np.ndarray
    kind: np.ndarray
    normal: np.ndarray
    t_robot: np.ndarray


def trace(cam: RenderCamera, prims: _CamPrims, rays: RaySet, layer: str = "all") -> Trace:
    """Cast ``rays`` against the primitives of ``layer`` (``"all"``, ``"dynamic"`` = robot and
    moving occluders, ``"static"`` = tissue and static occluders, ``"robot"``); the nearest
    hit wins (depth test)."""
    if layer not in ("all", "dynamic", "static", "robot"):
        raise ValueError(f"unknown layer {layer!r}")
    m = len(rays.row)
    t_best = np.full(m, np.inf)
    mat = np.full(m, -1)
    normal = np.zeros((m, 3))
    t_robot = np.full(m, np.inf)

    def wanted(static: bool) -> bool:
        return layer == "all" or (layer == "static") == static

    nc = prims.n_robot_caps if layer == "robot" else len(prims.caps_r)
    if nc:
        lo = np.minimum(prims.caps_a[:nc], prims.caps_b[:nc]) - prims.caps_r[:nc, None]
        hi = np.maximum(prims.caps_a[:nc], prims.caps_b[:nc]) + prims.caps_r[:nc, None]
        boxes = pixel_boxes(cam, lo, hi)
        for k in range(nc):
            if not wanted(bool(prims.caps_static[k])):
                continue
            idx = rays.select(boxes[k])
            if len(idx) == 0:
                continue
            t, n = ray_capsule(
                np.zeros((len(idx), 3)),
                rays.d[idx],
                prims.caps_a[k],
                prims.caps_b[k],
                prims.caps_r[k],
            )
            if k < prims.n_robot_caps:
                t_robot[idx] = np.minimum(t_robot[idx], t)
            better = t < t_best[idx]
            sel = idx[better]
            t_best[sel] = t[better]
            mat[sel] = prims.caps_mat[k]
            normal[sel] = n[better]
    if layer == "robot":
        kind = np.where(np.isfinite(t_robot), KIND_ROBOT, KIND_NONE)
        return Trace(t_best, mat, kind, normal, t_robot)
    use = [b for b in prims.boxes if wanted(b[4])]
    if use:
        c = np.stack([b[0] for b in use])
        ext = np.stack([np.abs(b[1]) @ b[2] for b in use])
        boxes = pixel_boxes(cam, c - ext, c + ext)
        for (centre, axes, half, mi, _), box in zip(use, boxes, strict=True):
            idx = rays.select(box)
            if len(idx) == 0:
                continue
            t, n = ray_box(np.zeros((len(idx), 3)), rays.d[idx], centre, axes, half)
            better = t < t_best[idx]
            sel = idx[better]
            t_best[sel] = t[better]
            mat[sel] = mi
            normal[sel] = n[better]
    if wanted(True) and np.any(prims.plane_normal):
        t, n = ray_plane(np.zeros((m, 3)), rays.d, prims.plane_point, prims.plane_normal)
        better = t < t_best
        t_best[better] = t[better]
        mat[better] = 0
        normal[better] = n[better]
    kind = np.where(mat >= 0, prims.kinds[np.maximum(mat, 0)], KIND_NONE)
    return Trace(t_best, mat, kind, normal, t_robot)


def _remap(img: np.ndarray, mu: np.ndarray, mv: np.ndarray) -> np.ndarray:
    """Bilinear texture lookup at texel coordinates (mu, mv) (M,), mirrored at the borders."""
    m = len(mu)
    cols = 1024
    rows = max(1, -(-m // cols))
    pad = rows * cols - m
    mu_ = np.pad(mu.astype(np.float32), (0, pad)).reshape(rows, cols)
    mv_ = np.pad(mv.astype(np.float32), (0, pad)).reshape(rows, cols)
    out = cv2.remap(img, mu_, mv_, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT_101)
    out = out.reshape(rows * cols, -1)[:m]
    return out if img.ndim == 3 else out[:, 0]


_MIP_CACHE: dict[int, list] = {}


def _mip_levels(texture) -> list[tuple[np.ndarray, np.ndarray]]:
    """Pre-filtered (albedo, wet) copies against texture aliasing at grazing views."""
    key = id(texture)
    if key not in _MIP_CACHE:
        levels = [(texture.albedo, texture.wet)]
        for sigma in (1.5, 4.0):
            levels.append(
                (
                    cv2.GaussianBlur(texture.albedo, (0, 0), sigma),
                    cv2.GaussianBlur(texture.wet, (0, 0), sigma),
                )
            )
        _MIP_CACHE.clear()
        _MIP_CACHE[key] = levels
    return _MIP_CACHE[key]


def shade(cam: RenderCamera, scene: Scene, prims: _CamPrims, rays: RaySet, tr: Trace) -> np.ndarray:
    """Linear RGB (M, 3) of each ray: Blinn-Phong with a key light and a headlight (the
    camera's own light), environment reflection on metals (Schlick Fresnel; the tissue's
    colour is reflected where the mirrored ray points at the tissue), bump-mapped textured
    tissue with wet specular glints."""
    R = cam.T_cam_robot[:3, :3]
    d = rays.d
    v = -d
    rgb = np.tile(_VOID_RGB, (len(d), 1))
    light = R @ (scene.light_dir / np.linalg.norm(scene.light_dir))
    n_t = prims.plane_normal
    # Tissue.
    ti = np.nonzero(tr.mat == 0)[0]
    if len(ti):
        tex = scene.tissue.texture
        p_cam = tr.t[ti, None] * d[ti]
        p_rob = (p_cam - cam.T_cam_robot[:3, 3]) @ R
        rel = p_rob - scene.tissue.origin
        scale = tex.size / tex.extent
        mu = (rel @ scene.tissue.eu) * scale + tex.size / 2 - 0.5
        mv = (rel @ scene.tissue.ev) * scale + tex.size / 2 - 0.5
        # Texels per pixel (footprint of one pixel on the plane, grazing-angle aware).
        cos_i = np.clip(np.abs(d[ti] @ n_t), 0.05, 1.0)
        foot = tr.t[ti] / cam.K[0, 0] / cos_i * scale
        levels = _mip_levels(tex)
        w1 = np.clip(foot - 1.0, 0.0, 1.0)
        w2 = np.clip((foot - 3.0) / 3.0, 0.0, 1.0)
        alb = [_remap(a, mu, mv) for a, _ in levels]
        wet = [_remap(w, mu, mv) for _, w in levels]
        albedo = (
            (1 - w1)[:, None] * alb[0]
            + (w1 * (1 - w2))[:, None] * alb[1]
            + (w1 * w2)[:, None] * alb[2]
        )
        wetv = (1 - w1) * wet[0] + w1 * (1 - w2) * wet[1] + w1 * w2 * wet[2]
        slope = _remap(tex.slope, mu, mv)
        eu_c, ev_c = R @ scene.tissue.eu, R @ scene.tissue.ev
        n = n_t[None, :] - slope[:, :1] * eu_c[None] - slope[:, 1:] * ev_c[None]
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        vv = v[ti]
        ndl = np.clip(n @ light, 0.0, 1.0)
        ndv = np.clip(np.einsum("ij,ij->i", n, vv), 0.0, 1.0)
        h = light[None] + vv
        h /= np.linalg.norm(h, axis=1, keepdims=True)
        ndh = np.clip(np.einsum("ij,ij->i", n, h), 0.0, 1.0)
        diffuse = 0.25 + 0.55 * ndl + 0.35 * ndv
        spec = wetv * (0.7 * ndh**90 + 0.5 * ndv**160)
        rgb[ti] = albedo * diffuse[:, None] + spec[:, None] * np.array([1.0, 0.97, 0.95])
    # Robot and occluders.
    for mi in range(1, len(prims.materials)):
        idx = np.nonzero(tr.mat == mi)[0]
        if not len(idx):
            continue
        mt = prims.materials[mi]
        n = tr.normal[idx]
        vv = v[idx]
        base = np.asarray(mt.colour)
        ndl = np.clip(n @ light, 0.0, 1.0)
        ndv = np.clip(np.einsum("ij,ij->i", n, vv), 0.0, 1.0)
        h = light[None] + vv
        h /= np.linalg.norm(h, axis=1, keepdims=True)
        ndh = np.clip(np.einsum("ij,ij->i", n, h), 0.0, 1.0)
        diffuse = 0.22 + 0.5 * ndl + 0.35 * ndv
        spec = mt.specular * (ndh**mt.shininess + 0.6 * ndv ** (2 * mt.shininess))
        col = base[None] * diffuse[:, None] + spec[:, None] * (0.5 + 0.5 * base)[None]
        if mt.reflect > 0:
            r = d[idx] - 2.0 * np.einsum("ij,ij->i", d[idx], n)[:, None] * n
            to_tissue = np.clip(-(r @ n_t) * 2.0 + 0.3, 0.0, 1.0)[:, None]
            env = (1 - to_tissue) * _ROOM_RGB + to_tissue * _TISSUE_MEAN_RGB
            fres = 0.5 + 0.5 * (1.0 - ndv) ** 5
            col = col * (1 - 0.5 * mt.reflect) + mt.reflect * fres[:, None] * env
        rgb[idx] = col
    return rgb


@dataclass
class RenderResult:
    """One rendered view: ``image`` (H, W, 3) float32 in [0, 1] before camera noise,
    ``visible``/``full``/``occluder`` (H, W) bool masks at pixel centres, ``depth``
    (H, W) first-hit distance along the ray (metres, inf where nothing) and ``mat`` (H, W)
    first-hit material index (-1 nothing, 0 tissue; valid within one scene)."""

    image: np.ndarray
    visible: np.ndarray
    full: np.ndarray
    occluder: np.ndarray
    depth: np.ndarray
    mat: np.ndarray


def _edge_pixels(mat: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """Pixels whose first-hit material or (relative) depth differs from a neighbour's,
    dilated by one pixel so that thin features between pixel centres are caught."""
    h, w = mat.shape
    edge = np.zeros((h, w), bool)
    logd = np.log(np.where(np.isfinite(depth), depth, 1e3))
    for dr, dc in ((0, 1), (1, 0), (1, 1), (1, -1)):
        sa = (slice(dr, h), slice(max(dc, 0), w + min(dc, 0)))
        sb = (slice(0, h - dr), slice(max(-dc, 0), w - max(dc, 0)))
        e = (mat[sa] != mat[sb]) | ((np.abs(logd[sa] - logd[sb]) > 0.02) & (mat[sa] > 0))
        edge[sa] |= e
        edge[sb] |= e
    return cv2.dilate(edge.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)


def _supersample(
    cam: RenderCamera, scene: Scene, prims: _CamPrims, rgb: np.ndarray, pixels: np.ndarray
) -> None:
    """Replace ``rgb`` at the ``pixels`` (H, W) bool by the mean of 3x3 sub-pixel rays."""
    rr, cc = np.nonzero(pixels)
    if len(rr):
        n = _SUPERSAMPLE
        sub = subpixel_rays(cam, rr, cc, n)
        tr = trace(cam, prims, sub)
        rgb[rr, cc] = shade(cam, scene, prims, sub, tr).reshape(len(rr), n * n, 3).mean(axis=1)


def render_static(cam: RenderCamera, scene: Scene, antialias: bool = True) -> RenderResult:
    """Render only the static layer (tissue and static occluders) of ``scene``: the
    robot-free, instrument-free view, reusable for every frame seen by ``cam``."""
    bare = Scene(scene.tissue, None, [], scene.static_occluders, scene.light_dir)
    return render(cam, bare, antialias=antialias)


def render(
    cam: RenderCamera, scene: Scene, antialias: bool = True, static: RenderResult | None = None
) -> RenderResult:
    """Render ``scene`` seen by ``cam`` (the pose used to render, i.e. the *true* camera).

    With ``static`` (from :func:`render_static` for the same camera and static objects) only
    the robot and the moving occluders are ray cast and composited over the cached layer by
    depth; the result equals a full render up to floating-point ties.
    """
    h, w = cam.height, cam.width
    prims = _prepare(cam, scene)
    rays = pixel_rays(cam)
    if static is None:
        tr = trace(cam, prims, rays)
        rgb = shade(cam, scene, prims, rays, tr).reshape(h, w, 3)
        mat = tr.mat.reshape(h, w)
        depth = tr.t.reshape(h, w)
        kind = tr.kind.reshape(h, w)
        if antialias:
            _supersample(cam, scene, prims, rgb, _edge_pixels(mat, depth))
    else:
        tr = trace(cam, prims, rays, layer="dynamic")
        front = tr.t < static.depth.ravel()
        rgb = static.image.astype(np.float64).copy()
        idx = np.nonzero(front)[0]
        sub = RaySet(rays.row[idx], rays.col[idx], rays.d[idx])
        sub_tr = Trace(tr.t[idx], tr.mat[idx], tr.kind[idx], tr.normal[idx], tr.t_robot[idx])
        rgb.reshape(-1, 3)[idx] = shade(cam, scene, prims, sub, sub_tr)
        # Static material indices: tissue is 0 in both; static occluders keep their kind.
        static_kind = np.where(
            static.occluder, KIND_OCCLUDER, np.where(static.mat >= 0, KIND_TISSUE, KIND_NONE)
        )
        kind = np.where(front.reshape(h, w), tr.kind.reshape(h, w), static_kind)
        depth = np.where(front.reshape(h, w), tr.t.reshape(h, w), static.depth)
        mat = np.where(
            front.reshape(h, w), tr.mat.reshape(h, w), static.mat + 1000 * (static.mat > 0)
        )
        if antialias:
            near_dyn = cv2.dilate(
                (np.isfinite(tr.t) & (tr.t < np.inf)).reshape(h, w).astype(np.uint8),
                np.ones((5, 5), np.uint8),
            ).astype(bool)
            _supersample(cam, scene, prims, rgb, _edge_pixels(mat, depth) & near_dyn)
    return RenderResult(
        image=np.clip(rgb, 0.0, 1.0).astype(np.float32),
        visible=kind == KIND_ROBOT,
        full=np.isfinite(tr.t_robot).reshape(h, w),
        occluder=kind == KIND_OCCLUDER,
        depth=depth,
        mat=mat,
    )


def robot_mask(cam: RenderCamera, body: TubeBody) -> np.ndarray:
    """(H, W) bool: pixel centres whose ray hits ``body`` (no occluders, no tissue)."""
    prims = _prepare(cam, Scene(None, body))  # type: ignore[arg-type]
    tr = trace(cam, prims, pixel_rays(cam), layer="robot")
    return np.isfinite(tr.t_robot).reshape(cam.height, cam.width)


def apply_camera_effects(
    image: np.ndarray, rng: np.random.Generator, blur_sigma: float = 0.6, noise: float = 0.012
) -> np.ndarray:
    """Optical blur (Gaussian, ``blur_sigma`` px), vignetting, signal-dependent sensor noise
    (read noise ``noise`` plus shot noise), 8-bit quantisation. Returns uint8 (H, W, 3)."""
    h, w = image.shape[:2]
    img = cv2.GaussianBlur(image, (0, 0), blur_sigma) if blur_sigma > 0 else image.copy()
    yy, xx = np.mgrid[0:h, 0:w]
    r2 = ((xx - (w - 1) / 2) ** 2 + (yy - (h - 1) / 2) ** 2) / ((w / 2) ** 2 + (h / 2) ** 2)
    img = img * (1.0 - 0.25 * r2)[..., None]
    sigma = np.sqrt(noise**2 + (0.02**2) * np.clip(img, 0, 1))
    img = img + sigma * rng.standard_normal(img.shape)
    return np.clip(np.round(img * 255.0), 0, 255).astype(np.uint8)
