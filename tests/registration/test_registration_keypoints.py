"""Keypoint lifting (sub-pixel bilinear depth) and the discontinuity-aware depth smoothing
it reads from, against independent references (scipy.ndimage, closed-form plane depth)."""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from jaxcr.registration.clouds import smooth_depth
from jaxcr.registration.keypoints import lift

K = np.array([[100.0, 0.0, 47.5], [0.0, 100.0, 35.5], [0.0, 0.0, 1.0]])
H, W = 72, 96


def _plane_depth(u, v, d=-0.4):
    """Depth (m) of the plane n . X = d along the ray of pixel (u, v) (closed form)."""
    ray = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    return d / (ray @ np.array([0.6, 0.1, -1.0]))


def test_lift_bilinear_matches_scipy_and_plane():
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    z = _plane_depth(u, v)
    rng = np.random.default_rng(0)
    uv = np.stack([rng.uniform(1, W - 2, 200), rng.uniform(1, H - 2, 200)], 1)
    P, ok = lift(uv, z, K)
    assert ok.all()
    # interpolation equals scipy's order-1 spline (independent implementation), 1e-12 m
    ref = ndimage.map_coordinates(z, [uv[:, 1], uv[:, 0]], order=1)
    np.testing.assert_allclose(P[:, 2], ref, atol=1e-12)
    # and lies on the true plane: bilinear error of 1/(linear) over one pixel is second
    # order; on this slanted plane (slope ~2.4 mm/px at 0.4 m) it stays below 0.05 mm,
    # while nearest-pixel depth is off by up to half a pixel of slope (> 0.5 mm here)
    ztrue = _plane_depth(uv[:, 0], uv[:, 1])
    assert np.max(np.abs(P[:, 2] - ztrue)) < 5e-5
    zr = z[np.rint(uv[:, 1]).astype(int), np.rint(uv[:, 0]).astype(int)]
    assert np.max(np.abs(zr - ztrue)) > 5e-4
    # x, y on the keypoint's own ray
    np.testing.assert_allclose(P[:, 0], (uv[:, 0] - K[0, 2]) / K[0, 0] * P[:, 2], atol=1e-12)
    np.testing.assert_allclose(P[:, 1], (uv[:, 1] - K[1, 2]) / K[1, 1] * P[:, 2], atol=1e-12)


def test_lift_drops_invalid_neighbourhood_and_outside():
    z = np.full((H, W), 0.5)
    z[30, 40] = np.nan
    uv = np.array([[40.4, 30.3], [39.6, 29.6], [38.0, 28.0], [-0.5, 10.0], [W - 0.5, 10.0]])
    P, ok = lift(uv, z, K)
    # a NaN among the four surrounding pixels drops the keypoint; away from it the depth
    # is exact; outside the pixel-centre range it is dropped
    np.testing.assert_array_equal(ok, [False, False, True, False, False])
    assert P[2, 2] == 0.5
    # integer positions read exactly that pixel, also on the last row and column
    z2 = np.arange(H * W, dtype=float).reshape(H, W) / (H * W) + 0.3
    uv2 = np.array([[0.0, 0.0], [W - 1.0, H - 1.0], [5.0, 7.0]])
    P2, ok2 = lift(uv2, z2, K)
    assert ok2.all()
    np.testing.assert_allclose(P2[:, 2], [z2[0, 0], z2[-1, -1], z2[7, 5]], atol=1e-15)


def test_smooth_depth_flags_windows_straddling_a_jump():
    rng = np.random.default_rng(1)
    z = 0.5 + 0.001 * rng.standard_normal((H, W))
    valid = np.ones((H, W), bool)
    z[:, 60:] = 0.7  # background 20 cm behind a silhouette at u = 60
    out = smooth_depth(z, valid, 5)
    # far from the jump: the normalised box mean (scipy uniform_filter reference)
    ref = ndimage.uniform_filter(z, 5, mode="constant")
    cnt = ndimage.uniform_filter(np.ones_like(z), 5, mode="constant")
    np.testing.assert_allclose(out[10:60, 10:50], (ref / cnt)[10:60, 10:50], atol=1e-12)
    # every window holding a pixel of the other surface is NaN, on both sides of the jump
    assert np.isnan(out[10:60, 58:62]).all()
    assert np.isfinite(out[10:60, 57]).all() and np.isfinite(out[10:60, 62]).all()
    # a single background pixel inside a window: 1 of 25 at +20 cm moves the mean 8 mm,
    # under the 2 cm step (the former mean test passed its neighbours), yet every window
    # holding it must be flagged
    z1 = np.full((H, W), 0.5)
    z1[30, 30] = 0.7
    out1 = smooth_depth(z1, valid, 5)
    assert np.isnan(out1[28:33, 28:33]).all()
    assert np.isfinite(out1[27, 27]) and out1[27, 27] == 0.5
    # invalid pixels are NaN and do not enter their neighbours' means
    v2 = valid.copy()
    v2[20, 20] = False
    z2 = np.where(v2, 0.5, 123.0)
    out2 = smooth_depth(z2, v2, 5)
    assert np.isnan(out2[20, 20]) and np.allclose(out2[19, 19], 0.5)


