"""Compile cost of one refinement program: the per-frame ``refine_frame`` of
tests/segmentation/test_refine.py's configuration (160x120, levels (1, 0), one camera).

Prints the jaxpr size (equations, nested jaxprs counted), the optimised HLO's instructions and
fusions (load-independent), the wall seconds of tracing, of
lowering + XLA compilation, the *process CPU* seconds of lowering + compilation (the figure
to compare on a loaded machine: the other engineers' processes inflate wall time, not the CPU
time this process spends), and the CPU seconds of running two frames. With ``--save F.npz``
it stores every output leaf of two refined frames, and ``--compare A.npz B.npz`` says which
leaves differ between two such files (e.g. before and after a change to refine.py).

    python experiments/segmentation/refine_compile_cost.py --save /tmp/after.npz
    python experiments/segmentation/refine_compile_cost.py --compare /tmp/before.npz /tmp/after.npz
    python experiments/segmentation/refine_compile_cost.py --solver gn   # RefineConfig.solver
    python experiments/segmentation/refine_compile_cost.py --breakdown 30

``--breakdown N`` also prints where the program comes from: the N jaxcr source lines with the
most jaxpr equations traced under them (inclusive: an equation counts for every jaxcr frame of
its traceback) and the N ``op_name`` scopes (first four levels) with the most optimised HLO
instructions (experiments/results/segmentation/refine_compile_r27.md).

The persistent compilation cache is switched off (``jax_enable_compilation_cache``, when run) so
that XLA really compiles. Results: experiments/results/suite_time.md.
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import os
import re
import time

os.environ.setdefault("JAX_PLATFORMS", "cpu")

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from fk_program_size import count_equations  # noqa: E402  (the same nested-jaxpr count)
from jax._src import core as jax_core  # noqa: E402

from jaxcr.camera import Camera  # noqa: E402
from jaxcr.kinematics.cosserat import integrate_centreline, perturb_centreline  # noqa: E402
from jaxcr.segmentation.background import colour_mask  # noqa: E402
from jaxcr.segmentation.refine import RefineConfig, refine_frame  # noqa: E402
from jaxcr.segmentation.shape import delta_u_steps  # noqa: E402
from jaxcr.segmentation.silhouette import project_tube, rasterise_dense  # noqa: E402

W, H = 160, 120
# an instruction line of the optimised HLO text (as refine_compile_profile.py counts them)
HLO_LINE = re.compile(r"\s+(ROOT )?%?[\w.\-]+ = ")
CFG = RefineConfig(  # tests/segmentation/test_refine.py's CFG
    n_coeffs=3, levels=(1, 0), steps=(30, 15), outer=(2, 1), tau=(1.0, 0.8), band_tiles=96,
    min_tiles=24, g_reg=0.5, local=False, camera_correction=False,
)  # fmt: skip
TRUE = [
    np.array([[0.35, -0.15, 0.05], [0.0, 0.0, 0.0]], np.float32),
    np.array([[-0.3, 0.1, 0.0], [0.0, 0.0, 0.0]], np.float32),
]


def jaxcr_lines(jaxpr, counts: collections.Counter) -> None:
    """Count equations (nested jaxprs included) per jaxcr source line of their traceback."""
    for eqn in jaxpr.eqns:
        tb = eqn.source_info.traceback
        frames = [] if tb is None else tb.frames
        for f in {(f.file_name, f.line_num, f.function_name) for f in frames}:
            if "/jaxcr/" in f[0]:
                counts[f"{f[0].split('/jaxcr/')[-1]}:{f[1]} {f[2]}"] += 1
        for p in eqn.params.values():
            for sub in p if isinstance(p, (list, tuple)) else [p]:
                if isinstance(sub, jax_core.ClosedJaxpr):
                    jaxcr_lines(sub.jaxpr, counts)
                elif isinstance(sub, jax_core.Jaxpr):
                    jaxcr_lines(sub, counts)


def hlo_scopes(txt: str, depth: int = 4) -> collections.Counter:
    """Optimised HLO instructions per ``op_name`` scope (its first ``depth`` levels)."""
    counts = collections.Counter()
    for line in txt.splitlines():
        if HLO_LINE.match(line):
            op = re.search(r'op_name="([^"]+)"', line)
            scope = "/".join(op.group(1).split("/")[1 : depth + 1]) if op else "(no op_name)"
            counts[re.sub(r"\[.*?\]", "", scope)] += 1
    return counts


def truth_centreline(base, c):
    """The true shape: ``base`` bent by coefficients ``c``, integrated by the kinematics'
    own integrator (not the refinement's), so that the images do not change with it."""
    return perturb_centreline(base, delta_u_steps(jnp.asarray(c), base.s))


def scene():
    """test_refine's arc and front camera; images drawn with jaxcr's exact rasteriser (grey
    tube on a noisy red background), colour-masked."""
    n = 41
    s = jnp.linspace(0.0, 0.12, n)
    u = jnp.tile(jnp.array([6.0, 0.0, 0.0]), (n - 1, 1))
    R0 = jnp.array([[0.0, 0, 1], [0, 1, 0], [-1, 0, 0]])
    base = integrate_centreline(s, u, jnp.full(n, 2.5e-3), jnp.array([-0.06, 0.01, 0.0]), R0)
    cam = Camera.look_at([0, 0, -0.3], [0, 0, 0], [0, -1, 0], fx=200.0, size=(W, H))
    frames = []
    for k, c in enumerate(TRUE):
        mask = np.asarray(rasterise_dense(project_tube(cam, truth_centreline(base, c)), H, W))
        rng = np.random.default_rng(k)
        img = np.empty((H, W, 3), np.float32)
        img[:] = [0.70, 0.25, 0.25]
        img += rng.normal(0, 0.05, img.shape).astype(np.float32)
        img[mask] = [0.6, 0.6, 0.62]
        bg, ip = colour_mask(jnp.asarray(np.clip(img, 0, 1)))
        frames.append((ip, bg))
    return base, cam, frames


def measure(save: str | None, breakdown: int = 0) -> None:
    base, cam, frames = scene()
    print(f"solver {CFG.solver}")

    def f(b, i, g):
        return refine_frame(b, cam, i, g, CFG)

    args = (base, *frames[0])
    t0 = time.perf_counter()
    jaxpr = jax.make_jaxpr(f)(*args)
    t1 = time.perf_counter()
    print(f"jaxpr equations {count_equations(jaxpr.jaxpr)}, trace {t1 - t0:.1f} s wall")
    if breakdown:
        lines = collections.Counter()
        jaxcr_lines(jaxpr.jaxpr, lines)
        print("jaxpr equations per jaxcr source line (inclusive):")
        for k, n in lines.most_common(breakdown):
            print(f"  {n:6d} {k}")
    t0, c0 = time.perf_counter(), time.process_time()
    compiled = jax.jit(f).lower(*args).compile()
    t1, c1 = time.perf_counter(), time.process_time()
    print(f"lower + XLA compile {t1 - t0:.1f} s wall, {c1 - c0:.1f} s CPU")
    txt = compiled.as_text()
    n_hlo = sum(1 for line in txt.splitlines() if HLO_LINE.match(line))
    n_fus = len(re.findall(r"\bfusion\(", txt))
    print(f"optimised HLO instructions {n_hlo}, fusions {n_fus}")
    if breakdown:
        print("optimised HLO instructions per op_name scope:")
        for k, n in hlo_scopes(txt).most_common(breakdown):
            print(f"  {n:6d} {k}")
    c0 = time.process_time()
    outs = jax.block_until_ready([compiled(base, *fr) for fr in frames])
    print(f"run two frames {time.process_time() - c0:.2f} s CPU")
    print(f"load average {os.getloadavg()[0]:.1f}")
    if save:
        np.savez(save, *[np.asarray(x) for o in outs for x in jax.tree.leaves(o)])


def compare(a: str, b: str) -> None:
    """Which output leaves differ; for those, the largest difference (masks: pixels), and
    each file's IoU of the refined mask against the true silhouette of each frame."""
    x, y = np.load(a), np.load(b)
    diff = [k for k in x.files if not np.array_equal(x[k], y[k], equal_nan=True)]
    print(f"{len(x.files)} output leaves, {len(diff)} differ")
    base, cam, frames = scene()
    shapes = jax.eval_shape(lambda b, i, g: refine_frame(b, cam, i, g, CFG), base, *frames[0])
    paths = [jax.tree_util.keystr(p) for p, _ in jax.tree_util.tree_flatten_with_path(shapes)[0]]
    n = len(paths)
    for k in diff:
        i = int(k.split("_")[1])
        u, v = x[k], y[k]
        d = np.sum(u != v) if u.dtype == bool else np.nanmax(np.abs(u.astype(float) - v))
        print(f"  frame {i // n} {paths[i % n]}: max |difference| {d}")
    mask = paths.index(".masks[0]")
    for k, c in enumerate(TRUE):
        truth = np.asarray(rasterise_dense(project_tube(cam, truth_centreline(base, c)), H, W))
        ious = []
        for z in (x, y):
            m = z[f"arr_{k * n + mask}"]
            ious.append(np.sum(m & truth) / max(np.sum(m | truth), 1))
        print(
            f"frame {k}: IoU of the refined mask with the truth {ious[0]:.4f} (A), {ious[1]:.4f} (B)"
        )


if __name__ == "__main__":
    # XLA really compiles: no persistent cache (set here, not at import: importing this
    # module, as test_experiments_imports and refine_compile_profile do, must not change
    # the importing process's or its subprocesses' environment)
    jax.config.update("jax_enable_compilation_cache", False)
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--save", help="store the outputs of two refined frames (.npz)")
    ap.add_argument("--compare", nargs=2, metavar=("A", "B"), help="compare two --save files")
    ap.add_argument("--solver", default=CFG.solver, help="RefineConfig.solver (default bfgs)")
    ap.add_argument("--breakdown", type=int, default=0, metavar="N", help="top-N sources")
    ns = ap.parse_args()
    CFG = dataclasses.replace(CFG, solver=ns.solver)
    if ns.compare:
        compare(*ns.compare)
    else:
        measure(ns.save, ns.breakdown)
