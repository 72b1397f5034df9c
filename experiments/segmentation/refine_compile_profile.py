"""Where the refinement's XLA compile time goes: its pieces compiled one by one (issue 18,
compilation row).

On the scene and configuration of :mod:`refine_compile_cost` (tests/segmentation/test_refine.py:
160x120, levels (1, 0), one camera, no camera correction) each piece of one pyramid level of
:func:`jaxcr.segmentation.refine.refine_frame` is rebuilt from the public functions and
compiled alone: the centreline integration + projection (forward, and its gradient), band
selection + gather, the objective, its gradient, the forward-mode Jacobian of the projected
points (the motion Jacobian), and one Optimistix BFGS solve (the objective and its gradient
inside the solver's loop); then the whole ``refine_frame`` for each level alone and for both.

Per piece: jaxpr equations (nested jaxprs counted), StableHLO lines of the lowered module,
HLO instructions and fusions of the optimised module (``compiled.as_text()``), and the
process CPU seconds of lowering and of XLA compilation (less sensitive to the machine's load
than wall seconds; the load average is printed at the end).

    python experiments/segmentation/refine_compile_profile.py [--pieces] [--whole]

Results: experiments/results/segmentation/refine_compile_profile.md.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import re
import time

os.environ.setdefault("JAX_PLATFORMS", "cpu")

import jax  # noqa: E402
import jax.flatten_util  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import optimistix as optx  # noqa: E402
from refine_compile_cost import CFG, count_equations, scene  # noqa: E402

from jaxcr.segmentation.energy import chan_vese_energy, pyramid, region_data_from_level  # noqa: E402
from jaxcr.segmentation.refine import ImageSpaceBFGS, refine_frame  # noqa: E402
from jaxcr.segmentation.shape import perturbed_centreline, regularisation  # noqa: E402
from jaxcr.segmentation.silhouette import level_tube, project_tube, select_band  # noqa: E402

HLO_LINE = re.compile(r"\s+(ROOT )?%?[\w.\-]+ = ")


def cost(name: str, f, *args) -> dict:
    """Compile ``f(*args)`` and print its size and compile CPU seconds."""
    neq = count_equations(jax.make_jaxpr(f)(*args).jaxpr)
    c0 = time.process_time()
    low = jax.jit(f).lower(*args)
    c1 = time.process_time()
    comp = low.compile()
    c2 = time.process_time()
    txt = comp.as_text()
    row = {
        "piece": name,
        "eqns": neq,
        "stablehlo": sum(1 for line in low.as_text().splitlines() if " = " in line),
        "hlo": sum(1 for line in txt.splitlines() if HLO_LINE.match(line)),
        "fusions": len(re.findall(r"\bfusion\(", txt)),
        "lower_cpu_s": c1 - c0,
        "compile_cpu_s": c2 - c1,
    }
    print(
        f"{name:30s} eqns {row['eqns']:6d}  stablehlo {row['stablehlo']:6d}  hlo {row['hlo']:6d}"
        f"  fusions {row['fusions']:5d}  lower {row['lower_cpu_s']:5.1f} s  compile "
        f"{row['compile_cpu_s']:5.1f} s CPU",
        flush=True,
    )
    return row


def pieces(base, cam, ip, bg) -> None:
    pyr = pyramid(ip, bg, 2)
    for li in range(len(CFG.levels)):
        level_pieces(base, cam, pyr, li)


def level_pieces(base, cam, pyr, li: int) -> None:
    cfg, w = CFG, CFG.weights
    level = cfg.levels[li]
    tau, k = cfg.tau[li], cfg.tiles_at(level)
    data = region_data_from_level(*pyr[level], level, cfg.tile)
    params = {"c": jnp.zeros(cfg.coeff_shape)}
    area_ref = jnp.asarray(300.0)

    def tube_of(p):
        return project_tube(cam, perturbed_centreline(base, p["c"]))

    def band_of(p, level=level, data=data, k=k):
        t = level_tube(tube_of(p), level, cfg.seg_merge)
        return select_band(t, data.grid, k, cfg.k_seg)

    band = band_of(params)
    args = (band, data.gather(band.tiles))

    def obj(p, args, level=level, data=data, tau=tau):
        band, gat = args
        t = level_tube(tube_of(p), level, cfg.seg_merge)
        J, _ = chan_vese_energy(
            t, band, data, 0.0, w, tau, area_ref, cfg.local, cfg.robust, None, False, gat
        )
        return w.g_reg * regularisation(p["c"], base.s) + J

    print(f"--- level {level}, band tiles {k}")
    cost("centreline + projection", tube_of, params)
    cost("  its gradient", jax.grad(lambda p: jnp.sum(tube_of(p).ax)), params)
    cost("band selection + gather", lambda p: (band_of(p), data.gather(band_of(p).tiles)), params)
    cost("objective", obj, params, args)
    cost("grad(objective)", jax.grad(obj), params, args)
    flat, unravel = jax.flatten_util.ravel_pytree(params)

    def points(f):
        t = tube_of(unravel(f))
        return jnp.stack([t.ax, t.ay], -1)

    cost("jacfwd(projected points)", jax.jacfwd(points), flat)
    n_pts = base.p.shape[0] - 1

    def solve(z, args, obj=obj):
        return optx.minimise(
            lambda z, a: obj(unravel(z), a),
            ImageSpaceBFGS(cfg.xtol, cfg.ftol),
            z,
            args=args,
            options={"motion_jac": jnp.zeros((n_pts, 2, z.shape[0])), "f_scale": 1.0},
            max_steps=cfg.steps[li],
            throw=False,
        ).value

    cost("one BFGS solve", solve, flat, args)


def whole(base, cam, ip, bg) -> None:
    for li, level in enumerate(CFG.levels):
        one = dataclasses.replace(
            CFG, levels=(level,), steps=(CFG.steps[li],), outer=(CFG.outer[li],), tau=(CFG.tau[li],)
        )
        cost(
            f"refine_frame levels=({level},)",
            lambda b, i, g, c=one: refine_frame(b, cam, i, g, c),
            base,
            ip,
            bg,
        )
    cost(
        f"refine_frame levels={CFG.levels}",
        lambda b, i, g: refine_frame(b, cam, i, g, CFG),
        base,
        ip,
        bg,
    )


if __name__ == "__main__":
    # XLA really compiles: no persistent cache (set here, not at import: importing this
    # module, as test_experiments_imports and refine_compile_profile do, must not change
    # the importing process's or its subprocesses' environment)
    jax.config.update("jax_enable_compilation_cache", False)
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--pieces", action="store_true", help="only the pieces")
    ap.add_argument("--whole", action="store_true", help="only the whole refine_frame programs")
    ns = ap.parse_args()
    base, cam, frames = scene()
    ip, bg = frames[0]
    if not ns.whole:
        pieces(base, cam, ip, bg)
    if not ns.pieces:
        whole(base, cam, ip, bg)
    print(f"load average {os.getloadavg()[0]:.1f}")
