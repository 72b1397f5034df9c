"""Robot descriptions (robot.json / the ``robot`` entry of dataset.json) to model objects.

``robot_from_dict`` dispatches on ``kind`` (reading and writing robot.json files is
:mod:`jaxcr.io.robot`); every model class provides ``from_dict(d, file)`` and
``to_dict()``; the schemas are in docs/dataset-format.md. All validation problems raise
:class:`jaxcr.errors.InputError` naming the file and field.
"""

from __future__ import annotations

import inspect
import os
from collections.abc import Mapping
from typing import Any

from jaxcr.errors import InputError
from jaxcr.kinematics.base import RobotModel, require_mapping

KINDS = ("constant_curvature", "single_segment", "ctr")


def _model_class(kind: str):
    # Imported lazily: the CTR module is large and owned separately.
    if kind == "constant_curvature":
        from jaxcr.kinematics.constant_curvature import ConstantCurvature

        return ConstantCurvature
    if kind == "single_segment":
        from jaxcr.kinematics.single_segment import SingleSegment

        return SingleSegment
    if kind == "ctr":
        from jaxcr.kinematics.ctr import ConcentricTubeRobot

        return ConcentricTubeRobot
    raise KeyError(kind)


def robot_from_dict(d: Mapping[str, Any], *, file: str | os.PathLike | None = None) -> RobotModel:
    """Model described by ``d`` (``kind`` in :data:`KINDS`).

    The description format (per kind: geometry in metres, stiffnesses, joint layout,
    ``n_points``) is docs/dataset-format.md; bad descriptions raise :class:`InputError`
    naming the field.

    Parameters
    ----------
    d : Mapping[str, Any]
        the description, e.g. :data:`jaxcr.TEST_CTR` or the ``robot`` entry of a dataset.
    file : str, os.PathLike or None
        the file ``d`` came from, named in error messages.

    Returns
    -------
    RobotModel
        an ``eqx.Module`` with ``forward(q) -> FkResult`` for one joint vector
        ``q`` (n_joints,); jit and vmap it.

    Examples
    --------
    >>> import jax.numpy as jnp
    >>> import jaxcr as jcr
    >>> robot = jcr.robot_from_dict({"kind": "single_segment", "length": 0.04, "radius": 0.002})
    >>> fk = robot.forward(jnp.zeros(robot.n_joints))
    >>> fk.centreline.p.shape == (robot.n_points, 3), bool(fk.ok)
    (True, True)
    >>> jcr.robot_from_dict(jcr.TEST_CTR).kind
    'ctr'
    """
    file = None if file is None else str(file)
    d = require_mapping(d, file=file, field="robot")
    if "kind" not in d:
        raise InputError(f"missing required key (one of {list(KINDS)})", file=file, field="kind")
    kind = d["kind"]
    if not isinstance(kind, str) or kind not in KINDS:
        raise InputError(
            f"unknown robot kind {kind!r}; expected one of {list(KINDS)}", file=file, field="kind"
        )
    cls = _model_class(kind)
    if "file" in inspect.signature(cls.from_dict).parameters:
        return cls.from_dict(d, file=file)
    return cls.from_dict(d)


def robot_to_dict(model: RobotModel) -> dict[str, Any]:
    """JSON-ready description of ``model`` (``robot_from_dict(robot_to_dict(m))`` rebuilds it)."""
    d = model.to_dict()
    d.setdefault("kind", model.kind)
    return d
