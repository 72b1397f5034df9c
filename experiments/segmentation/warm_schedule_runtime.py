"""Run time of a warm-started refine_sequence chunk (6 frames, 160x120, levels (1, 0)): the
refine.py at git revision 0e5455b (a scan over the warm config's own refinement) against the
current one (the cold program with the coarse budget 0, skipped by lax.cond), interleaved, five
repeats, process CPU seconds per call after a compile call each.

    JAX_PLATFORMS=cpu PYTHONPATH=. python experiments/segmentation/warm_schedule_runtime.py

Results: experiments/results/segmentation/warm_schedule_check.md.
"""

import dataclasses
import os
import time

import jax
import jax.numpy as jnp
import numpy as np

import jaxcr.segmentation.refine as new
from experiments.segmentation.warm_schedule_check import TRUE, _old_module
from tests.helpers import refine_scene as rs
from tests.helpers.tube_render import tube_frames


def main():
    jax.config.update("jax_enable_compilation_cache", False)
    old = _old_module("0e5455b")

    base, cam = rs.base(), rs.camera()
    CFG = dataclasses.replace(rs.CFG, steps=(30, 40))
    fr = tube_frames(base, cam, TRUE * 3, (rs.W, rs.H))
    F = len(fr)
    seq = (
        jax.tree.map(lambda *x: jnp.stack(x), *[base] * F),
        cam,
        jnp.stack([f["img"] for f in fr]),
        jnp.stack([f["bg"] for f in fr]),
    )
    init = new.refine_frame_jit(base, cam, fr[0]["img"], fr[0]["bg"], CFG).coeffs
    print("load", os.getloadavg(), flush=True)
    res = {"old": [], "new": []}
    for m in (old, new):
        m.refine_sequence(*seq, CFG, init=init)  # compile (warm-only chunk)
    for _ in range(5):
        for name, m in (("old", old), ("new", new)):
            t = time.process_time()
            w = time.perf_counter()
            r = m.refine_sequence(*seq, CFG, init=init)
            res[name].append(
                (time.process_time() - t, time.perf_counter() - w, int(np.sum(r.num_steps)))
            )
    for k, v in res.items():
        v = np.array(v)
        print(
            k,
            "CPU s per 6-frame warm chunk median",
            np.median(v[:, 0]),
            "all",
            np.round(v[:, 0], 3).tolist(),
            "wall med",
            np.median(v[:, 1]),
            "steps",
            v[0, 2],
        )
    print("load", os.getloadavg())


if __name__ == "__main__":
    main()
