"""Projection accuracy and speed against OpenCV (the tool a user would otherwise call).

    python experiments/kinematics/camera_projection_bench.py

Prints: max |uv - cv2.projectPoints| in float32 and x64 (5 x 1000 random points, 640x480,
OpenCV 5-parameter distortion), jit compile time, median/p90 of jitted ``project_xy`` and of
its gradient for 1024 points (64 samples x 16 around the tube), and cv2.projectPoints on the
same points, plus ``read_image`` on a 640x480 PNG. Warm-up excluded; block_until_ready used.
"""

from __future__ import annotations

import platform
import subprocess
import tempfile
import time

import cv2
import jax
import jax.numpy as jnp
import numpy as np

from jaxcr.camera import Camera, project_points, project_xy
from jaxcr.io.images import read_image, write_png

DIST = [-0.2, 0.05, 0.001, -0.002, 0.01]


def make_camera():
    return Camera.look_at([0.1, -0.05, -0.3], [0, 0, 0.05], [0, 0, 1], 600.0, (640, 480), dist=DIST)


def cv2_uv(cam, P):
    T = np.asarray(cam.T_cam_robot, np.float64)
    rv, _ = cv2.Rodrigues(T[:3, :3])
    K, d = np.asarray(cam.K, np.float64), np.asarray(cam.dist, np.float64)
    return cv2.projectPoints(P, rv, T[:3, 3], K, d)[0][:, 0]


def timeit(fn, n=200):
    ts = []
    for _ in range(n):
        t = time.perf_counter()
        jax.block_until_ready(fn())
        ts.append(time.perf_counter() - t)
    return np.median(ts) * 1e6, np.percentile(ts, 90) * 1e6


def main():
    commit = subprocess.run(
        ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True
    ).stdout.strip()
    print(
        f"commit {commit}; jax {jax.__version__}; cv2 {cv2.__version__}; {platform.processor() or platform.machine()}"
    )
    errs = []
    for seed in range(5):
        cam = make_camera()
        P = np.random.default_rng(seed).normal(size=(1000, 3)) * 0.03 + [0, 0, 0.05]
        uv, valid = project_points(cam, jnp.asarray(P, jnp.float32))
        v = np.asarray(valid)
        errs.append(np.abs(np.asarray(uv)[v] - cv2_uv(cam, P)[v]).max())
    print(f"float32 max |uv - cv2| = {max(errs):.2e} px")
    with jax.enable_x64(True):
        cam = make_camera()
        P = np.random.default_rng(0).normal(size=(1000, 3)) * 0.03 + [0, 0, 0.05]
        uv, _ = project_points(cam, jnp.asarray(P))
        print(f"x64     max |uv - cv2| = {np.abs(np.asarray(uv) - cv2_uv(cam, P)).max():.2e} px")

    cam = make_camera()
    P = jnp.asarray(
        np.random.default_rng(0).normal(size=(1024, 3)) * 0.03 + [0, 0, 0.05], jnp.float32
    )
    f = jax.jit(project_xy)
    t = time.perf_counter()
    jax.block_until_ready(f(cam, P))
    print(f"project_xy compile {time.perf_counter() - t:.2f} s")
    print("project_xy 1024 pts: median {:.0f} us, p90 {:.0f} us".format(*timeit(lambda: f(cam, P))))
    g = jax.jit(jax.grad(lambda P: sum(x.sum() for x in project_xy(cam, P)[:2])))
    jax.block_until_ready(g(P))
    print(
        "grad(project_xy) 1024 pts: median {:.0f} us, p90 {:.0f} us".format(*timeit(lambda: g(P)))
    )
    Pn = np.asarray(P, np.float64)
    print(
        "cv2.projectPoints 1024 pts: median {:.0f} us, p90 {:.0f} us".format(
            *timeit(lambda: cv2_uv(cam, Pn))
        )
    )
    with tempfile.TemporaryDirectory() as d:
        path = write_png(f"{d}/x.png", np.random.default_rng(0).random((480, 640, 3)))
        print(
            "read_image 640x480 noise PNG: median {:.0f} us, p90 {:.0f} us".format(
                *timeit(lambda: read_image(path), 20)
            )
        )


if __name__ == "__main__":
    main()
