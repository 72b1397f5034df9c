"""A cheap segment dataset for the scale-out tests and benchmark: a one-section
constant-curvature robot (no CTR solver to compile) rendered by the independent tube renderer
of :mod:`tests.helpers.tube_render`, 160x120, one camera. The rendered robot bends 15 %
more than the nominal joints say (a model error for the refinement to correct)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from tests.helpers.datasets import spoil_joint_values

ROBOT = {
    "kind": "constant_curvature",
    "sections": [{"length": 0.1, "radius": 0.002}],
    "joints": ["kappa", "phi"],
    "n_points": 24,
}
SIZE = (160, 120)
#: a short refinement schedule (one level, few steps, 2 coefficients): the compile is the
#: cost of these tests, the answer's quality is not what they check
FAST_FLAGS = ["--levels", "1", "--max-steps", "6", "--basis", "2", "--no-camera-correction"]


def camera():
    from jaxcr.camera import Camera

    return Camera.look_at([0.0, -0.3, 0.05], [0.0, 0.0, 0.05], [0.0, 0.0, 1.0], 160.0, SIZE)


def make_segment_dataset(root: Path, n_frames: int = 12, seed: int = 0,
                         bad: tuple[int, ...] = ()) -> Path:  # fmt: skip
    """``n_frames`` frames with joints (kappa 2-9 /m, phi in [-pi, pi]); frames listed in
    ``bad`` get a joint value beyond the float32 range (recorded as failed by jaxcr
    segment, by whichever process runs the frame)."""
    import jax
    import jax.numpy as jnp

    from jaxcr.io.dataset import DatasetWriter
    from jaxcr.kinematics.robots import robot_from_dict
    from tests.helpers.tube_render import render_tube

    robot = robot_from_dict(ROBOT)
    rng = np.random.default_rng(seed)
    q = np.stack([rng.uniform(2.0, 9.0, n_frames), rng.uniform(-np.pi, np.pi, n_frames)], 1)
    q_true = q * np.array([1.15, 1.0])
    fk = jax.jit(jax.vmap(robot.forward))(jnp.asarray(q_true, jnp.float32))
    cam = camera()
    with DatasetWriter(root, "scale", ROBOT, {"main": cam}, meta={"seed": seed}) as w:
        for i in range(n_frames):
            cl = jax.tree.map(lambda a, i=i: a[i], fk.centreline)
            img, mask = render_tube(cl, cam, seed * 1000 + i, SIZE)
            w.add_frame(i, q[i].tolist(), {"main": img}, masks={"main": mask},
                        truth={"centreline": np.asarray(cl.p)})  # fmt: skip
    if bad:
        spoil_joint_values(root, bad)
    return Path(root)