def _textured_pair(shift: int = 4):
    """Two 160x120 views of a blurred-noise texture on a fronto-parallel plane at 0.5 m,
    the second shifted ``shift`` pixels (enough SIFT keypoints to match)."""
    rng = np.random.default_rng(3)
    tex = ndimage.gaussian_filter(rng.uniform(0, 1, (140, 190)), 1.5)
    tex = (tex - tex.min()) / (tex.max() - tex.min())
    a = tex[10:130, 10:170]
    b = tex[10:130, 10 + shift : 170 + shift]
    depth = np.full((120, 160), 0.5, np.float32)
    depth[:, :3] = np.nan  # some invalid depth
    return [np.repeat(x[..., None], 3, 2).astype(np.float32) for x in (a, b)], depth


def test_frame_feature_cache_gives_the_uncached_correspondences(monkeypatch):
    """The per-frame cache (:func:`jaxcr.registration.pairwise.frame_features`) returns what
    the uncached :func:`matched_points` computes (same functions on the same arrays in one
    process: equal exactly), detects each frame once across the pairs it takes part in, and
    recomputes when the frame's image is replaced."""
    from jaxcr.registration import keypoints
    from jaxcr.registration.keypoints import matched_features, matched_points
    from jaxcr.registration.pairwise import frame_features, make_frame

    Kt = np.array([[150.0, 0.0, 79.5], [0.0, 150.0, 59.5], [0.0, 0.0, 1.0]])
    (ra, rb), depth = _textured_pair()
    fa = make_frame(ra, depth, Kt, size=256, sample_size=256)
    fb = make_frame(rb, depth, Kt, size=256, sample_size=256)
    ka0, kb0 = matched_points(ra, depth, rb, depth, Kt)
    assert len(ka0) >= 20  # the case matches: the comparison below is not vacuous
    calls = []
    detect = keypoints.detect
    monkeypatch.setattr(keypoints, "detect", lambda *a: calls.append(1) or detect(*a))
    ka, kb = matched_features(frame_features(fa), frame_features(fb), Kt)
    np.testing.assert_array_equal(ka, ka0)
    np.testing.assert_array_equal(kb, kb0)
    # reversed pair (the pose graph's other direction) and a repeat: no new detection
    kb1, ka1 = matched_features(frame_features(fb), frame_features(fa), Kt)
    assert len(calls) == 2
    ref = keypoints.frame_features(ra, depth)
    np.testing.assert_array_equal(frame_features(fa).uv, ref.uv)
    np.testing.assert_array_equal(frame_features(fa).desc, ref.desc)
    assert len(calls) == 3  # ``ref`` itself
    # a replaced image is detected again, and gives that image's features
    fa.rgb = rb.copy()
    assert len(frame_features(fa).uv) == len(frame_features(fb).uv)
    np.testing.assert_array_equal(frame_features(fa).desc, frame_features(fb).desc)
    assert len(calls) == 4


def test_crop_box_and_cropped_detection_against_slow_references():
    from jaxcr.registration import keypoints

    rng = np.random.default_rng(3)
    for _ in range(5):  # crop_box against a slow per-pixel loop over the mask
        mask = np.zeros((H, W), bool)
        y0, x0 = rng.integers(0, H - 10), rng.integers(0, W - 10)
        mask[y0 : y0 + rng.integers(1, 10), x0 : x0 + rng.integers(1, 10)] = True
        ys, xs = [], []
        for y in range(H):
            for x in range(W):
                if mask[y, x]:
                    ys.append(y)
                    xs.append(x)
        ref = (max(min(xs) - 6, 0), max(min(ys) - 6, 0), min(max(xs) + 7, W), min(max(ys) + 7, H))
        assert keypoints.crop_box(mask, 6) == ref
    assert keypoints.crop_box(np.zeros((H, W), bool), 6) == (0, 0, W, H)
    # detect on a crop = OpenCV SIFT run by hand on the cropped grey image and mask, with
    # the crop's corner added to the keypoints (exact: the same calls on the same pixels)
    import cv2

    rgb = rng.uniform(0, 1, (3 * H, 3 * W, 3))
    rgb = cv2.GaussianBlur(rgb, (0, 0), 1.5)
    mask = np.zeros(rgb.shape[:2], bool)
    mask[60:150, 80:200] = True
    uv, desc = keypoints.detect(rgb, mask, crop_margin=16)
    x0, y0, x1, y1 = keypoints.crop_box(mask, 16)
    g = keypoints._gray(rgb)[y0:y1, x0:x1]
    m = mask[y0:y1, x0:x1].astype(np.uint8) * 255
    kps, d_ref = keypoints._sift().detectAndCompute(g, m)
    assert len(kps) > 10
    np.testing.assert_allclose(uv, np.array([k.pt for k in kps]) + [x0, y0], atol=1e-9)
    np.testing.assert_array_equal(desc, d_ref)
