"""jaxcr.io.exported.cached_call: stored traced programs (jax.export) reused by a later process.

A small eqx.filter_jit function with a module argument (arrays and a static field) stands in
for the refinement; the reference is the direct call (same compiled arithmetic, so equality
is exact up to XLA's choice of fusion: float32 rounding, rtol 1e-6)."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxcr.io import exported
from jaxcr.kinematics.cosserat import Centreline


class Params(eqx.Module):
    a: jax.Array
    power: int = eqx.field(static=True)


@eqx.filter_jit
def _poly(p: Params, x, mode):
    y = p.a * x**p.power
    n = y.shape[0]
    # an equinox module in the output (its structure must survive a new process)
    cl = Centreline(s=y, p=jnp.zeros((n, 3)), R=jnp.zeros((n, 3, 3)), u=jnp.zeros((n, 3)), rho=y)
    return {"y": y if mode == "plain" else -y, "s": jnp.sum(y), "cl": cl}


STORED = []


@pytest.fixture
def folder(tmp_path, monkeypatch):
    d = str(tmp_path / "exported")
    monkeypatch.setattr(exported, "_folder", lambda: d)
    monkeypatch.setattr(exported, "_memo", {})
    store = exported._store
    STORED.clear()

    def counting_store(*a):  # an entry is stored exactly when the function was exported
        STORED.append(a[0])
        store(*a)

    monkeypatch.setattr(exported, "_store", counting_store)
    return tmp_path / "exported"


def test_stored_program_is_reused_without_tracing(folder):
    p, x = Params(jnp.arange(3.0), 2), jnp.linspace(0.0, 1.0, 3)
    ref = _poly(p, x, "plain")
    out = exported.cached_call(_poly, p, x, "plain")
    assert len(STORED) == 1
    np.testing.assert_allclose(out["y"], ref["y"], rtol=1e-6)
    np.testing.assert_allclose(out["s"], ref["s"], rtol=1e-6)
    assert len(list(folder.glob("*.jaxexport"))) == 1
    # a new process: empty memo, the file is loaded and called, nothing is exported again
    exported._memo.clear()
    x2 = x + 1.0
    out2 = exported.cached_call(_poly, p, x2, "plain")
    assert len(STORED) == 1
    np.testing.assert_allclose(out2["y"], _poly(p, x2, "plain")["y"], rtol=1e-6)
    assert isinstance(out2["cl"], Centreline)
    np.testing.assert_allclose(out2["cl"].rho, out2["y"], rtol=1e-6)


def test_static_values_and_shapes_make_new_entries(folder):
    p, x = Params(jnp.arange(3.0), 2), jnp.ones(3)
    exported.cached_call(_poly, p, x, "plain")
    neg = exported.cached_call(_poly, p, x, "negated")  # a static string argument
    np.testing.assert_allclose(neg["y"], -_poly(p, x, "plain")["y"], rtol=1e-6)
    cube = exported.cached_call(_poly, Params(p.a, 3), 2.0 * x, "plain")  # a static field
    np.testing.assert_allclose(cube["y"], p.a * 8.0, rtol=1e-6)
    exported.cached_call(_poly, Params(jnp.arange(4.0), 2), jnp.ones(4), "plain")  # shapes
    assert len(list(folder.glob("*.jaxexport"))) == 4


def test_cache_off_calls_directly(monkeypatch, tmp_path):
    monkeypatch.setattr(exported, "_folder", lambda: None)
    p, x = Params(jnp.arange(2.0), 1), jnp.ones(2)
    out = exported.cached_call(_poly, p, x, "plain")
    np.testing.assert_allclose(out["y"], np.arange(2.0))
    assert not any(tmp_path.iterdir())


@pytest.mark.parametrize("stored", [True, False])
def test_compiler_options_reach_xla_and_share_the_stored_program(stored, folder, monkeypatch):
    """``compiler_options`` (jaxcr segment compiles the kinematics with FAST_COMPILE, the
    legacy loop emitter): the same arithmetic as the direct call (rtol 1e-6 as above), one
    stored program for every set of options, and the options really reach XLA (an unknown
    one is rejected), with the cache on (stored program) and off (traced here)."""
    if not stored:
        monkeypatch.setattr(exported, "_folder", lambda: None)
    p, x = Params(jnp.arange(3.0), 2), jnp.linspace(0.0, 1.0, 3)
    ref = _poly(p, x, "plain")
    plain = exported.cached_call(_poly, p, x, "plain")
    fast = exported.cached_call(_poly, p, x, "plain", compiler_options=exported.FAST_COMPILE)
    for out in (plain, fast):
        np.testing.assert_allclose(out["y"], ref["y"], rtol=1e-6)
        np.testing.assert_allclose(out["s"], ref["s"], rtol=1e-6)
    assert len(STORED) == (1 if stored else 0)
    with pytest.raises(Exception, match="xla_jaxcr_no_such_option"):
        exported.cached_call(_poly, p, x, "plain", compiler_options={"xla_jaxcr_no_such_option": 1})


def test_unreadable_entry_is_rebuilt(folder):
    p, x = Params(jnp.arange(3.0), 2), jnp.ones(3)
    exported.cached_call(_poly, p, x, "plain")
    (path,) = folder.glob("*.jaxexport")
    path.write_bytes(b"garbage")
    exported._memo.clear()
    out = exported.cached_call(_poly, p, x, "plain")
    np.testing.assert_allclose(out["y"], np.arange(3.0))
    assert path.read_bytes().startswith(exported.FORMAT)


def test_kinematics_round_trip_equals_the_direct_call(folder):
    """`jaxcr segment` calls the batched forward kinematics through cached_call, so a second
    process neither traces nor lowers it. The stored-and-reloaded program gives the direct
    call's FkResult (same arithmetic: float32 rounding, rtol 1e-6 as above). A single-segment
    arc keeps this cheap; the CTR path (which once fell back to tracing) runs end to end in
    the `jaxcr segment` tests, whose synthetic datasets are CTRs."""
    import jaxcr as jcr
    from jaxcr.kinematics.batch import forward_batch

    robot = jcr.robot_from_dict({"kind": "single_segment", "length": 0.04, "radius": 0.002})
    qs = jnp.asarray(np.linspace(-1.0, 1.0, 2 * robot.n_joints).reshape(2, -1), jnp.float32)
    ref = forward_batch(robot, qs)
    exported.cached_call(forward_batch, robot, qs)
    exported._memo.clear()  # a new process: the stored program is loaded, not traced
    out = exported.cached_call(forward_batch, robot, qs)
    assert len(STORED) == 1
    assert type(out) is type(ref)
    np.testing.assert_array_equal(np.asarray(out.ok), np.asarray(ref.ok))
    np.testing.assert_allclose(out.centreline.p, ref.centreline.p, rtol=1e-6, atol=1e-9)


def _chain(x, p):
    """Two stored programs, the second taking the first's output (as segment's refinement
    takes the kinematics')."""
    first = exported.cached_call(_poly, p, x, "plain")
    return first, exported.cached_call(_poly, Params(first["y"], 3), x, "negated")


