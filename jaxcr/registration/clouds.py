"""Point clouds from RGB-D frames (paper Sec. III.A / IV): back-projection with the pinhole
intrinsics, per-pixel normals from the organised depth image, voxel down-sampling and
fixed-size padding (so the jitted registration compiles once per size).

Frames: camera frame (OpenCV: z forward, x right, y down), metres. Colours RGB in [0, 1].
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from jaxcr.errors import InputError


@dataclass(frozen=True)
class Cloud:
    """A coloured point cloud with normals, in one frame. ``points``/``normals`` (n, 3),
    ``colours`` (n, 3); normals are unit and point towards the camera that saw them."""

    points: np.ndarray
    colours: np.ndarray
    normals: np.ndarray

    def __len__(self) -> int:
        return int(self.points.shape[0])

    def transformed(self, T: np.ndarray) -> Cloud:
        return Cloud(self.points @ T[:3, :3].T + T[:3, 3], self.colours, self.normals @ T[:3, :3].T)

    def subset(self, idx) -> Cloud:
        return Cloud(self.points[idx], self.colours[idx], self.normals[idx])


def organised_cloud(
    rgb: np.ndarray,
    depth: np.ndarray,
    K: np.ndarray,
    max_depth: float = 3.0,
    frame: int | str | None = None,
    normal_window: int = 7,
    normal_step: int = 2,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Organised camera-frame cloud of an RGB-D frame: points (H, W, 3), colours (H, W, 3),
    unit normals (H, W, 3) facing the camera, and the mask (H, W) of pixels with a valid
    depth and a valid normal. ``depth`` (H, W) in metres (0 or NaN = invalid), ``rgb`` in
    [0, 1], intrinsics ``K`` (3, 3).

    Normals: cross product of the central differences (over +-``normal_step`` px) of the
    box-smoothed back-projected image along u and v (needs both neighbours valid); windows
    holding a valid depth more than 2 cm from their centre pixel's are invalid, so pixels at
    depth discontinuities carry no normal. Raises :class:`InputError` for mismatched shapes or a frame without a single
    valid depth / normal.
    """
    depth = np.asarray(depth, np.float64)
    rgb = np.asarray(rgb, np.float64)
    if depth.ndim != 2 or rgb.shape[:2] != depth.shape or rgb.ndim != 3:
        raise InputError(
            f"rgb {rgb.shape} and depth {depth.shape} do not form an RGB-D pair",
            frame=frame,
            field="depth",
        )
    h, w = depth.shape
    valid = np.isfinite(depth) & (depth > 0) & (depth < max_depth)
    if not valid.any():
        raise InputError(
            "depth image has no valid pixel (all NaN/zero)", frame=frame, field="depth"
        )
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    z = np.where(valid, depth, np.nan)
    x = (u - K[0, 2]) / K[0, 0] * z
    y = (v - K[1, 2]) / K[1, 1] * z
    P = np.stack([x, y, z], axis=-1)
    # Normals from a smoothed depth (normalised box filter over valid pixels; consumer depth
    # noise would otherwise dominate 1-pixel differences), differenced over +-normal_step px.
    Ps = smooth_points(P, valid, normal_window)
    k = normal_step
    du = np.full_like(P, np.nan)
    dv = np.full_like(P, np.nan)
    du[:, k:-k] = Ps[:, 2 * k :] - Ps[:, : -2 * k]
    dv[k:-k, :] = Ps[2 * k :, :] - Ps[: -2 * k, :]
    n = np.cross(du, dv)
    norm = np.linalg.norm(n, axis=-1, keepdims=True)
    ok = valid & np.isfinite(norm[..., 0]) & (norm[..., 0] > 0)
    n = np.where(ok[..., None], n / np.where(norm > 0, norm, 1.0), 0.0)
    flip = np.sum(n * P, axis=-1) > 0  # the normal must face the camera (P points away)
    n = np.where(flip[..., None], -n, n)
    if not ok.any():
        raise InputError("depth image has no pixel with a valid normal", frame=frame, field="depth")
    P = np.where(ok[..., None], P, 0.0)
    return P, rgb, n, ok


def cloud_from_rgbd(
    rgb: np.ndarray,
    depth: np.ndarray,
    K: np.ndarray,
    max_depth: float = 3.0,
    frame: int | str | None = None,
    normal_window: int = 7,
    normal_step: int = 2,
) -> Cloud:
    """Camera-frame cloud of the pixels of :func:`organised_cloud` with a valid depth and
    normal (same arguments, same errors)."""
    P, rgb, n, ok = organised_cloud(rgb, depth, K, max_depth, frame, normal_window, normal_step)
    return Cloud(P[ok], rgb[ok], n[ok])


