"""Scene presets reproducing the evaluation of Watson et al. (kinematic prior), Sec. III-A:
a 3-tube CTR above animal tissue, seen from an "orthogonal" viewpoint (camera orthogonal to
the insertion axis) and an "endoscopic" one (camera nearly parallel to it, behind the
actuation unit, which hides the base), each with and without a laparoscopic instrument
occluding the robot; 20 frames each at 640x480 along a tip trajectory spanning the workspace.

Robot frame: the tubes leave the actuation unit at the origin along +z; the tissue lies on
the +x side ("below" the robot).
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from jaxcr.synth.model_error import ModelErrorSpec


#: The scene robot: the tubes of jaxcr's public TEST_CTR (diameters, moduli, precurvatures)
#: with lengths cut so that 8-16 cm are exposed in front of the actuation unit (the tip then
#: sweeps a ~10 cm wide workspace, fitting a 640x480 view at 20 cm).
def _scene_ctr() -> dict[str, Any]:
    from jaxcr.kinematics.ctr import TEST_CTR

    robot = copy.deepcopy(TEST_CTR)
    for tube, length in zip(robot["tubes"], (0.30, 0.22, 0.12), strict=True):
        tube["length"] = length
        tube["curved_length"] = min(tube["curved_length"], 0.75 * length)
    robot["n_points"] = 97
    return robot


SCENE_CTR: dict[str, Any] = _scene_ctr()


@dataclass(frozen=True)
class ViewSpec:
    """A camera (robot frame, metres): ``eye``, ``target``, ``up``; focal length in pixels at
    640x480 (scaled with the image size); OpenCV distortion; stereo ``baseline`` (metres,
    along the image x axis) used when a rig of several cameras is requested."""

    eye: tuple[float, float, float]
    target: tuple[float, float, float]
    up: tuple[float, float, float]
    fx: float
    dist: tuple[float, float, float, float, float] = (-0.04, 0.06, 4e-4, -3e-4, 0.0)
    baseline: float = 0.05


@dataclass(frozen=True)
class TissueSpec:
    """The tissue plane through ``origin`` with normal ``normal`` (towards the robot)."""

    origin: tuple[float, float, float]
    normal: tuple[float, float, float]


@dataclass(frozen=True)
class PresetConfig:
    """Everything that defines one synthetic dataset (one preset)."""

    name: str
    view: str  # "orthogonal" | "endoscopic"
    occluded: bool
    camera: ViewSpec
    tissue: TissueSpec
    robot: dict[str, Any] = field(default_factory=lambda: copy.deepcopy(SCENE_CTR))
    frames: int = 20
    size: tuple[int, int] = (640, 480)
    n_cameras: int = 1
    model_error: ModelErrorSpec = field(default_factory=ModelErrorSpec)
    # Trajectory: exposed lengths (m) l_n (outermost) range and the increments to the inner
    # tubes; rotation amplitudes (rad).
    exposed_outer: tuple[float, float] = (0.03, 0.06)
    exposed_step: tuple[float, float] = (0.02, 0.05)
    alpha_amplitude: float = 1.4
    instrument_depth: float = 0.018  # instrument axis this far in front of the robot (m)
    instrument_span: tuple[float, float] = (0.35, 0.75)  # crossing, fraction of samples
    preset_index: int = 0

    @property
    def tags(self) -> list[str]:
        return [self.view] + (["occluded"] if self.occluded else [])


_ORTHO_VIEW = ViewSpec(
    eye=(-0.21, -0.042, 0.055),
    target=(0.0, -0.042, 0.055),
    up=(0.0, -1.0, 0.0),
    fx=700.0,
    baseline=0.06,
)
_ORTHO_TISSUE = TissueSpec(origin=(0.075, -0.04, 0.06), normal=(-1.0, 0.0, 0.0))
_ENDO_VIEW = ViewSpec(
    eye=(-0.075, 0.006, -0.06),
    target=(0.01, 0.0, 0.10),
    up=(-1.0, 0.0, 0.0),
    fx=500.0,
    dist=(-0.12, 0.08, 3e-4, -2e-4, -0.01),
    baseline=0.006,
)
_ENDO_TISSUE = TissueSpec(origin=(0.085, 0.0, 0.20), normal=(-1.0, 0.0, -0.7))

PRESETS: dict[str, PresetConfig] = {
    "orthogonal": PresetConfig(
        "orthogonal", "orthogonal", False, _ORTHO_VIEW, _ORTHO_TISSUE, preset_index=0
    ),
    "orthogonal_occluded": PresetConfig(
        "orthogonal_occluded", "orthogonal", True, _ORTHO_VIEW, _ORTHO_TISSUE, preset_index=1
    ),
    "endoscopic": PresetConfig(
        "endoscopic", "endoscopic", False, _ENDO_VIEW, _ENDO_TISSUE, preset_index=2
    ),
    "endoscopic_occluded": PresetConfig(
        "endoscopic_occluded",
        "endoscopic",
        True,
        _ENDO_VIEW,
        _ENDO_TISSUE,
        preset_index=3,
        instrument_span=(0.6, 0.9),
    ),
}


def ctr_trajectory(cfg: PresetConfig, rng: np.random.Generator, frames: int) -> np.ndarray:
    """Nominal joint values (frames, 2n) of a CTR along a closed smooth tip trajectory.

    Exposed lengths follow random-phase sinusoids inside the configured ranges (keeping the
    telescoping order with a margin for the joint-offset error), rotations sweep
    ``+-alpha_amplitude`` with different frequencies per tube, so the tip visits the
    workspace instead of a single arc.
    """
    tubes = cfg.robot["tubes"]
    n = len(tubes)
    ph = 2.0 * np.pi * np.arange(frames) / max(frames, 1)
    phases = rng.uniform(0, 2 * np.pi, size=(2 * n,))
    lo, hi = cfg.exposed_outer
    exposed = np.zeros((frames, n))
    exposed[:, n - 1] = 0.5 * (lo + hi) + 0.5 * (hi - lo) * np.sin(ph + phases[0])
    slo, shi = cfg.exposed_step
    for k, i in enumerate(range(n - 2, -1, -1)):
        freq = 1 + (k % 2)
        exposed[:, i] = (
            exposed[:, i + 1]
            + 0.5 * (slo + shi)
            + 0.5 * (shi - slo) * np.sin(freq * ph + phases[1 + k])
        )
    beta = exposed - np.array([t["length"] for t in tubes])[None, :]
    alpha = np.zeros((frames, n))
    for i in range(n):
        freq = 1 + (i % 2)
        amp = cfg.alpha_amplitude * (1.0 if i == 0 else 0.7)
        alpha[:, i] = amp * np.sin(freq * ph + phases[n + i])
    return np.concatenate([beta, alpha], axis=1)


def generic_trajectory(
    robot: dict[str, Any], rng: np.random.Generator, frames: int
) -> tuple[np.ndarray, np.ndarray]:
    """Nominal joint values (frames, m) and per-joint ranges (m,) for the other robot kinds,
    on random-phase sinusoids:

    * ``constant_curvature``: per section and declared joint, ``kappa`` in +-(1.2 rad /
      length), ``phi`` sweeping +-pi/2 about a random plane, ``length`` in 85-100 % of the
      section length;
    * ``single_segment``: ``theta_L`` in pi/2 - [0.2, 1.4] rad (bending angle), ``delta``
      sweeping +-pi/2 (Reiter et al. eq. 1).
    """
    ph = 2.0 * np.pi * np.arange(frames) / max(frames, 1)
    cols, ranges = [], []
    if robot["kind"] == "constant_curvature":
        joints = robot.get("joints", ["kappa", "phi", "length"])
        for sec in robot["sections"]:
            L = float(sec["length"])
            for j in joints:
                p0, freq = rng.uniform(0, 2 * np.pi), rng.integers(1, 3)
                if j == "kappa":
                    amp = 1.2 / L
                    cols.append(amp * np.sin(freq * ph + p0))
                elif j == "phi":
                    amp = np.pi / 2
                    cols.append(rng.uniform(-np.pi, np.pi) + amp * np.sin(freq * ph + p0))
                else:
                    amp = 0.075 * L
                    cols.append(0.925 * L + amp * np.sin(freq * ph + p0))
                ranges.append(amp)
    elif robot["kind"] == "single_segment":
        p0, p1 = rng.uniform(0, 2 * np.pi, 2)
        cols.append(np.pi / 2 - (0.8 + 0.6 * np.sin(ph + p0)))
        cols.append(rng.uniform(-np.pi, np.pi) + np.pi / 2 * np.sin(2 * ph + p1))
        ranges += [0.6, np.pi / 2]
    else:
        raise ValueError(f"no trajectory for robot kind {robot['kind']!r}")
    return np.stack(cols, axis=1), np.asarray(ranges)
