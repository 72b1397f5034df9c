"""Tests of the concentric-tube robot model (jaxcr.kinematics.ctr).

References and tolerances:
* closed-form planar arcs (aligned tubes: no torsion, piecewise-constant curvature
  sum(EI kappa)/sum(EI)): 1e-6 m in float32, 1e-12 m in x64;
* the independent scipy model tests/helpers/ctr_reference.py (solve_ivp DOP853 rtol 1e-10 + root):
  stored tips in tests/helpers/data/ctr_reference.json (``python tests/helpers/ctr_reference.py`` regenerates
  them) plus one live re-solve; max tip error 0.05 mm in float32, 1e-3 mm in x64;
* finite differences for d tip / d q (x64, relative 1e-5);
* step allocation: every non-empty piece gets a step, no duplicated samples (reference q);
* conservation: sum_i GJ_i u_iz = 0 along s.
"""

from __future__ import annotations

import json
import os

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxcr.errors import InputError
from jaxcr.io.exported import FAST_COMPILE, cached_call
from jaxcr.kinematics.cosserat import perturb_centreline
from jaxcr.kinematics.ctr import TEST_CTR, ConcentricTubeRobot, make_test_ctr
from jaxcr.kinematics.ctr_mechanics import allocate_steps, make_grid
from tests.helpers.ctr_reference import TEST_ROBOT, Tubes, random_q, solve_all

HERE = os.path.dirname(__file__)
with open(os.path.join(HERE, "..", "helpers", "data", "ctr_reference.json")) as fh:
    REFERENCE = json.load(fh)["cases"]


# ------------------------------------------------------------------ shared compiled functions
# The model is an argument, so every model with the same static fields and dtype shares one
# compile (compiling the solver is the slow part of this file).

TRACES: dict = {}


def _count_trace(model, q):
    key = (model.n_tubes, model.n_points, model.transmission_torsion, str(q.dtype))
    TRACES[key] = TRACES.get(key, 0) + 1  # runs once per trace, not per call


def _forward_cold(model, q):
    _count_trace(model, q)
    return model.forward(q)


def forward_batch(model, q):
    # The name and body of jaxcr.kinematics.batch.forward_batch, which the synthetic scenes
    # (tests/synth) run on TEST_CTR's tubes at 97 samples for 2 frames: the same program
    # (the persistent compile cache keys on the lowered program, not on where the function
    # is defined), so MODEL's cold solve is compiled once in the run, not once here and
    # once there. The trace counter does not change the program.
    _count_trace(model, q)
    return jax.vmap(model.forward)(q)


FWD = eqx.filter_jit(_forward_cold)
_FWD_PAIR = eqx.filter_jit(forward_batch)
WARM = eqx.filter_jit(lambda model, q, guess: model.forward(q, guess))
MODEL = make_test_ctr()


def cold_solve(q):
    """MODEL's cold solve of one q, as the first row of a batch of two (the synthetic
    scenes' batch shape, above; that vmap equals a loop is test_vmap_equals_loop_and_no_
    retracing's check, on the warm path). The other models' cold solves (transmission
    torsion, one tube) are shared with nothing: unbatched (FWD), whose programs are smaller
    (the batched cold solve of MODEL took ~1.3x the CPU of the unbatched one, 13.5 vs
    10.4 s in two loaded runs)."""
    # through the stored traced program with FAST_COMPILE, as jaxcr.synth and jaxcr segment
    # call jaxcr.kinematics.batch.forward_batch (docs/decisions.md S25): the same lowered
    # program and XLA options, so the run's persistent cache compiles it once for all three
    res = cached_call(_FWD_PAIR, MODEL, jnp.stack([q, q]), compiler_options=FAST_COMPILE)
    return jax.tree.map(lambda a: a[0], res)


MODEL_TT = make_test_ctr(transmission_torsion=True)
N_FINE = 577  # 96 RK4 steps per piece: O(h^2) centreline error ~ 7e-4 mm on TEST_CTR


