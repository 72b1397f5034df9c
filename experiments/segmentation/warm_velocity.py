"""A constant-velocity warm start for tracked frames, on a smoothly moving tube (issue 18,
refinement row, lever 3; engineer track31, docs/decisions.md S28).

``refine_sequence`` starts frame t from frame t-1's answer c(t-1). A constant-velocity
prediction starts it from 2 c(t-1) - c(t-2) instead, falling back to c(t-1) when the
prediction's energy J is higher than c(t-1)'s. The bench's sequences
(``jaxcr.benchmarks.segment.make_scene(smooth=True)``: a random walk of the coefficients plus
a +-0.25 zigzag of the first one) cannot show it: for them the prediction is worse by
construction (decisions S21). Here the scene is ``make_scene``'s (same nominal tube, camera,
background texture and noise model), but the true coefficients move **smoothly**:

    c(t) = c_mid + A * sin(2 pi t / T + phi),

``c_mid`` ~ N(0, 0.12) per coefficient (as ``make_scene``'s start), ``A`` ~ U(0.05, 0.25),
``phi`` ~ U(0, 2 pi), period ``T`` = ``--period`` frames (24 by default: the coefficients move
by up to 2 pi A / T = 0.065 per frame, like the bench's zigzag, with a second difference of
(2 pi / T)^2 A <= 0.017, which the prediction leaves).

Per variant, frames 2.. (frames 0 and 1 as in a sequence: 0 cold, 1 warm from 0) each one
``refine_frame_jit`` call with the package-default warm schedule from its own previous
answers: process CPU ms and wall ms of the tracked call, steps, IoU against the rendered
truth; for "velocity" also the cost of choosing the start (two step-budget-0 calls of the
same compiled program, whose ``energy.total`` is J at the start; the first tracked frames use
the previous answer), and how often it fell back. Variants interleaved per repeat.

Run: ``PYTHONPATH=$PWD python experiments/segmentation/warm_velocity.py [--size 640x480]
[--frames 12] [--repeats 2] [--seed 1] [--period 24] [--tag NAME]`` (writes
``experiments/results/segmentation/warm_velocity<tag>.md`` and ``.json``).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import time
from pathlib import Path

import jax.numpy as jnp
import numpy as np
from skimage.draw import polygon

import jaxcr.benchmarks.segment as bs
from jaxcr.segmentation.background import colour_mask
from jaxcr.segmentation.metrics import iou
from jaxcr.segmentation.refine import RefineConfig, refine_frame_jit

OUT = Path(__file__).resolve().parents[1] / "results" / "segmentation"


def smooth_scene(n_frames: int, seed: int, period: float):
    """``make_scene``'s nominal tube, camera and rendering with sinusoidal coefficients."""
    base, cam, _ = bs.make_scene(1, seed=seed)
    rng = np.random.default_rng(seed + 1000)
    bg_img = bs.tissue_background(rng)
    c_mid = rng.normal(0, 0.12, (2, 4))
    amp = rng.uniform(0.05, 0.25, (2, 4))
    phase = rng.uniform(0, 2 * np.pi, (2, 4))
    frames = []
    for k in range(n_frames):
        c = c_mid + amp * np.sin(2 * np.pi * k / period + phase)
        frames.append(bs.render_frame(base, cam, bg_img, c, rng, polygon))
    return base, cam, frames


