"""The stereo pipeline's fast paths against their straightforward references: fused chroma
key (channel arithmetic, uint8 input) vs the ``(..., 3) @ k_hat`` form in numpy, the
two-view segmentation call vs the single-view functions, two-view cropped thinning vs
full-image thinning, the numpy essential matrix vs the JAX one, and the vectorised
piecewise-constant DP vs a loop over end points."""

import cv2
import jax.numpy as jnp
import numpy as np
import pytest

from jaxcr.stereo import pipeline as pl
from jaxcr.stereo.chroma import (
    KEY_COLOURS,
    chroma_alpha,
    chroma_alpha_and_projection,
    key_projection,
    plate_alpha,
    plate_alpha_shadow_invariant,
)
from jaxcr.stereo.correspondence import dtw_path_costs_np
from jaxcr.stereo.segments import piecewise_constant
from jaxcr.stereo.thinning import zhang_suen_thin
from jaxcr.stereo.triangulation import essential_matrix

H, W = 72, 96


@pytest.fixture(scope="module")
def images():
    rng = np.random.default_rng(3)
    key = np.array(KEY_COLOURS["green"])
    ims = []
    for _ in range(2):
        im = np.clip(
            key * rng.uniform(0.4, 1.1, (H, W, 1)) + 0.03 * rng.standard_normal((H, W, 3)), 0, 1
        )
        m = np.zeros((H, W), np.uint8)
        pts = (rng.random((4, 2)) * [W - 10, H - 10] + 5).astype(np.int32)
        cv2.polylines(m, [pts], False, 1, thickness=int(rng.integers(3, 7)))
        im[m > 0] = rng.uniform(0.2, 0.7, (int(m.sum()), 1)) * np.array([0.9, 1.0, 0.9])
        ims.append(np.round(im * 255).astype(np.uint8))
    return ims


def _score_ref(rgb, key):
    """The chroma score in its vector form (module docstring), numpy float64."""
    kc = key - key.mean()
    k_hat = kc / np.linalg.norm(kc)

    def raw(x):
        c = x - x.mean(-1, keepdims=True)
        along = c @ k_hat
        across = np.linalg.norm(c - along[..., None] * k_hat, axis=-1)
        return (along - across) / (x.max(-1) + 1e-3), along

    return raw(rgb)[0] / raw(key)[0], raw(rgb)[1]


def test_chroma_fused_against_vector_form(images):
    key = np.array(KEY_COLOURS["green"])
    for im in images:
        f = im.astype(np.float64) / 255
        s_ref, along_ref = _score_ref(f, key)
        a_ref = np.clip((0.8 - s_ref) / 0.3, 0, 1)
        a8, k8 = chroma_alpha_and_projection(
            jnp.asarray(im), jnp.asarray(key, jnp.float32), 0.5, 0.8
        )
        af = chroma_alpha(jnp.asarray(f, jnp.float32), jnp.asarray(key, jnp.float32), 0.5, 0.8)
        kf = key_projection(jnp.asarray(f, jnp.float32), jnp.asarray(key, jnp.float32))
        np.testing.assert_allclose(np.asarray(a8), a_ref, atol=2e-5)
        np.testing.assert_allclose(np.asarray(af), a_ref, atol=2e-5)
        np.testing.assert_allclose(np.asarray(k8), along_ref, atol=1e-6)
        np.testing.assert_allclose(np.asarray(kf), along_ref, atol=1e-6)


@pytest.mark.parametrize("mode", ["chroma", "plate", "plate_shadow", "both"])
def test_two_view_segmentation_equals_single_views(images, mode):
    key = jnp.asarray(KEY_COLOURS["green"], jnp.float32)
    plates = [np.clip(im.astype(int) + 40, 0, 255).astype(np.uint8) for im in images]
    a, kp, m = pl._segment_views(
        jnp.asarray(np.stack(images)),
        jnp.asarray(np.stack(plates)),
        key,
        0.5,
        0.8,
        0.06,
        0.15,
        mode=mode,
    )
    for v in range(2):
        f = jnp.asarray(images[v].astype(np.float32) / 255)
        pf = jnp.asarray(plates[v].astype(np.float32) / 255)
        if mode == "chroma":
            ref = chroma_alpha(f, key, 0.5, 0.8)
        elif mode == "plate":
            ref = plate_alpha(f, pf, 0.06, 0.15)
        elif mode == "plate_shadow":
            ref = plate_alpha_shadow_invariant(f, pf, 0.06, 0.15)
        else:
            ref = chroma_alpha(f, key, 0.5, 0.8) * plate_alpha(f, pf, 0.06, 0.15)
        np.testing.assert_allclose(np.asarray(a[v]), np.asarray(ref), atol=2e-5)
        np.testing.assert_allclose(np.asarray(kp[v]), np.asarray(key_projection(f, key)), atol=1e-6)
        np.testing.assert_array_equal(np.asarray(m[v]), (np.asarray(a[v]) > 0.5).astype(np.uint8))