def fine_x64(transmission_torsion=False):
    with jax.enable_x64(True):
        return make_test_ctr(
            dtype=jnp.float64, n_points=N_FINE, transmission_torsion=transmission_torsion
        )


def _q(*vals):
    return jnp.asarray(vals, jnp.float32)


Q0 = _q(-0.1, -0.05, -0.02, 0.3, -1.0, 2.0)


# ------------------------------------------------------------------ closed forms


def _planar_arcs(rows, beta, alpha):
    """Closed-form backbone for equal tube rotations (numpy): piecewise circular arcs.

    rows: (length, curved_length, id, od, E, kappa) per tube. Returns a function s -> p.
    """
    rows = np.asarray(rows, float)
    L, Lc, id_, od, E, kappa = rows.T
    EI = E * (od**4 - id_**4)
    ends = beta + L
    knots = np.unique(np.clip(np.concatenate([[0.0], ends - Lc, ends]), 0, ends.max()))
    pieces = []
    for a, b in zip(knots[:-1], knots[1:], strict=True):
        mid = 0.5 * (a + b)
        here = mid < ends
        curved = here & (mid > ends - Lc)
        k = np.sum(EI * kappa * curved) / np.sum(EI * here)
        pieces.append((a, b, k))

    def at(s):
        y = z = phi = 0.0
        for a, b, k in pieces:
            h = min(max(s - a, 0.0), b - a)
            if k == 0.0:
                y, z = y - np.sin(phi) * h, z + np.cos(phi) * h
            else:
                y += (np.cos(phi + k * h) - np.cos(phi)) / k
                z += (np.sin(phi + k * h) - np.sin(phi)) / k
            phi += k * h
        # bending about the tube-1 x axis, then the base rotation Rz(alpha)
        c, sn = np.cos(alpha), np.sin(alpha)
        return np.array([-sn * y, c * y, z])

    return at


def _rows(d):
    return [
        (t["length"], t["curved_length"], t["id"], t["od"], t["E"], t["kappa"]) for t in d["tubes"]
    ]


@pytest.mark.parametrize("use_x64", [False, True])
def test_single_tube_is_closed_form_arc(use_x64):
    tube = dict(TEST_CTR["tubes"][0])
    d = {"kind": "ctr", "tubes": [tube]}
    with jax.enable_x64(use_x64):
        dtype = jnp.float64 if use_x64 else jnp.float32
        model = ConcentricTubeRobot.from_dict(d, dtype=dtype, n_points=21)
        q = jnp.asarray([-0.05, 0.7], dtype)
        res = FWD(model, q)  # compiled (eager solves took ~30 s); jit == eager: its own test
        c = res.centreline
        arc = _planar_arcs(_rows(d), np.array([-0.05]), 0.7)
        want = np.stack([arc(s) for s in np.asarray(c.s, float)])
        tol = 1e-12 if use_x64 else 1e-6
        np.testing.assert_allclose(np.asarray(c.p), want, atol=tol)
        assert bool(res.ok)
        assert c.s[-1] == pytest.approx(0.431 - 0.05, abs=1e-6)
        # energy of the straightened-free arc is zero: the tube takes its precurvature
        assert float(res.energy) == pytest.approx(0.0, abs=1e-9)


@pytest.mark.parametrize("alpha", [0.0, 1.3])
def test_equal_rotations_are_piecewise_arcs(alpha):
    beta = np.array([-0.12, -0.08, -0.03])
    q = _q(*beta, alpha, alpha, alpha)
    res = cold_solve(q)
    c = res.centreline
    arc = _planar_arcs(_rows(TEST_CTR), beta, alpha)
    want = np.stack([arc(s) for s in np.asarray(c.s, float)])
    np.testing.assert_allclose(np.asarray(c.p), want, atol=2e-6)
    assert bool(res.ok)
    # no twist anywhere: the backbone frame is Rz(alpha) rotated about its own x only
    np.testing.assert_allclose(np.asarray(c.u[:, 1:]), 0.0, atol=1e-4)


