"""Issue 18's faster registration paths against the implementations they replace.

- The k-d tree clearance check (:func:`batch_clearance_kdtree`, the planner's default)
  against a slow double loop and the dense JAX check, and the planner with either check on a
  small case: the same route.
"""

import jax.numpy as jnp
import numpy as np
import pytest

from jaxcr.registration.arm import ArmSpec, arc_points_np
from jaxcr.registration.collision import batch_clearance, batch_clearance_kdtree
from jaxcr.registration.planning import ArcPlanner, PlannerConfig


def _slow_clearance(start, kappa, length, cloud, height, n=24):
    s = np.linspace(0.0, 1.0, n) * length
    c = arc_points_np(np.asarray(start, np.float64), np.array([kappa], np.float64), s[None])[0]
    best = np.inf
    for x, y, _ in c:
        for p in cloud:
            best = min(best, float(np.linalg.norm(p - np.array([x, y, height]))))
    return best


def test_kdtree_clearance_matches_slow_loop_and_dense_check():
    rng = np.random.default_rng(1)
    cloud = rng.uniform(-0.3, 0.3, (40, 3)).astype(np.float32)
    padded = np.zeros((48, 3), np.float32)
    padded[:40] = cloud
    mask = np.arange(48) < 40
    starts = rng.uniform(-0.1, 0.1, (6, 3)).astype(np.float32)
    ks = np.r_[rng.uniform(-5, 5, 5), 0.0].astype(np.float32)  # incl. a straight arc
    ls = rng.uniform(0.05, 0.4, 6).astype(np.float32)
    got = batch_clearance_kdtree(starts, ks, ls, padded, mask, 0.05)
    ref = [_slow_clearance(starts[i], ks[i], ls[i], cloud, 0.05) for i in range(6)]
    # both float64 on the same samples: rounding only
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-12)
    dense = np.asarray(batch_clearance(starts, ks, ls, padded, mask, jnp.float32(0.05)))
    # the dense check is float32: its (1 - cos a) / a cancels for a just above the 1e-4
    # series threshold, error ~ eps32 s / a <= 6e-8 x 0.4 m / 1e-4 = 2.4e-4 m worst case
    # (8e-6 m here, kappa 0.0036 1/m); the old test's float32-vs-float64 tolerance was 1e-4
    np.testing.assert_allclose(got, dense, rtol=0, atol=2.5e-4)
    empty = batch_clearance_kdtree(starts, ks, ls, padded, np.zeros(48, bool), 0.0)
    assert np.all(np.isinf(empty))


def test_planner_kdtree_plans_the_dense_checks_route():
    spec = ArmSpec(3, 0.15, 0.01, 0.1, (0.3, -0.1, np.pi / 2), 12.0)
    rng = np.random.default_rng(0)
    # obstacles on a ring around the object (radius 0.05) and a post beside the path
    ang = rng.uniform(0, 2 * np.pi, 150)
    ring = np.stack([0.05 * np.cos(ang), 0.05 * np.sin(ang), np.full(150, 0.1)], 1)
    post = rng.normal([0.2, 0.2, 0.1], 0.01, (60, 3))
    cloud = np.concatenate([ring, post])
    routes = {}
    for coll in ("jax", "kdtree"):
        cfg = PlannerConfig(
            direction=1,
            delta_s=0.02,
            view_radius=0.3,
            n_kappa=5,
            n_length=4,
            cloud_size=64,
            collision=coll,
        )
        planner = ArcPlanner(spec, cfg)
        for _ in range(8):
            if planner.step(cloud, np.zeros(2)) != "moving":
                break
        st = planner.state
        routes[coll] = (st.arcs, st.travelled, st.events, st.status)
    assert len(routes["jax"][2]) >= 2  # the case plans (not an immediate 'no motion')
    assert routes["kdtree"] == routes["jax"]


def test_planner_rejects_unknown_collision_check():
    spec = ArmSpec(3, 0.15, 0.01, 0.1, (0.3, -0.1, np.pi / 2), 12.0)
    with pytest.raises(ValueError, match="collision"):
        ArcPlanner(spec, PlannerConfig(direction=1, delta_s=0.02, view_radius=0.3, collision="x"))


# ------------------------------------------------------------------ robust scale (ICP)
@pytest.mark.parametrize("n", [1, 2, 7, 100, 8192])
@pytest.mark.parametrize("scale", [1e-4, 1.0])
def test_masked_median_equals_numpy_median(n, scale):
    from jaxcr.registration.projective import masked_median

    rng = np.random.default_rng(n)
    x = (np.abs(rng.normal(size=n)) * scale).astype(np.float32)
    ok = rng.random(n) < 0.7
    ok[0] = True
    got = float(masked_median(jnp.asarray(x), jnp.asarray(ok)))
    ref = float(np.median(x[ok]))
    # the bisection ends on the order statistics themselves (docstring); their mean in
    # float32 vs numpy's float32 mean: 1 ulp
    assert got == pytest.approx(ref, rel=2.4e-7, abs=0)


def test_masked_median_of_nothing_is_nan():
    from jaxcr.registration.projective import masked_median

    assert np.isnan(float(masked_median(jnp.ones(5), jnp.zeros(5, bool))))


def test_first_per_cell_equals_rowwise_unique():
    from jaxcr.registration.planning import _first_per_cell

    rng = np.random.default_rng(3)
    pts = rng.uniform(-0.4, 0.4, (3000, 3))
    pts[1000:1500] = pts[:500] + 1e-4  # many points sharing cells
    ref = np.unique(np.floor(pts / 0.005).astype(np.int64), axis=0, return_index=True)[1]
    np.testing.assert_array_equal(_first_per_cell(pts, 0.005), ref)


def test_kdtree_clearance_upper_bound_keeps_values_below_it():
    rng = np.random.default_rng(4)
    cloud = rng.uniform(-0.3, 0.3, (200, 3))
    starts = rng.uniform(-0.1, 0.1, (50, 3))
    ks = rng.uniform(-8, 8, 50)
    ls = rng.uniform(0.05, 0.4, 50)
    full = batch_clearance_kdtree(starts, ks, ls, cloud, np.ones(200, bool), 0.05)
    bound = float(np.median(full))
    cut = batch_clearance_kdtree(starts, ks, ls, cloud, np.ones(200, bool), 0.05, upper_bound=bound)
    below = full < bound
    assert below.any() and (~below).any()
    np.testing.assert_array_equal(cut[below], full[below])  # the same exact search
    assert np.all(np.isinf(cut[~below]))
