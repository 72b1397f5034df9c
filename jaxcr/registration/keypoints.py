"""Keypoint matching between two colour images (paper Sec. IV.A, Fig. 4): SIFT from OpenCV
(Lowe's ratio test, mutual check), optionally affine-simulated SIFT (ASIFT, Morel & Yu 2009,
the paper's ref. [29]): keypoints are also detected on affinely tilted copies of each image
and mapped back to the original pixels. Keypoints are lifted to 3-D with the depth image.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from jaxcr.registration.clouds import smooth_depth

_SIFT = None


def _sift():
    global _SIFT
    if _SIFT is None:
        _SIFT = cv2.SIFT_create(nfeatures=3000, contrastThreshold=0.02)
    return _SIFT


def _gray(rgb: np.ndarray) -> np.ndarray:
    return cv2.cvtColor((np.clip(rgb, 0, 1) * 255).astype(np.uint8), cv2.COLOR_RGB2GRAY)


def _affine_views(tilts=(1.0, 2.0**0.5, 2.0), n_rot=(1, 3, 5)):
    """(tilt, angle) pairs sampled as in ASIFT (fewer angles, for speed)."""
    out = []
    for t, k in zip(tilts, n_rot, strict=True):
        for j in range(k):
            out.append((t, 0.0 if t == 1.0 else 180.0 * j / k))
    return out


def crop_box(mask: np.ndarray, margin: int) -> tuple[int, int, int, int]:
    """(x0, y0, x1, y1): the bounding box of ``mask``'s True pixels grown by ``margin``
    pixels on each side, clipped to the image (the whole image when nothing is True)."""
    h, w = mask.shape
    rows, cols = np.flatnonzero(mask.any(1)), np.flatnonzero(mask.any(0))
    if len(rows) == 0:
        return 0, 0, w, h
    return (
        max(int(cols[0]) - margin, 0),
        max(int(rows[0]) - margin, 0),
        min(int(cols[-1]) + 1 + margin, w),
        min(int(rows[-1]) + 1 + margin, h),
    )


def detect(
    rgb: np.ndarray,
    mask: np.ndarray | None = None,
    asift: bool = False,
    crop_margin: int | None = None,
):
    """Keypoint pixels (n, 2) (u, v) and SIFT descriptors (n, 128) of an RGB image in [0, 1].
    ``mask`` (H, W) bool restricts detection (e.g. to valid depth). ``crop_margin`` (px):
    run SIFT on the mask's bounding box grown by this margin only (:func:`crop_box`; the
    scale-space pyramid is built over the crop, not the whole image, so its cost follows
    the object's size; keypoints near the crop border and at coarse scales differ from
    the whole image's: the blur sees the border replicated instead of the true pixels)."""
    g = _gray(rgb)
    m = None if mask is None else mask.astype(np.uint8) * 255
    x0 = y0 = 0
    if crop_margin is not None and mask is not None:
        x0, y0, x1, y1 = crop_box(mask, int(crop_margin))
        g, m = g[y0:y1, x0:x1], m[y0:y1, x0:x1]
    uvs, descs = [], []
    views = _affine_views() if asift else [(1.0, 0.0)]
    h, w = g.shape
    for t, ang in views:
        if t == 1.0:
            A = np.array([[1.0, 0, 0], [0, 1.0, 0]])
            img, mm = g, m
        else:
            R = cv2.getRotationMatrix2D((w / 2, h / 2), ang, 1.0)
            A = np.array([[1.0, 0, 0], [0, 1.0 / t, 0]]) @ np.vstack([R, [0, 0, 1]])
            img = cv2.warpAffine(g, A, (w, h), flags=cv2.INTER_LINEAR)
            mm = None if m is None else cv2.warpAffine(m, A, (w, h), flags=cv2.INTER_NEAREST)
        kps, d = _sift().detectAndCompute(img, mm)
        if d is None or not kps:
            continue
        uv = np.array([k.pt for k in kps], np.float64)
        Ai = cv2.invertAffineTransform(A)
        uvs.append(uv @ Ai[:, :2].T + Ai[:, 2] + np.array([x0, y0], np.float64))
        descs.append(d)
    if not uvs:
        return np.zeros((0, 2)), np.zeros((0, 128), np.float32)
    return np.concatenate(uvs), np.concatenate(descs)


def match(desc_a: np.ndarray, desc_b: np.ndarray, ratio: float = 0.8) -> np.ndarray:
    """Index pairs (k, 2) of mutual nearest neighbours passing Lowe's ratio test."""
    if len(desc_a) < 2 or len(desc_b) < 2:
        return np.zeros((0, 2), np.int64)
    bf = cv2.BFMatcher(cv2.NORM_L2)
    ab = bf.knnMatch(desc_a, desc_b, k=2)
    ba = {m[0].queryIdx: m[0].trainIdx for m in bf.knnMatch(desc_b, desc_a, k=1) if m}
    pairs = [
        (m[0].queryIdx, m[0].trainIdx)
        for m in ab
        if len(m) == 2
        and m[0].distance < ratio * m[1].distance
        and ba.get(m[0].trainIdx) == m[0].queryIdx
    ]
    return np.asarray(pairs, np.int64).reshape(-1, 2)


