"""Multi-backbone single-segment continuum robot (IREP-like), Reiter et al. eqs. 1-4.

Configuration q = psi = (theta_L, delta) (Reiter et al. eq. 1): ``theta_L`` is the angle of the
backbone tangent at the end disk, ``theta_0 = pi/2`` is the straight configuration, so the
bending angle is ``theta_0 - theta_L``; ``delta`` selects the bending plane. The end-disk
orientation is (Reiter et al. eq. 2)

    R = Rz Ry Rz^T,  Rz = exp(-delta [e3 x]),  Ry = exp((theta_0 - theta_L) [e2 x]),

and the inverse map is eqs. 3-4:

    theta_L = theta_0 - atan2(sqrt(R13^2 + R23^2), R33),   delta = -atan2(R23, R13).

The backbone is a circular arc (the segment bends in a circular shape), so the frame at
arclength s is ``Rz Ry(s/L (theta_0 - theta_L)) Rz^T``: constant body curvature
``u = ((theta_0 - theta_L)/L) (sin delta, cos delta, 0)``.

Workspace: bending angle in [0, pi] (theta_L in [-pi/2, pi/2]), delta in (-pi, pi].
Outside it ``forward`` and ``angles_to_rotation`` still follow the formulas (theta_L > pi/2
bends towards delta + pi), and ``rotation_to_angles`` returns the equivalent workspace angles.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, ClassVar

import equinox as eqx
import jax.numpy as jnp

from jaxcr._types import Array, Float, Mat3
from jaxcr.geometry import rot_y, rot_z
from jaxcr.kinematics.base import (
    MAX_POINTS,
    FkResult,
    check_keys,
    closed_form_result,
    get_int,
    get_number,
    require_mapping,
)
from jaxcr.kinematics.cosserat import integrate_centreline

THETA_0 = jnp.pi / 2
# Below this bending magnitude sqrt(R13^2 + R23^2) the bending plane is undefined (straight).
_STRAIGHT_EPS = 1e-7
_TOP_KEYS = {"kind", "length", "radius", "bending_stiffness", "n_points", "name"}


def angles_to_rotation(theta_L: Float[Array, ""], delta: Float[Array, ""]) -> Mat3:
    """End-disk rotation R = Rz Ry Rz^T (Reiter et al. eq. 2), robot frame."""
    Rz = rot_z(-delta)
    return Rz @ rot_y(THETA_0 - theta_L) @ Rz.T


def rotation_to_angles(R: Mat3) -> Float[Array, "2"]:
    """(theta_L, delta) from an end-disk rotation (Reiter et al. eqs. 3-4).

    Inverse of :func:`angles_to_rotation` on the workspace (bending angle in (0, pi],
    delta in (-pi, pi]). At the straight configuration (theta_L = pi/2) delta is undefined:
    when sqrt(R13^2 + R23^2) < 1e-7 this returns delta = 0 and theta_L = pi/2 - atan2(0, R33)
    (= pi/2 for a proper rotation), both with finite (zero) gradients ("double where").
    """
    r13, r23, r33 = R[0, 2], R[1, 2], R[2, 2]
    n2 = r13**2 + r23**2
    straight = n2 < _STRAIGHT_EPS**2
    safe_n2 = jnp.where(straight, 1.0, n2)
    # sqrt has an infinite derivative at 0: below the threshold use bend = 0 (error < 1e-7 rad).
    bend = jnp.where(straight, 0.0, jnp.sqrt(safe_n2))
    theta_L = THETA_0 - jnp.arctan2(bend, r33)
    safe_r13 = jnp.where(straight, 1.0, r13)
    safe_r23 = jnp.where(straight, 0.0, r23)
    delta = jnp.where(straight, 0.0, -jnp.arctan2(safe_r23, safe_r13))
    return jnp.stack([theta_L, delta])


class SingleSegment(eqx.Module):
    """One circular-arc segment with q = (theta_L, delta) (see module docstring).

    Attributes:
        length: backbone arclength L (m).
        radius: outer radius (m).
        bending_stiffness: EI (N m^2) for the energy ``EI (theta_0 - theta_L)^2 / (2 L)``;
            0 when unknown (energy 0).
        n_points: number of centreline samples (static).
    """

    kind: ClassVar[str] = "single_segment"

    length: Float[Array, ""]
    radius: Float[Array, ""]
    bending_stiffness: Float[Array, ""]
    n_points: int = eqx.field(static=True, default=64)

    def __check_init__(self):
        if self.n_points < 2:
            raise ValueError("n_points must be >= 2")

    @classmethod
    def make(cls, length, radius, bending_stiffness=0.0, n_points: int = 64, dtype=jnp.float32):
        return cls(
            length=jnp.asarray(length, dtype),
            radius=jnp.asarray(radius, dtype),
            bending_stiffness=jnp.asarray(bending_stiffness, dtype),
            n_points=int(n_points),
        )

    @property
    def n_joints(self) -> int:
        return 2

    def forward(self, q: Float[Array, "2"], guess: Array | None = None) -> FkResult:
        """Centreline for q = (theta_L, delta); tip frame equals :func:`angles_to_rotation`."""
        del guess
        q = jnp.asarray(q)
        if q.shape != (2,):
            raise ValueError(f"q must have shape (2,), got {q.shape}")
        dtype = jnp.result_type(q.dtype, self.length.dtype)
        theta_L, delta = q.astype(dtype)
        L = self.length.astype(dtype)
        k = (THETA_0 - theta_L) / L
        u = k * jnp.stack([jnp.sin(delta), jnp.cos(delta), jnp.zeros_like(delta)])
        n = self.n_points
        s = L * jnp.linspace(0.0, 1.0, n, dtype=dtype)
        u_steps = jnp.broadcast_to(u, (n - 1, 3))
        rho = jnp.broadcast_to(self.radius.astype(dtype), (n,))
        centreline = integrate_centreline(s, u_steps, rho)
        energy = 0.5 * self.bending_stiffness.astype(dtype) * k**2 * L
        return closed_form_result(centreline, energy)

    @classmethod
    def from_dict(cls, d: Mapping[str, Any], file: str | None = None) -> SingleSegment:
        """Parse ``{"kind": "single_segment", "length": L, "radius": r}`` (docs/dataset-format.md)."""
        d = require_mapping(d, file=file, field=None)
        check_keys(d, _TOP_KEYS, file=file)
        return cls.make(
            length=get_number(d, "length", file=file, positive=True),
            radius=get_number(d, "radius", file=file, positive=True),
            bending_stiffness=get_number(
                d, "bending_stiffness", file=file, default=0.0, nonnegative=True
            ),
            n_points=get_int(d, "n_points", file=file, default=64, minimum=2, maximum=MAX_POINTS),
        )

    def to_dict(self) -> dict[str, Any]:
        d = {
            "kind": self.kind,
            "length": float(self.length),
            "radius": float(self.radius),
            "n_points": self.n_points,
        }
        if float(self.bending_stiffness) != 0.0:
            d["bending_stiffness"] = float(self.bending_stiffness)
        return d
