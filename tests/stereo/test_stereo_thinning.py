"""Thinning in JAX: the bit-parallel Zhang-Suen and its table-lookup form against a slow
per-pixel loop of the paper's algorithm (exact), every one of the 256 neighbourhoods against
the tables, Guo-Hall against scikit-image's ``thin`` (exact), and Zhang-Suen against
scikit-image's ``skeletonize`` (a different Zhang-Suen table: close, not identical)."""

import cv2
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import ndimage as ndi
from skimage.morphology import skeletonize, thin

from jaxcr.stereo import thinning as T
from jaxcr.stereo.thinning import (
    guo_hall_thin,
    zhang_suen_step,
    zhang_suen_thin,
    zhang_suen_thin_lut,
)

SHAPE = (72, 96)


def _slow_zhang_suen(img: np.ndarray) -> np.ndarray:
    """Zhang & Suen (1984), literally: two sub-iterations, flags collected then deleted."""
    x = np.pad(img.astype(np.uint8), 1)
    changed = True
    while changed:
        changed = False
        for step in (0, 1):
            dele = []
            for r in range(1, x.shape[0] - 1):
                for c in range(1, x.shape[1] - 1):
                    if not x[r, c]:
                        continue
                    p = [
                        x[r - 1, c],
                        x[r - 1, c + 1],
                        x[r, c + 1],
                        x[r + 1, c + 1],
                        x[r + 1, c],
                        x[r + 1, c - 1],
                        x[r, c - 1],
                        x[r - 1, c - 1],
                    ]  # noqa: E501
                    b = sum(p)
                    a = sum(1 for k in range(8) if p[k] == 0 and p[(k + 1) % 8] == 1)
                    p2, _, p4, _, p6, _, p8, _ = p
                    if step == 0:
                        ok = p2 * p4 * p6 == 0 and p4 * p6 * p8 == 0
                    else:
                        ok = p2 * p4 * p8 == 0 and p2 * p6 * p8 == 0
                    if 2 <= b <= 6 and a == 1 and ok:
                        dele.append((r, c))
            for r, c in dele:
                x[r, c] = 0
            changed |= bool(dele)
    return x[1:-1, 1:-1].astype(bool)


