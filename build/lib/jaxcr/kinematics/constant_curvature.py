"""Piecewise-constant-curvature (PCC) continuum robot, Webster & Jones (2010) convention.

Each section ``i`` is a circular arc of arclength ``L_i`` (m) and curvature ``kappa_i`` (1/m)
bending in the plane at angle ``phi_i`` (rad) about the local z axis of the previous section's
tip frame. The section transform is (Webster & Jones 2010, eq. 1 / Fig. 5)

    T_i = [Rz(phi) Ry(kappa L) Rz(-phi),  Rz(phi) ((1 - cos kappa L)/kappa, 0, sin(kappa L)/kappa)]

so sections are tangent-continuous and the frame carries no torsion. Equivalently the body
curvature is constant on a section, ``u_i = kappa_i (-sin phi_i, cos phi_i, 0)``, which is what
is integrated here (exactly, by :func:`jaxcr.kinematics.cosserat.integrate_steps`).

``kappa`` is *signed*: ``(kappa, phi)`` and ``(-kappa, phi + pi)`` give the same shape. A
signed curvature keeps the straight configuration (kappa = 0) a smooth interior point, so
gradients with respect to q are finite there.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, ClassVar

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from jaxcr._types import Array, Float
from jaxcr.errors import InputError
from jaxcr.kinematics.base import (
    MAX_POINTS,
    FkResult,
    check_keys,
    closed_form_result,
    get_int,
    get_number,
    piece_index,
    piecewise_arclength,
    require_mapping,
    steps_per_piece,
)
from jaxcr.kinematics.cosserat import integrate_centreline

SECTION_QUANTITIES = ("kappa", "phi", "length")
_SECTION_KEYS = {"length", "radius", "kappa", "phi", "bending_stiffness"}
_TOP_KEYS = {"kind", "sections", "joints", "n_points", "name"}


class ConstantCurvature(eqx.Module):
    """n tangent-continuous constant-curvature sections (see module docstring).

    Attributes:
        length: (n,) section arclengths (m), used where ``"length"`` is not a joint.
        kappa: (n,) signed curvatures (1/m), used where ``"kappa"`` is not a joint.
        phi: (n,) bending-plane angles (rad), used where ``"phi"`` is not a joint.
        radius: (n,) outer radius of each section (m).
        bending_stiffness: (n,) EI (N m^2) for the elastic energy ``sum EI kappa^2 L / 2``;
            zeros (energy 0) when unknown.
        joints: which per-section quantities q holds, in this order for each section;
            q = (section 0 joints, section 1 joints, ...). Static.
        n_points: number of centreline samples N (static); every section boundary is a sample.
    """

    kind: ClassVar[str] = "constant_curvature"

    length: Float[Array, " n"]
    kappa: Float[Array, " n"]
    phi: Float[Array, " n"]
    radius: Float[Array, " n"]
    bending_stiffness: Float[Array, " n"]
    joints: tuple[str, ...] = eqx.field(static=True, default=SECTION_QUANTITIES)
    n_points: int = eqx.field(static=True, default=64)

    def __check_init__(self):
        bad = [j for j in self.joints if j not in SECTION_QUANTITIES]
        if bad or len(set(self.joints)) != len(self.joints):
            raise ValueError(
                f"joints must be distinct names from {SECTION_QUANTITIES}, got {self.joints}"
            )
        steps_per_piece(self.n_sections, self.n_points)  # raises if n_points is too small

    @classmethod
    def make(
        cls,
        length,
        radius,
        kappa=None,
        phi=None,
        bending_stiffness=None,
        joints: tuple[str, ...] = SECTION_QUANTITIES,
        n_points: int = 64,
        dtype=jnp.float32,
    ) -> ConstantCurvature:
        """Build from per-section sequences (missing kappa/phi/EI default to zeros)."""
        length = jnp.asarray(length, dtype).reshape(-1)
        n = length.shape[0]

        def arr(x):
            return (
                jnp.zeros(n, dtype) if x is None else jnp.broadcast_to(jnp.asarray(x, dtype), (n,))
            )

        return cls(
            length=length,
            kappa=arr(kappa),
            phi=arr(phi),
            radius=arr(radius),
            bending_stiffness=arr(bending_stiffness),
            joints=tuple(joints),
            n_points=int(n_points),
        )

    @property
    def n_sections(self) -> int:
        return int(self.length.shape[0])

    @property
    def n_joints(self) -> int:
        return self.n_sections * len(self.joints)

    def section_parameters(
        self, q: Float[Array, " m"]
    ) -> tuple[Float[Array, " n"], Float[Array, " n"], Float[Array, " n"]]:
        """(kappa, phi, length) per section with the joint values of ``q`` substituted."""
        q = jnp.asarray(q)
        if q.shape != (self.n_joints,):
            raise ValueError(f"q must have shape ({self.n_joints},), got {q.shape}")
        dtype = jnp.result_type(q.dtype, self.length.dtype)
        qs = q.astype(dtype).reshape(self.n_sections, len(self.joints))
        values = {"kappa": self.kappa, "phi": self.phi, "length": self.length}
        for j, name in enumerate(self.joints):
            values[name] = qs[:, j]
        return tuple(jnp.asarray(values[k], dtype) for k in SECTION_QUANTITIES)

    def forward(self, q: Float[Array, " m"], guess: Array | None = None) -> FkResult:
        """Centreline for joint vector ``q`` (closed form; ``guess`` is ignored).

        ``ok`` is False when an output is non-finite or a section length is <= 0.
        """
        del guess
        kappa, phi, length = self.section_parameters(q)
        counts = steps_per_piece(self.n_sections, self.n_points)
        idx = piece_index(counts)
        s = piecewise_arclength(length, counts)
        u_sec = kappa[:, None] * jnp.stack(
            [-jnp.sin(phi), jnp.cos(phi), jnp.zeros_like(phi)], axis=1
        )
        u_steps = u_sec[idx]
        radius = self.radius.astype(s.dtype)
        rho = jnp.concatenate([radius[:1], radius[idx]])
        centreline = integrate_centreline(s, u_steps, rho)
        energy = 0.5 * jnp.sum(self.bending_stiffness.astype(s.dtype) * kappa**2 * length)
        # A non-positive section length (possible when length is a joint) is not a robot.
        return closed_form_result(centreline, energy, valid=jnp.all(length > 0))

    # ---------------------------------------------------------------- robot.json

    @classmethod
    def from_dict(cls, d: Mapping[str, Any], file: str | None = None) -> ConstantCurvature:
        """Parse ``{"kind": "constant_curvature", "sections": [...], "joints": [...]}``.

        Schema in docs/dataset-format.md. Raises :class:`InputError` naming the field.
        """
        d = require_mapping(d, file=file, field=None)
        check_keys(d, _TOP_KEYS, file=file)
        if "sections" not in d:
            raise InputError("missing required key", file=file, field="sections")
        sections = d["sections"]
        if not isinstance(sections, list) or not sections:
            raise InputError("expected a non-empty list of sections", file=file, field="sections")
        joints = d.get("joints", list(SECTION_QUANTITIES))
        if not isinstance(joints, list) or not all(isinstance(j, str) for j in joints):
            raise InputError("expected a list of names", file=file, field="joints")
        bad = [j for j in joints if j not in SECTION_QUANTITIES]
        if bad or len(set(joints)) != len(joints):
            raise InputError(
                f"expected distinct names from {list(SECTION_QUANTITIES)}, got {joints}",
                file=file,
                field="joints",
            )
        rows = []
        for i, sec in enumerate(sections):
            prefix = f"sections[{i}]."
            sec = require_mapping(sec, file=file, field=f"sections[{i}]")
            check_keys(sec, _SECTION_KEYS, file=file, prefix=prefix)
            rows.append(
                (
                    get_number(sec, "length", file=file, prefix=prefix, positive=True),
                    get_number(sec, "radius", file=file, prefix=prefix, positive=True),
                    get_number(sec, "kappa", file=file, prefix=prefix, default=0.0),
                    get_number(sec, "phi", file=file, prefix=prefix, default=0.0),
                    get_number(
                        sec,
                        "bending_stiffness",
                        file=file,
                        prefix=prefix,
                        default=0.0,
                        nonnegative=True,
                    ),
                )
            )
        n_points = get_int(
            d, "n_points", file=file, default=64, minimum=len(sections) + 1, maximum=MAX_POINTS
        )
        a = np.asarray(rows, np.float64)
        return cls.make(
            length=a[:, 0],
            radius=a[:, 1],
            kappa=a[:, 2],
            phi=a[:, 3],
            bending_stiffness=a[:, 4],
            joints=tuple(joints),
            n_points=n_points,
        )

    def to_dict(self) -> dict[str, Any]:
        """The robot.json description (inverse of :meth:`from_dict`)."""
        sections = []
        for i in range(self.n_sections):
            sec = {"length": float(self.length[i]), "radius": float(self.radius[i])}
            if "kappa" not in self.joints:
                sec["kappa"] = float(self.kappa[i])
            if "phi" not in self.joints:
                sec["phi"] = float(self.phi[i])
            if float(self.bending_stiffness[i]) != 0.0:
                sec["bending_stiffness"] = float(self.bending_stiffness[i])
            sections.append(sec)
        return {
            "kind": self.kind,
            "sections": sections,
            "joints": list(self.joints),
            "n_points": self.n_points,
        }
