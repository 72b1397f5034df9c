"""Frame batches over all local JAX devices: a 1-D split over frames.

A batch function ``fn(batched, *shared)`` whose every output has the frame axis first runs,
with D local devices, as D copies of ``fn``, one per device, each on a contiguous block of the
frames (the shared arguments copied to every device); the blocks are dispatched together (JAX
runs them asynchronously, one per device) and the outputs concatenated. Each device runs the
same per-frame program a single device runs on the whole batch, with nothing crossing devices,
so the per-frame results are the single-device results bit for bit (checked by
``tests/scale/test_devices.py``). The batch is padded to a multiple of D by repeating its last
frame; the padded results are dropped.

Why not ``jax.shard_map`` / ``pmap``: under either, Optimistix's BFGS (the refinement's
solver) fails in jax 0.10 -- lineax compares the structure of ``y`` with that of the Hessian's
output, which carries the manual mesh's sharding ("Symmetric/Hermitian matrices must have
matching input and output structures") -- and the pruned k-NN search's ``top_k`` +
``optimization_barrier`` crashes XLA's CPU SPMD pipeline. Explicit per-device dispatch needs
neither. Its cost: each device compiles its copy once (in parallel threads; XLA compiles
without the GIL), then the compiled copies are reused for every batch of that shape.

With one device (a laptop, one GPU: the usual case) :func:`map_frames` calls ``fn`` directly,
so nothing changes. On CPU, ``XLA_FLAGS=--xla_force_host_platform_device_count=D`` (set before
JAX starts) makes D host devices, which is how the tests check equality.
"""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

import equinox as eqx
import jax
import jax.numpy as jnp


def device_count(devices: int | None = None) -> int:
    """The number of devices a batch is spread over: ``devices`` (at most the local device
    count), or all local devices of the default backend when None."""
    n = jax.local_device_count()
    return n if devices is None else max(1, min(int(devices), n))


def _pad(tree, n_to: int):
    def pad(x):
        extra = n_to - x.shape[0]
        if extra == 0:
            return x
        return jnp.concatenate([x, jnp.repeat(x[-1:], extra, axis=0)], axis=0)

    return jax.tree.map(pad, tree)


def _on(tree, device):
    return jax.tree.map(lambda x: jax.device_put(x, device) if eqx.is_array(x) else x, tree)


def map_frames(fn: Callable, batched, *shared, devices: int | None = None):
    """``fn(batched, *shared)`` with the frame axis (axis 0 of every leaf of ``batched``)
    spread over the local devices.

    Args:
        fn: a (jit-compatible) batch function; every output leaf has the frame axis first.
        batched: a pytree of arrays with a common leading frame axis F.
        shared: arguments every device gets whole (cameras, configs); non-array leaves are
            static.
        devices: how many local devices to use (None: all; 1: no sharding).

    Returns ``fn``'s output for the F frames.
    """
    d = device_count(devices)
    leaves = jax.tree.leaves(batched)
    if d == 1 or not leaves:
        return fn(batched, *shared)
    f = leaves[0].shape[0]
    per = -(-f // d)
    padded = _pad(batched, per * d)
    devs = jax.local_devices()[:d]

    def run(k):
        block = jax.tree.map(lambda x: x[k * per : (k + 1) * per], padded)
        return fn(_on(block, devs[k]), *_on(shared, devs[k]))

    with ThreadPoolExecutor(d) as pool:  # trace/compile the D copies in parallel
        outs = list(pool.map(run, range(d)))
    dev0 = devs[0]
    out = jax.tree.map(lambda *xs: jnp.concatenate([jax.device_put(x, dev0) for x in xs]), *outs)
    return jax.tree.map(lambda x: x[:f], out) if per * d != f else out
