"""Cross-route ring edges are gated against the routes' chained registrations, not the
nominal kinematics at both ends (jaxcr.registration.pipeline.route_estimates /
cross_route_edge). The defect on fresh Task 2 seed 300: the nominal relative poses of the
far cross-route edges were 9.7-11.6 deg off the truth (the arm's curvature error adds up
along each route) while the registrations erred 0.02-0.07 deg; the 10 deg gate rejected the
right registrations, the edges took the nominal and the loop composed to 35 deg / 386 mm (no
model). Constructed: two routes winding opposite ways from a common start, their nominal
poses rotated by a drift growing along the route (6 deg per route at the far end, 12 deg
between the far views), their forward registrations exact up to 0.1 deg / 0.5 mm noise, a
registration oracle for the cross edge. Reference: the true poses."""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.spatial.transform import Rotation

from jaxcr.registration.metrics import pose_error
from jaxcr.registration.pairwise import PairResult
from jaxcr.registration.pipeline import PipelineConfig, chain, cross_route_edge, route_estimates
from tests.helpers.ring import ring_pose

N = 10  # captures per route
DRIFT_DEG = 6.0  # nominal rotation error of each route's last view about the vertical


def _T(rotvec, t):
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = t
    return T


def _routes(seed=0):
    """True and nominal world <- camera poses of routes A (+ direction) and B (-), and the
    noisy forward registrations of each."""
    rng = np.random.default_rng(seed)
    out = []
    for sign in (1.0, -1.0):
        angles = sign * np.deg2rad(np.linspace(0.0, 175.0, N))
        truth = [ring_pose(a) for a in angles]
        # the nominal kinematics drift: a rotation about the vertical through the start
        # growing along the route (curvature error), plus a tilt
        nominal = [
            _T(np.deg2rad(DRIFT_DEG * k / (N - 1)) * np.array([0.2, 0.0, sign]), [0, 0, 0]) @ T
            for k, T in enumerate(truth)
        ]
        pairs = []
        for k in range(N - 1):
            noise = _T(
                rng.normal(0, np.deg2rad(0.1) / np.sqrt(3), 3), rng.normal(0, 5e-4 / np.sqrt(3), 3)
            )
            pairs.append(noise @ np.linalg.inv(truth[k + 1]) @ truth[k])
        out.append((truth, nominal, pairs))
    return out


@dataclasses.dataclass(frozen=True)
class OracleConfig(PipelineConfig):
    """The cross edge's registration: the truth up to 0.05 deg (frames are 4x4 poses)."""

    def register(self, src, tgt, K, prior, seed, prior_gate=None):
        E = _T(np.deg2rad(0.05) * np.array([0.0, 0.0, 1.0]), [0.0, 0.0, 0.0])
        return PairResult(E @ np.linalg.inv(tgt) @ src, 60, 50, True, 0.9, 1e-3, 0.0)


def test_far_cross_edge_is_kept_against_the_chained_reference():
    (tA, nA, fA), (tB, nB, fB) = _routes()
    a, b = N - 1, N - 1  # the routes' far ends meet: the worst nominal error
    truth = np.linalg.inv(tB[b]) @ tA[a]
    nominal = np.linalg.inv(nB[b]) @ nA[a]
    assert pose_error(nominal, truth)[0] > 10.0  # the nominal is outside the 10 deg gate
    init = np.linalg.inv(nB[0]) @ nA[0]
    ref = route_estimates(chain([_pair(T) for T in fA]), chain([_pair(T) for T in fB]), init)
    reference = np.linalg.inv(ref[(1, b)]) @ ref[(0, a)]
    # two chains of 9 registrations at 0.1 deg each: ~0.4 deg (3 sigma ~1.3 deg)
    assert pose_error(reference, truth)[0] < 1.5
    notes: list[str] = []
    cfg = OracleConfig()
    pair = cross_route_edge(cfg, tA[a], tB[b], np.eye(3), nominal, reference, 0, notes, "e")
    assert notes == [] and pair.n_matches == 60  # the registration, not the fallback
    assert pose_error(pair.T, truth)[0] < 0.06  # the oracle's 0.05 deg
    # the behaviour before the fix: gated against the nominal kinematics, the right
    # registration is rejected and the edge falls back to the 12 deg-off nominal
    notes = []
    old = cross_route_edge(cfg, tA[a], tB[b], np.eye(3), nominal, nominal, 0, notes, "e")
    assert old.n_matches == 0 and len(notes) == 3
    assert pose_error(old.T, truth)[0] > 10.0


def _pair(T):
    return PairResult(T, 0, 0, False, 0.0, 0.0, 0.0)


def test_route_estimates_join_the_chains_at_the_first_views():
    (tA, nA, fA), (tB, nB, fB) = _routes(1)
    init = np.linalg.inv(tB[0]) @ tA[0]
    exact = [[_pair(np.linalg.inv(t[k + 1]) @ t[k]) for k in range(N - 1)] for t in (tA, tB)]
    ref = route_estimates(chain(exact[0]), chain(exact[1]), init)
    for r, t in ((0, tA), (1, tB)):
        for i in range(N):
            # exact registrations: the true poses in B's first camera frame (float64
            # products of <= 10 4x4 matrices: ~1e-15; 1e-12 leaves margin)
            np.testing.assert_allclose(ref[(r, i)], np.linalg.inv(tB[0]) @ t[i], atol=1e-12)
