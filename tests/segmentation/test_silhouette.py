"""jaxcr.segmentation.silhouette: capsule projection vs the rasterised tube surface (Watson eq. 7), band
rasterisation vs dense, margins and gradients."""

import cv2
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from skimage.draw import polygon

from jaxcr.camera import Camera, project_points, surface_points
from jaxcr.segmentation.silhouette import (
    TileGrid,
    TubeImage,
    band_margin,
    capsule_margin,
    coarsen_tube,
    level_tube,
    margin_dense,
    project_tube,
    rasterise,
    scale_tube,
)
from tests.helpers.jitted import integrate_centreline  # compiled: input construction only

# The rasterisers and band selection compiled (one program per image and band size; the
# dense one and select_band shared with other modules through the run's compilation cache):
# run op by op, each primitive was its own XLA compilation per shape (~270 more programs in this
# module). refine_frame only runs them jitted; test_vmap_equals_loop keeps the eager
# rasteriser (the loop) against the jitted vmap.
from tests.helpers.jitted import rasterise_dense as _rasterise_dense
from tests.helpers.jitted import select_band as _select_band

_rasterise = eqx.filter_jit(rasterise)


def _scene(w=640, h=480, rho=1.5e-3):
    n = 48
    s = jnp.linspace(0.0, 0.12, n)
    u = jnp.tile(jnp.array([8.0, 3.0, 0.0]), (n - 1, 1))
    R0 = jnp.array([[0.0, 0, 1], [0, 1, 0], [-1, 0, 0]])
    cl = integrate_centreline(s, u, jnp.full(n, rho), jnp.array([-0.05, 0.0, 0.0]), R0)
    cam = Camera.look_at([0, 0, -0.3], [0, 0, 0], [0, -1, 0], fx=800 * w / 640, size=(w, h))
    return cl, cam


def _iou(a, b):
    return (a & b).sum() / max((a | b).sum(), 1)


@pytest.fixture(scope="module")
def scene640():
    return _scene()


def test_capsules_match_rasterised_surface(scene640):
    """Union of 2-D capsules vs eq. 7 surface points projected and filled per segment."""
    cl, cam = scene640
    pts = jax.jit(surface_points, static_argnums=1)(cl, 24)  # (N, 24, 3)
    uv, _ = eqx.filter_jit(project_points)(cam, pts.reshape(-1, 3))
    uv = np.asarray(uv).reshape(pts.shape[0], 24, 2)
    ref = np.zeros((cam.height, cam.width), np.uint8)
    for i in range(pts.shape[0] - 1):
        poly = np.concatenate([uv[i], uv[i + 1]]).astype(np.float32)
        hull = cv2.convexHull(poly)[:, 0]
        # pixels whose centre lies inside the hull (cv2.fillPoly would also take edge pixels)
        rr, cc = polygon(hull[:, 1], hull[:, 0], ref.shape)
        ref[rr, cc] = 1
    mask = np.asarray(_rasterise_dense(project_tube(cam, cl), 480, 640))
    assert _iou(mask, ref.astype(bool)) > 0.97


def test_band_rasterise_equals_dense(scene640):
    cl, cam = scene640
    tube = project_tube(cam, cl)
    dense = np.asarray(_rasterise_dense(tube, 480, 640))
    band, exact = _rasterise(tube, 480, 640, k_tiles=600)
    assert bool(exact)
    assert (np.asarray(band) != dense).sum() == 0


def test_margin_is_signed_distance_for_a_disc():
    # degenerate segment = disc of radius 3 around (10, 10)
    t = TubeImage(*(jnp.array([v]) for v in (10.0, 10.0, 10.0, 10.0, 3.0, 3.0)), jnp.array([True]))
    px = jnp.array([10.0, 13.0, 15.0, 10.0])
    py = jnp.array([10.0, 10.0, 10.0, 5.0])
    m, idx = margin_dense(px, py, t)
    np.testing.assert_allclose(m, [3.0, 0.0, -2.0, -2.0], atol=1e-6)
    assert (np.asarray(idx) == 0).all()


def test_margin_gradients_finite_at_singular_points():
    def f(args):
        return capsule_margin(10.0, 10.0, *args, True)

    # zero distance (point on the axis) and zero-length segment
    for args in [
        (jnp.array(10.0), jnp.array(10.0), jnp.array(20.0), jnp.array(10.0), 2.0, 2.0),
        (jnp.array(10.0), jnp.array(10.0), jnp.array(10.0), jnp.array(10.0), 2.0, 2.0),
    ]:
        g = jax.grad(lambda a, b, c, d, r=args[4:]: f((a, b, c, d) + r), argnums=(0, 1, 2, 3))(
            *args[:4]
        )
        assert all(np.isfinite(np.asarray(x)) for x in g)