def test_compile_ahead_compiles_each_program_once_and_gives_the_sequential_results(folder):
    """A dry run inside compile_ahead returns zeros of the programs' output shapes and starts
    their XLA compilation; the real run then compiles nothing more (no backend compile nor
    cache load of a stored program: the zeros are placed as real outputs, so the second
    program lowers as in the real run) and its results are those of the sequential path bit
    for bit (the same stored programs and executables' arithmetic)."""
    import jax.monitoring as monitoring

    p, x = Params(jnp.arange(4.0), 2), jnp.linspace(0.0, 1.0, 4)
    seq = _chain(x, p)  # the sequential path, in a "process" of its own
    exported._memo.clear()
    compiled = []

    def listener(event, duration, **kw):
        if event == "/jax/core/compile/backend_compile_duration":
            compiled.append(kw.get("fun_name"))

    with exported.compile_ahead():
        dry = _chain(x, p)
    assert jax.tree.structure(dry) == jax.tree.structure(seq)
    for d, s in zip(jax.tree.leaves(dry), jax.tree.leaves(seq), strict=True):
        assert d.shape == s.shape and d.dtype == s.dtype and not np.any(np.asarray(d))
    for fut in list(exported._compiling.values()):
        fut.result()
    monitoring.register_event_duration_secs_listener(listener)
    try:
        real = _chain(x, p)
    finally:
        monitoring.unregister_event_duration_listener(listener)
    assert not [n for n in compiled if "_stored" in str(n)], compiled
    assert not exported._compiling
    for r, s in zip(jax.tree.leaves(real), jax.tree.leaves(seq), strict=True):
        np.testing.assert_array_equal(np.asarray(r), np.asarray(s))
    # a second dry run in the same process (a new Segmenter): nothing is lowered or queued
    with exported.compile_ahead():
        again = _chain(x, p)
    assert not exported._compiling
    assert jax.tree.structure(again) == jax.tree.structure(seq)