def test_two_view_cropped_thinning_equals_full_images():
    ms = []
    for pts, circ in [
        ([[20, 110], [30, 50], [150, 20]], (221, 100)),  # touches the right border
        ([[60, 100], [70, 80], [90, 75]], (40, 40)),  # small box, padded to the other's
    ]:
        m = np.zeros((400, 224), np.uint8)
        cv2.polylines(m, [np.array(pts, np.int32)], False, 1, 6)
        cv2.circle(m, circ, 6, 1, -1)
        ms.append(m.astype(bool))
    out = pl._thin_cropped_views(ms, block=32)
    shapes = {sk.shape for sk, _ in out}
    # one square window for both views, side 32 * 2^3 = 256 >= the larger box (207 px wide)
    # + 4: rows cropped, columns cut to the image's width
    assert shapes == {(256, 224)}
    for m, (sk, (r, c)) in zip(ms, out, strict=True):
        full = np.asarray(zhang_suen_thin(jnp.asarray(m)))
        placed = np.zeros_like(m)
        placed[r : r + sk.shape[0], c : c + sk.shape[1]] = sk
        np.testing.assert_array_equal(placed, full)
        np.testing.assert_array_equal(pl._thin_cropped(m, block=32), full)


def test_essential_np_equals_jax():
    rng = np.random.default_rng(1)
    Ts = []
    for _ in range(2):
        R = cv2.Rodrigues(rng.standard_normal(3))[0]
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, rng.standard_normal(3) * 0.2
        Ts.append(T)
    np.testing.assert_allclose(
        pl._essential_np(*Ts),
        np.asarray(essential_matrix(jnp.asarray(Ts[0]), jnp.asarray(Ts[1]))),
        atol=1e-6,
    )


def _piecewise_constant_loop(y, k, min_len=3):
    """The DP with an explicit loop over end points j (the previous implementation)."""
    n = len(y)
    c1 = np.concatenate([[0.0], np.cumsum(y)])
    c2 = np.concatenate([[0.0], np.cumsum(y * y)])
    cost = np.full((k + 1, n + 1), np.inf)
    arg = np.zeros((k + 1, n + 1), np.int64)
    cost[0, 0] = 0.0
    for p in range(1, k + 1):
        for j in range(p * min_len, n + 1):
            i = np.arange((p - 1) * min_len, j - min_len + 1)
            s = c1[j] - c1[i]
            c = cost[p - 1, i] + (c2[j] - c2[i] - s * s / np.maximum(j - i, 1))
            b = int(np.argmin(c))
            cost[p, j], arg[p, j] = c[b], i[b]
    starts, j = [], n
    for p in range(k, 0, -1):
        starts.append(arg[p, j])
        j = arg[p, j]
    return np.array(starts[::-1]), float(cost[k, n])


def test_piecewise_constant_equals_loop():
    rng = np.random.default_rng(5)
    for t in range(30):
        n, k = int(rng.integers(9, 600)), int(rng.integers(1, 5))
        y = np.repeat(rng.random(k + 1), n // (k + 1) + 1)[:n] + 0.05 * rng.standard_normal(n)
        if t % 3 == 0:
            y = np.round(y, 1)  # many exact ties
        st, e = piecewise_constant(y, k)
        st_ref, e_ref = _piecewise_constant_loop(y, k)
        np.testing.assert_array_equal(st, st_ref)
        assert e == e_ref  # same float operations: bit-identical


def _dtw_rows_reference(cost):
    """The DTW recursion with per-row temporaries (the previous implementation)."""
    n, m = cost.shape
    D = np.empty((n, m))
    K = np.zeros((n, m), np.int64)
    D[0] = np.cumsum(cost[0])
    idx = np.arange(m)
    for i in range(1, n):
        prev = D[i - 1]
        M = np.minimum(prev, np.concatenate([[np.inf], prev[:-1]]))
        S = np.cumsum(cost[i])
        v = M - np.concatenate([[0.0], S[:-1]])
        cm = np.minimum.accumulate(v)
        K[i] = np.maximum.accumulate(np.where(v <= cm, idx, 0))
        D[i] = S + cm
    return D, K


def test_dtw_buffers_equal_reference():
    rng = np.random.default_rng(2)
    for n, m in [(1, 5), (5, 1), (7, 9), (120, 90)]:
        c = np.round(rng.random((n, m)), 1)  # ties
        D, K = dtw_path_costs_np(c)
        D_ref, K_ref = _dtw_rows_reference(c)
        np.testing.assert_array_equal(D, D_ref)
        np.testing.assert_array_equal(K, K_ref)


def _resample_dense(p, step, sigma):
    """Arclength Gaussian local-linear smoothing with the full kernel (previous version)."""
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])
    for _ in range(2):
        grid = np.arange(0.0, s[-1] + 1e-12, step)
        w = np.exp(-0.5 * ((grid[:, None] - s[None]) / sigma) ** 2)
        ds = s[None] - grid[:, None]
        sw, sx, sxx = w.sum(1), (w * ds).sum(1), (w * ds * ds).sum(1)
        sy, sxy = w @ p, (w * ds) @ p
        det = sw * sxx - sx * sx
        p = (sxx[:, None] * sy - sx[:, None] * sxy) / np.maximum(det, 1e-300)[:, None]
        s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])
    return s, p


