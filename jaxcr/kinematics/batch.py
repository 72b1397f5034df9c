"""Batched forward kinematics with failure reasons as data.

One jitted ``vmap`` of ``model.forward`` over rows of joint values (compiled once per model
and chunk shape; the last chunk is padded), then, for every row that failed, why: non-finite
joint values, joint values outside a CTR's limits, no converged solution, or a non-finite
result. ``jaxcr fk`` is this plus file writing; a notebook calls :func:`forward`.

Example::

    import numpy as np
    import jaxcr as jcr

    robot = jcr.robot_from_dict(jcr.TEST_CTR)
    q = np.array([[-0.1, -0.05, -0.02, 0.0, 0.5, 1.0]])
    fk = jcr.forward(robot, q)
    fk.p[:, -1]          # (B, 3) tip positions, robot frame, metres
    fk.reasons           # ("",) -- "" where ok, else why the row failed
"""

from __future__ import annotations

import functools
import types

import equinox as eqx
import numpy as np

CHUNK = 1024


def batch_bucket(n_rows: int, chunk: int = CHUNK) -> int:
    """The rows of one compiled forward program for a batch of ``n_rows``: the smallest
    power of two >= ``n_rows``, at most ``chunk`` (issue 18, "compiles once per robot shape
    class, not per batch size"). Batches of 65-128 rows share one program, and so on; a
    batch over ``chunk`` runs in chunks of ``chunk``. The padding rows repeat the last row
    and are discarded, so a row's result does not depend on the bucket beyond float rounding
    of the vectorised program (tests/cli/test_cli_fk.py)."""
    n = max(1, int(n_rows))
    return max(1, min(int(chunk), 1 << (n - 1).bit_length()))


@eqx.filter_jit
def forward_batch(model, q):
    """The :class:`~jaxcr.kinematics.base.FkResult` of every row of ``q`` (B, n_joints):
    ``jax.vmap(model.forward)`` compiled once per model structure and B (jax arrays with a
    leading axis B, e.g. the nominal centrelines :func:`jaxcr.refine_batch` takes).

    The model is an argument, not a closure, so one program serves every robot of the same
    structure; the synthetic-data generator :mod:`jaxcr.synth` and ``jaxcr segment`` call it through
    ``jaxcr.io.exported.cached_call`` with ``FAST_COMPILE`` (one stored program and one
    compile for both, docs/decisions.md S25; a direct call is the plain jit of the same
    body). For failure reasons and numpy outputs use :func:`forward` (its program,
    :func:`forward_batch_rotvec`, adds the tip's rotation vector).
    """
    import jax

    return jax.vmap(model.forward)(q)


@eqx.filter_jit
def forward_batch_rotvec(model, qs):
    """:func:`forward_batch` of ``qs`` (B, n_joints) and the rotation vector of every row's tip
    frame (B, 3): the one program of :func:`batch_forward` (``jaxcr fk``, :func:`forward`).

    A module-level function of its arguments alone, so that :func:`batch_forward` can call it
    through :func:`jaxcr.io.exported.cached_call`: a second process loads the stored traced
    program instead of tracing the CTR solver again (docs/decisions.md K4)."""
    import jax

    from jaxcr.geometry import so3_log

    res = jax.vmap(model.forward)(qs)
    rotvec = jax.vmap(so3_log)(res.centreline.R[:, -1])
    return res, rotvec


def _run_chunk_body(qs, model, jit_call=None):
    # ``jit_call(fn, *args)``: how the program is called; ``jaxcr fk`` passes
    # jaxcr.io.exported.cached_call (the stored traced program when the persistent cache is
    # on, XLA's default options: the program's run time is the command's work, unlike
    # segment's once-per-process kinematics); None: the plain jit of the same body
    if jit_call is None:
        return forward_batch_rotvec(model, qs)
    return jit_call(forward_batch_rotvec, model, qs)