def track(base, cam, ims, truth, velocity: bool):
    warm = RefineConfig().warm()
    zero = dataclasses.replace(warm, steps=(0,) * len(warm.steps))
    first = refine_frame_jit(base, cam, ims[0][1], ims[0][0], RefineConfig())
    prev2, prev = (
        first,
        refine_frame_jit(
            base, cam, ims[1][1], ims[1][0], warm, first.coeffs, True, first.camera_correction
        ),
    )
    rows = []
    for k in range(2, len(ims)):
        img, bg = ims[k][1], ims[k][0]
        start, check_cpu, fell_back = prev.coeffs, 0.0, False
        if velocity:
            pred = 2 * prev.coeffs - prev2.coeffs
            c0 = time.process_time()
            j_pred = refine_frame_jit(base, cam, img, bg, zero, pred, True, prev.camera_correction)
            j_prev = refine_frame_jit(
                base, cam, img, bg, zero, prev.coeffs, True, prev.camera_correction
            )
            check_cpu = 1e3 * (time.process_time() - c0)
            fell_back = bool(j_pred.energy.total > j_prev.energy.total)
            start = prev.coeffs if fell_back else pred
        c0 = time.process_time()
        r = refine_frame_jit(base, cam, img, bg, warm, start, True, prev.camera_correction)
        cpu = 1e3 * (time.process_time() - c0)
        rows.append(
            (1e3 * float(r.time_s), cpu, int(r.num_steps), float(iou(r.masks[0], truth[k])),
             check_cpu, float(fell_back))
        )  # fmt: skip
        prev2, prev = prev, r
    return np.asarray(rows)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", default="640x480")
    ap.add_argument("--frames", type=int, default=12)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--period", type=float, default=24.0)
    ap.add_argument("--tag", default="")
    args = ap.parse_args(argv)
    w, h = (int(x) for x in args.size.lower().split("x"))
    bs.W, bs.H = w, h
    load0 = os.getloadavg()[0]
    base, cam, fr = smooth_scene(args.frames, args.seed, args.period)
    ims = [colour_mask(jnp.asarray(f["img"])) for f in fr]
    truth = [f["mask"] for f in fr]
    names = {"previous answer (package)": False, "constant velocity, J fall-back": True}
    for v in names.values():  # compile
        track(base, cam, ims[:3], truth, v)
    runs = {n: [] for n in names}
    loads = []
    for _ in range(args.repeats):
        for n, v in names.items():
            runs[n].append(track(base, cam, ims, truth, v))
        loads.append(os.getloadavg()[0])
    res = {}
    for n in names:
        a = np.stack(runs[n])  # (repeats, frames - 2, 6)
        med = np.median(a, axis=(0, 1))
        res[n] = {
            "ms": float(med[0]),
            "cpu_ms": float(med[1]),
            "steps_mean": float(np.mean(a[0, :, 2])),
            "steps": a[0, :, 2].astype(int).tolist(),
            "iou_mean": float(np.mean(a[0, :, 3])),
            "iou_per_frame": a[0, :, 3].tolist(),
            "check_cpu_ms": float(med[4]),
            "fallbacks": int(a[0, :, 5].sum()),
        }
    ref = res[next(iter(names))]
    cmd = (
        "PYTHONPATH=$PWD python experiments/segmentation/warm_velocity.py "
        f"--size {args.size} --frames {args.frames} --repeats {args.repeats} --seed {args.seed} "
        f"--period {args.period:g}" + (f" --tag {args.tag}" if args.tag else "")
    )
    meta = bs._meta()
    stem = f"warm_velocity{args.tag}"
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / f"{stem}.json").write_text(
        json.dumps({"command": cmd, "results": res, "loads": loads, "meta": meta}, indent=1)
    )
    lines = [
        f"# Constant-velocity warm start on a smooth sequence, {w}x{h}, {args.frames - 2} "
        "tracked frames",
        "",
        f"Command: `{cmd}`",
        "",
        "| warm start | tracked call ms (CPU ms) | CPU ratio | steps/frame | IoU mean | "
        "max per-frame IoU change | start check CPU ms | fall-backs |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for n, r in res.items():
        dmax = float(np.max(np.abs(np.subtract(r["iou_per_frame"], ref["iou_per_frame"]))))
        lines.append(
            f"| {n} | {r['ms']:.1f} ({r['cpu_ms']:.1f}) | {r['cpu_ms'] / ref['cpu_ms']:.2f} | "
            f"{r['steps_mean']:.1f} | {r['iou_mean']:.4f} | {dmax:.4f} | "
            f"{r['check_cpu_ms']:.1f} | {r['fallbacks']} |"
        )
    lines += [
        "",
        "Scene: make_scene's tube, camera and rendering, coefficients c(t) = c_mid + A sin(2 pi "
        f"t / {args.period:g} + phi) (module docstring). Frame 0 cold, frame 1 warm from frame "
        "0, frames 2.. measured (medians over frames x repeats); the start check (two "
        "step-budget-0 calls) is not in the tracked call's time.",
        f"1-min load before/after: {load0:.1f} / {os.getloadavg()[0]:.1f}; per repeat: "
        + ", ".join(f"{x:.1f}" for x in loads)
        + f" on {os.cpu_count()} cores.",
    ]
    print(bs.write_markdown(OUT / f"{stem}.md", lines, meta))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
