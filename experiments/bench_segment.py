"""Segmentation throughput: one compiled ``refine_batch`` call over F frames against the
Python loop of per-frame jitted ``refine_frame_jit`` calls a user would otherwise write.

Both paths refine the same frames of a synthetic ``orthogonal`` preset (colour-mask
background subtraction, default RefineConfig). Each is compiled (timed separately) and
warmed up, then timed ``repeats`` times with ``block_until_ready``; the report gives the median
seconds per frame, the IQR, and loop / batch. Used by ``jaxcr bench segment`` (which writes the
Markdown with metadata); standalone: ``python experiments/bench_segment.py``.
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def _median_iqr(x):
    x = np.asarray(x, float)
    q1, med, q3 = np.percentile(x, [25, 50, 75])
    return float(med), float(q3 - q1)


def run_segment_benchmark(frames: int = 4, size=(320, 240), repeats: int = 3, seed: int = 0):
    import jax
    import jax.numpy as jnp

    from jaxcr.background import colour_mask
    from jaxcr.commands._timing import CompileTimer
    from jaxcr.io.dataset import load_dataset
    from jaxcr.refine import RefineConfig, refine_batch, refine_frame_jit
    from jaxcr.synth.generate import generate

    with tempfile.TemporaryDirectory() as tmp:
        generate("orthogonal", Path(tmp) / "ds", seed=seed, frames=frames, size=size,
                 progress=False)  # fmt: skip
        ds = load_dataset(Path(tmp) / "ds")
        cam_name = next(iter(ds.cameras))
        images = np.stack([f.load_image(cam_name) for f in ds.frames])
        qs = jnp.asarray(np.stack([f.q for f in ds.frames]), jnp.float32)
    cam = ds.cameras[cam_name]
    cls = jax.jit(jax.vmap(ds.robot.forward))(qs).centreline
    bgs, subs = jax.jit(jax.vmap(colour_mask))(jnp.asarray(images))
    cfg = RefineConfig()
    n = qs.shape[0]

    def batch():
        return jax.block_until_ready(refine_batch(cls, (cam,), (subs,), (bgs,), cfg))

    def loop():
        out = []
        for i in range(n):
            base = jax.tree.map(lambda a, i=i: a[i], cls)
            out.append(refine_frame_jit(base, (cam,), (subs[i],), (bgs[i],), cfg))
        return jax.block_until_ready(out)

    results = {}
    for name, fn in (("batch", batch), ("loop", loop)):
        with CompileTimer() as t:
            fn()
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            fn()
            times.append((time.perf_counter() - t0) / n)
        results[name] = (t.compile_s, *_median_iqr(times))
    (cb, mb, sb), (cl, ml, sl) = results["batch"], results["loop"]
    return {
        "name": f"refine_batch over {n} frames at {size[0]}x{size[1]} (orthogonal preset)",
        "unit": "frame",
        "median_s": mb,
        "spread_s": sb,
        "compile_s": cb,
        "reference": "Python loop of refine_frame_jit",
        "reference_median_s": ml,
        "reference_compile_s": cl,
        "frames": n,
        "repeats": repeats,
        "rows": [
            {
                "path": "refine_batch (lax.map)",
                "ms/frame": 1e3 * mb,
                "IQR ms": 1e3 * sb,
                "compile s": cb,
            },
            {
                "path": "loop of refine_frame_jit",
                "ms/frame": 1e3 * ml,
                "IQR ms": 1e3 * sl,
                "compile s": cl,
            },
        ],  # fmt: skip
        "notes": "Medians of per-frame wall time over repeats after a warm-up call; compile "
        "time (tracing + lowering + XLA) measured on the first call via jax.monitoring.",
    }


if __name__ == "__main__":
    import json

    print(json.dumps(run_segment_benchmark(), indent=1))
    sys.exit(0)