def test_margin_gradient_vs_finite_differences():
    args = [jnp.array(v) for v in (1.0, 2.0, 9.0, 5.0, 2.0, 3.0)]

    def f(a):
        return capsule_margin(4.0, 7.0, *a, True)

    g = jax.grad(lambda *a: f(a), argnums=tuple(range(6)))(*args)
    eps = 1e-3
    for i in range(6):
        hi = list(args)
        lo = list(args)
        hi[i] = hi[i] + eps
        lo[i] = lo[i] - eps
        fd = (f(hi) - f(lo)) / (2 * eps)
        np.testing.assert_allclose(float(g[i]), float(fd), atol=2e-3)


def test_scale_tube_matches_downsampled_camera():
    """Level-1 capsules equal the projection by a camera with half the focal length and the
    principal point moved as (c + 0.5) / 2 - 0.5."""
    cl, cam = _scene(160, 120)
    t1 = scale_tube(project_tube(cam, cl), 1)
    K = np.asarray(cam.K).copy()
    K[:2, :2] /= 2
    K[0, 2] = (K[0, 2] + 0.5) / 2 - 0.5
    K[1, 2] = (K[1, 2] + 0.5) / 2 - 0.5
    from jaxcr.camera import camera_from_arrays

    cam2 = camera_from_arrays(K, np.zeros(5), np.asarray(cam.T_cam_robot), 80, 60)
    t2 = project_tube(cam2, cl)
    for a, b in zip(jax.tree.leaves(t1), jax.tree.leaves(t2), strict=True):
        np.testing.assert_allclose(np.asarray(a, float), np.asarray(b, float), atol=1e-3)


def test_vmap_equals_loop():
    cl, cam = _scene(96, 72)
    shifts = jnp.array([0.0, 0.003, -0.004])

    def mask(dx):
        c2 = type(cl)(cl.s, cl.p + jnp.array([0.0, dx, 0.0]), cl.R, cl.u, cl.rho)
        return rasterise(project_tube(cam, c2), 72, 96)[0]

    batched = jax.jit(jax.vmap(mask))(shifts)
    for i, dx in enumerate(shifts):
        np.testing.assert_array_equal(np.asarray(batched[i]), np.asarray(mask(dx)))


def test_coarsen_tube_keeps_the_silhouette(scene640):
    """Merged capsules (stride 4 of 47 segments, last run shorter) vs the dense raster of the
    original: a pixel can only change class if its margin is within the chord sag of the
    merged segments (the distance of the dropped joints from the merged chord, ~0.3 px here)
    plus the radius interpolation change; checked with a 0.5 px allowance. The ends are kept."""
    cl, cam = scene640
    tube = project_tube(cam, cl)
    c = coarsen_tube(tube, 4)
    assert c.ax.shape == (12,)
    np.testing.assert_allclose(c.ax[0], tube.ax[0])
    np.testing.assert_allclose(c.bx[-1], tube.bx[-1])
    np.testing.assert_allclose(c.rb[-1], tube.rb[-1])
    a = np.asarray(_rasterise_dense(tube, 480, 640))
    b = np.asarray(_rasterise_dense(c, 480, 640))
    # sag: distance of every original joint from its merged capsule's axis
    px, py = np.asarray(tube.ax), np.asarray(tube.ay)
    idx = np.arange(px.size) // 4
    m_axis = np.asarray(capsule_margin(px, py, c.ax[idx], c.ay[idx], c.bx[idx], c.by[idx],
                                       0.0, 0.0, True))  # fmt: skip
    sag = float(np.max(-m_axis))
    assert 0.0 < sag < 1.0
    diff = a != b
    assert diff.sum() > 0
    yy, xx = np.nonzero(diff)
    m, _ = margin_dense(jnp.asarray(xx, jnp.float32), jnp.asarray(yy, jnp.float32), tube)
    assert np.max(np.abs(np.asarray(m))) <= sag + 0.5
    # a run containing an invalid segment is invalid
    bad = TubeImage(*(x for x in (tube.ax, tube.ay, tube.bx, tube.by, tube.ra, tube.rb)),
                    valid=tube.valid.at[5].set(False))  # fmt: skip
    v = np.asarray(coarsen_tube(bad, 4).valid)
    assert not v[1] and v[0] and v[2]
    # level_tube: scaled to the level grid, 2**level segments merged
    lt = level_tube(tube, 2)
    np.testing.assert_allclose(lt.ax[0], (tube.ax[0] + 0.5) / 4 - 0.5, rtol=1e-6)
    assert lt.ax.shape == (12,)
    # merge: merge * 2**level segments per capsule
    assert level_tube(tube, 2, 2).ax.shape == (6,)
    np.testing.assert_allclose(level_tube(tube, 1, 2).bx, level_tube(tube, 2).bx * 2 + 0.5)


