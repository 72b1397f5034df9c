"""Planar multi-section constant-curvature arm with a tip RGB-D camera (Wang/Xiao et al.,
"Progressive object modeling with a continuum manipulator", Sec. III.B).

World frame: z up, the table top is z = 0, metres. The arm moves in the horizontal plane
z = ``height``: every section bends in that plane (phi = 0), so a tip path is a chain of
tangent-continuous planar arcs ``(x0, y0, heading0, kappa, length)`` with signed curvature
(kappa > 0 turns counter-clockwise seen from above).

Robot (base) frame of :class:`jaxcr.kinematics.constant_curvature.ConstantCurvature`: the
backbone leaves along +z; we place it so that robot z = horizontal heading, robot x = the
horizontal left normal and robot y = world up. With phi = 0 the body curvature is
``kappa * e_y``, i.e. a positive kappa turns the tangent towards robot +x (left): the planar
arc formula and the 3-D kinematics agree (tested).

Constrained inverse kinematics (paper ref. [19]) here means: given the planned arcs and the
arclength travelled by the tip, find section curvatures and lengths so that every section
lies on the planned path (sections conform to arcs), subject to a per-section maximum length
and a number of sections; an arc longer than one section is split over several.
"""

from __future__ import annotations

from dataclasses import dataclass

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from jaxcr._types import Array, Float
from jaxcr.kinematics.constant_curvature import ConstantCurvature


def _sinc_terms(a):
    """(sin a / a, (1 - cos a) / a) with the double-where trick at a = 0."""
    small = jnp.abs(a) < 1e-4
    a_safe = jnp.where(small, 1.0, a)
    s = jnp.where(small, 1.0 - a * a / 6.0, jnp.sin(a_safe) / a_safe)
    c = jnp.where(small, a / 2.0 - a**3 / 24.0, (1.0 - jnp.cos(a_safe)) / a_safe)
    return s, c


def arc_points(
    start: Float[Array, "3"], kappa: Float[Array, ""], s: Float[Array, " n"]
) -> Float[Array, "n 3"]:
    """Planar arc states ``(x, y, heading)`` at arclengths ``s`` (m) from ``start``
    ``(x0, y0, heading0)`` with signed curvature ``kappa`` (1/m). Closed form, finite at
    kappa = 0."""
    x0, y0, th0 = start[0], start[1], start[2]
    a = kappa * s
    sa, ca = _sinc_terms(a)
    dx = s * (jnp.cos(th0) * sa - jnp.sin(th0) * ca)
    dy = s * (jnp.sin(th0) * sa + jnp.cos(th0) * ca)
    return jnp.stack([x0 + dx, y0 + dy, th0 + a], axis=-1)


def arc_points_np(start: np.ndarray, kappa: np.ndarray, s: np.ndarray) -> np.ndarray:
    """numpy :func:`arc_points` for a batch of curvatures ``kappa`` (b,) and arclengths
    ``s`` (b, n): states (b, n, 3). For the planner's per-step geometry, where dispatching
    (and on first use compiling) JAX operations would cost more than the arithmetic."""
    a = kappa[:, None] * s
    small = np.abs(a) < 1e-6
    a_s = np.where(small, 1.0, a)
    sa = np.where(small, 1.0, np.sin(a_s) / a_s)
    ca = np.where(small, a / 2.0, (1.0 - np.cos(a_s)) / a_s)
    x0, y0, th = start
    x = x0 + s * (np.cos(th) * sa - np.sin(th) * ca)
    y = y0 + s * (np.sin(th) * sa + np.cos(th) * ca)
    return np.stack([x, y, th + a], axis=-1)


@dataclass(frozen=True)
class Arc:
    """A planned planar arc: start state ``(x, y, heading)`` (m, rad), curvature (1/m),
    length (m)."""

    start: tuple[float, float, float]
    kappa: float
    length: float

    def state_at(self, s: float) -> np.ndarray:
        start = np.asarray(self.start, np.float64)
        return arc_points_np(start, np.array([self.kappa]), np.array([[float(s)]]))[0, 0]

    @property
    def end(self) -> np.ndarray:
        return self.state_at(self.length)


@dataclass(frozen=True)
class ArmSpec:
    """The arm: ``n_sections`` sections of at most ``max_length`` (m) each, outer
    ``radius`` (m), moving at ``height`` (m) above the table, base state ``(x, y, heading)``."""

    n_sections: int
    max_length: float
    radius: float
    height: float
    base: tuple[float, float, float]
    max_kappa: float = 12.0

    def model(self, n_points: int = 48) -> ConstantCurvature:
        return ConstantCurvature.make(
            length=[self.max_length] * self.n_sections,
            radius=[self.radius] * self.n_sections,
            joints=("kappa", "length"),
            n_points=n_points,
        )


