"""Diagnose why refine_frame's BFGS solves never stop on their tolerance.

Instruments every Optimistix step of :func:`jaxcr.segmentation.refine.refine_frame` (a BFGS subclass
patched into :mod:`jaxcr.segmentation.refine` for this process only) and prints, per solve and step:
trial energy, accepted?, line-search step size, last accepted energy, gradient max-norm, the
parameter step max-norm, the image motion of the trial step (pixels of the level, linearised,
see :class:`jaxcr.segmentation.refine.ImageSpaceBFGS`), |df| of accepted steps, the predicted Armijo
decrease, the termination flag and the exact (non-linearised) motion of accepted steps in
full-resolution pixels.

    python experiments/segmentation/refine_convergence_diag.py DATASET [--frames 2] [--camera NAME]
    python experiments/segmentation/refine_convergence_diag.py --bench   # the bench_segment scene
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import jax
import jax.flatten_util
import jax.numpy as jnp
import numpy as np

import jaxcr.segmentation.refine as R

LOG: list[dict] = []
CHECK_GRAD = False


def _rec(tag, **kw):
    LOG.append({"tag": tag, **{k: jax.tree.map(np.asarray, v) for k, v in kw.items()}})


def make_diag_solver(base_cls):
    class Diag(base_cls):
        def step(self, fn, y, args, options, state, tags):
            y2, st2, aux = super().step(fn, y, args, options, state, tags)
            accepted = st2.num_accepted_steps > state.num_accepted_steps
            k = options.get("f_scale", 1.0)  # report J, not the solver's scaled J / kappa
            f_trial = fn(state.y_eval, args)[0] * k
            f_old = state.f_info.f * k
            f_new = st2.f_info.f * k
            dy = jax.tree.map(lambda a, b: a - b, y2, y)
            num = jnp.max(jnp.concatenate([jnp.abs(x).ravel() for x in jax.tree.leaves(dy)]))
            dflat = (jax.flatten_util.ravel_pytree(state.y_eval)[0]
                     - jax.flatten_util.ravel_pytree(y)[0])  # fmt: skip
            uv = options["motion_jac"] @ dflat
            yr = jnp.max(jnp.hypot(uv[:, 0], uv[:, 1]))  # trial motion, level px
            fr = jnp.abs(f_new - f_old)
            g = st2.f_info.grad
            gmax = jnp.max(jnp.concatenate([jnp.abs(x).ravel() for x in jax.tree.leaves(g)]))
            # predicted decrease of the trial (Armijo's right-hand side / slope)
            ydiff = jax.tree.map(lambda a, b: a - b, state.y_eval, y)
            pred = k * sum(
                jnp.sum(a * b) for a, b in zip(jax.tree.leaves(state.f_info.grad),
                                               jax.tree.leaves(ydiff), strict=True)
            )  # fmt: skip
            if CHECK_GRAD:
                # directional derivative along -g vs finite differences (first step of a solve:
                # the gradient is evaluated at the accepted point y2 = y0)
                gv = jax.flatten_util.ravel_pytree(st2.f_info.grad)[0]
                yv, unr = jax.flatten_util.ravel_pytree(y2)
                f0 = fn(unr(yv), args)[0]
                hs = jnp.asarray([1.0, 0.3, 0.1, 0.03, 0.01, 1e-3, 1e-4])
                fd = jax.vmap(lambda h: fn(unr(yv - h * gv), args)[0] - f0)(hs)
                ratio = fd / (-hs * jnp.sum(gv * gv))
                jax.debug.callback(
                    lambda first, r, g: print("   FD/grad along -g at h=1..1e-4:", np.round(r, 2),
                                              "\n   scaled grad:", np.round(g, 4))
                    if bool(first) else None,
                    state.first_step, ratio, gv,
                )  # fmt: skip
            jax.debug.callback(
                lambda *a: _rec("step", **dict(zip(NAMES, a, strict=True))),
                state.first_step, accepted, f_trial, f_old, f_new,
                st2.search_state.step_size, gmax, num, yr, fr, pred, st2.terminate, y, y2,
            )  # fmt: skip
            return y2, st2, aux

    return Diag


NAMES = ["first", "acc", "f_trial", "f_old", "f_new", "next_step", "gmax", "dy", "y_ratio",
         "f_ratio", "pred", "term", "y", "y2"]  # fmt: skip


def patch():
    R.ImageSpaceBFGS = make_diag_solver(R.ImageSpaceBFGS)
    R.ImageSpaceLBFGS = make_diag_solver(R.ImageSpaceLBFGS)


def pixel_motion(frame, cfg, y_old, y_new):
    """Max displacement (full-resolution px) of the projected centreline between params."""
    from jaxcr.camera import project_points
    from jaxcr.segmentation.shape import perturbed_centreline

    cl, cams, _, _ = frame
    d = 0.0
    for i, cam in enumerate(cams):
        z_ref = jnp.mean(cl.p @ cam.R[2] + cam.t[2])
        uv = []
        for y in (y_old, y_new):
            c = cam
            if "cam" in y:
                c = R._corrected_camera(cam, jnp.asarray(y["cam"][i]), z_ref)
            p = perturbed_centreline(cl, jnp.asarray(y["c"]), cfg.torsion).p
            uv.append(np.asarray(project_points(c, p)[0]))
        d = max(d, float(np.max(np.hypot(*(uv[1] - uv[0]).T))))
    return d


def print_log(rows, max_rows=200, frame=None, cfg=None):
    print(f"{'#':>3} {'acc':>3} {'f_trial':>12} {'f_acc':>12} {'df':>10} {'step':>9} "
          f"{'|g|max':>9} {'|dy|max':>9} {'trial_px':>8} {'|df|':>8} {'pred':>10} term  px(full)")  # fmt: skip
    solve = 0
    for i, r in enumerate(rows[:max_rows]):
        if bool(r["first"]):
            solve += 1
            print(f"--- solve {solve}")
        print(
            f"{i:3d} {int(r['acc']):3d} {float(r['f_trial']):12.7f} {float(r['f_new']):12.7f} "
            f"{float(r['f_new'] - r['f_old']):10.2e} {float(r['next_step']):9.2e} "
            f"{float(r['gmax']):9.2e} {float(r['dy']):9.2e} {float(r['y_ratio']):8.2f} "
            f"{float(r['f_ratio']):8.1e} {float(r['pred']):10.2e} {int(r['term'])}"
            + (f" {pixel_motion(frame, cfg, r['y'], r['y2']):8.3f}"
               if frame is not None and bool(r['acc']) and not bool(r['first'])
               and isinstance(r['y'], dict) else "")
        )  # fmt: skip


def load_frames(path, n, camera=None):
    from jaxcr.io.dataset import load_dataset
    from jaxcr.segmentation.background import colour_mask

    ds = load_dataset(Path(path))
    cams = [camera] if camera else list(ds.cameras)[:1]
    out = []
    for f in ds.frames[:n]:
        q = jnp.asarray(np.asarray(f.q), jnp.float32)
        cl = ds.robot.forward(q).centreline
        ims, bgs = [], []
        for c in cams:
            b, i = colour_mask(jnp.asarray(f.load_image(c)))
            ims.append(i)
            bgs.append(b)
        out.append((cl, tuple(ds.cameras[c] for c in cams), tuple(ims), tuple(bgs)))
    return out


def bench_frames(n):
    from jaxcr.benchmarks.segment import make_scene
    from jaxcr.segmentation.background import colour_mask

    base, cam, fr = make_scene(n)
    out = []
    for f in fr:
        b, i = colour_mask(jnp.asarray(f["img"]))
        out.append((base, (cam,), (i,), (b,)))
    return out


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("dataset", nargs="?")
    ap.add_argument("--bench", action="store_true")
    ap.add_argument("--frames", type=int, default=2)
    ap.add_argument("--camera", default=None)
    ap.add_argument("--solver", default=None, help="lbfgs|bfgs (default: RefineConfig's)")
    ap.add_argument("--from-answer", action="store_true", help="log a re-run from the answer")
    ap.add_argument("--paper-energy", action="store_true", help="local=False, no camera corr.")
    ap.add_argument("--check-grad", action="store_true", help="FD along -g at each solve start")
    a = ap.parse_args(argv)
    global CHECK_GRAD
    CHECK_GRAD = a.check_grad
    patch()
    frames = bench_frames(a.frames) if a.bench else load_frames(a.dataset, a.frames, a.camera)
    kw = dict(local=False, camera_correction=False) if a.paper_energy else {}
    if a.solver:
        kw["solver"] = a.solver
    cfg = R.RefineConfig(**kw)
    fn = jax.jit(lambda *x: R.refine_frame(*x, config=cfg))
    warm = jax.jit(lambda *x: R.refine_frame(*x[:4], config=cfg, init=x[4], init_cam=x[5]))
    for k, (cl, cams, ims, bgs) in enumerate(frames):
        LOG.clear()
        out = fn(cl, cams, ims, bgs)
        jax.block_until_ready(out)
        if a.from_answer:
            print(f"=== frame {k}: cold steps {int(out.num_steps)}; restarted from its answer:")
            LOG.clear()
            out = warm(cl, cams, ims, bgs, out.coeffs, out.camera_correction)
            jax.block_until_ready(out)
        print(f"=== frame {k}: steps {int(out.num_steps)} per level "
              f"{np.asarray(out.steps_per_level)} status {int(out.status)} "
              f"J {float(out.energy.total):.5f} (nominal {float(out.energy.total_nominal):.5f})")  # fmt: skip
        print_log(LOG, frame=frames[k], cfg=cfg)
    return 0


if __name__ == "__main__":
    sys.exit(main())