TWO_TUBES = ConcentricTubeRobot.from_dict(
    {"kind": "ctr", "tubes": TEST_CTR["tubes"][:2]}, n_points=13
)


def test_fully_overlapping_tubes_give_one_arc_with_weighted_curvature():
    t1, t2 = dict(TEST_CTR["tubes"][0]), dict(TEST_CTR["tubes"][1])
    t2["length"], t2["curved_length"] = t1["length"], t1["curved_length"]
    model = ConcentricTubeRobot.from_dict({"kind": "ctr", "tubes": [t1, t2]}, n_points=13)
    # equal rotations: the untwisted state (tip angle = base angle difference 0) is exact
    res = WARM(model, _q(0.0, 0.0, 0.4, 0.4), jnp.zeros(1))
    EI = np.array([t["E"] * (t["od"] ** 4 - t["id"] ** 4) for t in (t1, t2)])
    k = np.sum(EI * np.array([t1["kappa"], t2["kappa"]])) / np.sum(EI)
    c = res.centreline
    s = np.asarray(c.s)
    steps = np.diff(s) > 0  # zero-length pieces (coinciding breakpoints) carry no curvature
    curved = s[1:] > t1["length"] - t1["curved_length"] + 1e-6
    np.testing.assert_allclose(np.asarray(c.u[1:, 0])[steps & curved], k, rtol=1e-5)
    np.testing.assert_allclose(np.asarray(c.u[1:, 0])[steps & ~curved], 0.0, atol=1e-6)
    arc = _planar_arcs(_rows({"tubes": [t1, t2]}), np.zeros(2), 0.4)
    want = np.stack([arc(si) for si in s])
    np.testing.assert_allclose(np.asarray(c.p), want, atol=2e-6)
    assert bool(res.ok)


# ------------------------------------------------------------------ scipy reference


def _tip_errors(fn, cases, dtype):
    errs = []
    for case in cases:
        res = fn(jnp.asarray(case["q"], dtype))
        assert bool(res.ok), case["q"]
        # steps shared in proportion to piece lengths: no sample collapses onto the previous one
        assert np.all(np.diff(np.asarray(res.centreline.s, float)) > 0), case["q"]
        errs.append(np.linalg.norm(np.asarray(res.centreline.p[-1], float) - case["tip"]))
        # the least-energy equilibrium, as in the reference
        assert float(res.energy) == pytest.approx(case["energy"], rel=1e-3, abs=1e-6)
    return np.array(errs) * 1e3  # mm


@pytest.mark.parametrize("transmission_torsion", [False, True])
def test_reference_tips_float32(transmission_torsion):
    """Cold start (residual scan + Newton, least energy) against the scipy model's minimum."""
    model = MODEL_TT if transmission_torsion else MODEL
    cases = [c for c in REFERENCE if c["transmission_torsion"] == transmission_torsion]
    err = _tip_errors(
        lambda q: FWD(model, q) if transmission_torsion else cold_solve(q), cases, jnp.float32
    )
    print(
        f"float32 tt={transmission_torsion} max tip error over {len(cases)} q: {err.max():.2e} mm"
    )
    assert err.max() < 0.05


def test_reference_tips_x64():
    """Discretisation error with N_FINE samples, warm-started from the float32 solution (rigid
    transmission only: one x64 compile; transmission torsion is checked in float32)."""
    transmission_torsion = False
    cases = [c for c in REFERENCE if not c["transmission_torsion"]]
    states = [np.asarray(cold_solve(jnp.asarray(c["q"], jnp.float32)).state) for c in cases]
    model = fine_x64(transmission_torsion)
    with jax.enable_x64(True):
        it = iter(states)
        # the x64 program of the gradient tests below (the warm solve and its tip Jacobian:
        # one x64 compile for the three tests instead of two)
        err = _tip_errors(
            lambda q: TIP_JAC_FK(model, q, jnp.asarray(next(it), jnp.float64))[1], cases, None
        )
    print(f"x64 tt={transmission_torsion} max tip error over {len(cases)} q: {err.max():.2e} mm")
    assert err.max() < 1e-3