def smooth_points(P: np.ndarray, valid: np.ndarray, window: int) -> np.ndarray:
    """Mean of the valid back-projected points (H, W, 3) in a ``window`` box (zeros outside
    the image). The mean of points on a plane lies on that plane, so normals from
    differences of smoothed points stay exact on planar patches; NaN across depth jumps."""
    import cv2

    cnt = cv2.boxFilter(
        valid.astype(np.float64),
        -1,
        (window, window),
        normalize=False,
        borderType=cv2.BORDER_CONSTANT,
    )
    out = np.empty_like(P)
    for c in range(3):
        s = cv2.boxFilter(
            np.where(valid, P[..., c], 0.0),
            -1,
            (window, window),
            normalize=False,
            borderType=cv2.BORDER_CONSTANT,
        )
        out[..., c] = np.where(cnt > 0, s / np.maximum(cnt, 1e-12), np.nan)
    # A window holding any valid depth more than 2 cm from the centre straddles a depth
    # discontinuity: its mean mixes two surfaces (a 1-pixel intrusion of a 10 cm step
    # tilts the normal by ~30 degrees while moving the mean by only 1.4 cm).
    kern = np.ones((window, window), np.uint8)
    z = P[..., 2].astype(np.float32)
    zmax = cv2.dilate(np.where(valid, z, -np.inf).astype(np.float32), kern)
    zmin = cv2.erode(np.where(valid, z, np.inf).astype(np.float32), kern)
    jump = ~((zmax - z <= 0.02) & (z - zmin <= 0.02))
    out[jump | ~valid] = np.nan
    return out


def plane_points(
    P: np.ndarray, normals: np.ndarray, valid: np.ndarray, window: int = 7
) -> np.ndarray:
    """Denoised back-projection (H, W, 3): each valid pixel's point moved along its own
    viewing ray onto the local plane through the ``window`` mean of the valid points
    (:func:`smooth_points`) with the pixel's unit normal ``normals``, i.e. the depth
    ``z = (n . m) / (n . r)`` with ``r = P / P_z`` the pixel's ray (z = 1) and ``m`` the
    window mean. The pixel keeps its image position (the precise coordinate of a
    structured-light sensor) and gets the depth of a local plane fit instead of its own
    noisy depth: with i.i.d. depth noise sigma the plane's depth varies by about
    sigma / window (x 1.4 for the normal's tilt). On a plane it is exact; on a surface of
    radius of curvature R the window's sagitta (s^2 / (8 R) for a footprint s) is the
    model error. Pixels whose window straddles a depth jump, with a ray grazing the plane
    (|n . r| < 0.05 |r|) or moved by more than 1 cm keep their raw point; invalid ones are
    zero. ``P``: camera-frame points of :func:`organised_cloud` (metres)."""
    P = np.asarray(P, np.float64)
    normals = np.asarray(normals, np.float64)
    valid = np.asarray(valid, bool)
    m = smooth_points(np.where(valid[..., None], P, 0.0), valid, window)
    zr = np.where(valid, P[..., 2], 1.0)
    r = P / np.where(np.abs(zr) > 1e-12, zr, 1.0)[..., None]
    den = np.sum(normals * r, -1)
    num = np.sum(normals * m, -1)
    ok = valid & np.isfinite(num) & (np.abs(den) >= 0.05 * np.linalg.norm(r, axis=-1))
    z = np.where(ok, num / np.where(ok, den, 1.0), np.nan)
    ok &= np.abs(z - P[..., 2]) <= 0.01
    out = np.where(ok[..., None], r * np.where(ok, z, 0.0)[..., None], P)
    return np.where(valid[..., None], out, 0.0)


def plane_residual_variance(
    P: np.ndarray, normals: np.ndarray, valid: np.ndarray, window: int = 7
) -> np.ndarray:
    """Variance (H, W) (m^2) of the valid points of each pixel's ``window`` box about the
    plane through their mean with the pixel's unit normal, ``n^T C n`` with ``C`` the
    points' covariance: the local plane fit's residual, about sigma_z^2 (n . r)^2 (depth
    noise along the normal, r the ray scaled to z = 1) on a plane, more where the window
    straddles a crease or a curved patch (the fit's model error). 0 where ``normals`` or
    the window mean is invalid. ``P``: camera-frame points of :func:`organised_cloud`."""
    import cv2

    P = np.asarray(P, np.float64)
    valid = np.asarray(valid, bool)
    X = np.where(valid[..., None], P, 0.0)
    m = smooth_points(X, valid, window)
    box = (window, window)
    cnt = cv2.boxFilter(
        valid.astype(np.float64), -1, box, normalize=False, borderType=cv2.BORDER_CONSTANT
    )
    n = np.asarray(normals, np.float64)
    var = np.zeros(P.shape[:2])
    for a in range(3):
        for b in range(a, 3):
            s = cv2.boxFilter(
                X[..., a] * X[..., b], -1, box, normalize=False, borderType=cv2.BORDER_CONSTANT
            )
            c = s / np.maximum(cnt, 1.0) - m[..., a] * m[..., b]
            var += (1.0 if a == b else 2.0) * n[..., a] * n[..., b] * c
    ok = valid & np.all(np.isfinite(m), -1)
    return np.where(ok, np.maximum(var, 0.0), 0.0)


