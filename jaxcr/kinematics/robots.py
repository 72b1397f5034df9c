"""Robot descriptions (robot.json / the ``robot`` entry of dataset.json) to model objects.

``robot_from_dict`` dispatches on ``kind``; every model class provides ``from_dict(d, file)`` and
``to_dict()``; the schemas are in docs/dataset-format.md. All validation problems raise
:class:`jaxcr.errors.InputError` naming the file and field.
"""

from __future__ import annotations

import inspect
import json
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
    """Model described by ``d`` (``kind`` in :data:`KINDS`)."""
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


def _read_json(path: str) -> Any:
    from jaxcr.io.jsonfile import read_json

    return read_json(path)


def load_robot(path: str | os.PathLike) -> RobotModel:
    """Load a robot from a robot.json, a dataset.json, or a dataset folder.

    A dataset's ``robot`` entry is either the description itself or a path (relative to the
    dataset folder) of a robot.json.
    """
    path = os.fspath(path)
    if os.path.isdir(path):
        path = os.path.join(path, "dataset.json")
        if not os.path.exists(path):
            from jaxcr.io.dataset import other_format_hint

            folder = os.path.dirname(path)
            raise InputError(f"folder has no dataset.json{other_format_hint(folder)}", file=folder)
    d = _read_json(path)
    d = require_mapping(d, file=path, field=None)
    if "kind" not in d and "robot" in d:  # a dataset.json
        robot = d["robot"]
        if isinstance(robot, str):
            return load_robot(os.path.join(os.path.dirname(path), robot))
        return robot_from_dict(robot, file=path)
    return robot_from_dict(d, file=path)


def save_robot(model: RobotModel, path: str | os.PathLike) -> None:
    """Write ``model`` as a robot.json (atomically: temp file, then rename)."""
    path = os.fspath(path)
    tmp = f"{path}.tmp{os.getpid()}"
    with open(tmp, "w", encoding="utf-8") as fh:
        json.dump(robot_to_dict(model), fh, indent=2)
        fh.write("\n")
    os.replace(tmp, path)
