"""Model error between the rendered ("true") robot and camera and the nominal ones written to
``dataset.json``, so that projecting the nominal model misses the robot as in the papers
(Watson et al. Sec. III-B: unmodelled phenomena, parameter uncertainty in stiffness and
precurvature, small calibration errors in camera pose and joint offsets).

Error sources (all scaled by one factor ``scale``):

* precurvature ``kappa_i`` and Young's modulus ``E_i`` of each tube: relative errors
  (concentric-tube robots only);
* joint offsets: translations ``beta_i`` (metres) and rotations ``alpha_i`` (radians) for CTRs,
  or every joint of other kinds (relative to the joint range);
* an unmodelled tip force ``F`` (newtons, robot frame), applied as a *linearised* curvature
  perturbation of the unloaded true shape

      du(s) = R(s)^T ((p(L) - p(s)) x F) / EI(s),

  with EI(s) the summed bending stiffness of the tubes present at s. It is the first-order
  (small-deflection) change of a Cosserat rod's curvature under a tip force, ignoring the
  torsional coupling between tubes and the change of the moment arm as the rod deflects;
  the perturbed curvature is re-integrated exactly with
  :func:`jaxcr.kinematics.cosserat.perturb_centreline`;
* the camera pose: a rotation (radians, random axis) and translation (metres) composed with
  the nominal robot->camera transform.

Magnitudes are drawn as ``sign * U(0.5, 1) * sigma * scale`` so that every source is really
present (never accidentally near zero) at a given scale.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxcr.kinematics.cosserat import Centreline, perturb_centreline


@dataclass(frozen=True)
class ModelErrorSpec:
    """Magnitudes of each error source at ``scale = 1`` (SI units)."""

    kappa_rel: float = 0.10
    stiffness_rel: float = 0.10
    beta_offset: float = 2.5e-3
    alpha_offset: float = np.deg2rad(6.0)
    joint_rel: float = 0.03
    tip_force: float = 0.05
    camera_rotation: float = np.deg2rad(0.3)
    camera_translation: float = 1.0e-3
    scale: float = 1.0

    def scaled(self, scale: float) -> ModelErrorSpec:
        return replace(self, scale=float(scale))


@dataclass
class ModelError:
    """One drawn realisation (what was actually applied; stored in ``meta``)."""

    kappa_factor: list[float] = field(default_factory=list)
    stiffness_factor: list[float] = field(default_factory=list)
    joint_offset: list[float] = field(default_factory=list)
    tip_force: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    camera_rotvec: dict[str, list[float]] = field(default_factory=dict)
    camera_translation: dict[str, list[float]] = field(default_factory=dict)
    scale: float = 1.0

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def _magnitude(rng: np.random.Generator, sigma: float, size=None) -> np.ndarray:
    sign = rng.choice([-1.0, 1.0], size=size)
    return sign * rng.uniform(0.5, 1.0, size=size) * sigma


def _unit(rng: np.random.Generator) -> np.ndarray:
    v = rng.standard_normal(3)
    return v / np.linalg.norm(v)


def draw_model_error(
    rng: np.random.Generator,
    spec: ModelErrorSpec,
    robot: dict[str, Any],
    n_joints: int,
    camera_names: list[str],
    joint_range: np.ndarray | None = None,
) -> ModelError:
    """Draw one model error for ``robot`` (a robot description dict) and the named cameras."""
    s = spec.scale
    err = ModelError(scale=s)
    if robot["kind"] == "ctr":
        n = len(robot["tubes"])
        err.kappa_factor = list(1.0 + _magnitude(rng, spec.kappa_rel * s, n))
        err.stiffness_factor = list(1.0 + _magnitude(rng, spec.stiffness_rel * s, n))
        err.joint_offset = list(
            np.concatenate(
                [
                    _magnitude(rng, spec.beta_offset * s, n),
                    _magnitude(rng, spec.alpha_offset * s, n),
                ]
            )
        )
    else:
        rng_ = np.ones(n_joints) if joint_range is None else np.asarray(joint_range, float)
        err.joint_offset = list(_magnitude(rng, spec.joint_rel * s, n_joints) * rng_)
    err.tip_force = list(_unit(rng) * spec.tip_force * s * rng.uniform(0.5, 1.0))
    for name in camera_names:
        err.camera_rotvec[name] = list(_unit(rng) * _magnitude(rng, spec.camera_rotation * s))
        err.camera_translation[name] = list(
            _unit(rng) * abs(_magnitude(rng, spec.camera_translation * s))
        )
    return err


def perturbed_robot(robot: dict[str, Any], err: ModelError) -> dict[str, Any]:
    """The true robot description: nominal precurvatures and moduli times the drawn factors
    (CTRs; other kinds are returned unchanged)."""
    out = dict(robot)
    if robot["kind"] == "ctr" and err.kappa_factor:
        tubes = []
        for tube, fk, fe in zip(
            robot["tubes"], err.kappa_factor, err.stiffness_factor, strict=True
        ):
            t = dict(tube)
            t["kappa"] = float(tube["kappa"]) * fk
            t["E"] = float(tube["E"]) * fe
            if "G" in t:
                t["G"] = float(tube["G"]) * fe
            tubes.append(t)
        out["tubes"] = tubes
    return out


def _rotvec_to_matrix(w: np.ndarray) -> np.ndarray:
    th = float(np.linalg.norm(w))
    if th < 1e-15:
        return np.eye(3)
    k = w / th
    Kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(th) * Kx + (1 - np.cos(th)) * Kx @ Kx


def perturbed_camera_pose(T_cam_robot: np.ndarray, err: ModelError, name: str) -> np.ndarray:
    """True robot->camera transform: the nominal one followed by the drawn camera-frame error
    ``T_true = [R_e, t_e] T_nominal``."""
    E = np.eye(4)
    E[:3, :3] = _rotvec_to_matrix(np.asarray(err.camera_rotvec.get(name, [0, 0, 0]), float))
    E[:3, 3] = np.asarray(err.camera_translation.get(name, [0, 0, 0]), float)
    return E @ np.asarray(T_cam_robot, float)


def bending_stiffness_along(robot: dict[str, Any], q: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Summed bending stiffness EI (N m^2) of the robot at arclengths ``s`` (pass step
    midpoints so that tube ends fall between evaluation points).

    CTR: tubes ``i`` with ``s < beta_i + L_i`` contribute ``E_i pi (od^4 - id^4) / 64``. Other
    kinds: their ``bending_stiffness`` per section if given, else a solid NiTi rod
    (E = 60 GPa) of the section radius.
    """
    s = np.asarray(s, float)
    if robot["kind"] == "ctr":
        ei = np.zeros_like(s)
        for i, tube in enumerate(robot["tubes"]):
            I = np.pi * (tube["od"] ** 4 - tube["id"] ** 4) / 64.0
            end = float(q[i]) + float(tube["length"])
            ei += np.where(s < end, float(tube["E"]) * I, 0.0)
        return np.maximum(ei, 1e-12)
    if robot["kind"] == "constant_curvature":
        secs = robot["sections"]
        edges = np.cumsum([float(sec["length"]) for sec in secs])
        idx = np.minimum(np.searchsorted(edges, s - 1e-12), len(secs) - 1)
        ei = np.array(
            [
                float(sec.get("bending_stiffness", 0.0))
                or 60e9 * np.pi * float(sec["radius"]) ** 4 / 4
                for sec in secs
            ]
        )
        return ei[idx]
    r = float(robot.get("radius", 1e-3))
    return np.full_like(s, 60e9 * np.pi * r**4 / 4)


