"""The canonical scene of the tests that run ``jaxcr segment`` end to end on a tiny dataset
(tests/cli/test_cli_segment.py, test_cli_segment_plate.py, test_cli_contract.py's Ctrl-C run,
tests/scale/test_ray_fault.py): one camera, 96x72, a one-section constant-curvature robot of
24 samples, and one set of refinement options, :data:`FAST`.

Why shared: each of these runs compiles (or loads) the same programs -- the refinement
(~20-30 s of CPU to compile, one pyramid level), the tip covariance, the FK and background
batches -- and the run-wide persistent compilation cache (tests/conftest.py) serves a program
to every later process and module only when it is the very same program: same image size,
sample count, camera count, batch size and refinement options. Before, the Ctrl-C run and the
Ray fault test each compiled a refinement of their own (other sizes and options). The images
are drawn with ``cv2.polylines`` from the projected centreline (independent of jaxcr's
silhouette code). Change nothing here without re-deriving the thresholds of the modules that
import it.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from tests.helpers.datasets import spoil_joint_values

W, H = 96, 72
ROBOT = {
    "kind": "constant_curvature",
    "sections": [{"length": 0.08, "radius": 0.003}],
    "joints": ["kappa", "phi"],
    "n_points": 24,
}
#: one pyramid level (a program half the size of two levels' to compile), 4 steps, chunks of
#: 2 frames: these runs check the commands' plumbing, not the refinement's accuracy
#: (tests/segmentation/test_refine*.py)
FAST = ["--levels", "1", "--max-steps", "4", "--batch-size", "2"]
#: the joint offset of the drawn robot from the nominal joints: a model error to refine
Q_ERROR = (1.5, 0.05)


def camera():
    from jaxcr.camera import Camera

    return Camera.look_at((-0.15, 0.0, 0.04), (0.0, 0.0, 0.04), (0.0, -1.0, 0.0), 110.0, (W, H))


def draw(camera, p: np.ndarray, radius: float) -> np.ndarray:
    """The tube's mask: centreline ``p`` (N, 3) projected by OpenCV, drawn as a polyline as
    thick as the tube's mean projected diameter."""
    K = np.asarray(camera.K, np.float64)
    T = np.asarray(camera.T_cam_robot, np.float64)
    rvec, _ = cv2.Rodrigues(T[:3, :3])
    uv, _ = cv2.projectPoints(p, rvec, T[:3, 3], K, np.zeros(5))
    depth = (p @ T[:3, :3].T + T[:3, 3])[:, 2]
    thick = max(1, int(round(2 * radius * K[0, 0] / depth.mean())))
    mask = np.zeros((H, W), np.uint8)
    pts = np.round(uv.reshape(-1, 1, 2) * 8).astype(np.int32)  # 3 fractional bits
    cv2.polylines(mask, [pts], False, 255, thick, cv2.LINE_8, shift=3)
    return mask > 0


def render(mask: np.ndarray, rng) -> np.ndarray:
    """A grey tube over a noisy red background (the colour key's default), float32 RGB."""
    img = np.empty((H, W, 3), np.float32)
    img[...] = [0.55, 0.2, 0.2]
    img += 0.05 * rng.standard_normal((H, W, 3)).astype(np.float32)
    img[mask] = [0.7, 0.7, 0.72]
    return np.clip(img, 0, 1)


def make_frames(root: Path, n_frames: int, bad: tuple[int, ...] = (), seed: int = 0) -> Path:
    """``n_frames`` clean frames (kappa in [-6, 6] 1/m, phi in [-0.3, 0.3]) with masks and
    true centrelines; frames listed in ``bad`` get a joint value beyond the float32 range
    (recorded as failed by jaxcr segment, by whichever process runs the frame)."""
    import jax.numpy as jnp

    from jaxcr.io.dataset import DatasetWriter
    from jaxcr.kinematics.robots import robot_from_dict

    rng = np.random.default_rng(seed)
    robot = robot_from_dict(ROBOT)
    cam = camera()
    q = np.stack([rng.uniform(-6.0, 6.0, n_frames), rng.uniform(-0.3, 0.3, n_frames)], 1)
    with DatasetWriter(root, "scene", ROBOT, {"main": cam}, meta={"seed": seed}) as w:
        for k in range(n_frames):
            q_true = q[k] + np.asarray(Q_ERROR)
            p = np.asarray(robot.forward(jnp.asarray(q_true, jnp.float32)).centreline.p)
            mask = draw(cam, p, ROBOT["sections"][0]["radius"])
            w.add_frame(k, q[k].tolist(), {"main": render(mask, rng)}, masks={"main": mask},
                        truth={"centreline": p})  # fmt: skip
    if bad:
        spoil_joint_values(root, bad)
    return Path(root)
