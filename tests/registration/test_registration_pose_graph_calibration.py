"""Covariance calibration of the pose graph (jaxcr.registration.pose_graph:
graph_linearisation, variance_components, calibrate_edges, consistency_chi2,
optimize_pose_graph(calibrate=True)) against independent references: central finite
differences of a numpy/scipy residual, a float64 scipy maximisation of the restricted
likelihood (REML) written out with dense matrices, the minimum of a float64 scipy
least-squares solve, and graphs simulated from a known covariance model."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import least_squares, minimize
from scipy.spatial.transform import Rotation

from jaxcr.registration.pipeline import _graph_weights
from jaxcr.registration.pose_graph import (
    EdgeCalibration,
    GraphEdge,
    calibrate_edges,
    consistency_chi2,
    graph_linearisation,
    optimize_pose_graph,
    variance_components,
)


def _T(rotvec, t):
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = t
    return T


def _ring(m, radius=0.3):
    out = [
        _T([0, -a, 0], [radius * np.sin(a), 0.02 * np.cos(3 * a), -radius * np.cos(a)])
        for a in (2 * np.pi * k / m for k in range(m))
    ]
    A = np.linalg.inv(out[-1])
    return [A @ P for P in out]


def _np_residual(Ti, Tj, Z):
    E = np.linalg.inv(Tj) @ Ti @ np.linalg.inv(Z)
    return np.r_[E[:3, 3], Rotation.from_matrix(E[:3, :3]).as_rotvec()]


def _spd(rng, spread):
    """Random 6x6 SPD covariance with eigenvalues spread over ``spread`` decades, blocks
    scaled like a registration (translation ~0.3 mm, rotation ~0.05 deg)."""
    V = np.linalg.qr(rng.normal(size=(6, 6)))[0]
    lam = 10.0 ** rng.uniform(-spread, 0, 6)
    C = (V * lam) @ V.T
    s = np.r_[[3e-4] * 3, [1e-3] * 3]
    return C * np.outer(s, s)


def _simulated_graph(m, gaps, a, ft, fr, seed, spread=2.0):
    """Ring graph whose edge errors are drawn from Sigma_e = a Q_e + diag(ft, fr) while
    the stated information is Q_e^-1 (the registrations' model: optimistic and too
    anisotropic). Residual of edge e at the true poses = its drawn error exactly."""
    rng = np.random.default_rng(seed)
    truth = _ring(m)
    edges, noise = [], []
    for g in gaps:
        for i in range(m):
            j = (i + g) % m
            Q = _spd(rng, spread)
            S = a * Q + np.diag([ft] * 3 + [fr] * 3)
            n = rng.multivariate_normal(np.zeros(6), S)
            Z = np.linalg.inv(_T(n[3:], n[:3])) @ np.linalg.inv(truth[j]) @ truth[i]
            edges.append(GraphEdge(i, j, Z, np.linalg.inv(Q)))
            noise.append(n)
    return truth, edges, np.array(noise)


def test_linearisation_matches_finite_differences():
    truth, edges, _ = _simulated_graph(6, (1, 2), 50.0, 1e-6, 1e-4, seed=1)
    rng = np.random.default_rng(2)
    # evaluate away from the truth: residuals of a few mm / tenths of a degree
    poses = [P @ _T(rng.normal(0, 0.01, 3), rng.normal(0, 0.005, 3)) for P in truth]
    poses[-1] = truth[-1]
    r, J = graph_linearisation(poses, edges, anchor=-1)
    ref_r = np.concatenate([_np_residual(poses[e.i], poses[e.j], e.Z) for e in edges])
    np.testing.assert_allclose(r, ref_r, atol=1e-12)
    h = 1e-6
    for n, k in enumerate(range(5)):  # free poses 0..4 (5 is the anchor)
        for c in range(6):
            d = np.zeros(6)
            d[c] = h

            def res(dd, k=k):
                P = list(poses)
                P[k] = poses[k] @ _T(dd[3:], dd[:3])
                return np.concatenate([_np_residual(P[e.i], P[e.j], e.Z) for e in edges])

            fd = (res(d) - res(-d)) / (2 * h)
            np.testing.assert_allclose(J[:, 6 * n + c], fd, atol=2e-8)
    assert J.shape == (6 * len(edges), 30)


def _reml_nll(r, J, infos):
    """float64 restricted negative log-likelihood of theta = (a, ft, fr) (log-parametrised):
    log det Sigma + log det(J^T Sigma^-1 J) + v^T Sigma^-1 v, v the GLS residuals
    (block-diagonal Sigma written out edge by edge)."""
    Q = np.stack([np.linalg.inv(w) for w in infos])
    Jb, rb = J.reshape(len(Q), 6, -1), r.reshape(len(Q), 6)

    def nll(p):
        a, ft, fr = np.exp(p)
        S = a * Q + np.diag([ft] * 3 + [fr] * 3)
        W = np.linalg.inv(S)
        N = sum(Je.T @ We @ Je for Je, We in zip(Jb, W, strict=True))
        g = sum(Je.T @ We @ re for Je, We, re in zip(Jb, W, rb, strict=True))
        v = rb - Jb @ np.linalg.solve(N, g)
        quad = sum(ve @ We @ ve for ve, We in zip(v, W, strict=True))
        return np.sum(np.linalg.slogdet(S)[1]) + np.linalg.slogdet(N)[1] + quad

    return nll


def test_variance_components_match_float64_reml_and_recover_the_model():
    a, ft, fr = 20.0, (3e-4) ** 2, (2e-3) ** 2
    truth, edges, _ = _simulated_graph(12, (1, 2, 3), a, ft, fr, seed=0, spread=3.0)
    infos = [e.info for e in edges]
    r, J = graph_linearisation(truth, edges, anchor=-1)
    cal = variance_components(r, J, infos, tol=1e-10, iterations=3000)
    assert cal.converged and cal.redundancy == 6 * 36 - 6 * 11
    nll = _reml_nll(r, J, infos)
    opts = dict(maxiter=4000, xatol=1e-8, fatol=1e-10)
    refs = [
        minimize(nll, np.log(p0), method="Nelder-Mead", options=opts)
        for p0 in ([a, ft, fr], [1.0, 1e-8, 1e-6])
    ]
    best = min(refs, key=lambda b: b.fun)
    ours = np.array([cal.scale, cal.floor_t, cal.floor_r])
    assert nll(np.log(ours)) <= best.fun + 1e-6
    np.testing.assert_allclose(ours, np.exp(best.x), rtol=1e-3)
    # and near the model the errors were drawn from (150 dof)
    assert 0.5 * a < cal.scale < 2 * a
    np.testing.assert_allclose(np.sqrt(ours[1:]), np.sqrt([ft, fr]), rtol=0.4)
    ratio = np.mean(
        [
            np.trace(
                np.linalg.solve(
                    cal.covariance(w), a * np.linalg.inv(w) + np.diag([ft] * 3 + [fr] * 3)
                )
            )
            / 6
            for w in infos
        ]
    )
    assert 0.8 < ratio < 1.25, ratio


def _rms(P, truth):
    d = [np.sum((x[:3, 3] - y[:3, 3]) ** 2) for x, y in zip(P, truth, strict=True)]
    return float(np.sqrt(np.mean(d)))


def test_calibrated_graph_beats_the_stated_information_when_it_is_too_anisotropic():
    """Errors with an isotropic floor, stated information anisotropic over 3 decades: the
    calibrated solve is closer to the truth on average than the stated one (a fixed
    set of 4 simulated graphs)."""
    plain, calib = [], []
    for seed in range(4):
        truth, edges, _ = _simulated_graph(10, (1, 2), 5.0, (3e-4) ** 2, 1e-6, 10 + seed, 3.0)
        p = optimize_pose_graph(truth, edges)
        c = optimize_pose_graph(truth, edges, calibrate=True)
        assert isinstance(c.calibration, EdgeCalibration)
        np.testing.assert_allclose(np.stack(c.stated_poses), np.stack(p.poses), atol=1e-9)

        plain.append(_rms(p.poses, truth))
        calib.append(_rms(c.poses, truth))
    assert np.mean(calib) < 0.8 * np.mean(plain), (plain, calib)


def test_consistency_chi2_is_the_least_squares_minimum():
    truth, edges, _ = _simulated_graph(8, (1,), 1.0, 1e-9, 1e-9, seed=5)
    m = len(truth)
    chi2, dof = consistency_chi2(truth, edges, anchor=-1)
    assert dof == 6
    L = [np.linalg.cholesky(e.info) for e in edges]

    def fun(x):
        P = [truth[k] @ _T(x[6 * k + 3 : 6 * k + 6], x[6 * k : 6 * k + 3]) for k in range(m - 1)]
        P.append(truth[-1])
        return np.concatenate(
            [Lc.T @ _np_residual(P[e.i], P[e.j], e.Z) for e, Lc in zip(edges, L, strict=True)]
        )

    ref = least_squares(fun, np.zeros(6 * (m - 1)), xtol=1e-15, ftol=1e-15, gtol=1e-15)
    assert chi2 == pytest.approx(float(np.sum(ref.fun**2)), rel=1e-4)
    # a loop consistent with its (calibrated) covariances: chi^2_6-sized, an inconsistent
    # closure (10 mm added) is far out
    bad = list(edges)
    bad[-1] = bad[-1]._replace(Z=_T([0, 0, 0], [0.01, 0, 0]) @ bad[-1].Z)
    assert consistency_chi2(truth, bad, anchor=-1)[0] > 100 * max(chi2, 1.0)
    with pytest.raises(ValueError, match="anchor"):
        consistency_chi2(truth, edges[:2], anchor=-1)


def test_calibration_edge_cases():
    # a graph without a cycle: nothing to calibrate from, the stated solve is returned
    truth = _ring(4)
    chain = [
        GraphEdge(k, k + 1, np.linalg.inv(truth[k + 1]) @ truth[k], np.eye(6) * 1e6)
        for k in range(3)
    ]
    out = optimize_pose_graph(truth, chain, calibrate=True)
    assert out.calibration is None and out.stated_poses is not None
    with pytest.raises(ValueError, match="redundancy"):
        r, J = graph_linearisation(truth, chain)
        variance_components(r, J, [e.info for e in chain])
    with pytest.raises(ValueError, match="6e"):
        variance_components(np.zeros(5), np.zeros((5, 2)), [np.eye(6)])
    # a direction without information stays without information after calibration
    info = np.diag([1e6, 1e6, 1e6, 1e4, 1e4, 0.0])
    cal = EdgeCalibration(4.0, 1e-8, 1e-6, 10.0, 3, True)
    W = np.linalg.inv(cal.covariance(info))
    assert W[5, 5] < 1e-6 * W[4, 4]
    np.testing.assert_allclose(
        np.linalg.inv(cal.covariance(np.eye(6) * 1e6)),
        np.eye(6) / (4e-6 + np.r_[[1e-8] * 3, [1e-6] * 3]),
    )
    edges, cal2 = calibrate_edges(*_simulated_graph(6, (1, 2), 3.0, 1e-8, 1e-7, seed=9)[:2])
    assert len(edges) == 12 and cal2.scale > 0
    # pipeline option names
    assert _graph_weights("calibrated") == "information"
    assert _graph_weights("points") == "points"
    with pytest.raises(ValueError, match="edge_weights"):
        _graph_weights("uniform")
