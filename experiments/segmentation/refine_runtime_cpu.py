"""Run time of the package-default refinement per frame, in *process CPU* seconds.

On a shared, loaded machine wall time says little; the CPU seconds this process spends
running an already compiled ``refine_batch`` are far less sensitive to the other processes.
Loads a jaxcr dataset, compiles ``refine_batch`` (``mode="map"``) for its frames once, then
runs it ``--repeats`` times and prints the median CPU and wall seconds per frame, the steps
per frame and the load average. Run it in two checkouts side by side to compare them.

    python experiments/segmentation/refine_runtime_cpu.py DS/orthogonal --frames 6 --repeats 5
"""

from __future__ import annotations

import argparse
import os
import time

import jax
import jax.numpy as jnp
import numpy as np

from jaxcr.segmentation.background import colour_mask
from jaxcr.segmentation.refine import RefineConfig, refine_batch


def main(argv=None) -> int:
    from experiments.segmentation.eval_segment import load_frames

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset")
    ap.add_argument("--frames", type=int, default=6)
    ap.add_argument("--repeats", type=int, default=5)
    a = ap.parse_args(argv)
    ds, names, frames, fk, imgs, *_ = load_frames(a.dataset, a.frames)
    cams = tuple(ds.cameras[n] for n in names)
    bgs, ims = [], []
    for n in names:
        b, i = jax.jit(jax.vmap(colour_mask))(jnp.asarray(imgs[n], jnp.float32))
        bgs.append(b)
        ims.append(i)
    cfg = RefineConfig()
    c0 = time.process_time()
    out = refine_batch(fk.centreline, cams, tuple(ims), tuple(bgs), cfg)
    print(f"first call (compile + run) {time.process_time() - c0:.1f} s CPU")
    cpu, wall = [], []
    for _ in range(a.repeats):
        c0, t0 = time.process_time(), time.perf_counter()
        out = refine_batch(fk.centreline, cams, tuple(ims), tuple(bgs), cfg)
        cpu.append((time.process_time() - c0) / len(frames))
        wall.append((time.perf_counter() - t0) / len(frames))
    print(
        f"{len(frames)} frames x {a.repeats}: median {1e3 * np.median(cpu):.0f} ms CPU/frame "
        f"({1e3 * min(cpu):.0f}-{1e3 * max(cpu):.0f}), {1e3 * np.median(wall):.0f} ms wall/frame; "
        f"steps/frame {float(jnp.mean(out.num_steps)):.1f}, per level "
        f"{np.asarray(jnp.mean(out.steps_per_level, axis=0)).round(1).tolist()}; "
        f"load {os.getloadavg()[0]:.1f}"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
