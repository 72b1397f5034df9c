"""A 5-DOF articulated arm (Katana-like) for robot-based segmentation: forward kinematics g(x).

Joints x = (yaw, shoulder pitch, elbow pitch, wrist pitch, wrist roll), radians. Robot frame:
the table is the plane z = 0, the base sits at the origin, +z up. The shoulder is at height
``base_height`` above the base; the three links (upper arm, forearm, hand) lie in the vertical
plane rotated by the yaw, with link k at absolute elevation a_k = x1 + ... + x_k above the
horizontal. The wrist roll turns the hand about its own axis (it moves no joint position,
only the end-effector frame used to carry a gripped object).

g(x) (M-L paper Table 1, "forward kinematics function", R^5 -> R^3) is
:func:`end_effector`; :func:`arm_inverse` is a closed-form inverse used by the scene
generator to drive the tip along straight lines.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from jaxcr.errors import InputError


class ArmModel(eqx.Module):
    """Link lengths of the 5-DOF chain, metres."""

    base_height: float = 0.20
    upper: float = 0.19
    forearm: float = 0.14
    hand: float = 0.12

    def to_dict(self) -> dict:
        return {
            "kind": "chain5",
            "base_height": float(self.base_height),
            "links": [float(self.upper), float(self.forearm), float(self.hand)],
        }


def arm_from_dict(d: dict, file: str | None = None) -> ArmModel:
    """Parse ``{"kind": "chain5", "base_height": h, "links": [l1, l2, l3]}`` (metres)."""
    if not isinstance(d, dict) or d.get("kind") != "chain5":
        raise InputError("arm.kind must be 'chain5'", file=file, field="arm.kind")
    try:
        links = [float(v) for v in d["links"]]
        h = float(d["base_height"])
    except (KeyError, TypeError, ValueError) as err:
        raise InputError(
            f"arm needs base_height and 3 links ({err})", file=file, field="arm"
        ) from None
    # lengths beyond float32's range would be inf in the core
    big = float(np.finfo(np.float32).max)
    if len(links) != 3 or min(links) <= 0 or not np.all(np.abs(links) <= big):
        raise InputError("arm.links must be 3 positive lengths", file=file, field="arm.links")
    if not abs(h) <= big:
        raise InputError(f"must be a finite length, got {h}", file=file, field="arm.base_height")
    return ArmModel(h, *links)


def _rz(a):
    c, s = jnp.cos(a), jnp.sin(a)
    z, o = jnp.zeros_like(a), jnp.ones_like(a)
    return jnp.stack([jnp.stack([c, -s, z]), jnp.stack([s, c, z]), jnp.stack([z, z, o])])


def joint_positions(arm: ArmModel, x: Float[Array, "5"]) -> Float[Array, "5 3"]:
    """Robot-frame positions (m) of base, shoulder, elbow, wrist and tip for joints ``x``."""
    x = jnp.asarray(x)
    a = jnp.cumsum(x[1:4])  # absolute link elevations
    lengths = jnp.array([arm.upper, arm.forearm, arm.hand], dtype=x.dtype)
    r = jnp.concatenate([jnp.zeros(1, x.dtype), jnp.cumsum(lengths * jnp.cos(a))])
    z = arm.base_height + jnp.concatenate([jnp.zeros(1, x.dtype), jnp.cumsum(lengths * jnp.sin(a))])
    c, s = jnp.cos(x[0]), jnp.sin(x[0])
    chain = jnp.stack([r * c, r * s, z], axis=1)  # shoulder, elbow, wrist, tip
    base = jnp.zeros((1, 3), x.dtype)
    return jnp.concatenate([base, chain], axis=0)


def end_effector(arm: ArmModel, x: Float[Array, "5"]) -> Float[Array, "3"]:
    """g(x): robot-frame tip position, metres (M-L paper eq. 3, inner function)."""
    return joint_positions(arm, x)[-1]


def end_effector_frame(arm: ArmModel, x: Float[Array, "5"]) -> Float[Array, "4 4"]:
    """Pose of the hand: columns of R are the hand axis (along the last link), the roll-turned
    side axis and their cross product; translation is the tip. Robot frame, metres."""
    x = jnp.asarray(x)
    a3 = x[1] + x[2] + x[3]
    c3, s3 = jnp.cos(a3), jnp.sin(a3)
    z, o = jnp.zeros_like(a3), jnp.ones_like(a3)
    # Elevation a3 in the arm plane: rotate +x up by a3 about -y.
    r_pitch = jnp.stack([jnp.stack([c3, z, -s3]), jnp.stack([z, o, z]), jnp.stack([s3, z, c3])])
    cr, sr = jnp.cos(x[4]), jnp.sin(x[4])
    r_roll = jnp.stack([jnp.stack([o, z, z]), jnp.stack([z, cr, -sr]), jnp.stack([z, sr, cr])])
    R = _rz(x[0]) @ r_pitch @ r_roll
    T = jnp.eye(4, dtype=x.dtype).at[:3, :3].set(R).at[:3, 3].set(end_effector(arm, x))
    return T


def arm_inverse(
    arm: ArmModel, tip: np.ndarray, hand_elevation: float, roll: float = 0.0
) -> np.ndarray:
    """Closed-form joints (elbow up) putting the tip at ``tip`` (robot frame, m) with the hand at
    elevation ``hand_elevation`` (rad, negative = pointing down). Raises ValueError out of reach."""
    tip = np.asarray(tip, np.float64)
    yaw = np.arctan2(tip[1], tip[0])
    r = np.hypot(tip[0], tip[1]) - arm.hand * np.cos(hand_elevation)
    zw = tip[2] - arm.hand * np.sin(hand_elevation) - arm.base_height
    d2 = r * r + zw * zw
    c2 = (d2 - arm.upper**2 - arm.forearm**2) / (2 * arm.upper * arm.forearm)
    if abs(c2) > 1.0:
        raise ValueError("target out of reach")
    q2 = -np.arccos(c2)  # elbow up: the forearm bends down from the upper arm
    q1 = np.arctan2(zw, r) - np.arctan2(
        arm.forearm * np.sin(q2), arm.upper + arm.forearm * np.cos(q2)
    )
    q3 = hand_elevation - q1 - q2
    return np.array([yaw, q1, q2, q3, roll])