@eqx.filter_jit
def _qr_solve(A, b):
    """A least-squares solve through lineax's QR (LAPACK geqrf + ormqr): what Optimistix's
    Levenberg-Marquardt runs inside `jaxcr fit`."""
    import lineax as lx

    # throw=False as inside Optimistix (a raising solve is a host callback: never exportable)
    return lx.linear_solve(lx.MatrixLinearOperator(A), b, solver=lx.QR(), throw=False).value


def test_programs_with_lapack_qr_are_stored(folder):
    """jax.export refuses jaxlib's `ormqr` kernel (no cross-version guarantee) unless allowed;
    cached_call allows it (its entries are keyed by the exact jaxlib version), so a QR solve is
    stored and reloaded instead of being traced in every process. Reference: numpy's lstsq
    (float32 on a well-conditioned 6x3 system: rtol 1e-4)."""
    rng = np.random.default_rng(0)
    A = jnp.asarray(rng.normal(size=(6, 3)), jnp.float32)
    b = jnp.asarray(rng.normal(size=6), jnp.float32)
    ref = np.linalg.lstsq(np.asarray(A, np.float64), np.asarray(b, np.float64), rcond=None)[0]
    np.testing.assert_allclose(exported.cached_call(_qr_solve, A, b), ref, rtol=1e-4, atol=1e-5)
    assert len(STORED) == 1
    exported._memo.clear()  # a new process loads it
    np.testing.assert_allclose(exported.cached_call(_qr_solve, A, b), ref, rtol=1e-4, atol=1e-5)
    assert len(STORED) == 1


def test_fit_backbone_second_process_loads_its_programs(folder):
    """`jaxcr fit` (jaxcr.kinematics.fit with ``jit_call=cached_call``) runs its
    Levenberg-Marquardt solve and its summary as stored programs (docs/decisions.md K4): a second process stores (= traces) nothing new.
    Reference: the true q of noise-free points sampled from the model (the LM's float32
    resolution on unit-scale q is ~1e-5: atol 1e-4); the two processes run the same program
    (atol 1e-6)."""
    import jaxcr as jcr
    from jaxcr.kinematics.fit import _cold_forward, fit_backbone

    robot = jcr.robot_from_dict(
        {"kind": "single_segment", "length": 0.1, "radius": 0.003, "n_points": 12}
    )
    q_true = np.array([0.55, 0.8])
    p = np.asarray(_cold_forward(robot, jnp.asarray(q_true)).centreline.p)
    pts = jnp.asarray(p[np.r_[0:12:3, 11]], jnp.float32)  # the last point is the tip
    first = fit_backbone(robot, pts, jit_call=exported.cached_call)
    stored = len(STORED)
    assert stored >= 2  # the LM solve and the summary
    exported._memo.clear()
    second = fit_backbone(robot, pts, jit_call=exported.cached_call)
    assert len(STORED) == stored
    np.testing.assert_allclose(first.q, q_true, atol=1e-4)
    np.testing.assert_allclose(second.q, first.q, atol=1e-6)
    assert bool(first.ok) and bool(second.ok)