def batch_forward(
    model,
    q: np.ndarray,
    chunk: int = CHUNK,
    progress: bool = True,
    devices: int | None = None,
    jit_call=None,
) -> dict[str, np.ndarray]:
    """Forward kinematics of every row of ``q`` (B, m) with one jitted ``vmap`` (one compile).

    Rows are processed in chunks of :func:`batch_bucket` ``(B, chunk)`` rows (the last chunk
    padded to the same shape, so there is a single trace, and batches of sizes in one
    power-of-two bucket share the compiled program; ``jit_call`` =
    :func:`jaxcr.io.exported.cached_call`, as ``jaxcr fk`` passes, also stores the traced
    program, so a later process neither traces nor lowers it, docs/decisions.md K4). Returns numpy arrays keyed as in ``jaxcr fk``'s
    ``centrelines.npz``: ``s`` (B, N), ``p`` (B, N, 3), ``R`` (B, N, 3, 3), ``rho`` (B, N),
    ``ok``, ``residual``, ``energy``, ``num_steps`` (B,), ``tip_rotvec`` (B, 3).

    ``devices``: local devices to spread each chunk's rows over (1-D mesh over rows,
    :func:`jaxcr.scale.devices.map_frames`; bit-identical per row); None: all local devices
    (one on a usual machine: no sharding).
    """
    import jax.numpy as jnp

    from jaxcr.scale.devices import map_frames

    B = q.shape[0]
    chunk = batch_bucket(B, chunk)
    outs = []
    starts = range(0, B, chunk)
    bar = None
    if progress and len(starts) > 1:
        from jaxcr.progress import progress as progress_bar

        bar = progress_bar(total=B, desc="fk", unit="row")
    for start in starts:
        part = q[start : start + chunk]
        n = part.shape[0]
        if n < chunk:
            part = np.concatenate([part, np.repeat(part[-1:], chunk - n, axis=0)])
        res, rotvec = map_frames(
            functools.partial(_run_chunk_body, jit_call=jit_call),
            jnp.asarray(part, jnp.float32),
            model,
            devices=devices,
        )
        c = res.centreline
        outs.append(
            {
                "s": np.asarray(c.s)[:n],
                "p": np.asarray(c.p)[:n],
                "R": np.asarray(c.R)[:n],
                "rho": np.asarray(c.rho)[:n],
                "ok": np.asarray(res.ok)[:n],
                "residual": np.asarray(res.residual)[:n],
                "energy": np.asarray(res.energy)[:n],
                "num_steps": np.asarray(res.num_steps)[:n],
                "tip_rotvec": np.asarray(rotvec)[:n],
            }
        )
        if bar is not None:
            bar.update(n)
    if bar is not None:
        bar.close()
    out = {k: np.concatenate([o[k] for o in outs]) for k in outs[0]}
    # A row with non-finite joint values never counts as a success.
    out["ok"] = out["ok"].astype(bool) & np.all(np.isfinite(q), axis=1)
    return out


def failure_reasons(model, q: np.ndarray, out: dict) -> dict[int, str]:
    """Row index -> why it failed (ok False): non-finite joint values, joint values outside a
    CTR's limits (``jaxcr.kinematics.ctr_mechanics.telescoping_ok``), no converged solution
    (residual above the robot's tolerance), or a non-finite result."""
    reasons = {}
    tol = getattr(model, "tol", None)
    for i in np.flatnonzero(~out["ok"]):
        if not np.all(np.isfinite(q[i])):
            reasons[int(i)] = "non-finite joint values"
            continue
        if model.kind == "ctr":
            import jax.numpy as jnp

            from jaxcr.kinematics.ctr_mechanics import telescoping_ok

            n = len(np.atleast_1d(model.length))
            tubes = types.SimpleNamespace(length=jnp.asarray(model.length, jnp.float32))
            if not bool(telescoping_ok(tubes, jnp.asarray(q[i, :n], jnp.float32))):
                reasons[int(i)] = (
                    "outside the joint limits (beta_1 <= ... <= beta_n <= 0, every tube "
                    "out of the actuation unit, inner tubes ending beyond outer ones)"
                )
                continue
        r = float(out["residual"][i])
        if tol is not None and not r <= float(tol):
            reasons[int(i)] = f"no converged solution (residual {r:.3g} > tolerance {float(tol):g})"
        elif not np.all(np.isfinite(out["p"][i])):
            reasons[int(i)] = "non-finite centreline"
        else:
            reasons[int(i)] = "kinematics reported failure"
    return reasons