def test_transmission_torsion_changes_the_shape():
    case = next(c for c in REFERENCE if c["transmission_torsion"])
    rigid = cold_solve(jnp.asarray(case["q"], jnp.float32)).centreline.p[-1]
    assert np.linalg.norm(np.asarray(rigid) - case["tip"]) > 1e-3


def test_live_reference_agrees_with_stored_fixture():
    """Re-solve one stored configuration with the scipy model (guards the fixture)."""
    case = next(c for c in REFERENCE if not c["transmission_torsion"])
    t = Tubes(TEST_ROBOT)
    found = solve_all(t, np.asarray(case["q"]), [np.asarray(case["uz0"]) * t.GJ], rtol=1e-9)
    assert found
    np.testing.assert_allclose(found[0]["tip"], case["tip"], atol=1e-8)


def test_branches_match_reference_branches():
    case = next(c for c in REFERENCE if not c["transmission_torsion"] and len(c["branches"]) > 2)
    q = jnp.asarray(case["q"], jnp.float32)
    res = eqx.filter_jit(lambda m, q: m.forward_branches(q))(MODEL, q)
    conv = np.asarray(res.residual) < MODEL.tol
    energies = np.asarray(res.energy)[conv]
    tips = np.asarray(res.centreline.p[:, -1])[conv]
    # every reference equilibrium is found by one of the starts, with the same tip
    for br in case["branches"]:
        j = np.argmin(np.abs(energies - br["energy"]))
        assert energies[j] == pytest.approx(br["energy"], rel=1e-4)
        assert np.linalg.norm(tips[j] - br["tip"]) < 5e-5
    # forward returns the least-energy one
    best = cold_solve(q)
    assert float(best.energy) == pytest.approx(min(b["energy"] for b in case["branches"]), rel=1e-4)


# ------------------------------------------------------------------ invariants


def test_total_torsional_moment_is_zero_along_s():
    res = cold_solve(Q0)
    # compiled: run eagerly, its ~80 operations were compiled one by one
    s, uz = eqx.filter_jit(lambda m, q, x: m.twist_profile(q, x))(MODEL, Q0, res.state)
    GJ = np.asarray(MODEL.mechanics().GJ)
    total = np.asarray(uz) @ GJ
    scale = np.max(np.abs(np.asarray(uz) * GJ))
    assert scale > 1e-4  # the tubes do twist here
    np.testing.assert_allclose(total, 0.0, atol=1e-5 * scale)
    assert uz.shape == (MODEL.n_points, 3)


def test_perturb_centreline_reproduces_forward():
    c = cold_solve(Q0).centreline
    # compiled (run eagerly, its operations were compiled one by one)
    again = jax.jit(perturb_centreline)(c, jnp.zeros_like(c.u[1:]))
    np.testing.assert_allclose(np.asarray(again.p), np.asarray(c.p), atol=1e-7)
    np.testing.assert_allclose(np.asarray(again.R), np.asarray(c.R), atol=1e-6)


def test_frames_and_radius():
    res = cold_solve(Q0)
    c = res.centreline
    assert c.p.shape == (MODEL.n_points, 3) and c.R.shape == (MODEL.n_points, 3, 3)
    np.testing.assert_allclose(np.asarray(c.p[0]), 0.0)
    np.testing.assert_allclose(
        np.asarray(c.R[0]), np.asarray(jnp.array(_rz(0.3))), atol=1e-6
    )  # R(0) = Rz(alpha_1)
    RtR = np.einsum("nij,nik->njk", np.asarray(c.R), np.asarray(c.R))
    np.testing.assert_allclose(RtR, np.broadcast_to(np.eye(3), RtR.shape), atol=1e-5)
    ends = np.asarray(Q0[:3]) + np.array([t["length"] for t in TEST_CTR["tubes"]])
    ods = np.array([t["od"] for t in TEST_CTR["tubes"]])
    s = np.asarray(c.s)
    for k in range(1, len(s)):
        mid = 0.5 * (s[k - 1] + s[k])
        if s[k] - s[k - 1] > 1e-9:
            assert float(c.rho[k]) == pytest.approx(ods[mid < ends].max() / 2)
    # every breakpoint (curved starts, ends) is a sample
    lc = np.array([t["curved_length"] for t in TEST_CTR["tubes"]])
    for b in np.concatenate([ends, ends - lc]):
        assert np.min(np.abs(s - b)) < 1e-6


