"""jaxcr: a JAX batch estimation engine for the vision of continuum robots.

The public API, flat (``import jaxcr as jcr``); the concept modules behind it are listed in
docs/ARCHITECTURE.md. Names are imported on first use, so ``import jaxcr`` itself is cheap
(no JAX, no OpenCV).

Robots and kinematics
    :func:`robot_from_dict` (a robot description, e.g. :data:`TEST_CTR`, to a model with
    ``model.forward(q)`` for one joint vector: jit/vmap it), :func:`load_robot`,
    :func:`forward` (many joint vectors (B, n_joints) in one compile, with failure reasons:
    :class:`BatchFk`).
Cameras and images
    :class:`Camera` (K (3, 3), dist (5,), T_cam_robot (4, 4), width, height),
    :func:`project_points` (robot-frame points (n, 3) -> pixels (n, 2), valid (n,)),
    :func:`colour_mask` ((h, w, 3) image in [0, 1] -> background mask (h, w), image).
Kinematic-prior segmentation (Watson et al.)
    :func:`refine` (one frame), :func:`refine_batch` (F frames), :class:`RefineConfig`,
    :class:`RefineResult` (its ``energy``: :class:`RefineEnergy`).
Data and runtime
    :func:`load_dataset` (a jaxcr dataset folder), :func:`enable_compile_cache`.
The other papers, one subpackage each
    :mod:`jaxcr.stereo` (``jcr.stereo.reconstruct``), :mod:`jaxcr.eigen`
    (``jcr.eigen.train`` / ``jcr.eigen.query``), :mod:`jaxcr.motion` (``jcr.motion.segment``),
    :mod:`jaxcr.registration` (``jcr.registration.register_pair``), :mod:`jaxcr.synth`.

Example::

    import jax, jax.numpy as jnp
    import jaxcr as jcr

    robot = jcr.robot_from_dict(jcr.TEST_CTR)
    qs = jnp.array([[-0.1, -0.05, -0.02, 0.0, 0.5, 1.0]])
    fk = jax.jit(jax.vmap(robot.forward))(qs)            # FkResult, leading axis B
    fk = jcr.forward(robot, qs)                          # the same with failure reasons
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

__version__ = "0.1.0"

# public name -> the module defining it (imported on first attribute access, PEP 562)
_NAMES = {
    "robot_from_dict": "jaxcr.kinematics.robots",
    "load_robot": "jaxcr.io.robot",
    "TEST_CTR": "jaxcr.kinematics.ctr",
    "forward": "jaxcr.kinematics.batch",
    "BatchFk": "jaxcr.kinematics.batch",
    "Camera": "jaxcr.camera",
    "project_points": "jaxcr.camera",
    "colour_mask": "jaxcr.segmentation.background",
    "refine": "jaxcr.segmentation.api",
    "refine_batch": "jaxcr.segmentation.api",
    "RefineConfig": "jaxcr.segmentation.refine",
    "RefineResult": "jaxcr.segmentation.refine",
    "RefineEnergy": "jaxcr.segmentation.refine",
    "load_dataset": "jaxcr.io.dataset",
    "enable_compile_cache": "jaxcr.io.compile_cache",
    "InputError": "jaxcr.errors",
}
_SUBPACKAGES = ("eigen", "io", "kinematics", "motion", "registration", "segmentation", "stereo",
                "synth")  # fmt: skip

__all__ = [
    "BatchFk",
    "Camera",
    "InputError",
    "RefineConfig",
    "RefineEnergy",
    "RefineResult",
    "TEST_CTR",
    "colour_mask",
    "enable_compile_cache",
    "forward",
    "load_dataset",
    "load_robot",
    "project_points",
    "refine",
    "refine_batch",
    "robot_from_dict",
    "eigen",
    "io",
    "kinematics",
    "motion",
    "registration",
    "segmentation",
    "stereo",
    "synth",
]


def __getattr__(name: str):
    if name in _NAMES:
        value = getattr(importlib.import_module(_NAMES[name]), name)
    elif name in _SUBPACKAGES:
        value = importlib.import_module(f"jaxcr.{name}")
    else:
        raise AttributeError(f"module 'jaxcr' has no attribute {name!r}")
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(__all__))


if TYPE_CHECKING:  # for type checkers and IDEs: the same names, imported eagerly
    from jaxcr import eigen, io, kinematics, motion, registration, segmentation, stereo, synth
    from jaxcr.camera import Camera, project_points
    from jaxcr.errors import InputError
    from jaxcr.io.compile_cache import enable_compile_cache
    from jaxcr.io.dataset import load_dataset
    from jaxcr.io.robot import load_robot
    from jaxcr.kinematics.batch import BatchFk, forward
    from jaxcr.kinematics.ctr import TEST_CTR
    from jaxcr.kinematics.robots import robot_from_dict
    from jaxcr.segmentation.api import refine, refine_batch
    from jaxcr.segmentation.background import colour_mask
    from jaxcr.segmentation.refine import RefineConfig, RefineEnergy, RefineResult