class BatchFk(eqx.Module):
    """Forward kinematics of B joint vectors (numpy arrays; robot frame, metres, radians).

    Attributes
    ----------
    s : np.ndarray
        (B, N) arc length of each centreline sample.
    p : np.ndarray
        (B, N, 3) centreline positions.
    R : np.ndarray
        (B, N, 3, 3) backbone frames (columns: the frame's axes in the robot frame).
    rho : np.ndarray
        (B, N) tube radius at each sample.
    ok : np.ndarray
        (B,) whether the row converged to a valid configuration.
    residual, energy : np.ndarray
        (B,) solver residual and elastic energy (0 for closed-form models).
    num_steps : np.ndarray
        (B,) solver iterations.
    tip_rotvec : np.ndarray
        (B, 3) rotation vector of the tip frame.
    reasons : tuple[str, ...]
        B strings, ``""`` where ``ok``, else why the row failed.

    Examples
    --------
    >>> import numpy as np
    >>> import jaxcr as jcr
    >>> d = {"kind": "single_segment", "length": 0.04, "radius": 0.002, "n_points": 9}
    >>> robot = jcr.robot_from_dict(d)
    >>> q = np.tile([np.pi / 2, 0.0], (2, 1))  # theta_L = pi/2: straight (Reiter et al.)
    >>> fk = jcr.forward(robot, q)
    >>> isinstance(fk, jcr.BatchFk), fk.s.shape == (2, robot.n_points)
    (True, True)
    >>> round(float(fk.p[0, -1, 2]), 6)  # the straight rod's tip at z = length
    0.04
    """

    s: np.ndarray
    p: np.ndarray
    R: np.ndarray
    rho: np.ndarray
    ok: np.ndarray
    residual: np.ndarray
    energy: np.ndarray
    num_steps: np.ndarray
    tip_rotvec: np.ndarray
    reasons: tuple[str, ...]


def forward(
    model, q, *, chunk: int = CHUNK, progress: bool = False, devices: int | None = None
) -> BatchFk:
    """Forward kinematics of every row of ``q`` (B, n_joints), with failure reasons.

    Parameters
    ----------
    model : RobotModel
        a robot model (:func:`jaxcr.robot_from_dict`).
    q : array_like, shape (B, n_joints) or (n_joints,)
        (B, n_joints) joint values (a single (n_joints,) vector is treated as B = 1);
        ``nan`` rows are reported as failed, not raised.
    chunk : int
        rows per compiled batch (one compile per model and chunk size).
    progress : bool
        show a progress bar for more than one chunk.
    devices : int or None
        local devices to spread the rows over (None: all; see :func:`batch_forward`).

    Returns
    -------
    BatchFk
        numpy arrays with a leading axis B and a failure reason per row; for one
        configuration inside ``jax.jit``/``jax.vmap`` use ``model.forward(q)`` directly.

    Examples
    --------
    >>> import numpy as np
    >>> import jaxcr as jcr
    >>> d = {"kind": "single_segment", "length": 0.04, "radius": 0.002, "n_points": 9}
    >>> robot = jcr.robot_from_dict(d)
    >>> fk = jcr.forward(robot, np.array([[0.0, 0.0], [np.nan, 0.0]]))
    >>> fk.p.shape == (2, robot.n_points, 3), fk.ok.tolist()
    (True, [True, False])
    >>> fk.reasons
    ('', 'non-finite joint values')
    """
    q = np.atleast_2d(np.asarray(q, np.float64))
    out = batch_forward(model, q, chunk=chunk, progress=progress, devices=devices)
    why = failure_reasons(model, q, out)
    reasons = tuple(why.get(i, "") for i in range(q.shape[0]))
    return BatchFk(**out, reasons=reasons)
