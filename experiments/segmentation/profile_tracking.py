"""Where the time of a tracked (warm-started) frame goes (issue 18, refinement row, engineer
track29): fixed cost per frame, steps per frame, cost per step and per band pixel.

Scene: the smooth 640x480 sequence of ``experiments/segmentation/bench_tracking.py``
(``jaxcr.benchmarks.segment.make_scene(frames, seed=1, smooth=True)``). The previous frame's
answer comes from ``refine_sequence`` with the package defaults; each frame k >= 1 is then
refined alone by :func:`refine_frame_jit` with the warm schedule (``RefineConfig().warm()``,
optionally changed by ``--set``), started from frame k-1's coefficients and camera correction:
what ``refine_sequence`` does for that frame.

Per warm schedule (one compiled program each; the step budget is traced, so the budgets below
share it):

* ``fixed``: the frame with a step budget of 0 per solve (pyramid and region data, per solve
  the tube Jacobian, band selection, band gather and first gradient, then the two
  full-resolution output masks): everything but the solver steps;
* ``full``: the frame with the schedule's budget, its solver steps;
* per step: ``(full - fixed) / steps``; per band pixel: per step / (band tiles x tile**2).

Wall medians over frames and repeats (compile excluded) and process CPU per frame; the
1-minute load is recorded.

Run: ``PYTHONPATH=$PWD python experiments/segmentation/profile_tracking.py [--frames 8]
[--repeats 3] [--size 640x480] [--band 384 192 128] [--tag NAME]`` (writes
``experiments/results/segmentation/profile_tracking<tag>.md`` and ``.json``).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import jaxcr.benchmarks.segment as bs
from jaxcr.segmentation.background import colour_mask
from jaxcr.segmentation.metrics import iou
from jaxcr.segmentation.refine import RefineConfig, refine_frame_jit, refine_sequence

OUT = Path(__file__).resolve().parents[1] / "results" / "segmentation"


def _scene(frames: int):
    base, cam, fr = bs.make_scene(frames, seed=1, smooth=True)
    I, B = [], []
    for f in fr:
        b, i = colour_mask(jnp.asarray(f["img"]))
        I.append(i)
        B.append(b)
    bases = jax.tree.map(lambda x: jnp.broadcast_to(x, (frames,) + x.shape), base)
    return base, bases, cam, jnp.stack(I), jnp.stack(B), [f["mask"] for f in fr]


def profile(frames: int, repeats: int, bands: list[int]) -> dict:
    base, bases, cam, imgs, bgs, truth = _scene(frames)
    ref = refine_sequence(bases, (cam,), (imgs,), (bgs,), RefineConfig())
    out = {}
    for band in bands:
        warm = dataclasses.replace(RefineConfig().warm(), band_tiles=band)
        zero = dataclasses.replace(warm, steps=(0,))

        def frame(k, cfg, warm=warm):
            return refine_frame_jit(
                base, cam, imgs[k], bgs[k], cfg, ref.coeffs[k - 1], True,
                ref.camera_correction[k - 1],
            )  # fmt: skip

        frame(1, warm)  # compile (the budgets share one program)
        rows = {"fixed": [], "full": [], "fixed_cpu": [], "full_cpu": []}
        steps, ious = [], []
        for _ in range(repeats):
            for k in range(1, frames):
                for name, cfg in (("fixed", zero), ("full", warm)):
                    c0 = time.process_time()
                    r = frame(k, cfg)
                    rows[f"{name}_cpu"].append(1e3 * (time.process_time() - c0))
                    rows[name].append(1e3 * float(r.time_s))
                    if name == "full" and len(steps) < frames - 1:
                        steps.append(int(r.num_steps))
                        ious.append(float(iou(r.masks[0], truth[k])))
        med = {k: float(np.median(v)) for k, v in rows.items()}
        n_steps = float(np.mean(steps))
        per_step = (med["full"] - med["fixed"]) / max(n_steps, 1e-9)
        per_step_cpu = (med["full_cpu"] - med["fixed_cpu"]) / max(n_steps, 1e-9)
        pixels = min(band, warm.tiles_at(0)) * warm.tile**2
        out[band] = {
            **med,
            "steps_mean": n_steps,
            "steps": steps,
            "per_step_ms": per_step,
            "per_step_cpu_ms": per_step_cpu,
            "band_pixels": pixels,
            "ns_per_band_pixel_step": 1e6 * per_step / pixels,
            "iou_mean": float(np.mean(ious)),
        }
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=8)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--size", default="640x480")
    ap.add_argument("--band", type=int, nargs="+", default=[384, 192, 128])
    ap.add_argument("--tag", default="")
    args = ap.parse_args(argv)
    w, h = (int(x) for x in args.size.lower().split("x"))
    bs.W, bs.H = w, h
    load0 = os.getloadavg()[0]
    res = profile(args.frames, args.repeats, args.band)
    load1 = os.getloadavg()[0]
    cmd = (
        "PYTHONPATH=$PWD python experiments/segmentation/profile_tracking.py "
        f"--frames {args.frames} --repeats {args.repeats} --size {args.size} "
        f"--band {' '.join(map(str, args.band))}" + (f" --tag {args.tag}" if args.tag else "")
    )
    meta = bs._meta()
    stem = f"profile_tracking{args.tag}"
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / f"{stem}.json").write_text(
        json.dumps({"command": cmd, "results": res, "meta": meta}, indent=1)
    )
    lines = [
        f"# Tracked-frame profile, {w}x{h}, warm schedule, {args.frames - 1} warm frames",
        "",
        f"Command: `{cmd}`",
        "",
        "| warm band tiles (pixels) | fixed ms (CPU) | full ms (CPU) | steps/frame | "
        "ms per step (CPU) | ns per band pixel per step | IoU |",
        "|---|---|---|---|---|---|---|",
    ]
    for band, r in res.items():
        lines.append(
            f"| {band} ({r['band_pixels']}) | {r['fixed']:.1f} ({r['fixed_cpu']:.1f}) | "
            f"{r['full']:.1f} ({r['full_cpu']:.1f}) | {r['steps_mean']:.1f} | "
            f"{r['per_step_ms']:.2f} ({r['per_step_cpu_ms']:.2f}) | "
            f"{r['ns_per_band_pixel_step']:.0f} | {r['iou_mean']:.4f} |"
        )
    lines += [
        "",
        "fixed: the frame with a step budget of 0 (everything but the solver steps); full: the "
        "warm schedule's budget. Medians over frames x repeats, one frame per call "
        "(refine_frame_jit), started from the previous frame's answer of refine_sequence.",
        f"1-min load before/after: {load0:.1f} / {load1:.1f} on {os.cpu_count()} cores.",
        "",
        "Machine: " + json.dumps(meta),
    ]
    (OUT / f"{stem}.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
