"""Whether a chroma-key mask looks like a real background rather than a key-coloured cloth
(issue 16, audit round 31 case S18: one camera, the chroma key on a real_like frame, exit 0
with the tip 337 / 664 px off and no word).

Two calibrated views check each other (``tip_epipolar_px``); one camera has no such check.
The chroma key is made for a scene whose background is the key colour everywhere but the
robot (and its base); on a real background (creased, shadowed cloth, a board, tape) the key
leaves large non-key areas, and the region grown from the base, which becomes "the robot",
is a large blob rather than a thin tube. Two measures of the key's mask, one frame at a
time (host numpy, outside jit):

- ``robot_fraction``: the robot region (the mask's connected component at the base, after
  the pipeline's 3x3 closing) as a fraction of the frame; a tube is thin: a 10 px wide,
  400 px long tube is 0.4 % of a 1280x720 frame;
- ``border_fraction``: the fraction of the frame's one-pixel border that is not key colour;
  a chroma-key rig fills the view with its cloth.

The mask is *suspect* when ``robot_fraction > ROBOT_FRACTION_MAX`` (2 %) or
``border_fraction > BORDER_FRACTION_MAX`` (15 %). Measured (docs/decisions.md S32,
experiments/results/stereo/key_check_s32.md): the stereo synth's clean chroma scenes (green
and blue keys, 320x240 and 640x480, seeds 0-2 and 4, 42 views) reach at most 0.7 % and
5.7 %; the ``real_like`` preset's 12 views (1280x720, development seeds 4000-4005) have a
non-key border of 23-44 % (every one over 15 %) and a robot region of 0-25 % (10 of 12 over
2 %; a view whose base finds no key-mask pixel fails anyway). 15 % keeps a factor 2.6 above
the clean scenes and 1.5 below the real-like ones.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["BORDER_FRACTION_MAX", "ROBOT_FRACTION_MAX", "KeyMaskCheck", "key_mask_check"]

#: Robot region over this fraction of the frame: a blob, not a tube (module docstring).
ROBOT_FRACTION_MAX = 0.02
#: Non-key pixels over this fraction of the frame's border: not a key-coloured backdrop.
BORDER_FRACTION_MAX = 0.15


@dataclass
class KeyMaskCheck:
    """Result of :func:`key_mask_check`: ``robot_fraction`` and ``border_fraction`` (0-1,
    module docstring) and ``suspect`` (either above its limit)."""

    robot_fraction: float
    border_fraction: float
    suspect: bool


def _border(a: np.ndarray) -> np.ndarray:
    """The one-pixel frame of a 2-D array, each pixel once."""
    return np.concatenate([a[0], a[-1], a[1:-1, 0], a[1:-1, -1]])


def key_mask_check(mask: np.ndarray, robot: np.ndarray) -> KeyMaskCheck:
    """Check one view's chroma-key mask. ``mask``: (H, W) bool, the non-key pixels (after the
    closing); ``robot``: (H, W) bool, its connected component at the base (the robot region
    the pipeline goes on with)."""
    mask = np.asarray(mask, bool)
    robot = np.asarray(robot, bool)
    robot_fraction = float(np.count_nonzero(robot)) / robot.size
    border_fraction = float(np.mean(_border(mask)))
    suspect = robot_fraction > ROBOT_FRACTION_MAX or border_fraction > BORDER_FRACTION_MAX
    return KeyMaskCheck(round(robot_fraction, 4), round(border_fraction, 4), bool(suspect))
