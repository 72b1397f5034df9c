"""Issue 6: why the registrations of Task 1's first ring view err together (ground truth).

Builds one scene's ring (pipeline, Algorithm 2 only), prints each ring view's distance to
the object and its number of valid depth pixels, then re-renders the views at their TRUE
poses with the scene's simulator and registers the edges of one view (``--views``; to and
from its two neighbours on each side) by projective ICP started at the true relative pose,
without keypoints or colour, over several noise draws of that view (the other views one
fixed draw), with the point-to-plane source positions raw (measured depth) or denoised
(:func:`jaxcr.registration.pairwise.geometric_sample`), and once without depth noise.
Errors ``log(T_est T_true^-1)`` in the target camera frame (x right, y down, z forward).

    python experiments/registration/model_object_view0.py [--task 1] [--seed 3] [--views 0 6] [--draws 6]

Writes experiments/results/registration/model_object_view0.md.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import time
from pathlib import Path

import jax.numpy as jnp
import numpy as np
from model_object_edge_noise import render  # noqa: E402  (the frame with or without depth noise)
from scipy.spatial.transform import Rotation

from jaxcr.registration.icp import DEFAULT_ICP, no_keypoints
from jaxcr.registration.pairwise import geometric_sample, make_frame
from jaxcr.registration.pipeline import PipelineConfig, _capture, build_model
from jaxcr.registration.projective import projective_icp_jit
from jaxcr.synth.rgbd_tasks import RgbdSimulator, generate_task

OUT = Path(__file__).parent.parent / "results" / "registration"


def err(T, truth):
    E = T @ np.linalg.inv(truth)
    return np.r_[1000 * E[:3, 3], np.rad2deg(Rotation.from_matrix(E[:3, :3]).as_rotvec())]


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--task", default="1")
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--views", type=int, nargs="+", default=[0, 6])
    ap.add_argument("--draws", type=int, default=6)
    ap.add_argument("--scratch", default="/tmp/model_object_view0")
    args = ap.parse_args()
    t0 = time.perf_counter()
    scene = generate_task(f"{args.scratch}/t{args.task}_s{args.seed}", args.task, args.seed)
    sim = RgbdSimulator(scene, seed=args.seed)
    res = build_model(sim, PipelineConfig(global_method="alg2", extra_gaps=()), seed=args.seed)
    T = [_capture(res.runs, k).T_true for k in res.ring]
    m = len(T)
    K = sim.K
    sim = RgbdSimulator(scene, seed=args.seed + 777)
    md = [
        "# Issue 6: the first ring view's registrations (Task 1), against the truth",
        "",
        f"commit {subprocess.run(['git', 'rev-parse', '--short', 'HEAD'], capture_output=True, text=True).stdout.strip()}; "
        f"command: `python experiments/registration/model_object_view0.py --task {args.task} --seed {args.seed} "
        f"--views {' '.join(map(str, args.views))} --draws {args.draws}`. See the module docstring.",
        "",
        "| view | distance to the object axis (m) | median depth (m) | valid depth pixels |",
        "|---|---|---|---|",
    ]
    base = {k: render(sim, T[k], True) for k in range(m)}
    for k in range(m):
        d = base[k][1]
        c = T[k][:3, 3]
        md.append(
            f"| {k} | {np.linalg.norm(c[:2]):.3f} | {np.nanmedian(d):.3f} | {np.isfinite(d).sum()} |"
        )
    md += [
        "",
        "| view | edge | depth noise | source points | mean t x, y, z (mm) | sd t x, y, z (mm) "
        "| mean rot x, y, z (deg) |",
        "|---|---|---|---|---|---|---|",
    ]
    for v in args.views:
        E = [(v, (v + 1) % m), (v, (v + 2) % m), ((v - 1) % m, v), ((v - 2) % m, v)]
        for noisy, draws in ((True, args.draws), (False, 1)):
            R = {(p, e): [] for p in ("raw", "plane") for e in E}
            for draw in range(draws):
                sim.rng = np.random.default_rng(1000 + draw)
                imgs = dict(base) if noisy else {k: render(sim, T[k], False) for k in range(m)}
                imgs[v] = render(sim, T[v], noisy)
                need = {i for e in E for i in e}
                F = {
                    k: make_frame(*imgs[k], K, 0.004, 1024, 50 + draw, sample_size=8192)
                    for k in need
                }
                for i, j in E:
                    truth = np.linalg.inv(T[j]) @ T[i]
                    for p in ("raw", "plane"):
                        r = projective_icp_jit(
                            geometric_sample(F[i], p),
                            F[j].image,
                            jnp.asarray(truth, jnp.float32),
                            DEFAULT_ICP,
                            no_keypoints(),
                            window=0,
                        )
                        R[(p, (i, j))].append(err(np.asarray(r.T, np.float64), truth))
            for (p, e), L in R.items():
                L = np.array(L)
                mu, sd = L.mean(0), L.std(0)
                md.append(
                    f"| {v} | {e[0]}->{e[1]} | {'yes' if noisy else 'no'} ({len(L)} draws) | {p} | "
                    f"{mu[0]:+.2f}, {mu[1]:+.2f}, {mu[2]:+.2f} | {sd[0]:.2f}, {sd[1]:.2f}, {sd[2]:.2f} | "
                    f"{mu[3]:+.3f}, {mu[4]:+.3f}, {mu[5]:+.3f} |"
                )
    md += ["", f"{time.perf_counter() - t0:.0f} s, load {os.getloadavg()[0]:.1f}.", ""]
    OUT.mkdir(exist_ok=True)
    (OUT / "model_object_view0.md").write_text("\n".join(md))
    print("\n".join(md))


if __name__ == "__main__":
    main()
