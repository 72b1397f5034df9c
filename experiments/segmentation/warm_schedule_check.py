"""refine_sequence's warm frames through the cold frame's program (a zero step budget skips a
pyramid level): what it changes, on tests/segmentation/test_refine_convergence.py's scene.

1. The new sequence against its per-frame slow loop (``refine_frame_jit``: frame 0 cold,
   frame 1 with the coarse budget 0 from frame 0's answer): which output leaves differ.
2. The warm schedule through the cold program (coarse budget 0) against ``RefineConfig.warm()``'s
   own program (the finest level only): largest differences of the coefficients, equal masks.
3. With ``--old REV``: the sequence of ``jaxcr/segmentation/refine.py`` at git revision REV
   (two refinements: the cold first frame and the warm scan) against the new one (one
   refinement, per-frame budgets), and the process CPU seconds of each first call (compile +
   two frames): the compile cost a ``--warm-start`` run pays.

    JAX_PLATFORMS=cpu PYTHONPATH=. python experiments/segmentation/warm_schedule_check.py --old 0e5455b

The persistent compilation cache is off (nothing is loaded). Results:
experiments/results/segmentation/warm_schedule_check.md.
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib.util
import os
import subprocess
import sys
import tempfile
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import jaxcr.segmentation.refine as new
from tests.helpers import refine_scene as rs
from tests.helpers.tube_render import tube_frames

TRUE = [  # test_refine_convergence's frames
    np.array([[0.15, -0.05, 0.0], [0.0, 0.0, 0.0]], np.float32),
    np.array([[-0.12, 0.06, 0.0], [0.0, 0.0, 0.0]], np.float32),
]
CFG = dataclasses.replace(rs.CFG, steps=(30, 40))
WARM = dataclasses.replace(CFG, steps=(0, 40))


def _leaves(r):
    r = eqx.tree_at(lambda x: x.time_s, r, jnp.zeros_like(r.time_s))
    return [
        (jax.tree_util.keystr(p), np.asarray(x)) for p, x in jax.tree_util.tree_leaves_with_path(r)
    ]


def _differ(a, b):
    out = []
    for (name, x), (_, y) in zip(_leaves(a), _leaves(b), strict=True):
        if x.shape != y.shape:
            out.append(f"{name} shape {x.shape} vs {y.shape}")
        elif not np.array_equal(x, y, equal_nan=True):
            d = np.max(np.abs(x.astype(np.float64) - y.astype(np.float64)))
            out.append(f"{name} max|d| {d:.2e}")
    return out or ["none"]


def _frame(r, k):
    return jax.tree.map(lambda x: x[k], r)


def _old_module(rev):
    src = subprocess.run(
        ["git", "show", f"{rev}:jaxcr/segmentation/refine.py"], capture_output=True, text=True,
        check=True,
    ).stdout  # fmt: skip
    path = os.path.join(tempfile.mkdtemp(), "refine_old.py")
    with open(path, "w") as f:
        f.write(src)
    spec = importlib.util.spec_from_file_location("jaxcr.segmentation.refine_old", path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod
    spec.loader.exec_module(mod)
    return mod


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--old", help="git revision of the previous refine.py to compare with")
    args = ap.parse_args()
    jax.config.update("jax_enable_compilation_cache", False)
    print(f"load average {os.getloadavg()}")
    base, cam = rs.base(), rs.camera()
    frames = tube_frames(base, cam, TRUE, (rs.W, rs.H))
    seq = (
        jax.tree.map(lambda *x: jnp.stack(x), base, base),
        cam,
        jnp.stack([f["img"] for f in frames]),
        jnp.stack([f["bg"] for f in frames]),
    )
    t = time.process_time()
    s_new = new.refine_sequence(*seq, CFG)
    cpu_new = time.process_time() - t
    cold = new.refine_frame_jit(base, cam, frames[0]["img"], frames[0]["bg"], CFG)
    w1 = new.refine_frame_jit(base, cam, frames[1]["img"], frames[1]["bg"], WARM, init=cold.coeffs)
    print("1. sequence vs per-frame slow loop, frame 0 (cold):", _differ(_frame(s_new, 0), cold))
    print("   frame 1 (warm, coarse budget 0):", _differ(_frame(s_new, 1), w1))
    for k, f in enumerate(frames):
        r = new.refine_frame_jit(base, cam, f["img"], f["bg"], CFG)
        a = new.refine_frame_jit(base, cam, f["img"], f["bg"], WARM, init=r.coeffs)
        b = new.refine_frame_jit(base, cam, f["img"], f["bg"], CFG.warm(), init=r.coeffs)
        b = eqx.tree_at(
            lambda x: x.steps_per_level, b, jnp.concatenate([jnp.zeros(1, jnp.int32),
                                                             b.steps_per_level])
        )  # fmt: skip
        print(f"2. frame {k} warm from its answer, coarse budget 0 vs CFG.warm():", _differ(a, b))
    if args.old:
        old = _old_module(args.old)
        t = time.process_time()
        s_old = old.refine_sequence(*seq, CFG)
        cpu_old = time.process_time() - t
        for k in range(2):
            print(f"3. sequence {args.old} vs new, frame {k}:", _differ(_frame(s_old, k),
                                                                      _frame(s_new, k)))  # fmt: skip
        print(
            f"   first call CPU s (compile + 2 frames): {args.old} {cpu_old:.1f}, new {cpu_new:.1f}"
        )
    else:
        print(f"   first sequence call CPU s (compile + 2 frames): {cpu_new:.1f}")
    print(f"load average {os.getloadavg()}")


if __name__ == "__main__":
    main()