def _rz(a):
    c, s = np.cos(a), np.sin(a)
    return [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]


def test_steps_shared_in_proportion_to_piece_lengths():
    """No zero-length steps for typical q; every breakpoint is a sample; counts ~ lengths."""
    rng = np.random.default_rng(5)
    t = Tubes(TEST_ROBOT)
    tubes = MODEL.mechanics()
    grid_fn = jax.jit(lambda beta: make_grid(tubes, beta, MODEL.n_points))
    clipped = 0
    for _ in range(20):
        q = random_q(rng, t)
        beta = jnp.asarray(q[:3], jnp.float32)
        s = np.asarray(grid_fn(beta).s, float)
        assert s.shape == (MODEL.n_points,)
        assert np.all(np.diff(s) > 0), q
        ends = q[:3] + t.L
        bps = np.clip(np.concatenate([ends - t.Lc, ends]), 0.0, ends.max())
        clipped += int(np.any(bps == 0.0))
        for b in bps:
            assert np.min(np.abs(s - b)) < 1e-6
    assert clipped > 0  # some q had a curved part starting behind s = 0 (an empty piece)
    # compiled (run eagerly, its ~15 operations were compiled one by one at each shape)
    alloc = jax.jit(allocate_steps, static_argnums=1)
    lengths = jnp.asarray([0.0, 0.1, 0.0, 0.3, 0.05, 0.0])
    counts = np.asarray(alloc(lengths, 12))
    # one step each for the 3 non-empty pieces, the other 9 by rounded cumulative shares
    # round(9 * [0, 2/9, 2/9, 8/9, 1, 1]) = [0, 2, 2, 8, 9, 9]
    np.testing.assert_array_equal(counts, [0, 3, 0, 7, 2, 0])
    assert np.asarray(alloc(jnp.zeros(4), 7)).tolist() == [7, 0, 0, 0]
    tiny = np.asarray(alloc(jnp.asarray([1e-9, 1.0, 1e-9]), 5))
    assert tiny.tolist() == [1, 3, 1]


def test_joint_limit_violation_is_not_ok_but_finite():
    for q in (
        _q(-0.02, -0.05, -0.01, 0, 0, 0),  # beta_1 > beta_2
        _q(-0.1, -0.05, 0.01, 0, 0, 0),  # beta_3 > 0
        _q(-0.2, -0.01, -0.005, 0, 0, 0),  # tube 2 extends beyond tube 1
    ):
        res = cold_solve(q)
        assert not bool(res.ok)
        assert np.all(np.isfinite(np.asarray(res.centreline.p)))


# ------------------------------------------------------------------ transformations


def test_jit_equals_eager():
    q = _q(-0.1, -0.05, 0.2, 1.9)
    guess = _q(0.3)  # near the tip angle 0.2558 of this q's equilibrium (twisted by 1.4 rad)
    eager = TWO_TUBES.forward(q, guess)
    jitted = WARM(TWO_TUBES, q, guess)
    assert bool(jitted.ok) and bool(eager.ok)
    assert float(jitted.state[0]) == pytest.approx(0.2558, abs=1e-3)
    np.testing.assert_allclose(
        np.asarray(eager.centreline.p), np.asarray(jitted.centreline.p), atol=1e-6
    )
    assert float(eager.energy) == pytest.approx(float(jitted.energy), rel=1e-5)