def test_band_flags_incomplete_candidates(scene640):
    """With one candidate segment per tile for a tube of many short segments, the band mask
    has holes (differs from the dense raster) and ``exact`` must say so; with enough
    candidates it equals the dense raster and ``exact`` holds."""
    cl, cam = scene640
    tube = scale_tube(project_tube(cam, cl), 2)  # 160x120 grid, segments ~2-3 px long
    grid = TileGrid(120, 160, 8)
    dense = np.asarray(_rasterise_dense(tube, 120, 160))
    few = _select_band(tube, grid, grid.n_tiles, 1)
    many = _select_band(tube, grid, grid.n_tiles, 47)
    m_few, ex_few = _rasterise(tube, 120, 160, tile=8, k_tiles=grid.n_tiles, k_seg=1)
    m_many, ex_many = _rasterise(tube, 120, 160, tile=8, k_tiles=grid.n_tiles, k_seg=47)
    assert not bool(few.exact) and not bool(ex_few)
    assert (np.asarray(m_few) != dense).sum() > 0
    assert bool(many.exact) and bool(ex_many)
    np.testing.assert_array_equal(np.asarray(m_many), dense)


def _band_margin_max_reference(tube, grid, band):
    """Slow reference: margin of every candidate of each band pixel, max over candidates
    (whose gradient JAX routes to the winner), pixel by pixel in a Python loop over tiles."""
    ox, oy = grid.pixel_offsets()
    rows = []
    tiles = np.asarray(band.tiles)  # the band is data (no gradient): its tiles on the host
    for k in range(tiles.shape[0]):
        t = int(tiles[k])
        px = (t % grid.cols) * grid.tile + ox
        py = (t // grid.cols) * grid.tile + oy
        segs = band.segs[k]
        m = capsule_margin(
            px[:, None], py[:, None], *(a[segs][None] for a in
            (tube.ax, tube.ay, tube.bx, tube.by, tube.ra, tube.rb, tube.valid))
        )  # fmt: skip
        rows.append(jnp.max(m, axis=1))
    return jnp.stack(rows)


def test_band_margin_value_and_gradient_equal_max_over_candidates(scene640):
    """band_margin differentiates only the winning candidate; value and gradient (of a soft
    silhouette sum w.r.t. the projected centreline points and radii) must equal those of max
    over all candidates. Consecutive capsules share their joint, where both margins tie over
    a wedge: max splits the gradient between the two copies of the joint, argmax gives it to
    one, so gradients are compared w.r.t. the shared points. Tolerance: float32 rounding."""
    cl, cam = scene640
    t0 = level_tube(project_tube(cam, cl), 1, 2)  # 320x240, merged capsules
    grid = TileGrid(240, 320, 8)
    band = _select_band(t0, grid, 40, 3)
    pts = (jnp.append(t0.ax, t0.bx[-1]), jnp.append(t0.ay, t0.by[-1]), jnp.append(t0.ra, t0.rb[-1]))

    def loss(fn, pts):
        x, y, r = pts
        t = TubeImage(x[:-1], y[:-1], x[1:], y[1:], r[:-1], r[1:], t0.valid)
        m = fn(t, grid, band)
        return jnp.sum(jax.nn.sigmoid(m / 0.7)), m

    # margins (the aux output, at the unperturbed points) and gradient: band_margin's in one
    # compiled program (op by op it was ~100 XLA compilations of single primitives); the
    # reference stays eager (compiled, its loop of 40 tiles costs more than its primitives)
    g, m = jax.jit(jax.grad(lambda p: loss(band_margin, p), has_aux=True))(pts)
    g_ref, m_ref = jax.grad(lambda p: loss(_band_margin_max_reference, p), has_aux=True)(pts)
    np.testing.assert_allclose(np.asarray(m), np.asarray(m_ref), rtol=1e-5, atol=1e-5)
    for a, b in zip(g, g_ref, strict=True):
        a, b = np.asarray(a), np.asarray(b)
        assert np.abs(b).max() > 0
        np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-4 * np.abs(b).max())