def _random_tube_mask(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    m = np.zeros(SHAPE, np.uint8)
    pts = (rng.random((5, 2)) * [SHAPE[1] - 10, SHAPE[0] - 10] + 5).astype(np.int32)
    cv2.polylines(m, [pts], False, 1, thickness=int(rng.integers(3, 8)))
    return m.astype(bool)


@pytest.fixture(scope="module")
def masks():
    return [_random_tube_mask(s) for s in range(4)]


@pytest.fixture(scope="module")
def noise():
    # Random blobs with holes, touching the border; width not a multiple of 32.
    rng = np.random.default_rng(7)
    return [
        ndi.binary_opening(rng.random((40, 70)) > 0.4) | (rng.random((40, 70)) > 0.9)
        for _ in range(3)
    ]


def test_equals_slow_reference(masks, noise):
    for m in masks + noise:
        ref = _slow_zhang_suen(m)
        np.testing.assert_array_equal(np.asarray(zhang_suen_thin(jnp.asarray(m))), ref)
        np.testing.assert_array_equal(np.asarray(zhang_suen_thin_lut(jnp.asarray(m))), ref)


def test_every_neighbourhood_against_tables():
    """One sub-iteration of the bit-parallel rule on all 256 3x3 neighbourhoods (centre
    set) deletes the centre exactly where the table built from the paper's rule says."""
    codes = np.arange(256)
    imgs = np.zeros((256, 3, 3), bool)
    imgs[:, 1, 1] = True
    for k, (dr, dc) in enumerate(T._OFFSETS):
        imgs[:, 1 + dr, 1 + dc] = (codes >> k) & 1
    tables = T.zhang_suen_tables()
    for first in (True, False):
        out = jax.vmap(
            lambda m, f=first: T._unpack(
                T._packed_sub_iteration(T._pack(jnp.pad(m, ((0, 0), (0, 29)))), f), 3
            )
        )(jnp.asarray(imgs))
        np.testing.assert_array_equal(~np.asarray(out)[:, 1, 1], tables[0 if first else 1])
    # the codes themselves
    c = np.asarray(jax.vmap(T.neighbour_codes)(jnp.asarray(imgs, jnp.uint8)))[:, 1, 1]
    np.testing.assert_array_equal(c, codes)


def test_guo_hall_equals_skimage_thin(masks, noise):
    for m in masks + noise:
        np.testing.assert_array_equal(np.asarray(guo_hall_thin(jnp.asarray(m))), thin(m))


def test_close_to_skimage(masks):
    for m in masks:
        ours = np.asarray(zhang_suen_thin(jnp.asarray(m)))
        ref = skeletonize(m)
        d_ref = ndi.distance_transform_edt(~ref)
        d_ours = ndi.distance_transform_edt(~ours)
        # Every pixel of ours lies next to skimage's skeleton; skimage's ends may be a few
        # pixels longer or shorter (its lookup table differs at stroke ends).
        assert d_ref[ours].max() <= 1.5
        assert np.percentile(d_ours[ref], 95) <= 1.5
        assert ndi.label(ours, np.ones((3, 3)))[1] == ndi.label(ref, np.ones((3, 3)))[1] == 1
        assert ours.sum() <= 1.3 * ref.sum() + 5


def test_subset_thin_and_idempotent(masks):
    for m in masks:
        sk = np.asarray(zhang_suen_thin(jnp.asarray(m)))
        assert not (sk & ~m).any()
        np.testing.assert_array_equal(np.asarray(zhang_suen_step(jnp.asarray(sk))), sk)
        gh = np.asarray(guo_hall_thin(jnp.asarray(m)))
        np.testing.assert_array_equal(np.asarray(zhang_suen_step(jnp.asarray(gh), "guo-hall")), gh)
        # One pixel wide: no 2x2 block fully set.
        blocks = sk[:-1, :-1] & sk[1:, :-1] & sk[:-1, 1:] & sk[1:, 1:]
        assert not blocks.any()


def test_empty_and_full_lines():
    z = np.zeros(SHAPE, bool)
    assert not np.asarray(zhang_suen_thin(jnp.asarray(z))).any()
    line = z.copy()
    line[30, 10:80] = True
    np.testing.assert_array_equal(np.asarray(zhang_suen_thin(jnp.asarray(line))), line)


def test_jit_eager_vmap_and_no_retrace(masks):
    m = jnp.asarray(np.stack(masks))
    batched = jax.vmap(zhang_suen_thin)(m)
    for k in range(len(masks)):
        np.testing.assert_array_equal(np.asarray(batched[k]), np.asarray(zhang_suen_thin(m[k])))
    # eager loop of steps == jitted while_loop
    x = m[0]
    for _ in range(50):
        x = zhang_suen_step(x)
    np.testing.assert_array_equal(np.asarray(x), np.asarray(zhang_suen_thin(m[0])))
    with jax.disable_jit():
        eager = zhang_suen_thin(m[1])
    np.testing.assert_array_equal(np.asarray(eager), np.asarray(zhang_suen_thin(m[1])))

    @eqx.debug.assert_max_traces(max_traces=1)
    def f(a):
        return zhang_suen_thin(a)

    g = jax.jit(f)
    for k in range(len(masks)):
        g(m[k])


def test_cropped_thinning_equals_full_image():
    from jaxcr.stereo.pipeline import _thin_cropped

    m = np.zeros((120, 160), np.uint8)
    cv2.polylines(m, [np.array([[20, 110], [30, 50], [150, 20]], np.int32)], False, 1, 6)
    cv2.circle(m, (155, 115), 6, 1, -1)  # touches the image border
    m = m.astype(bool)
    np.testing.assert_array_equal(
        _thin_cropped(m, block=32), np.asarray(zhang_suen_thin(jnp.asarray(m)))
    )