def depth_scaled_window(
    z: np.ndarray, focal: float, footprint: float, smallest: int = 3, largest: int = 7
) -> np.ndarray:
    """Odd pixel window (int array, shape of ``z``) whose footprint on the surface is
    ``footprint`` (m) at depth ``z`` (m) for a camera of focal length ``focal`` (px): the
    odd integer nearest to ``footprint * focal / z``, clipped to [``smallest``,
    ``largest``] (odd; invalid depths get ``largest``).

    Why a metric footprint: a plane fit's model error is set by the surface it spans (a
    crease or a curved patch of footprint s errs by ~s^2 / (8 R) or ~s/8 at a crease), so a
    fixed pixel window errs more the farther the view (its footprint grows as z), and two
    views at different depths get different biases that a registration between them cannot
    remove. With the footprint fixed, both get the same model error."""
    z = np.asarray(z, np.float64)
    ok = np.isfinite(z) & (z > 0)
    x = np.where(ok, footprint * focal / np.where(ok, z, 1.0), float(largest))
    w = 2 * np.round((x - 1.0) / 2.0).astype(np.int64) + 1
    return np.clip(w, smallest, largest)


def plane_points_scaled(
    P: np.ndarray,
    normals: np.ndarray,
    valid: np.ndarray,
    focal: float,
    footprint: float,
    smallest: int = 3,
    largest: int = 7,
) -> np.ndarray:
    """:func:`plane_points` with a per-pixel window of a fixed metric footprint
    (:func:`depth_scaled_window` of the pixel's depth): each pixel takes the denoised point
    of the window its own depth asks for. Same arguments as :func:`plane_points`, plus the
    focal length ``focal`` (px) and ``footprint`` (m)."""
    P = np.asarray(P, np.float64)
    valid = np.asarray(valid, bool)
    win = depth_scaled_window(
        np.where(valid, P[..., 2], np.nan), focal, footprint, smallest, largest
    )
    out = np.zeros_like(P)
    for w in np.unique(win[valid]):
        sel = valid & (win == w)
        out[sel] = plane_points(P, normals, valid, int(w))[sel]
    return out


def smooth_depth(
    z: np.ndarray, valid: np.ndarray, window: int, max_step: float = 0.02
) -> np.ndarray:
    """Normalised box filter of ``z`` (m) over the ``valid`` pixels; NaN where the pixel is
    invalid or its window holds any valid depth more than ``max_step`` (m) from the centre
    (the window straddles a depth discontinuity, e.g. a silhouette against the background).

    The test is on the window's extremes, not on its mean: a mean test lets a few background
    pixels (e.g. 1 of 25 at +20 cm) pull the depth of a silhouette pixel back by up to
    ``max_step`` without being flagged (same rule as :func:`smooth_points`)."""
    import cv2

    zf = cv2.boxFilter(np.where(valid, z, 0.0), -1, (window, window), normalize=False)
    cnt = cv2.boxFilter(valid.astype(np.float64), -1, (window, window), normalize=False)
    out = np.where(cnt > 0, zf / np.maximum(cnt, 1e-12), np.nan)
    kern = np.ones((window, window), np.uint8)
    z32 = np.asarray(z, np.float32)
    zmax = cv2.dilate(np.where(valid, z32, -np.inf).astype(np.float32), kern)
    zmin = cv2.erode(np.where(valid, z32, np.inf).astype(np.float32), kern)
    jump = ~((zmax - z32 <= max_step) & (z32 - zmin <= max_step))
    return np.where(valid & ~jump, out, np.nan)


def voxel_downsample(cloud: Cloud, voxel: float) -> Cloud:
    """One point per occupied voxel of edge ``voxel`` (m): the mean position and colour, the
    renormalised mean normal."""
    if len(cloud) == 0:
        return cloud
    key = np.floor(cloud.points / voxel).astype(np.int64)
    _, inv, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    inv = inv.reshape(-1)

    def mean(a):
        out = np.zeros((counts.size, a.shape[1]))
        np.add.at(out, inv, a)
        return out / counts[:, None]

    nrm = mean(cloud.normals)
    nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
    return Cloud(mean(cloud.points), mean(cloud.colours), nrm)


def pad_cloud(
    cloud: Cloud, size: int, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(points, colours, normals, mask) arrays of exactly ``size`` rows (float32): a random
    subset when the cloud is larger, zero rows with mask False when smaller."""
    n = len(cloud)
    idx = np.sort(rng.choice(n, size, replace=False)) if n > size else np.arange(n)
    m = len(idx)
    out = []
    for a in (cloud.points, cloud.colours, cloud.normals):
        b = np.zeros((size, 3), np.float32)
        b[:m] = a[idx]
        out.append(b)
    mask = np.zeros(size, bool)
    mask[:m] = True
    return out[0], out[1], out[2], mask
