"""Compile cost (process CPU seconds) of the kinematic fit's Levenberg-Marquardt programs.

Lowers and compiles ``jaxcr.kinematics.fit._solve`` (and the cold forward kinematics
``fit._cold_forward``) for the problems tests/kinematics/test_kinematics_fit.py solves, and
prints trace+lower and XLA compile CPU seconds of each. Used to decide which suite-time
levers are worth it (issues 15 and 19); results: experiments/results/kinematics/fit_compile_cost.md.

    python experiments/kinematics/fit_compile_cost.py {ss,ctr13,ctr2,ctr97}

The machine's load changes these figures by tens of per cent: compare only runs made side by
side.
"""

from __future__ import annotations

import argparse
import time

import jax.numpy as jnp

from jaxcr.kinematics import SingleSegment
from jaxcr.kinematics import fit as F
from jaxcr.kinematics.ctr import TEST_CTR, ConcentricTubeRobot, make_test_ctr


def measure(name, fn, *args, **kwargs):
    t0 = time.process_time()
    lowered = fn.lower(*args, **kwargs)
    t1 = time.process_time()
    lowered.compile()
    t2 = time.process_time()
    print(f"{name:24s} trace+lower {t1 - t0:6.2f} s  compile {t2 - t1:6.2f} s CPU", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("problem", choices=("ss", "ctr13", "ctr2", "ctr97"))
    which = ap.parse_args().problem
    backbone = dict(mode="backbone", fit_pose=False, tip_weight=1.0, prior_weight=0.0)
    if which == "ss":  # the single-segment recovery / `jaxcr fit` problem
        model, n_pts, guess = SingleSegment.make(0.1, 0.003, n_points=24), 9, None
        kw = dict(backbone, base_weight=1.0, max_steps=100, rtol=1e-6, atol=1e-6)
    else:
        if which == "ctr13":  # test_kinematics_fit's CTR (coarse grid = full grid)
            d, n_pts = dict(TEST_CTR, n_points=13), 7
        elif which == "ctr2":  # the same with two tubes
            d, n_pts = {"kind": "ctr", "tubes": TEST_CTR["tubes"][:2], "n_points": 13}, 7
        if which == "ctr97":  # TEST_CTR with the default settings (test_ctr's MODEL)
            model, n_pts = make_test_ctr(), 49
        else:
            model = ConcentricTubeRobot.from_dict(d, scan_points=8, n_starts=2, cold_steps=15)
        guess = jnp.zeros(model.n_tubes - 1)
        kw = dict(backbone, base_weight=0.0, max_steps=60, rtol=1e-4, atol=1e-4)
    q0 = jnp.asarray(F.default_start(model), jnp.float32)
    measure(f"{which} cold forward", F._cold_forward, model, q0)
    pts = jnp.zeros((n_pts, 3), jnp.float32)
    measure(f"{which} LM solve", F._solve, model, pts, q0, jnp.eye(4), guess, **kw)


if __name__ == "__main__":
    main()
