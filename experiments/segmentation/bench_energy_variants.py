"""Per-frame refinement time of RefineConfig energy variants on bench_segment's 640x480 scene.

Compares the package defaults with variants given as ``key=value`` RefineConfig overrides
(interleaved repeats, one compile each, reported separately): median ms per frame of one
``refine_batch`` call (lax.map) over the frames, median solver steps, ms per step, IoU
against the rendered truth, and the load average.

    python experiments/segmentation/bench_energy_variants.py [--frames 8] [--repeats 3] \
        [--variant "data_var='residual' robust=1.0" ...]
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
from bench_segment import make_scene  # noqa: E402

from jaxcr.segmentation.background import colour_mask  # noqa: E402
from jaxcr.segmentation.metrics import iou  # noqa: E402
from jaxcr.segmentation.refine import RefineConfig, refine_batch  # noqa: E402


def parse(spec: str) -> dict:
    kw = {}
    for item in spec.split():
        k, v = item.split("=", 1)
        kw[k] = eval(v)  # experiment script: floats/strings from the command line
    return kw


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=8)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--variant", action="append", default=None)
    a = ap.parse_args(argv)
    variants = [""] + (a.variant or ["data_var='residual' robust=1.0"])
    base, cam, frames = make_scene(a.frames)
    bgs, ims = jax.vmap(colour_mask)(jnp.stack([jnp.asarray(f["img"]) for f in frames]))
    truth = [f["mask"] for f in frames]
    bases = jax.tree.map(lambda x: jnp.broadcast_to(x, (a.frames,) + x.shape), base)
    cfgs = [RefineConfig(**parse(v)) for v in variants]
    compile_s, times, res = [], [[] for _ in cfgs], [None] * len(cfgs)
    for i, cfg in enumerate(cfgs):
        t0 = time.perf_counter()
        res[i] = refine_batch(bases, (cam,), (ims,), (bgs,), cfg)
        compile_s.append(time.perf_counter() - t0)
    for _ in range(a.repeats):
        for i, cfg in enumerate(cfgs):
            t0 = time.perf_counter()
            res[i] = refine_batch(bases, (cam,), (ims,), (bgs,), cfg)
            times[i].append((time.perf_counter() - t0) / a.frames)
    print(f"load average {os.getloadavg()}, {a.frames} frames x {a.repeats} repeats, 640x480")
    print("| variant | first call (s) | ms/frame (median) | steps (median) | ms/step | IoU |")
    print("|---|---|---|---|---|---|")
    for v, c, t, r in zip(variants, compile_s, times, res, strict=True):
        ms = 1e3 * float(np.median(t))
        steps = float(np.median(np.asarray(r.num_steps)))
        m = np.asarray(r.masks[0])
        io = float(np.mean([iou(m[k], truth[k]) for k in range(a.frames)]))
        print(
            f"| {v or 'defaults'} | {c:.1f} | {ms:.1f} | {steps:.0f} | {ms / steps:.2f} | {io:.3f} |"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