def tip_force_curvature(
    p: np.ndarray, R: np.ndarray, force: np.ndarray, ei_steps: np.ndarray
) -> np.ndarray:
    """Linearised tip-load curvature change (module docstring) per integration step k
    (samples k..k+1): du_k = R_k^T m_k / EI_k with m_k the moment (p(L) - p(s)) x F at the
    step's midpoint (robot frame) and ``ei_steps`` (N-1,) the stiffness on the step.

    Shapes: ``p`` (N, 3), ``R`` (N, 3, 3), ``force`` (3,) newtons; returns (N-1, 3) in 1/m."""
    p = np.asarray(p, float)
    moment = np.cross(p[-1][None, :] - p, np.asarray(force, float)[None, :])
    m_mid = 0.5 * (moment[:-1] + moment[1:])
    return (
        np.einsum("nji,nj->ni", np.asarray(R, float)[:-1], m_mid)
        / np.asarray(ei_steps, float)[:, None]
    )


_perturb_batch = jax.jit(jax.vmap(perturb_centreline))


def apply_tip_force(
    centrelines: Centreline, forces: np.ndarray, ei_steps: np.ndarray
) -> Centreline:
    """Apply :func:`tip_force_curvature` to a batch of centrelines (leading axis F; ``forces``
    (F, 3), ``ei_steps`` (F, N-1)) and re-integrate each with
    :func:`jaxcr.kinematics.cosserat.perturb_centreline` (one compiled call)."""
    p = np.asarray(centrelines.p, float)
    R = np.asarray(centrelines.R, float)
    du = np.stack([tip_force_curvature(p[k], R[k], forces[k], ei_steps[k]) for k in range(len(p))])
    return _perturb_batch(centrelines, jnp.asarray(du, centrelines.p.dtype))