def lift(uv: np.ndarray, depth: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Camera-frame 3-D points (n, 3) of keypoints at sub-pixel ``uv`` (pixel centres at
    integer coordinates, OpenCV's keypoint convention) and a validity mask.

    The depth is bilinearly interpolated at ``uv`` from the four surrounding pixels, all of
    which must be finite and positive (a keypoint whose neighbourhood touches an invalid or
    discontinuous depth is dropped rather than given a mixed depth). Rounding ``uv`` to the
    nearest pixel instead would give the point the depth of a ray up to 0.5 px away: on a
    surface inclined to the view (a can near its silhouette) that is a depth error of
    0.5 px times the depth slope, while x and y still come from the unrounded ray."""
    h, w = depth.shape
    u, v = uv[:, 0], uv[:, 1]
    inside = (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1)
    u0 = np.clip(np.floor(u).astype(int), 0, max(w - 2, 0))
    v0 = np.clip(np.floor(v).astype(int), 0, max(h - 2, 0))
    u1 = np.minimum(u0 + 1, w - 1)
    v1 = np.minimum(v0 + 1, h - 1)
    fu = np.clip(u - u0, 0.0, 1.0)
    fv = np.clip(v - v0, 0.0, 1.0)
    z00, z01 = depth[v0, u0], depth[v0, u1]
    z10, z11 = depth[v1, u0], depth[v1, u1]
    corners = np.stack([z00, z01, z10, z11])
    ok = inside & np.all(np.isfinite(corners) & (corners > 0), axis=0)
    z = (1 - fv) * ((1 - fu) * z00 + fu * z01) + fv * ((1 - fu) * z10 + fu * z11)
    z = np.where(ok, z, 0.0)
    x = (u - K[0, 2]) / K[0, 0] * z
    y = (v - K[1, 2]) / K[1, 1] * z
    return np.stack([x, y, z], axis=1), ok


@dataclass(frozen=True)
class FrameFeatures:
    """The per-frame half of :func:`matched_points`: SIFT keypoint pixels ``uv`` (n, 2) and
    descriptors ``desc`` (n, 128) detected on the valid depth, and the locally averaged
    depth ``z`` (H, W, metres, NaN where invalid or across a discontinuity) the keypoints
    are lifted with. A frame takes part in several pairs (target of one forward pair, source
    of the next, loop closure, extra pose-graph edges): these depend on the frame only, so
    they are computed once per frame (:func:`jaxcr.registration.pairwise.frame_features`)."""

    uv: np.ndarray
    desc: np.ndarray
    z: np.ndarray


def frame_features(
    rgb, depth, *, asift: bool = False, smooth: int = 5, crop_margin: int | None = None
) -> FrameFeatures:
    """:class:`FrameFeatures` of one RGB-D frame (RGB in [0, 1], depth in metres);
    ``crop_margin``: SIFT on the valid depth's bounding box (:func:`detect`)."""
    valid = np.isfinite(depth) & (depth > 0)
    uv, desc = detect(rgb, valid, asift, crop_margin)
    # Lift with locally averaged depth: a keypoint's depth is its noisiest coordinate.
    z = smooth_depth(np.nan_to_num(depth), valid, smooth)
    return FrameFeatures(uv, desc, z)


def matched_features(fa: FrameFeatures, fb: FrameFeatures, K):
    """3-D keypoint correspondences (k, 3), (k, 3) between two frames' features (each in its
    own camera frame): mutual ratio-test matches lifted with the smoothed depth."""
    pairs = match(fa.desc, fb.desc)
    if len(pairs) == 0:
        return np.zeros((0, 3)), np.zeros((0, 3))
    pa, oka = lift(fa.uv[pairs[:, 0]], fa.z, K)
    pb, okb = lift(fb.uv[pairs[:, 1]], fb.z, K)
    ok = oka & okb
    return pa[ok], pb[ok]


def matched_points(rgb_a, depth_a, rgb_b, depth_b, K, asift: bool = False, smooth: int = 5):
    """3-D keypoint correspondences (k, 3), (k, 3) between two RGB-D frames (each in its own
    camera frame); :func:`frame_features` of both, then :func:`matched_features`."""
    return matched_features(
        frame_features(rgb_a, depth_a, asift=asift, smooth=smooth),
        frame_features(rgb_b, depth_b, asift=asift, smooth=smooth),
        K,
    )
