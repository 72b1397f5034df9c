"""Where the time of a tracked (warm-started) frame goes (issue 18, refinement row, engineer
track29): fixed cost per frame, steps per frame, cost per step and per band pixel.

Scene: the smooth 640x480 sequence of ``experiments/segmentation/bench_tracking.py``
(``jaxcr.benchmarks.segment.make_scene(frames, seed=1, smooth=True)``; ``--seed`` another
sequence). Frame 0 is refined
cold with the package defaults; frames 1.. are tracked one :func:`refine_frame_jit` call each,
every frame warm-started from its own previous answer (coefficients and camera correction:
what ``refine_sequence`` does), with a warm schedule (``RefineConfig().warm()`` changed by one
of :data:`VARIANTS`; one compiled program per schedule, the step budget is traced).

Per schedule: wall and process CPU ms per tracked frame, the *fixed* cost (the same frame
with a step budget of 0 started from the same previous answer: pyramid and region data, per
solve the tube Jacobian, band selection, gather and first gradient, the two full-resolution
output masks), solver steps per frame, ms per step ``(ms - fixed) / steps``, ns per solve-band
pixel per step, IoU against the rendered truth. Variants interleaved per repeat; the 1-minute
load is recorded.

Run: ``PYTHONPATH=$PWD python experiments/segmentation/profile_tracking.py [--frames 8]
[--repeats 3] [--size 640x480] [--variants NAME ...] [--tag NAME] [--seed N]`` (writes
``experiments/results/segmentation/profile_tracking<tag>.md`` and ``.json``).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import time
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from profile_fixed_cost import region_data_stacked  # the S24 candidate (one copy)

import jaxcr.benchmarks.segment as bs
import jaxcr.segmentation.refine as rf
from jaxcr.segmentation.background import colour_mask
from jaxcr.segmentation.metrics import iou
from jaxcr.segmentation.refine import RefineConfig, refine_frame_jit, tracking_roi

OUT = Path(__file__).resolve().parents[1] / "results" / "segmentation"


def _scene(frames: int, seed: int = 1):
    base, cam, fr = bs.make_scene(frames, seed=seed, smooth=True)
    I, B = [], []
    for f in fr:
        b, i = colour_mask(jnp.asarray(f["img"]))
        I.append(i)
        B.append(b)
    bases = jax.tree.map(lambda x: jnp.broadcast_to(x, (frames,) + x.shape), base)
    return base, bases, cam, jnp.stack(I), jnp.stack(B), [f["mask"] for f in fr]


#: warm schedules compared (``RefineConfig().warm()`` changed by these fields); the first is
#: the reference (the package defaults). The narrower solve bands of
#: ``profile_tracking_r1_*.md`` ran at commit af98ddc, whose ``RefineConfig.solve_tiles`` (the
#: solves' band at level 0, the outputs keeping ``band_tiles``) was reverted as not adopted
#: (docs/decisions.md S18). Runs r1-r3 predate S18: their "defaults" had ``ftol`` 1e-4 on
#: the warm frames, the variant "ftol 1e-4 (before S18)" since
VARIANTS = {
    "defaults": {},
    "ftol 1e-4 (before S18)": {"ftol": 1e-4},
    "outer 1": {"outer": (1,)},
    "steps 2 x 20": {"steps": (20,)},
    "xtol 0.3 px": {"xtol": 0.3},
    "ftol 1e-3": {"ftol": 1e-3},
    "xtol 0.3 px, ftol 1e-3": {"xtol": 0.3, "ftol": 1e-3},
    # not a config field: the tracked frames on a region of interest (tracking_roi of the
    # sequence's nominal shapes, refine_frame_jit's ``roi``; docs/decisions.md S21)
    "roi": {"roi": True},
    "full frame": {"roi": False},
    # not a config field: the per-tile sums of region_data_from_level from one stacked array
    # (the candidate of profile_fixed_cost.py), traced in its own program, interleaved with
    # the library's; measured, not adopted (docs/decisions.md S24; the s24 results ran at
    # commit 1a23162, where the library had the stacked sums and this variant the old ones)
    "stacked tile sums (S24)": {"stacked_sums": True},
}


def _refine_frame_stacked(base, cameras, images, backgrounds, config, init, valid, cam, steps):
    # its own jit (own trace cache), traced while refine's region data is the stacked one
    return rf._refine_frame(
        base, cameras, images, backgrounds, config, init, valid, cam, None, nums=steps
    )[0]


def _frame_stacked(base, cam, img, bg, config, init, valid, init_cam):
    """``refine_frame_jit`` (no region of interest) with the stacked per-tile sums."""
    config, steps = rf._traced_apart(config, base.p.dtype)  # every traced setting
    args = (base, (cam,), (img,), (bg,), config, init, jnp.asarray(valid, bool), init_cam)
    lib, rf.region_data_from_level = rf.region_data_from_level, region_data_stacked
    try:
        t0 = time.perf_counter()
        out = jax.block_until_ready(_refine_frame_stacked(*args, steps))
    finally:
        rf.region_data_from_level = lib
    return eqx.tree_at(lambda r: r.time_s, out, jnp.asarray(time.perf_counter() - t0))


def profile(frames: int, repeats: int, names: list[str], seed: int = 1) -> dict:
    base, bases, cam, imgs, bgs, truth = _scene(frames, seed)
    cold = refine_frame_jit(base, cam, imgs[0], bgs[0], RefineConfig())
    extra = ("roi", "stacked_sums")
    fields = {n: {k: v for k, v in VARIANTS[n].items() if k not in extra} for n in names}
    warms = {n: dataclasses.replace(RefineConfig().warm(), **fields[n]) for n in names}
    roi = tracking_roi(bases, cam, config=RefineConfig().warm())
    rois = {n: roi if VARIANTS[n].get("roi") else None for n in names}

    def frame(k, cfg, prev, n):
        if VARIANTS[n].get("stacked_sums"):
            return _frame_stacked(
                base, cam, imgs[k], bgs[k], cfg, prev.coeffs, True, prev.camera_correction
            )
        return refine_frame_jit(
            base, cam, imgs[k], bgs[k], cfg, prev.coeffs, True, prev.camera_correction,
            roi=rois[n],
        )  # fmt: skip

    def track(cfg, n):
        # frames 1.. tracked from frame 0's cold answer, each from its own previous answer
        # (what refine_sequence does), and the same frames with a step budget of 0 started
        # from the same previous answers (the fixed cost)
        zero = dataclasses.replace(cfg, steps=(0,) * len(cfg.steps))
        prev, rows = cold, []
        for k in range(1, frames):
            c0 = time.process_time()
            r = frame(k, cfg, prev, n)
            cpu = 1e3 * (time.process_time() - c0)
            c0 = time.process_time()
            z = frame(k, zero, prev, n)
            zcpu = 1e3 * (time.process_time() - c0)
            rows.append(
                (1e3 * float(r.time_s), cpu, 1e3 * float(z.time_s), zcpu, int(r.num_steps),
                 float(iou(r.masks[0], truth[k])))
            )  # fmt: skip
            prev = r
        return np.asarray(rows)

    for n in names:  # compile (the budgets are traced: one program per schedule)
        frame(1, warms[n], cold, n)
    runs = {n: [] for n in names}
    loads = []
    for _ in range(repeats):
        for n in names:
            runs[n].append(track(warms[n], n))
        loads.append(os.getloadavg()[0])
    out = {}
    for n in names:
        a = np.stack(runs[n])  # (repeats, frames - 1, 6)
        med = np.median(a, axis=(0, 1))
        n_steps = float(np.mean(a[0, :, 4]))
        per_step = (med[0] - med[2]) / max(n_steps, 1e-9)
        pixels = warms[n].tiles_at(0) * warms[n].tile ** 2
        out[n] = {
            "fields": {k: list(v) if isinstance(v, tuple) else v for k, v in VARIANTS[n].items()},
            "ms": float(med[0]),
            "cpu_ms": float(med[1]),
            "fixed_ms": float(med[2]),
            "fixed_cpu_ms": float(med[3]),
            "steps_mean": n_steps,
            "steps": a[0, :, 4].astype(int).tolist(),
            "per_step_ms": per_step,
            "per_step_cpu_ms": (med[1] - med[3]) / max(n_steps, 1e-9),
            "band_pixels": pixels,
            "ns_per_band_pixel_step": 1e6 * per_step / pixels,
            "iou_mean": float(np.mean(a[0, :, 5])),
            "iou_per_frame": a[0, :, 5].tolist(),
            "roi": rois[n],
            "loads": loads,
        }
    ref = out[names[0]]
    for n in names:
        out[n]["ratio"] = out[n]["ms"] / ref["ms"]
        out[n]["cpu_ratio"] = out[n]["cpu_ms"] / ref["cpu_ms"]
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=8)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--size", default="640x480")
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    ap.add_argument("--tag", default="")
    ap.add_argument("--seed", type=int, default=1, help="make_scene seed (1: the bench's)")
    args = ap.parse_args(argv)
    w, h = (int(x) for x in args.size.lower().split("x"))
    bs.W, bs.H = w, h
    load0 = os.getloadavg()[0]
    res = profile(args.frames, args.repeats, args.variants, args.seed)
    load1 = os.getloadavg()[0]
    cmd = (
        "PYTHONPATH=$PWD python experiments/segmentation/profile_tracking.py "
        f"--frames {args.frames} --repeats {args.repeats} --size {args.size} "
        + "--variants "
        + " ".join(f"'{v}'" for v in args.variants)
        + (f" --tag {args.tag}" if args.tag else "")
        + (f" --seed {args.seed}" if args.seed != 1 else "")
    )
    meta = bs._meta()
    stem = f"profile_tracking{args.tag}"
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / f"{stem}.json").write_text(
        json.dumps({"command": cmd, "results": res, "meta": meta}, indent=1)
    )
    lines = [
        f"# Tracked-frame profile, {w}x{h}, warm schedule, {args.frames - 1} warm frames"
        + (f" (scene seed {args.seed})" if args.seed != 1 else ""),
        "",
        f"Command: `{cmd}`",
        "",
        "| warm schedule (RefineConfig().warm() with) | ms/frame (ratio) | CPU ms/frame (ratio) | "
        "fixed ms (CPU) | steps/frame | ms per step (CPU) | solve band pixels | "
        "ns per band pixel per step | IoU |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for n, r in res.items():
        lines.append(
            f"| {n} | {r['ms']:.1f} ({r['ratio']:.2f}) | {r['cpu_ms']:.1f} ({r['cpu_ratio']:.2f}) | "
            f"{r['fixed_ms']:.1f} ({r['fixed_cpu_ms']:.1f}) | {r['steps_mean']:.1f} | "
            f"{r['per_step_ms']:.2f} ({r['per_step_cpu_ms']:.2f}) | {r['band_pixels']} | "
            f"{r['ns_per_band_pixel_step']:.0f} | {r['iou_mean']:.4f} |"
        )
    lines += [
        "",
        "Frames 1.. tracked one call each (refine_frame_jit) from frame 0's cold answer (package "
        "defaults), each from its own previous answer (as refine_sequence). fixed: the same "
        "frame with a step budget of 0 from the same previous answer (everything but the solver "
        "steps); ms per step = (ms - fixed) / steps. Medians over frames x repeats (variants "
        "interleaved per repeat); IoU against the rendered truth, mean over the tracked frames.",
        f"1-min load before/after: {load0:.1f} / {load1:.1f} on {os.cpu_count()} cores.",
    ]
    print(bs.write_markdown(OUT / f"{stem}.md", lines, meta))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
