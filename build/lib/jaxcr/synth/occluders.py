"""Occluding objects of the synthetic scenes (robot frame, metres).

* :func:`laparoscopic_instrument`: a 5 mm laparoscopic scissors (Watson et al. used Endopath
  monopolar cautery scissors): a grey insulated shaft (capsules, split so each piece gets a
  tight pixel bound) ending in a metal clevis and two opened metal jaws (thin oriented boxes).
* :func:`actuation_unit`: the box housing of the robot's actuation unit behind the base
  (robot at z = 0 leaves its front face along +z), which hides the base in endoscopic views.
"""

from __future__ import annotations

import numpy as np

from jaxcr.synth.scene import JAW_MATERIAL, SHAFT_MATERIAL, UNIT_MATERIAL, Box, Capsule


def _frame_from_axis(axis: np.ndarray, roll: float) -> np.ndarray:
    """Rotation (3, 3) whose third column is ``axis``; ``roll`` spins the other two about it."""
    z = axis / np.linalg.norm(axis)
    helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    c, s = np.cos(roll), np.sin(roll)
    return np.stack([c * x + s * y, -s * x + c * y, z], axis=1)


def laparoscopic_instrument(
    tip: np.ndarray,
    direction: np.ndarray,
    roll: float = 0.0,
    open_angle: float = 0.35,
    shaft_radius: float = 2.5e-3,
    shaft_length: float = 0.30,
    jaw_length: float = 14e-3,
    pieces: int = 12,
) -> list[Capsule | Box]:
    """Surfaces of a laparoscopic scissors whose jaw tips end near ``tip``.

    ``direction`` points from the shaft towards the tip (the instrument's axis); ``roll``
    (rad) turns the jaws about it; ``open_angle`` is the full opening between the jaws (rad).
    """
    axis = np.asarray(direction, float)
    axis = axis / np.linalg.norm(axis)
    F = _frame_from_axis(axis, roll)
    hinge = np.asarray(tip, float) - 0.9 * jaw_length * axis
    clevis_end = hinge - 4e-3 * axis
    start = clevis_end - shaft_length * axis
    parts: list[Capsule | Box] = []
    knots = np.linspace(0.0, 1.0, pieces + 1)
    for k in range(pieces):
        a = start + knots[k] * (clevis_end - start)
        b = start + knots[k + 1] * (clevis_end - start)
        parts.append(Capsule(a, b, shaft_radius, SHAFT_MATERIAL))
    # Metal clevis holding the jaws (slightly thinner than the shaft).
    parts.append(Capsule(clevis_end, hinge, 0.85 * shaft_radius, JAW_MATERIAL))
    for sign in (1.0, -1.0):
        ang = sign * open_angle / 2
        jaw_dir = np.cos(ang) * F[:, 2] + np.sin(ang) * F[:, 0]
        side = np.cos(ang) * F[:, 0] - np.sin(ang) * F[:, 2]
        axes = np.stack([side, F[:, 1], jaw_dir], axis=1)
        centre = hinge + 0.5 * jaw_length * jaw_dir + sign * 0.45e-3 * side
        half = np.array([0.45e-3, 1.1e-3, 0.5 * jaw_length])
        parts.append(Box(centre, axes, half, JAW_MATERIAL))
    return parts


def actuation_unit(half_x: float = 0.02, half_y: float = 0.035, depth: float = 0.10) -> list[Box]:
    """The actuation unit: a box spanning ``z`` in [-depth, 0] around the insertion axis,
    plus a 6 mm front collar the tubes emerge from (both robot frame)."""
    body = Box(
        np.array([0.0, 0.0, -depth / 2 - 6e-3]),
        np.eye(3),
        np.array([half_x, half_y, depth / 2]),
        UNIT_MATERIAL,
    )
    collar = Box(
        np.array([0.0, 0.0, -3e-3]), np.eye(3), np.array([6e-3, 6e-3, 3e-3]), UNIT_MATERIAL
    )
    return [body, collar]