def base_transform(spec: ArmSpec) -> np.ndarray:
    """World <- robot-base transform (robot z = heading, robot y = world up)."""
    x, y, th = spec.base
    z_r = np.array([np.cos(th), np.sin(th), 0.0])
    x_r = np.array([-np.sin(th), np.cos(th), 0.0])
    y_r = np.array([0.0, 0.0, 1.0])
    T = np.eye(4)
    T[:3, :3] = np.stack([x_r, y_r, z_r], axis=1)
    T[:3, 3] = (x, y, spec.height)
    return T


class ArmLimit(Exception):
    """The path needs more sections than the arm has (paper: "arm reaches its limit")."""


def conform_sections(
    arcs: list[Arc], travelled: list[float], spec: ArmSpec, min_length: float = 1e-4
) -> tuple[np.ndarray, np.ndarray]:
    """Constrained IK: section (kappa, length) arrays (n_sections,) so that the arm lies on the
    planned arcs, the tip at arclength ``travelled[k]`` along arc ``k``.

    Sections are filled in order; an arc longer than ``max_length`` spans several sections.
    Unused distal sections get ``min_length`` (a straight stub). Raises :class:`ArmLimit`
    when more than ``n_sections`` are needed or a curvature exceeds ``max_kappa``.
    """
    kap, lens = [], []
    for arc, s in zip(arcs, travelled, strict=True):
        if abs(arc.kappa) > spec.max_kappa + 1e-9:
            raise ArmLimit(f"curvature {arc.kappa:.2f} 1/m exceeds {spec.max_kappa}")
        rest = float(s)
        while rest > 1e-9:
            piece = min(rest, spec.max_length)
            kap.append(arc.kappa)
            lens.append(piece)
            rest -= piece
    if len(kap) > spec.n_sections:
        raise ArmLimit(f"path needs {len(kap)} sections, the arm has {spec.n_sections}")
    while len(kap) < spec.n_sections:
        kap.append(0.0)
        lens.append(min_length)
    return np.asarray(kap), np.asarray(lens)


def joint_vector(kappa: np.ndarray, length: np.ndarray) -> np.ndarray:
    """q for ``ArmSpec.model()`` (joints ``("kappa", "length")`` per section)."""
    return np.stack([kappa, length], axis=1).reshape(-1)


def camera_from_tip(pan: float, tilt: float) -> np.ndarray:
    """Tip <- camera transform (OpenCV camera: z forward, x right, y down). The tip frame has
    z forward, x left, y up; the camera turns by ``pan`` (rad, positive = left) about the
    tip's up axis and by ``tilt`` (rad, positive = down) about its own x axis."""
    cp, sp = np.cos(pan), np.sin(pan)
    ry = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
    rz_pi = np.diag([-1.0, -1.0, 1.0])
    ct, st = np.cos(-tilt), np.sin(-tilt)
    rx = np.array([[1.0, 0.0, 0.0], [0.0, ct, -st], [0.0, st, ct]])
    R = ry @ rz_pi @ rx
    T = np.eye(4)
    T[:3, :3] = R
    return T


@eqx.filter_jit
def _centreline(model: ConstantCurvature, q):
    return model.forward(q).centreline


def tip_camera_pose(
    spec: ArmSpec,
    kappa: np.ndarray,
    length: np.ndarray,
    pan: float,
    tilt: float,
    mount: np.ndarray | None = None,
    model: ConstantCurvature | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """World <- camera pose (4x4) and the world-frame centreline (N, 3) of the arm for section
    curvatures/lengths, via :class:`ConstantCurvature` forward kinematics. ``mount`` is an
    extra tip <- camera-mount transform (a calibration error in the simulator)."""
    model = spec.model() if model is None else model
    c = _centreline(model, jnp.asarray(joint_vector(kappa, length), jnp.float32))
    T_base_tip = np.eye(4)
    T_base_tip[:3, :3] = np.asarray(c.R[-1], np.float64)
    T_base_tip[:3, 3] = np.asarray(c.p[-1], np.float64)
    T_wb = base_transform(spec)
    T_tip_cam = camera_from_tip(pan, tilt)
    if mount is not None:
        T_tip_cam = mount @ T_tip_cam
    centre = np.asarray(c.p, np.float64) @ T_wb[:3, :3].T + T_wb[:3, 3]
    return T_wb @ T_base_tip @ T_tip_cam, centre


def look_at_angles(T_world_tip: np.ndarray, target: np.ndarray) -> tuple[float, float]:
    """Pan and tilt (rad) that point the tip camera's optical axis at ``target`` (world)."""
    v = np.linalg.inv(T_world_tip)[:3, :3] @ (target - T_world_tip[:3, 3])
    pan = float(np.arctan2(v[0], v[2]))  # tip x is left
    tilt = float(np.arctan2(-v[1], np.hypot(v[0], v[2])))  # tip y is up
    return pan, tilt
