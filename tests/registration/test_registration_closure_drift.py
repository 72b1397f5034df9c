"""Loop-closure drift gate (jaxcr.registration.pipeline.check_closure / chained_closure),
on a small constructed ring: a closure that slid 15 mm (inside the 3 deg / 20 mm closure
gate) is spread by the pose graph over the loop (the defect seen on fresh Task 1 seed 303:
chain 1.45 mm, closure 15.2 mm off, poses after the global optimisation 17.6 mm); the
drift gate (3 sigma sqrt(n) of the expected per-registration drift) catches it and the
chained estimate keeps the chain's accuracy. References: the true poses of the ring, and
the chain of the same noisy registrations composed in float64."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from jaxcr.registration.metrics import pose_error
from jaxcr.registration.pairwise import PairResult
from jaxcr.registration.pipeline import PipelineConfig, chained_closure, check_closure
from jaxcr.registration.pose_graph import GraphEdge, optimize_pose_graph
from tests.helpers.ring import ring_pose


def _T(rotvec, t):
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = t
    return T


def _ring(m=13, seed=0, slide=0.015):
    """True camera poses T_O,i on a 0.3 m circle looking at the centre (O = the last view),
    the noisy forward registrations T_{i+1 <- i} (0.1 deg / 0.5 mm, the RMS error of the
    Task 1 forward registrations on seeds 303/304), and a closure T_{0 <- m-1} that is
    exact but for a ``slide`` (m) along the first view's x axis."""
    rng = np.random.default_rng(seed)
    world = [ring_pose(2 * np.pi * k / m * 0.9) for k in range(m)]
    truth = [np.linalg.inv(world[-1]) @ W for W in world]
    fwd = []
    for k in range(m - 1):
        E = np.linalg.inv(truth[k + 1]) @ truth[k]
        noise = _T(
            rng.normal(0, np.deg2rad(0.1) / np.sqrt(3), 3), rng.normal(0, 5e-4 / np.sqrt(3), 3)
        )
        fwd.append(noise @ E)
    closure = _T(np.zeros(3), [slide, 0, 0]) @ np.linalg.inv(truth[0]) @ truth[-1]
    return truth, fwd, closure


def _chain(fwd):
    """T_O,i from the forward registrations alone (O = the last view)."""
    P = [np.eye(4)]
    for E in reversed(fwd):
        P.insert(0, P[0] @ E)
    return P


def _solve(fwd, closure, m):
    edges = [GraphEdge(k, k + 1, E, np.eye(6)) for k, E in enumerate(fwd)]
    edges.append(GraphEdge(m - 1, 0, closure, np.eye(6)))
    return optimize_pose_graph(_chain(fwd), edges, anchor=m - 1).poses


def _worst(P, truth):
    return max(pose_error(p, t)[1] for p, t in zip(P, truth, strict=True))


def test_slid_closure_spreads_and_drift_gate_keeps_the_chain():
    m = 13
    truth, fwd, closure = _ring(m)
    cfg = PipelineConfig()
    chain = _chain(fwd)
    chained = np.linalg.inv(chain[0]) @ chain[-1]  # T_{0 <- m-1} by the chain
    e_chain = _worst(chain, truth)
    # The defect: inside the closure gate, and the pose graph with it is far worse than
    # the chain (the slide lands on view 0, one hop from the anchor).
    r, t = pose_error(closure, chained)
    assert r <= cfg.closure_gate_deg and t <= cfg.closure_gate_m
    e_graph = _worst(_solve(fwd, closure, m), truth)
    assert e_graph > 0.010 > 3 * e_chain, (e_graph, e_chain)
    # The drift gate rejects it; the chained estimate keeps the chain (float32 solve:
    # ~1e-6 m of round-off on 0.3 m poses, 1e-5 m tolerance).
    verdict, _, _, gate = check_closure(closure, chained, m - 1, cfg)
    assert verdict == "drift"
    np.testing.assert_allclose(gate, (3 * np.sqrt(12) * 0.2, 3 * np.sqrt(12) * 0.001))
    pair = PairResult(closure, 12, 12, False, 0.3, 0.001, 0.0, np.eye(6))
    sub = chained_closure(pair, chained)
    assert sub.n_matches == 0 and not np.isfinite(sub.rmse) and sub.information is None
    e_fixed = _worst(_solve(fwd, sub.T, m), truth)
    assert e_fixed <= e_chain + 1e-5, (e_fixed, e_chain)


def test_drift_gate_accepts_a_good_closure_and_rejects_a_false_one():
    m = 13
    cfg = PipelineConfig()
    for seed in range(5):
        truth, fwd, closure = _ring(m, seed, slide=0.0)
        chain = _chain(fwd)
        chained = np.linalg.inv(chain[0]) @ chain[-1]
        # an exact closure differs from the chain by the chain's drift only (~0.5 mm x
        # sqrt(12) plus rotation x 0.3 m lever), well inside 3 sigma sqrt(12) = 10 mm
        assert check_closure(closure, chained, m - 1, cfg)[0] == "ok"
        # and the pose graph with it is no worse than the chain (the closure is exact)
        assert _worst(_solve(fwd, closure, m), truth) <= _worst(chain, truth) + 1e-5
    truth, fwd, closure = _ring(m, 0, slide=0.03)
    chain = _chain(fwd)
    assert check_closure(closure, np.linalg.inv(chain[0]) @ chain[-1], m - 1, cfg)[0] == "reject"
    # the gate grows as sqrt(n) up to the closure gate
    g4 = check_closure(np.eye(4), np.eye(4), 4, cfg)[3]
    g16 = check_closure(np.eye(4), np.eye(4), 16, cfg)[3]
    np.testing.assert_allclose(np.array(g16) / np.array(g4), 2.0)
    g_big = check_closure(np.eye(4), np.eye(4), 10**6, cfg)[3]
    assert g_big == (cfg.closure_gate_deg, cfg.closure_gate_m)
