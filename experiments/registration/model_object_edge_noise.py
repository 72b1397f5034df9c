"""Issue 6: where the per-edge systematic registration error comes from (ground truth).

For each (task, scene seed): build the model once (pipeline defaults, Algorithm 2 only),
keep the ring views' true poses, then re-render every ring view at its true pose with the
scene's simulator under two conditions -- the generator's noise model as is ("noise") and
without depth noise (same quantisation, colour noise, holes; "no depth noise") -- and
re-register every ring edge (closure included) with the pipeline's ``register_pair`` under
four variants:

- previous: keypoint term with a fixed 30 % share of the dense weight, photometric term at
  the raw (noisy) source points;
- plane positions: photometric term at the denoised source positions
  (:func:`jaxcr.registration.clouds.plane_points`);
- noise balance: keypoint term weighted by its own noise (``keypoint_balance="noise"``);
- both (the new default).

It also runs ICP alone from the true relative pose without keypoints (the fixed point the
dense terms pull to). Errors: ``log(T_est T_true^-1)`` in the target camera frame, rotation
about y (vertical, deg) and translation x (sideways, mm) -- the coupled pair that carried the
error -- as mean / RMS over the ring edges, and the closure edge's error.

    python experiments/registration/model_object_edge_noise.py [--scenes 2:2 2:3 1:3]

Writes experiments/results/registration/model_object_edge_noise.md.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import time
from pathlib import Path

import jax.numpy as jnp
import numpy as np
from scipy.spatial.transform import Rotation

from jaxcr.registration.icp import IcpConfig, no_keypoints
from jaxcr.registration.pairwise import make_frame, register_pair
from jaxcr.registration.pipeline import PipelineConfig, _capture, build_model
from jaxcr.registration.projective import projective_icp_jit
from jaxcr.synth.rgbd_tasks import RgbdSimulator, generate_task

OUT = Path(__file__).parent.parent / "results" / "registration"

VARIANTS = {
    "previous (fixed 30 % keypoint share, raw photometric positions)": (
        IcpConfig(degeneracy_ratio=0.01, keypoint_weight=0.3),
        False,
    ),
    "plane positions only": (IcpConfig(degeneracy_ratio=0.01, keypoint_weight=0.3), True),
    "noise balance only": (
        IcpConfig(degeneracy_ratio=0.01, keypoint_weight=1.0, keypoint_balance="noise"),
        False,
    ),
    "both (new default)": (
        IcpConfig(degeneracy_ratio=0.01, keypoint_weight=1.0, keypoint_balance="noise"),
        True,
    ),
}


def render(sim, T, depth_noise: bool):
    """The simulator's frame at ``T``; without depth noise: the same model with sigma = 0
    (a copy of the scene's noise settings, the generator is untouched)."""
    if depth_noise:
        return sim.capture(T)
    saved = dict(sim.cfg["depth_noise"])
    try:
        sim.cfg["depth_noise"].update(sigma0=0.0, sigma2=0.0)
        return sim.capture(T)
    finally:
        sim.cfg["depth_noise"].clear()
        sim.cfg["depth_noise"].update(saved)


def err(T, truth):
    E = T @ np.linalg.inv(truth)
    return np.r_[np.rad2deg(Rotation.from_matrix(E[:3, :3]).as_rotvec()), 1000 * E[:3, 3]]


def scene_rows(task, seed, scratch):
    scene = generate_task(f"{scratch}/task{task}_s{seed}", task, seed)
    sim = RgbdSimulator(scene, seed=seed)
    res = build_model(sim, PipelineConfig(global_method="alg2", extra_gaps=()), seed=seed)
    caps = [_capture(res.runs, k) for k in res.ring]
    m = len(caps)
    K = sim.K
    rows = []
    for cond, noisy in (("noise", True), ("no depth noise", False)):
        frames = []
        for k, c in enumerate(caps):
            rgb, dep = render(sim, c.T_true, noisy)
            frames.append(make_frame(rgb, dep, K, 0.004, 1024, seed + k, str(k), sample_size=8192))
        for name, (cfg, plane) in VARIANTS.items():
            E, Ei = [], []
            for j in range(m):
                a, b = frames[j], frames[(j + 1) % m]
                if not plane:
                    a = type(a)(**{**a.__dict__, "sample_plane": None})
                truth = np.linalg.inv(caps[(j + 1) % m].T_true) @ caps[j].T_true
                prior = np.linalg.inv(caps[(j + 1) % m].T_nominal) @ caps[j].T_nominal
                try:
                    r = register_pair(
                        a, b, K, prior=prior, cfg=cfg, photometric="chromaticity", seed=seed + j
                    )
                    E.append(err(r.T, truth))
                except Exception:  # noqa: BLE001 - a failed edge is reported as NaN
                    E.append(np.full(6, np.nan))
                ri = projective_icp_jit(
                    a.sample,
                    b.image,
                    jnp.asarray(truth, jnp.float32),
                    cfg,
                    no_keypoints(),
                    window=0,
                    src_image=a.image,
                    photometric="chromaticity",
                    photo_points=a.sample_plane,
                )
                Ei.append(err(np.asarray(ri.T, np.float64), truth))
            for mode, A in (("register_pair", np.array(E)), ("ICP from truth", np.array(Ei))):
                rows.append((task, seed, cond, name, mode, A))
    return rows


def fmt(rows):
    out = [
        "| task | seed | depth | variant | estimate | edges | mean / RMS rot y (deg) | "
        "mean / RMS t x (mm) | RMS rot (x, z) deg | closure edge rot y (deg) / t x (mm) |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for task, seed, cond, name, mode, A in rows:
        mu, rms = np.nanmean(A, 0), np.sqrt(np.nanmean(A**2, 0))
        out.append(
            f"| {task} | {seed} | {cond} | {name} | {mode} | {len(A)} | "
            f"{mu[1]:+.3f} / {rms[1]:.3f} | {mu[3]:+.2f} / {rms[3]:.2f} | "
            f"{rms[0]:.3f}, {rms[2]:.3f} | {A[-1, 1]:+.2f} / {A[-1, 3]:+.2f} |"
        )
    return out


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--scenes", nargs="+", default=["2:2", "2:3", "1:3"])
    ap.add_argument("--scratch", default="/tmp/model_object_edge_noise")
    args = ap.parse_args()
    commit = subprocess.run(
        ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True
    ).stdout.strip()
    t0 = time.perf_counter()
    rows = []
    for s in args.scenes:
        task, seed = (int(x) for x in s.split(":"))
        rows += scene_rows(task, seed, args.scratch)
    md = [
        "# Issue 6: per-edge systematic registration error vs depth noise",
        "",
        f"commit {commit}; command: `python experiments/registration/model_object_edge_noise.py "
        f"--scenes {' '.join(args.scenes)}`; {time.perf_counter() - t0:.0f} s, load "
        f"{os.getloadavg()[0]:.1f}. Ring views re-rendered at their true poses (a fresh noise "
        "draw of the scene's own simulator; 'no depth noise': sigma = 0, everything else as "
        "generated, including the 0.5 mm depth quantisation, which then is an undithered "
        "staircase). Errors in the target camera frame (x right, y down = the vertical axis "
        "of the scene, z forward). See the module docstring.",
        "",
        *fmt(rows),
        "",
    ]
    (OUT / "model_object_edge_noise.md").write_text("\n".join(md))
    print("\n".join(md))


if __name__ == "__main__":
    main()