def test_vmap_equals_loop_and_no_retracing():
    # every cold solve of MODEL in this file (several q) uses one trace at most (none when
    # another process of the run stored the traced program first: cold_solve goes through
    # jaxcr.io.exported.cached_call, which then loads it)
    cold_solve(Q0)
    assert TRACES.get((3, MODEL.n_points, False, "float32"), 0) <= 1
    qs = jnp.stack(
        [_q(-0.1, -0.05, 0.2, 0.5), _q(-0.05, -0.02, -0.4, -0.1), _q(-0.05, -0.01, 1.0, 1.3)]
    )
    guesses = qs[:, 3:] - qs[:, 2:3]  # untwisted: 0.3 rad from the equilibrium at most
    loop = [WARM(TWO_TUBES, q, g) for q, g in zip(qs, guesses, strict=True)]
    batch = eqx.filter_jit(lambda m, qs, gs: jax.vmap(m.forward)(qs, gs))(TWO_TUBES, qs, guesses)
    for k, r in enumerate(loop):
        assert bool(r.ok) and bool(batch.ok[k])
        np.testing.assert_allclose(
            np.asarray(batch.centreline.p[k]), np.asarray(r.centreline.p), atol=2e-6
        )
        assert float(batch.energy[k]) == pytest.approx(float(r.energy), rel=1e-4)
    assert batch.centreline.p.shape == (3, TWO_TUBES.n_points, 3)


def test_warm_start_needs_fewer_iterations():
    cold = cold_solve(Q0)
    q1 = Q0 + _q(-0.002, 0.001, 0.0, 0.02, -0.03, 0.01)
    warm = WARM(MODEL, q1, cold.state)
    cold1 = cold_solve(q1)
    assert bool(warm.ok)
    assert int(warm.num_steps) < int(cold1.num_steps)
    assert int(warm.num_steps) <= MODEL.warm_steps // 2
    np.testing.assert_allclose(
        np.asarray(warm.centreline.p), np.asarray(cold1.centreline.p), atol=2e-6
    )


def _tip_jacobian_and_fk(model, q, guess):
    """d tip / d q (jacfwd through the warm solve's implicit derivative) and the warm solve
    itself (the primal of the same program): the x64 tests' one program."""

    def tip(qq):
        res = model.forward(qq, guess)
        return res.centreline.p[-1], res

    return jax.jacfwd(tip, has_aux=True)(q)


TIP_JAC_FK = eqx.filter_jit(_tip_jacobian_and_fk)


def test_gradient_matches_finite_differences_x64():
    state = np.asarray(cold_solve(Q0).state)
    with jax.enable_x64(True):
        model = fine_x64()
        q = jnp.asarray(np.asarray(Q0, float))
        guess = jnp.asarray(state, jnp.float64)
        J = np.asarray(TIP_JAC_FK(model, q, guess)[0])
        h = 1e-6
        fd = np.stack(
            [
                (
                    np.asarray(TIP_JAC_FK(model, q.at[i].add(h), guess)[1].centreline.p[-1])
                    - np.asarray(TIP_JAC_FK(model, q.at[i].add(-h), guess)[1].centreline.p[-1])
                )
                / (2 * h)
                for i in range(6)
            ],
            axis=1,
        )
        np.testing.assert_allclose(J, fd, rtol=1e-5, atol=1e-7)
        assert np.abs(J).max() > 0.1


def test_gradient_finite_at_straight_and_aligned():
    # aligned tubes (no twist; tip angles = base angles) and tubes without precurvature; x64
    # models of the same static fields as the FD test share its compiled Jacobian
    q_aligned = np.array([-0.1, -0.05, -0.02, 0.5, 0.5, 0.5])
    straight = {**TEST_CTR, "tubes": [{**t, "kappa": 0.0} for t in TEST_CTR["tubes"]]}
    with jax.enable_x64(True):
        curved = fine_x64()
        straight = ConcentricTubeRobot.from_dict(straight, dtype=jnp.float64, n_points=N_FINE)
        for model, q in ((curved, q_aligned), (straight, q_aligned), (straight, np.asarray(Q0))):
            q = jnp.asarray(q, jnp.float64)
            guess = q[4:] - q[3]
            J, res = TIP_JAC_FK(model, q, guess)
            assert np.all(np.isfinite(np.asarray(J))), (model.kappa, q)
            assert bool(res.ok)