def test_windowed_resample_equals_dense():
    rng = np.random.default_rng(4)
    for n in (12, 150, 500):  # samples ~0.3 mm apart, as skeleton pixels at the robot
        r = rng.uniform(0.01, 0.1)
        th = np.arange(n) * 3e-4 / r
        p = np.stack([r * np.cos(th), r * np.sin(th), 0.2 * r * th], 1)
        p += rng.normal(0, 5e-5, (n, 3))
        s, q = pl._resample(p, 5e-4, 1e-3)
        s_ref, q_ref = _resample_dense(p, 5e-4, 1e-3)
        assert s.shape == s_ref.shape
        np.testing.assert_allclose(q, q_ref, rtol=0, atol=1e-13)  # metres
        np.testing.assert_allclose(s, s_ref, rtol=0, atol=1e-13)


def test_views_of_different_sizes():
    """Stacking pads the smaller view (bottom/right) and the cropped thinning of views of
    different sizes still equals full-image thinning of each."""
    a = np.zeros((120, 160), np.uint8)
    b = np.zeros((100, 192), np.uint8)
    cv2.polylines(a, [np.array([[20, 110], [30, 50], [150, 20]], np.int32)], False, 1, 6)
    cv2.polylines(b, [np.array([[10, 90], [100, 40], [185, 60]], np.int32)], False, 1, 5)
    st = pl._image_stack([a, b])
    assert st.shape == (2, 120, 192) and st.dtype == np.uint8
    np.testing.assert_array_equal(st[0, :, :160], a)
    np.testing.assert_array_equal(st[1, :100], b)
    assert not st[0, :, 160:].any() and not st[1, 100:].any()
    rgb = pl._image_stack([np.zeros((4, 5, 3)), np.ones((6, 3, 3))])
    assert rgb.shape == (2, 6, 5, 3) and rgb.dtype == np.float32
    for m, (sk, (r, c)) in zip(
        (a, b), pl._thin_cropped_views([a > 0, b > 0], block=32), strict=True
    ):
        placed = np.zeros(m.shape, bool)
        placed[r : r + sk.shape[0], c : c + sk.shape[1]] = sk
        np.testing.assert_array_equal(placed, np.asarray(zhang_suen_thin(jnp.asarray(m > 0))))


def test_resample_across_a_gap_stays_finite():
    """Matched points with a 20 mm gap (audit r31: plate segmentation on a real_like frame;
    a window holding one sample made the local line 0/0, points at ~1e300 m, and the run
    died in np.arange): a finite backbone that crosses the gap between its two ends."""
    a = np.c_[np.zeros(40), np.zeros(40), np.arange(40) * 3e-4]  # 0 .. 11.7 mm, 0.3 mm apart
    b = a + [0.0, 0.0, 0.0117 + 0.02]  # then a 20 mm gap along z
    b[:, 0] = 0.002  # and a 2 mm step sideways
    p = np.vstack([a, b])
    s, q = pl._resample(p, 5e-4, 1e-3)
    assert np.all(np.isfinite(q)) and np.all(np.isfinite(s))
    # across the gap x goes from one side's 0 to the other's 2 mm (float64: 1e-9 m slack)
    assert q[:, 0].min() > -1e-9 and q[:, 0].max() < 0.002 + 1e-9
    # length: at most z's extent plus x's (a path monotone in both); at least the chord less
    # what the sigma = 1 mm kernel cuts off the two corners (under sigma each; measured
    # 0.57 mm in all)
    chord = np.linalg.norm(p[-1] - p[0])
    assert chord - 2e-3 <= s[-1] <= (p[-1, 2] - p[0, 2]) + 0.002 + 1e-9
