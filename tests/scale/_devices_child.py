"""Run by tests/scale/test_devices.py in a subprocess with XLA_FLAGS=
--xla_force_host_platform_device_count=2 (the flag must be set before JAX starts): the batch
paths on 2 host devices vs on 1, printed as JSON (max |difference| per output, and the
device count)."""

from __future__ import annotations

import json

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np


def max_diff(a, b) -> float:
    la, lb = jax.tree.leaves(a), jax.tree.leaves(b)
    assert len(la) == len(lb)
    worst = 0.0
    for x, y in zip(la, lb, strict=True):
        x, y = np.asarray(x), np.asarray(y)
        assert x.shape == y.shape, (x.shape, y.shape)
        if x.dtype == bool or np.issubdtype(x.dtype, np.integer):
            worst = max(worst, float(np.sum(x != y)))
        else:  # NaN in the same place counts as equal
            same = (x == y) | (np.isnan(x) & np.isnan(y))
            worst = max(worst, float(np.max(np.where(same, 0.0, np.abs(x - y)), initial=0.0)))
    return worst


def main() -> None:
    from jaxcr.camera import Camera
    from jaxcr.eigen.manifold import Manifold, query_batch
    from jaxcr.kinematics.batch import batch_forward
    from jaxcr.kinematics.robots import robot_from_dict
    from jaxcr.segmentation.refine import RefineConfig, refine_batch

    out = {"devices": jax.local_device_count()}
    robot = robot_from_dict({
        "kind": "constant_curvature",
        "sections": [{"length": 0.05, "radius": 0.001}],
        "joints": ["kappa", "phi"],
    })  # fmt: skip
    # 5 rows: odd, so the 2-device path pads
    q = np.array([[5.0, 0.1], [8.0, -0.4], [2.0, 1.0], [12.0, 0.3], [0.5, -1.2]])
    one = batch_forward(robot, q, chunk=5, progress=False, devices=1)
    two = batch_forward(robot, q, chunk=5, progress=False, devices=None)
    out["fk"] = max_diff(one, two)

    rng = np.random.default_rng(0)
    u = rng.uniform(0, 1, (600, 2)).astype(np.float32)
    F = np.concatenate([np.sin(3 * u), np.cos(2 * u), u**2], 1).astype(np.float32)
    m = Manifold(jnp.asarray(u), jnp.asarray(F))
    X = (F[rng.integers(0, 600, 7)] + 0.02 * rng.normal(size=(7, 6))).astype(np.float32)
    out["eigen_query"] = max_diff(query_batch(m, jnp.asarray(X), 3, devices=1),
                                  query_batch(m, jnp.asarray(X), 3))  # fmt: skip

    # refinement: 4 frames of a 48x36 camera, a short schedule (cheap compile). The
    # single-device reference refines frames 0-1 and 2-3 as two batches on device 0: the same
    # compiled program as the 2-device run's first block, so only device 1's copy compiles
    # anew (the padding path is covered by fk's 5 rows above). "The same program" needs the
    # same arguments as map_frames gives device 0's copy: every array committed to device 0
    # (jit compiles an uncommitted argument separately from a committed one), including the
    # traced settings refine_batch makes itself (_traced_apart), hence the commit in ``jit_call``
    # (refine_batch's hook for calling its compiled function) rather than on the inputs:
    # measured, three refinement compiles with the budgets uncommitted, two with this
    cam = Camera.look_at([0.0, -0.2, 0.03], [0.0, 0.0, 0.03], [0.0, 0.0, 1.0], 90.0, (48, 36))
    fk = jax.jit(jax.vmap(robot.forward))(jnp.asarray(q[:4], jnp.float32))
    imgs = jnp.asarray(rng.random((4, 36, 48, 3)), jnp.float32)
    bgs = jnp.asarray(rng.random((4, 36, 48)) > 0.7)
    cfg = RefineConfig(levels=(0,), steps=(3,), outer=(1,), tau=(0.8,), n_coeffs=2,
                       band_tiles=24, min_tiles=8, camera_correction=False)  # fmt: skip

    dev0 = jax.local_devices()[0]

    def on0(tree):
        return jax.tree.map(lambda x: jax.device_put(x, dev0) if eqx.is_array(x) else x, tree)

    def part(a, b):
        cl = jax.tree.map(lambda x: x[a:b], fk.centreline)
        return refine_batch(
            cl, (cam,), (imgs[a:b],), (bgs[a:b],), cfg, devices=1,
            jit_call=lambda fn, *args: fn(*on0(args)),
        )  # fmt: skip

    r1 = jax.tree.map(lambda x, y: jnp.concatenate([x, y]), part(0, 2), part(2, 4))
    r2 = refine_batch(fk.centreline, (cam,), (imgs,), (bgs,), cfg)
    # time_s is wall time, not a result
    r1, r2 = (eqx.tree_at(lambda r: r.time_s, r, None) for r in (r1, r2))
    out["refine"] = max_diff(r1, r2)
    out["refine_steps"] = np.asarray(r2.num_steps).tolist()
    print(json.dumps(out))


if __name__ == "__main__":
    main()
