"""What every robot model returns (:class:`FkResult`), the model protocol, and helpers shared by
all models: the piecewise arclength grid and the validation of robot-description dicts.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any, ClassVar, Protocol, runtime_checkable

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from jaxcr._types import Array, Bool, Float, Int
from jaxcr.errors import InputError
from jaxcr.kinematics.cosserat import Centreline


class FkResult(eqx.Module):
    """Forward-kinematics result for one joint vector (see docs/ARCHITECTURE.md).

    Attributes:
        centreline: the sampled backbone in the robot frame (N = ``model.n_points`` samples).
        ok: True when every output is finite (and, for iterative models, converged).
        residual: solver residual; exactly 0 for closed-form models.
        energy: elastic bending energy (J); 0 for models without a declared stiffness.
        num_steps: solver iterations; 0 for closed-form models.
        state: warm-start data for the next solve (``guess``); ``zeros(0)`` for closed forms.
    """

    centreline: Centreline
    ok: Bool[Array, ""]
    residual: Float[Array, ""]
    energy: Float[Array, ""]
    num_steps: Int[Array, ""]
    state: Array


@runtime_checkable
class RobotModel(Protocol):
    """Structural protocol every kinematic model satisfies (``kind`` and ``n_points`` static).

    An interface, not a base class: the built-in models (:class:`ConcentricTubeRobot`,
    :class:`ConstantCurvature`, :class:`SingleSegment`) are ``eqx.Module`` pytrees with these
    members, and so may a user's own model be, without inheriting from jaxcr. The pytree
    requirement (models are passed through ``jit``/``vmap`` as arguments) is a convention this
    protocol cannot express; see docs/ARCHITECTURE.md, "Robot model protocol".

    Attributes
    ----------
    kind : str
        Class-level name of the model kind (``"ctr"``, ``"constant_curvature"``,
        ``"single_segment"``).
    n_points : int
        Samples along the backbone (static).
    n_joints : int
        Length of the joint vector ``q``.
    """

    kind: ClassVar[str]
    n_points: int

    @property
    def n_joints(self) -> int: ...

    def forward(self, q: Float[Array, " m"], guess: Array | None = None) -> FkResult: ...


def closed_form_result(
    centreline: Centreline, energy: Float[Array, ""], valid: Bool[Array, ""] | bool = True
) -> FkResult:
    """Wrap a closed-form centreline: ok = ``valid`` and all outputs finite, residual 0, no
    solver state."""
    finite = (
        jnp.asarray(valid)
        & jnp.all(jnp.isfinite(centreline.p))
        & jnp.all(jnp.isfinite(centreline.R))
        & jnp.all(jnp.isfinite(centreline.s))
        & jnp.isfinite(energy)
    )
    dtype = centreline.p.dtype
    return FkResult(
        centreline=centreline,
        ok=finite,
        residual=jnp.zeros((), dtype),
        energy=energy,
        num_steps=jnp.zeros((), jnp.int32),
        state=jnp.zeros((0,), dtype),
    )


# --------------------------------------------------------------------------------------------
# Arclength grid
# --------------------------------------------------------------------------------------------


def steps_per_piece(n_pieces: int, n_points: int) -> tuple[int, ...]:
    """Split ``n_points - 1`` integration steps over ``n_pieces`` pieces (static integers).

    Every piece gets at least one step; the remainder goes to the first pieces. Because the
    counts do not depend on the (possibly traced) piece lengths, one compile serves every q.
    """
    n_steps = n_points - 1
    if n_pieces < 1:
        raise ValueError("need at least one piece")
    if n_steps < n_pieces:
        raise ValueError(
            f"n_points={n_points} is too few for {n_pieces} pieces (need >= {n_pieces + 1})"
        )
    base, extra = divmod(n_steps, n_pieces)
    return tuple(base + (1 if i < extra else 0) for i in range(n_pieces))


def piece_index(counts: Sequence[int]) -> np.ndarray:
    """Static (sum(counts),) array: which piece each integration step belongs to."""
    return np.repeat(np.arange(len(counts)), counts)


def piecewise_arclength(lengths: Float[Array, " k"], counts: Sequence[int]) -> Float[Array, " n"]:
    """Arclength samples (N = sum(counts) + 1,) covering pieces of the given ``lengths`` (m).

    Piece ``i`` is split uniformly into ``counts[i]`` steps, so every piece boundary
    ``sum(lengths[:i])`` is itself a sample (computed as that sum, not accumulated from steps).
    """
    counts = tuple(int(c) for c in counts)
    if len(counts) != lengths.shape[0]:
        raise ValueError("one step count per piece is needed")
    starts = jnp.concatenate([jnp.zeros(1, lengths.dtype), jnp.cumsum(lengths)[:-1]])
    idx = piece_index(counts)
    # Fraction j / m_i of the piece reached at the end of each step.
    frac = np.concatenate([np.arange(1, c + 1) / c for c in counts])
    s_end = starts[idx] + jnp.asarray(frac, lengths.dtype) * lengths[idx]
    return jnp.concatenate([jnp.zeros(1, lengths.dtype), s_end])


# --------------------------------------------------------------------------------------------
# Robot-description validation (used by every model's ``from_dict``)
# --------------------------------------------------------------------------------------------


def require_mapping(d: Any, *, file: str | None, field: str | None) -> Mapping[str, Any]:
    """``d`` itself, or an :class:`InputError` if it is not a JSON object."""
    if not isinstance(d, Mapping):
        raise InputError(f"expected an object, got {type(d).__name__}", file=file, field=field)
    return d


def get_number(
    d: Mapping[str, Any],
    key: str,
    *,
    file: str | None,
    prefix: str = "",
    default: float | None = None,
    positive: bool = False,
    nonnegative: bool = False,
) -> float:
    """Read the finite real number ``d[key]`` (``default`` if absent and given)."""
    field = f"{prefix}{key}"
    if key not in d:
        if default is not None:
            return float(default)
        raise InputError("missing required key", file=file, field=field)
    v = d[key]
    if isinstance(v, bool) or not isinstance(v, int | float):
        raise InputError(f"expected a number, got {type(v).__name__}", file=file, field=field)
    v = float(v)
    if not math.isfinite(v):
        raise InputError(f"must be finite, got {v}", file=file, field=field)
    if positive and v <= 0.0:
        raise InputError(f"must be > 0, got {v}", file=file, field=field)
    if nonnegative and v < 0.0:
        raise InputError(f"must be >= 0, got {v}", file=file, field=field)
    return v


# Upper bound on centreline samples N read from user input (robot files, --points): far
# beyond any need (0.01 mm spacing on a 10 cm robot), and it keeps a typo such as 100000000
# from allocating tens of GB (measured: `jaxcr fk --points 100000000` asked XLA for 61 GB).
MAX_POINTS = 10_000


def get_int(
    d: Mapping[str, Any],
    key: str,
    *,
    file: str | None,
    prefix: str = "",
    default: int | None = None,
    minimum: int | None = None,
    maximum: int | None = None,
) -> int:
    """Read the integer ``d[key]`` (``default`` if absent and given)."""
    field = f"{prefix}{key}"
    if key not in d:
        if default is not None:
            return int(default)
        raise InputError("missing required key", file=file, field=field)
    v = d[key]
    if isinstance(v, bool) or not isinstance(v, int):
        raise InputError(f"expected an integer, got {v!r}", file=file, field=field)
    if minimum is not None and v < minimum:
        raise InputError(f"must be >= {minimum}, got {v}", file=file, field=field)
    if maximum is not None and v > maximum:
        raise InputError(f"must be <= {maximum}, got {v}", file=file, field=field)
    return int(v)


def check_keys(
    d: Mapping[str, Any], allowed: set[str], *, file: str | None, prefix: str = ""
) -> None:
    """Reject unknown keys (typos such as ``"lenght"`` must not pass silently)."""
    unknown = sorted(set(d) - allowed)
    if unknown:
        raise InputError(
            f"unknown key(s) {unknown}; allowed: {sorted(allowed)}",
            file=file,
            field=f"{prefix}{unknown[0]}",
        )
