"""Regenerates ``tests/helpers/data/ctr_reference.json``: seeded random joint values of the public
test robot and their tips from the independent scipy model, which lives in
:mod:`jaxcr.benchmarks.ctr_reference` (it is also the reference of ``jaxcr bench fk``).

    python tests/helpers/ctr_reference.py
"""

from __future__ import annotations

import json
import os
import sys

import numpy as np

from jaxcr.benchmarks.ctr_reference import (  # noqa: F401  (re-exported for the tests)
    TEST_ROBOT,
    Tubes,
    default_starts,
    integrate,
    random_q,
    solve_all,
    solve_equilibrium,
)


def main(path=None, n_configs=10, seed=0):
    path = path or os.path.join(os.path.dirname(__file__), "data", "ctr_reference.json")
    rng = np.random.default_rng(seed)
    cases = []
    for tt in (False, True):
        t = Tubes(TEST_ROBOT, transmission_torsion=tt)
        for k in range(n_configs if not tt else max(2, n_configs // 2)):
            q = random_q(rng, t)
            found = solve_all(t, q, default_starts(t, q, n_random=10, seed=k))
            best = min(found, key=lambda f: f["energy"])
            cases.append(
                {
                    "transmission_torsion": tt,
                    "q": q.tolist(),
                    "tip": best["tip"].tolist(),
                    "uz0": best["uz0"].tolist(),
                    "energy": best["energy"],
                    "branches": [
                        {"tip": f["tip"].tolist(), "energy": f["energy"], "uz0": f["uz0"].tolist()}
                        for f in sorted(found, key=lambda f: f["energy"])
                    ],
                }
            )
            print(tt, k, len(found), [round(f["energy"], 5) for f in found], file=sys.stderr)
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(path, "w") as fh:
        json.dump(
            {
                "generator": "python tests/helpers/ctr_reference.py",
                "robot": "TEST_CTR",
                "seed": seed,
                "tol": "solve_ivp DOP853 rtol 1e-10 atol 1e-12, root hybr",
                "cases": cases,
            },
            fh,
            indent=1,
        )
    return cases


if __name__ == "__main__":
    main()
