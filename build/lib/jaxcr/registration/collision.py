"""Batched collision checks between planned arcs and point clouds (paper Sec. III.B, ref.
[27]): an arc swept by an arm of radius ``r`` collides when some cloud point is closer than
``r + clearance`` to the arc's centreline. The arc is sampled densely (spacing well below
the clearance) and the minimum point distance is taken by brute force in JAX; candidates
are vmapped, clouds padded to a fixed size with a mask so one compile serves a whole run.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxcr._types import Array, Bool, Float
from jaxcr.registration.arm import arc_points


def arc_clearance(
    start: Float[Array, "3"],
    kappa: Float[Array, ""],
    length: Float[Array, ""],
    cloud: Float[Array, "m 3"],
    mask: Bool[Array, " m"],
    height: Float[Array, ""],
    n_samples: int = 24,
) -> Float[Array, ""]:
    """Smallest distance (m) between the centreline of one arc (planar, at ``height``) and the
    masked cloud points (world frame). ``inf`` for an empty cloud."""
    s = jnp.linspace(0.0, 1.0, n_samples) * length
    xyh = arc_points(start, kappa, s)
    c = jnp.concatenate([xyh[:, :2], jnp.full((n_samples, 1), height)], axis=1)
    d2 = jnp.sum((c[:, None, :] - cloud[None, :, :]) ** 2, axis=-1)
    d2 = jnp.where(mask[None, :], d2, jnp.inf)
    m = jnp.min(d2)
    return jnp.sqrt(jnp.where(jnp.isfinite(m), m, 1.0)) * jnp.where(jnp.isfinite(m), 1.0, jnp.inf)


@jax.jit
def batch_clearance(
    starts: Float[Array, "b 3"],
    kappas: Float[Array, " b"],
    lengths: Float[Array, " b"],
    cloud: Float[Array, "m 3"],
    mask: Bool[Array, " m"],
    height: Float[Array, ""],
) -> Float[Array, " b"]:
    """:func:`arc_clearance` for ``b`` candidate arcs (the batched entry point)."""
    return jax.vmap(arc_clearance, in_axes=(0, 0, 0, None, None, None))(
        starts, kappas, lengths, cloud, mask, height
    )


def collision_free(clearance, radius: float, margin: float):
    """True where the clearance exceeds the arm radius plus the safety margin."""
    return clearance > radius + margin