# ------------------------------------------------------------------ robot description


def test_dict_round_trip():
    d = MODEL.to_dict()
    again = ConcentricTubeRobot.from_dict(d)
    for k in ("length", "curved_length", "od", "id", "E", "G", "kappa"):
        np.testing.assert_allclose(np.asarray(getattr(again, k)), np.asarray(getattr(MODEL, k)))
    assert again.transmission_torsion == MODEL.transmission_torsion
    assert again.n_points == MODEL.n_points
    assert MODEL.n_joints == 6 and MODEL.n_tubes == 3


def _bad(path, value):
    d = json.loads(json.dumps(TEST_CTR))
    if path[0] == "tubes" and len(path) == 3:
        d["tubes"][path[1]][path[2]] = value
    else:
        d[path[0]] = value
    return d


@pytest.mark.parametrize(
    "path,value,field",
    [
        (("tubes", 0, "id"), 2e-3, "tubes[0].id"),  # id >= od
        (("tubes", 1, "length"), -0.1, "tubes[1].length"),
        (("tubes", 1, "length"), 0.0, "tubes[1].length"),
        (("tubes", 2, "curved_length"), 0.2, "tubes[2].curved_length"),
        (("tubes", 0, "E"), float("nan"), "tubes[0].E"),
        (("tubes", 0, "kappa"), "big", "tubes[0].kappa"),
        (("tubes", 1, "id"), 1.0e-3, "tubes[1].id"),  # does not fit over tube 0
        (("tubes", 0, "lenght"), 0.1, "tubes[0].lenght"),
        (("transmission_torsion",), "yes", "transmission_torsion"),
        (("tubes",), [], "tubes"),
    ],
)
def test_bad_descriptions_raise_input_error(path, value, field):
    with pytest.raises(InputError) as err:
        ConcentricTubeRobot.from_dict(_bad(path, value), file="robot.json")
    assert err.value.field == field
    assert "\n" not in str(err.value)
    assert "robot.json" in str(err.value)


def test_missing_key_raises_input_error():
    d = json.loads(json.dumps(TEST_CTR))
    del d["tubes"][1]["G"]
    with pytest.raises(InputError) as err:
        ConcentricTubeRobot.from_dict(d)
    assert err.value.field == "tubes[1].G"


def test_shooting_map_is_fourth_order_x64():
    """The RK4 shooting map on (cos, sin) of the angles (:func:`shoot_torsion`) converges at
    fourth order: doubling the steps divides the base-angle error against an 8x finer grid by
    ~16. The steps are shared among the pieces by rounding, so the ratio is not exactly 16:
    the bound 8 (third order would give at most ~8) tells the orders apart."""
    with jax.enable_x64(True):
        model = make_test_ctr(dtype=jnp.float64)
        q = jnp.asarray(Q0, jnp.float64)
        x = jnp.asarray([0.7, -1.2], jnp.float64)
        ns = (49, 97, 769)
        # one compiled program for the three grids (run eagerly, ~150 operations were
        # compiled one by one)
        shoot = eqx.filter_jit(lambda m, q, x: [m._shooting(q, n)(x)[0] for n in ns])
        r = dict(zip(ns, (np.asarray(v) for v in shoot(model, q, x)), strict=True))
    e49, e97 = (np.max(np.abs(r[n] - r[769])) for n in (49, 97))
    print(f"base-angle error: N=49 {e49:.2e}, N=97 {e97:.2e} rad, ratio {e49 / e97:.1f}")
    assert e97 < 1e-5  # the float32 solver tolerance (tol / 10): the default grid resolves it
    assert e49 / e97 > 8.0
