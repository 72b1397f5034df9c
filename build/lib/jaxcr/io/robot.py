"""robot.json files: load a robot model from a robot.json, a dataset.json or a dataset
folder, and write one (atomically). The dict <-> model conversion is
:mod:`jaxcr.kinematics.robots` (no file access there)."""

from __future__ import annotations

import json
import os

from jaxcr.errors import InputError
from jaxcr.io.dataset import other_format_hint
from jaxcr.io.jsonfile import read_json
from jaxcr.kinematics.base import RobotModel, require_mapping
from jaxcr.kinematics.robots import robot_from_dict, robot_to_dict


def load_robot(path: str | os.PathLike) -> RobotModel:
    """Load a robot from a robot.json, a dataset.json, or a dataset folder.

    A dataset's ``robot`` entry is either the description itself or a path (relative to the
    dataset folder) of a robot.json. The description format is docs/dataset-format.md.

    Parameters
    ----------
    path : str or os.PathLike
        a robot.json, a dataset.json or a dataset folder.

    Returns
    -------
    RobotModel
        the model (:func:`jaxcr.robot_from_dict` of the description).

    Examples
    --------
    >>> import json, os, tempfile
    >>> import jaxcr as jcr
    >>> path = os.path.join(tempfile.mkdtemp(), "robot.json")
    >>> with open(path, "w") as fh:
    ...     json.dump({"kind": "single_segment", "length": 0.04, "radius": 0.002}, fh)
    >>> robot = jcr.load_robot(path)
    >>> robot.kind, robot.n_joints
    ('single_segment', 2)
    """
    path = os.fspath(path)
    if os.path.isdir(path):
        path = os.path.join(path, "dataset.json")
        if not os.path.exists(path):
            folder = os.path.dirname(path)
            raise InputError(f"folder has no dataset.json{other_format_hint(folder)}", file=folder)
    d = read_json(path)
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
