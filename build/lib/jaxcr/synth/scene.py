"""Scene description for the synthetic renderer: cameras, the robot body, occluders, tissue.

Everything here is plain numpy in float64 and in the robot frame (metres) unless stated.
The renderer (:mod:`jaxcr.synth.render`) moves the geometry into each camera frame and ray
casts it; nothing here projects points to draw images.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from jaxcr.synth.texture import TissueTexture


@dataclass(frozen=True)
class RenderCamera:
    """A pinhole camera with OpenCV distortion, used to render (float64 numpy).

    Attributes:
        K: (3, 3) intrinsics in pixels.
        dist: (5,) OpenCV ``(k1, k2, p1, p2, k3)``.
        T_cam_robot: (4, 4) robot frame -> camera frame (OpenCV axes: x right, y down,
            z forward).
        width, height: image size in pixels.
    """

    K: np.ndarray
    dist: np.ndarray
    T_cam_robot: np.ndarray
    width: int
    height: int

    def with_pose(self, T_cam_robot: np.ndarray) -> RenderCamera:
        return RenderCamera(
            self.K, self.dist, np.asarray(T_cam_robot, float), self.width, self.height
        )


def look_at_pose(eye, target, up) -> np.ndarray:
    """(4, 4) robot->camera transform of a camera at ``eye`` looking at ``target`` (robot
    frame, metres) with ``up`` pointing up in the image (image rows run along ``-up``)."""
    eye = np.asarray(eye, float)
    z = np.asarray(target, float) - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, np.asarray(up, float))
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = -R @ eye
    return T


@dataclass(frozen=True)
class Material:
    """Surface appearance. ``kind`` is ``"metal"``, ``"plastic"`` or ``"tissue"``.

    ``colour`` is the RGB base colour in [0, 1]; ``specular`` the highlight strength,
    ``shininess`` the Blinn-Phong exponent, ``reflect`` the strength of mirrored environment
    light (metals pick up the tissue's colour this way).
    """

    kind: str
    colour: tuple[float, float, float]
    specular: float = 0.3
    shininess: float = 40.0
    reflect: float = 0.0


# Three NiTi tubes: light grey with slightly different tints (innermost first).
TUBE_MATERIALS = (
    Material("metal", (0.66, 0.63, 0.62), specular=0.9, shininess=60.0, reflect=0.45),
    Material("metal", (0.60, 0.59, 0.60), specular=0.9, shininess=50.0, reflect=0.45),
    Material("metal", (0.63, 0.60, 0.58), specular=0.8, shininess=45.0, reflect=0.45),
)
SHAFT_MATERIAL = Material("plastic", (0.30, 0.31, 0.33), specular=0.35, shininess=25.0)
JAW_MATERIAL = Material("metal", (0.70, 0.70, 0.72), specular=1.0, shininess=70.0, reflect=0.5)
UNIT_MATERIAL = Material("plastic", (0.78, 0.78, 0.76), specular=0.15, shininess=15.0)


@dataclass(frozen=True)
class Capsule:
    """A capsule (segment ``a``-``b`` swept by a sphere of ``radius``), robot frame."""

    a: np.ndarray
    b: np.ndarray
    radius: float
    material: Material


@dataclass(frozen=True)
class Box:
    """An oriented box: ``axes`` (3, 3) unit axes as columns, ``half`` extents (metres)."""

    centre: np.ndarray
    axes: np.ndarray
    half: np.ndarray
    material: Material


@dataclass(frozen=True)
class TubeBody:
    """The robot surface: the chain of capsules along the centreline ``p`` (N, 3) with radius
    ``radius[k]`` on segment k (N-1,), and which tube is outermost on each segment."""

    p: np.ndarray
    radius: np.ndarray
    tube: np.ndarray

    def capsules(self) -> list[Capsule]:
        return [
            Capsule(
                self.p[k], self.p[k + 1], float(self.radius[k]), TUBE_MATERIALS[self.tube[k] % 3]
            )
            for k in range(len(self.radius))
        ]


@dataclass(frozen=True)
class Tissue:
    """The tissue surface: the plane through ``origin`` spanned by unit axes ``eu``, ``ev``
    (normal ``eu x ev`` faces the robot), textured by ``texture`` centred on ``origin``."""

    origin: np.ndarray
    eu: np.ndarray
    ev: np.ndarray
    texture: TissueTexture

    @property
    def normal(self) -> np.ndarray:
        n = np.cross(self.eu, self.ev)
        return n / np.linalg.norm(n)


@dataclass
class Scene:
    """All objects of one frame. Occluders are any surfaces other than robot and tissue;
    ``static_occluders`` (e.g. the actuation unit) do not move between frames, so the
    renderer can cache them with the tissue per camera, ``occluders`` may move."""

    tissue: Tissue
    robot: TubeBody | None = None
    occluders: list[Capsule | Box] = field(default_factory=list)
    static_occluders: list[Capsule | Box] = field(default_factory=list)
    light_dir: np.ndarray = field(default_factory=lambda: np.array([-0.7, -0.35, 0.25]))
