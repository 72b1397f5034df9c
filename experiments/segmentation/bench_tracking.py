"""Tracking (warm start) and cold refinement: today's solver schedule against changed ones, in
the same process, interleaved (issue 18, refinement row).

Scenes: the 640x480 scenes of ``jaxcr/benchmarks/segment.py``: ``make_scene(frames, seed=1,
smooth=True)`` (a smooth sequence, tracked with :func:`refine_sequence`: frame 0 cold, then
warm) and ``make_scene(frames, seed=0)`` (independent frames, :func:`refine_batch`, cold).
Each variant is a :class:`RefineConfig`; the reference is the first one (``baseline``, today's
package defaults, ``hessian_memory=False``). Repeats are interleaved (A, B, A, B, ...) so
the load of the shared machine falls on every variant alike; medians of ms/frame, their ratio
to the baseline, solver steps per frame and mean IoU against the rendered truth are reported.
Compile time is excluded (one call per variant first).

Run: ``PYTHONPATH=$PWD python experiments/segmentation/bench_tracking.py --frames 8 --repeats 3
[--size 640x480] [--tag NAME]`` (writes ``experiments/results/segmentation/bench_tracking<tag>.md``
and ``.json``).
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
from jaxcr.segmentation.refine import RefineConfig, refine_batch, refine_sequence

OUT = Path(__file__).resolve().parents[1] / "results" / "segmentation"

VARIANTS = {
    "baseline (hessian_memory=False)": RefineConfig(hessian_memory=False),
    "hessian_memory": RefineConfig(hessian_memory=True),
}
#: ``--variants solvers``: the package defaults with BFGS (reference), Gauss-Newton, and
#: BFGS for cold frames with Gauss-Newton for the warm (tracked) frames (a value may be a
#: pair ``(config, warm_config)``: ``refine_sequence``'s ``warm_config``; cold batches use
#: ``config``)
SOLVERS = {
    "bfgs (package defaults)": RefineConfig(),
    "gn": RefineConfig(solver="gn"),
    "bfgs cold, gn warm": (RefineConfig(), dataclasses.replace(RefineConfig().warm(), solver="gn")),
}


def _scene(frames: int, seed: int, smooth: bool):
    base, cam, fr = bs.make_scene(frames, seed=seed, smooth=smooth)
    I, B = [], []
    for f in fr:
        b, i = colour_mask(jnp.asarray(f["img"]))
        I.append(i)
        B.append(b)
    bases = jax.tree.map(lambda x: jnp.broadcast_to(x, (frames,) + x.shape), base)
    return bases, cam, jnp.stack(I), jnp.stack(B), [f["mask"] for f in fr]


def run(frames: int, repeats: int, variants: dict) -> dict:
    seq = _scene(frames, 1, True)
    ind = _scene(frames, 0, False)
    out: dict = {}
    variants = {k: v if isinstance(v, tuple) else (v, None) for k, v in variants.items()}
    for name, (cfg, warm) in variants.items():  # compile
        t0 = time.perf_counter()
        refine_sequence(*seq[:4], cfg, warm_config=warm)
        t1 = time.perf_counter()
        refine_batch(*ind[:4], cfg)
        out[name] = {
            "compile_s_sequence": t1 - t0,
            "compile_s_batch": time.perf_counter() - t1,
            "track_ms": [],
            "cold_ms": [],
            "track_cpu_ms": [],
            "cold_cpu_ms": [],
            "load": [],
        }
    for _ in range(repeats):
        for name, (cfg, warm) in variants.items():
            c0 = time.process_time()
            r = refine_sequence(*seq[:4], cfg, warm_config=warm)
            out[name]["track_cpu_ms"].append(1e3 * (time.process_time() - c0) / frames)
            out[name]["track_ms"].append(1e3 * float(r.time_s[0]))
            out[name]["track"] = r
            c0 = time.process_time()
            c = refine_batch(*ind[:4], cfg)
            out[name]["cold_cpu_ms"].append(1e3 * (time.process_time() - c0) / frames)
            out[name]["cold_ms"].append(1e3 * float(c.time_s[0]))
            out[name]["cold"] = c
            out[name]["load"].append(os.getloadavg()[0])
    res = {}
    ref = next(iter(variants))
    for name in variants:
        o = out[name]
        tr, co = o.pop("track"), o.pop("cold")
        tr_iou = [float(iou(tr.masks[0][k], m)) for k, m in enumerate(seq[4])]
        co_iou = [float(iou(co.masks[0][k], m)) for k, m in enumerate(ind[4])]
        res[name] = {
            **o,
            "track_ms_median": float(np.median(o["track_ms"])),
            "cold_ms_median": float(np.median(o["cold_ms"])),
            "track_cpu_ms_median": float(np.median(o["track_cpu_ms"])),
            "cold_cpu_ms_median": float(np.median(o["cold_cpu_ms"])),
            # frame 0 of the sequence is cold; frames 1.. are the tracking (warm) frames
            "track_steps_warm_frames_mean": float(np.mean(np.asarray(tr.num_steps)[1:])),
            "track_steps_per_frame": np.asarray(tr.num_steps).tolist(),
            "cold_steps_mean": float(np.mean(np.asarray(co.num_steps))),
            "track_iou_mean": float(np.mean(tr_iou)),
            "track_iou_per_frame": tr_iou,
            "cold_iou_mean": float(np.mean(co_iou)),
        }
    for name in variants:
        res[name]["track_ratio_to_baseline"] = (
            res[name]["track_ms_median"] / res[ref]["track_ms_median"]
        )
        res[name]["cold_ratio_to_baseline"] = (
            res[name]["cold_ms_median"] / res[ref]["cold_ms_median"]
        )
    return res


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=8)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--size", default="640x480")
    ap.add_argument("--tag", default="")
    ap.add_argument(
        "--variants",
        choices=("hessian", "solvers"),
        default="hessian",
        help="hessian: hessian_memory off/on (the default); solvers: BFGS against Gauss-Newton",
    )
    args = ap.parse_args(argv)
    w, h = (int(x) for x in args.size.lower().split("x"))
    bs.W, bs.H = w, h  # make_scene draws at the module's size
    load0 = os.getloadavg()[0]
    res = run(args.frames, args.repeats, SOLVERS if args.variants == "solvers" else VARIANTS)
    load1 = os.getloadavg()[0]
    cmd = (
        "PYTHONPATH=$PWD python experiments/segmentation/bench_tracking.py "
        f"--frames {args.frames} --repeats {args.repeats} --size {args.size}"
        + (f" --variants {args.variants}" if args.variants != "hessian" else "")
        + (f" --tag {args.tag}" if args.tag else "")
    )
    meta = bs._meta()
    OUT.mkdir(parents=True, exist_ok=True)
    stem = f"bench_tracking{args.tag}"
    (OUT / f"{stem}.json").write_text(
        json.dumps({"command": cmd, "size": args.size, "results": res, "meta": meta}, indent=1)
    )
    lines = [
        f"# Tracking (warm start) and cold refinement, {w}x{h}, {args.frames} frames",
        "",
        f"Command: `{cmd}`",
        "",
        "| variant | tracking ms/frame (ratio) | tracking CPU ms/frame | warm steps/frame | "
        "tracking IoU | cold ms/frame (ratio) | cold CPU ms/frame | cold steps/frame | "
        "cold IoU | compile s (seq / batch) |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, r in res.items():
        lines.append(
            f"| {name} | {r['track_ms_median']:.1f} ({r['track_ratio_to_baseline']:.2f}) | "
            f"{r['track_cpu_ms_median']:.1f} | "
            f"{r['track_steps_warm_frames_mean']:.1f} | {r['track_iou_mean']:.4f} | "
            f"{r['cold_ms_median']:.1f} ({r['cold_ratio_to_baseline']:.2f}) | "
            f"{r['cold_cpu_ms_median']:.1f} | "
            f"{r['cold_steps_mean']:.1f} | {r['cold_iou_mean']:.4f} | "
            f"{r['compile_s_sequence']:.0f} / {r['compile_s_batch']:.0f} |"
        )
    lines += [
        "",
        f"1-min load before/after: {round(load0, 1)} / {round(load1, 1)} on {os.cpu_count()} "
        "cores, shared with other engineers' jobs: absolute ms scale with the load; the ratios "
        "(same process, interleaved repeats) and the step counts are the comparable figures.",
        "Tracking ms/frame includes the cold first frame (sequence total / frames). CPU "
        "ms/frame: process CPU seconds (all threads) of the same calls / frames.",
        "1-min load at each repeat: "
        + "; ".join(f"{n}: {', '.join(f'{x:.1f}' for x in r['load'])}" for n, r in res.items()),
    ]
    print(bs.write_markdown(OUT / f"{stem}.md", lines, meta))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
