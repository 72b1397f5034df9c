"""Run time of the package-default refinement per frame, in *process CPU* seconds.

On a shared, loaded machine wall time says little; the CPU seconds this process spends
running an already compiled ``refine_batch`` are far less sensitive to the other processes.
Loads a jaxcr dataset, compiles ``refine_batch`` (``mode="map"``) for its frames once, then
runs it ``--repeats`` times and prints the median CPU and wall seconds per frame, the steps
per frame and the load average. Run it in two checkouts side by side to compare them; with
``--per-level`` it also compiles ``RefineConfig(share_levels=False)`` in the same process and
alternates the timed calls of the two programs. ``--save F.npz`` stores every output leaf of
the default program's last call, and ``--compare A.npz B.npz`` says which leaves differ between
two such files (e.g. two checkouts: a change meant to be bit-identical).

    python experiments/segmentation/refine_runtime_cpu.py DS/orthogonal --frames 6 --repeats 5
    python experiments/segmentation/refine_runtime_cpu.py --compare A.npz B.npz
"""

from __future__ import annotations

import argparse
import os
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from jaxcr.segmentation.refine import RefineConfig, refine_batch


def main(argv=None) -> int:
    from experiments.segmentation.eval_segment import colour_masks, load_frames

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset", nargs="?")
    ap.add_argument("--frames", type=int, default=6)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--per-level", action="store_true", help="also share_levels=False")
    ap.add_argument("--save", help="store the default program's outputs (.npz)")
    ap.add_argument("--compare", nargs=2, metavar=("A", "B"), help="compare two --save files")
    a = ap.parse_args(argv)
    if a.compare:
        x, y = np.load(a.compare[0]), np.load(a.compare[1])
        diff = [k for k in x.files if not np.array_equal(x[k], y[k], equal_nan=True)]
        print(f"{len(x.files)} output leaves, {len(diff)} differ: {diff}")
        return 0
    ds, names, frames, fk, imgs, *_ = load_frames(a.dataset, a.frames)
    cams = tuple(ds.cameras[n] for n in names)
    bgs, ims = colour_masks(imgs, names)
    cfgs = {"default": RefineConfig()}
    if a.per_level:
        cfgs["share_levels=False"] = RefineConfig(share_levels=False)
    args = (fk.centreline, cams, tuple(ims), tuple(bgs))
    for name, cfg in cfgs.items():
        c0 = time.process_time()
        refine_batch(*args, cfg)
        print(f"{name}: first call (compile + run) {time.process_time() - c0:.1f} s CPU")
    cpu = {n: [] for n in cfgs}
    wall = {n: [] for n in cfgs}
    outs = {}
    for _ in range(a.repeats):
        for name, cfg in cfgs.items():
            c0, t0 = time.process_time(), time.perf_counter()
            outs[name] = refine_batch(*args, cfg)
            cpu[name].append((time.process_time() - c0) / len(frames))
            wall[name].append((time.perf_counter() - t0) / len(frames))
    if a.save:
        # time_s (wall clock) is not a result
        out = eqx.tree_at(lambda r: r.time_s, outs["default"], jnp.zeros(()))
        np.savez(a.save, *[np.asarray(x) for x in jax.tree.leaves(out)])
    for name, out in outs.items():
        c, w = cpu[name], wall[name]
        print(
            f"{name}: {len(frames)} frames x {a.repeats}: median {1e3 * np.median(c):.0f} ms "
            f"CPU/frame ({1e3 * min(c):.0f}-{1e3 * max(c):.0f}), {1e3 * np.median(w):.0f} ms "
            f"wall/frame; steps/frame {float(jnp.mean(out.num_steps)):.1f}, per level "
            f"{np.asarray(jnp.mean(out.steps_per_level, axis=0)).round(1).tolist()}; "
            f"load {os.getloadavg()[0]:.1f}"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
