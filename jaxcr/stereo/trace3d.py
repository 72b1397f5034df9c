"""Stereo-coupled 3-D tracing of a tube's backbone (issue 16 item 2, docs/decisions.md S26).

Not called by the pipeline: on real_like development neither use of it won (S26; the hook
that was measured is at commit 1e5b703). It is kept, tested, as the start of a 3-D fit
of both views' traces.

Each view's 2-D tracer (:func:`jaxcr.segmentation.foreground.plate_foreground`) follows
whatever its own foreground supports, so a structure seen in one view only (a crossing
cable, a board's black tape, a crease or a shadow) can carry it away from the tube. Here
the backbone is marched in 3-D instead, from the base (the two entry pixels triangulated),
in steps of about one tube width: at each step the candidate directions in a cone bounded
by a maximum curvature are scored by the support of their projected segment in *both*
views' per-pixel evidence (the views' cue scores, clipped at the hysteresis ``high`` level
and smoothed across the tube), the smaller of the two views' mean evidence along the
segment. A stretch seen by one view only therefore cannot carry the path. A beam of the
best paths is kept (accumulated support less a penalty on changes of the turn: the tubes
of a concentric-tube robot bend with piecewise-constant curvature, a path that turns onto
a crossing object changes its turn abruptly); a path bridges stretches where the evidence
is missing in straight steps, up to a given gap length, and ends where no candidate is
supported. Where the tube runs along the epipolar lines its depth is ambiguous, which does
not matter here: what is used is the path's projections, which stay on the tube in both
views.

Pure numpy (host side, float64), per frame; the cameras are objects with ``K`` (3x3),
``dist`` (OpenCV ``k1, k2, p1, p2[, k3]``) and ``T_cam_robot`` (4x4) in a frame both
share.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage as ndi

__all__ = ["Trace3D", "Trace3DConfig", "project", "trace_backbone_3d", "undistort"]


@dataclass(frozen=True)
class Trace3DConfig:
    """Settings of :func:`trace_backbone_3d` (docs/decisions.md S26).

    ``step_widths`` (1.0): the 3-D step, in tube widths (the views' mean traced width at
    the base's depth). ``max_curvature`` (200 1/m, a bend radius of 5 mm): the largest
    turn per step is ``step * max_curvature`` rad (the ``real_like`` preset's tightest
    hook turns 250 deg over 22 mm, :func:`jaxcr.synth.stereo_ctr.sample_robot`).
    ``ring_points`` (6, 10, 14): the candidate directions, the predicted direction and
    rings at 1/3, 2/3 and 3/3 of that turn about it. ``beam`` (8): paths kept (new points
    closer than half a step to a kept one dropped). ``samples`` (6): points per step where
    the evidence is read. ``support`` (0.5): the smaller of the two views' mean evidence
    along a step for it to be on the tube. A path's score adds per supported step its
    support less ``baseline`` (0.5) less ``turn_penalty`` (1.0) x (change of the turn /
    the largest turn)^2; the turn predicted is the path's mean turn per step over its
    last ``2 turn_span`` (4) steps (the circle through three of its points). A path none
    of whose candidates is supported bridges a gap in straight steps along its chord over
    ``gap_chord`` (4) steps, each costing ``gap_cost`` (0.25), up to ``max_gap_px`` (80
    at a ``gap_width_ref_px`` (7) px tube, scaled with the width: the 2-D tracer's
    ``max_gap_px``). ``blur_widths`` (0.25): the evidence (the score clipped at the seed
    level) is smoothed by a Gaussian of this many widths. ``recentre`` (0.3): each new
    point is moved across its step by up to this many steps to where the two views'
    support is largest. ``start_directions`` (400): the sphere of start directions
    scored when no start direction is given. ``max_steps`` (400)."""

    step_widths: float = 1.0
    max_curvature: float = 200.0
    ring_points: tuple = (6, 10, 14)
    beam: int = 8
    samples: int = 6
    support: float = 0.5
    turn_penalty: float = 1.0
    baseline: float = 0.5
    gap_cost: float = 0.25
    max_gap_px: float = 80.0
    gap_width_ref_px: float = 7.0
    blur_widths: float = 0.25
    start_directions: int = 400
    max_steps: int = 400
    recentre: float = 0.3
    gap_chord: int = 4
    turn_span: int = 4


@dataclass
class Trace3D:
    """Result of :func:`trace_backbone_3d`: ``points`` (n, 3) the backbone from the base to
    its supported end (the cameras' frame, metres); ``pixels`` per view (n, 2) its
    projections (distorted (u, v)); ``end_px`` per view (2,) the end's projection;
    ``support`` (n - 1,) each step's support; ``score`` the path's accumulated score;
    ``step_m`` the step length (m); ``reason`` None or why no path was traced."""

    points: np.ndarray
    pixels: list
    end_px: list
    support: np.ndarray
    score: float
    step_m: float
    reason: str | None = None


def _dist5(cam) -> np.ndarray:
    d = np.zeros(5)
    src = np.asarray(cam.dist, np.float64).ravel()[:5]
    d[: len(src)] = src
    return d


def project(cam, X) -> np.ndarray:
    """Distorted pixels (..., 2) of points ``X`` (..., 3) through ``cam`` (OpenCV's pinhole
    with radial ``k1, k2, k3`` and tangential ``p1, p2`` distortion, as
    ``cv2.projectPoints``). Points behind the camera give NaN."""
    X = np.asarray(X, np.float64)
    T = np.asarray(cam.T_cam_robot, np.float64)
    Xc = X @ T[:3, :3].T + T[:3, 3]
    z = Xc[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        x, y = Xc[..., 0] / z, Xc[..., 1] / z
    k1, k2, p1, p2, k3 = _dist5(cam)
    r2 = x * x + y * y
    rad = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    K = np.asarray(cam.K, np.float64)
    u = K[0, 0] * xd + K[0, 1] * yd + K[0, 2]
    v = K[1, 1] * yd + K[1, 2]
    out = np.stack([u, v], -1)
    return np.where((z > 0)[..., None], out, np.nan)


def undistort(cam, uv, iterations: int = 20) -> np.ndarray:
    """Normalised image coordinates (n, 2) (``x/z, y/z`` in the camera frame) of distorted
    pixels ``uv`` (n, 2): the distortion inverted by fixed-point iteration (as OpenCV's
    ``undistortPoints``; converges for webcam distortions, |k1| r^2 << 1)."""
    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    K = np.asarray(cam.K, np.float64)
    yd = (uv[:, 1] - K[1, 2]) / K[1, 1]
    xd = (uv[:, 0] - K[0, 2] - K[0, 1] * yd) / K[0, 0]
    k1, k2, p1, p2, k3 = _dist5(cam)
    x, y = xd.copy(), yd.copy()
    for _ in range(iterations):
        r2 = x * x + y * y
        rad = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        x = (xd - 2 * p1 * x * y - p2 * (r2 + 2 * x * x)) / rad
        y = (yd - p1 * (r2 + 2 * y * y) - 2 * p2 * x * y) / rad
    return np.stack([x, y], 1)


def _triangulate(cams, uvs) -> np.ndarray:
    """The point (3,) seen at distorted pixels ``uvs[k]`` in ``cams[k]`` (linear DLT on
    normalised coordinates)."""
    rows = []
    for cam, uv in zip(cams, uvs, strict=True):
        x = undistort(cam, uv)[0]
        P = np.asarray(cam.T_cam_robot, np.float64)[:3]
        rows += [x[0] * P[2] - P[0], x[1] * P[2] - P[1]]
    _, _, vt = np.linalg.svd(np.asarray(rows))
    h = vt[-1]
    return h[:3] / h[3]


def _evidence(score, high: float, width: float, blur_widths: float) -> np.ndarray:
    """The score clipped at ``high`` and scaled to [0, 1], smoothed by a Gaussian of
    ``blur_widths * width`` px and divided by the smoothed level on the axis of a tube of
    that width (``erf(1 / (2 sqrt(2) blur_widths))``), so that a tube's axis reads 1 and
    its edges about a half."""
    from math import erf, sqrt

    e = np.clip(np.asarray(score, np.float32) / np.float32(high), 0.0, 1.0)
    if blur_widths <= 0:
        return e
    e = ndi.gaussian_filter(e, blur_widths * width)
    return np.minimum(e / np.float32(erf(1.0 / (2.0 * sqrt(2.0) * blur_widths))), 1.0)


def _sample(E, uv) -> np.ndarray:
    """Bilinear samples of ``E`` (H, W) at ``uv`` (..., 2); 0 outside or at NaN."""
    shp = uv.shape[:-1]
    u, v = uv[..., 0].ravel(), uv[..., 1].ravel()
    ok = np.isfinite(u) & np.isfinite(v)
    out = np.zeros(u.shape)
    out[ok] = ndi.map_coordinates(E, [v[ok], u[ok]], order=1, mode="constant", cval=0.0)
    return out.reshape(shp)


def _frame(d) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors (..., 3) orthogonal to the unit ``d`` (..., 3) and to each other."""
    a = np.where(np.abs(d[..., :1]) < 0.9, np.array([1.0, 0, 0]), np.array([0, 1.0, 0]))
    e1 = np.cross(d, a)
    e1 /= np.linalg.norm(e1, axis=-1, keepdims=True)
    return e1, np.cross(d, e1)


def _cone(angle: float, ring_points) -> np.ndarray:
    """Directions (C, 3) in a cone of half-angle ``angle`` about +z: the axis and rings."""
    out = [np.array([0.0, 0.0, 1.0])]
    n = len(ring_points)
    for i, m in enumerate(ring_points):
        th = angle * (i + 1) / n
        ph = np.arange(m) * 2 * np.pi / m + (i % 2) * np.pi / m
        out += list(np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph),
                              np.full(m, np.cos(th))], 1))  # fmt: skip
    return np.asarray(out)


def _fibonacci(n: int) -> np.ndarray:
    i = np.arange(n) + 0.5
    z = 1 - 2 * i / n
    r = np.sqrt(1 - z * z)
    ph = np.pi * (1 + 5**0.5) * i
    return np.stack([r * np.cos(ph), r * np.sin(ph), z], 1)


def _rotate(v, axis, ang) -> np.ndarray:
    """Rodrigues: ``v`` (..., 3) rotated by ``ang`` (...) about unit ``axis`` (..., 3)."""
    c, s = np.cos(ang)[..., None], np.sin(ang)[..., None]
    return v * c + np.cross(axis, v) * s + axis * np.sum(axis * v, -1, keepdims=True) * (1 - c)


def _support(cams, Es, P, D, step, t):
    """Per view mean evidence (V, ...) along segments from ``P`` (..., 3) in ``D`` (..., 3)."""
    pts = P[..., None, :] + step * t[:, None] * D[..., None, :]
    return np.stack([_sample(E, project(c, pts)).mean(-1) for c, E in zip(cams, Es, strict=True)])


def _plane_direction(cams, entries, ahead) -> np.ndarray | None:
    """The 3-D direction (3,) from the base seen from ``entries[k]`` towards ``ahead[k]``
    in both views: the line of the two planes through each camera's centre and the two
    pixels; None when the planes are within 10 deg of each other (the direction lies
    near an epipolar plane)."""
    normals = []
    for cam, a, b in zip(cams, entries, ahead, strict=True):
        x = undistort(cam, np.stack([a, b]))
        n_cam = np.cross(np.r_[x[0], 1.0], np.r_[x[1], 1.0])
        R = np.asarray(cam.T_cam_robot, np.float64)[:3, :3]
        normals.append(R.T @ (n_cam / np.linalg.norm(n_cam)))
    d = np.cross(normals[0], normals[1])
    if np.linalg.norm(d) < np.sin(np.radians(10)):
        return None
    d /= np.linalg.norm(d)
    # The sign: the one whose projection runs from the entry towards ``ahead`` in view 1.
    base = _triangulate(cams, entries)
    uv = project(cams[0], np.stack([base, base + 1e-3 * d]))
    return d if float((uv[1] - uv[0]) @ (np.asarray(ahead[0]) - np.asarray(entries[0]))) > 0 else -d


def _turn(a, b) -> np.ndarray:
    """The rotation (axis times angle, (3,)) taking unit ``a`` to unit ``b``."""
    axis = np.cross(a, b)
    sn = np.linalg.norm(axis)
    return axis / sn * np.arctan2(sn, float(a @ b)) if sn > 1e-12 else np.zeros(3)


def _chord(pts, n: int, fallback) -> np.ndarray:
    """Unit direction from the path's point ``n`` steps back to its last point
    (``fallback`` for a path of one point)."""
    m = min(n, len(pts) - 1)
    if m < 1:
        return np.asarray(fallback, np.float64)
    d = pts[-1] - pts[-1 - m]
    return d / max(float(np.linalg.norm(d)), 1e-15)


def _mean_turn(pts, span: int) -> np.ndarray:
    """The turn per step (axis times angle) over the path's last ``span`` steps: the
    rotation from the direction ``span`` steps back to the last one, divided by ``span``
    (a constant-curvature section turns by the same rotation per step; one step's turn is
    noisy)."""
    if len(pts) >= 2 * span + 1:
        # The circle through the points 2 span, span and 0 steps back: its curvature
        # about its normal, times the mean step (robust to one step's wobble).
        a, b, c = pts[-1 - 2 * span], pts[-1 - span], pts[-1]
        ab, bc, ac = b - a, c - b, c - a
        cr = np.cross(ab, bc)
        nc = float(np.linalg.norm(cr))
        if nc < 1e-15:
            return np.zeros(3)
        kappa = 2.0 * nc / (np.linalg.norm(ab) * np.linalg.norm(bc) * np.linalg.norm(ac))
        return cr / nc * kappa * float(np.linalg.norm(ac)) / (2 * span)
    n = min(span, len(pts) - 2)
    if n < 1:
        return np.zeros(3)
    a = pts[-1 - n] - pts[-2 - n]
    b = pts[-1] - pts[-2]
    return _turn(a / np.linalg.norm(a), b / np.linalg.norm(b)) / n


def _recentre(cams, Es, paths, step, t, reach):
    """Each path's new point moved across its step (a 5 x 5 grid of offsets up to ``reach``
    steps, perpendicular to the step) to where the smaller of the two views' mean evidence
    along the step is largest: both projections kept on the tube's axis, as the 2-D
    tracer re-centres (a path drifting in depth leaves the axis in one view first)."""
    P0 = np.stack([b["pts"][-2] for b in paths])
    Q = np.stack([b["pts"][-1] for b in paths])
    d = Q - P0
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    e1, e2 = _frame(d)
    g = np.linspace(-reach, reach, 5) * step
    a, b_ = np.meshgrid(g, g, indexing="ij")
    off = a.ravel()[None, :, None] * e1[:, None] + b_.ravel()[None, :, None] * e2[:, None]
    cand = Q[:, None] + off  # (K, 25, 3)
    seg = cand - P0[:, None]
    pts = P0[:, None, None] + seg[:, :, None] * t[None, None, :, None]
    sv = np.stack([_sample(E, project(c, pts)).mean(-1) for c, E in zip(cams, Es, strict=True)])
    sup = sv.min(0)  # (K, 25)
    best = np.argmax(sup, axis=1)
    for k, b in enumerate(paths):
        if b["gap"] > 0:  # a bridged step has nothing to centre on
            continue
        q = cand[k, best[k]]
        dn = (q - P0[k]) / np.linalg.norm(q - P0[k])
        b["pts"][-1] = q
        b["D"] = dn
    return paths


def trace_backbone_3d(
    cams, scores, entries, width_px: float, *, ahead=None, masks=None, high: float = 1.0,
    cfg: Trace3DConfig = Trace3DConfig(),
) -> Trace3D:  # fmt: skip
    """The tube's backbone traced in 3-D from its base, scored in both views at once.

    ``cams``: the two calibrated cameras. ``scores``: per view the cue score (H, W) of the
    plate foreground (:attr:`jaxcr.segmentation.foreground.TubeTrace.score`; ``high`` its
    hysteresis seed level). ``entries``: per view the entry pixel (distorted (u, v)), the
    base's projection. ``width_px``: the tube's width in pixels (the views' traced width).
    The method is in the module docstring; the settings in :class:`Trace3DConfig`.

    Returns a :class:`Trace3D` whose path ends at the last supported step, refined to a
    quarter step along its last direction (the last quarter step whose point has both
    views' evidence at least ``support``)."""
    w = float(width_px)
    base = _triangulate(cams, entries)
    depth = [float((np.asarray(c.T_cam_robot)[:3, :3] @ base + np.asarray(c.T_cam_robot)[:3, 3])[2])
             for c in cams]  # fmt: skip
    fpx = [float(np.asarray(c.K)[0, 0]) for c in cams]
    step = cfg.step_widths * w * min(z / f for z, f in zip(depth, fpx, strict=True))
    if masks is not None:  # the evidence kept on the given structures only
        scores = [np.where(m, s, 0.0) for s, m in zip(scores, masks, strict=True)]
    Es = [_evidence(s, high, w, cfg.blur_widths) for s in scores]
    t = (np.arange(cfg.samples) + 1.0) / cfg.samples
    cone = cfg.max_curvature * step
    local = _cone(cone, cfg.ring_points)
    ring_of = np.concatenate([[0]] + [[i + 1] * m for i, m in enumerate(cfg.ring_points)])
    max_gap = cfg.max_gap_px * w / cfg.gap_width_ref_px * step / (cfg.step_widths * w)

    # Start: the directions of a sphere scored over two steps, the best distinct ones kept;
    # with ``ahead`` given, the direction the two views' first stretches triangulate to
    # and the cone about it.
    dirs = _fibonacci(cfg.start_directions)
    if ahead is not None:
        d0 = _plane_direction(cams, entries, ahead)
        if d0 is not None:
            e1, e2 = _frame(d0)
            dirs = local[:, :1] * e1 + local[:, 1:2] * e2 + local[:, 2:] * d0
    s0 = _support(cams, Es, base[None], dirs, 2 * step, t).min(0)
    order = np.argsort(-s0)
    keep = []
    for i in order:
        if s0[i] < cfg.support or len(keep) == cfg.beam:
            break
        if all(float(dirs[i] @ dirs[j]) < np.cos(cone / 2) for j in keep):
            keep.append(int(i))
    if not keep:
        return Trace3D(base[None], [project(c, base[None]) for c in cams],
                       [project(c, base) for c in cams], np.zeros(0), 0.0, step,
                       "no supported direction at the base")  # fmt: skip
    # Beam state per path: points, supports, direction, last turn (axis * angle), score,
    # gap length, index of its last supported point.
    beam = [dict(pts=[base], sup=[], D=dirs[i], turn=np.zeros(3),
                 score=0.0, gap=0.0, last=0)
            for i in keep]  # fmt: skip
    best = (0.0, beam[0]["pts"][:1], [])
    for _ in range(cfg.max_steps):
        if not beam:
            break
        D = np.stack([b["D"] for b in beam])  # (K, 3)
        P = np.stack([b["pts"][-1] for b in beam])
        # The candidates: a cone about the previous turn continued (a constant-curvature
        # section followed at no change), within the largest turn per step from D.
        tv = np.stack([b["turn"] for b in beam])
        ang = np.linalg.norm(tv, axis=1)
        ax = np.where(ang[:, None] > 1e-12, tv / np.maximum(ang, 1e-12)[:, None], 0.0)
        pred = _rotate(D, ax, ang)
        e1, e2 = _frame(pred)
        C = (local[None, :, :1] * e1[:, None] + local[None, :, 1:2] * e2[:, None]
             + local[None, :, 2:] * pred[:, None])  # (K, C, 3)  # fmt: skip
        within = np.einsum("kcj,kj->kc", C, D) >= np.cos(cone) - 1e-9
        sup = _support(cams, Es, P[:, None], C, step, t).min(0)  # (K, C)
        change = np.arccos(np.clip(np.einsum("kcj,kj->kc", C, pred), -1, 1))
        pen = cfg.turn_penalty * (change / max(cone, 1e-9)) ** 2
        gain = sup - cfg.baseline - pen
        ok = (sup >= cfg.support) & within
        gaps = np.array([b["gap"] for b in beam])
        # A path none of whose candidates is supported bridges a gap, in straight steps
        # (the cone's axis and first ring), up to max_gap.
        bridge = (~ok) & within & (ring_of[None] <= 1) & (gaps[:, None] + step <= max_gap)
        bridge &= ~ok.any(1, keepdims=True)
        new_pts = P[:, None] + step * C
        # No path may come back onto itself (a U-turn along its own tube).
        for k, b in enumerate(beam):
            if len(b["pts"]) > 3:
                old = np.asarray(b["pts"][:-3])
                dmin = np.min(np.linalg.norm(new_pts[k][:, None] - old[None], axis=2), axis=1)
                near = dmin < 0.7 * step
                ok[k] &= ~near
                bridge[k] &= ~near
        # A gap is bridged along the path's chord over its last steps (one step at a gap's
        # edge may have turned onto the edge): the candidates near the predicted direction
        # are replaced by the same cone about the chord.
        chord = np.stack([_chord(b["pts"], cfg.gap_chord, b["D"]) for b in beam])
        g1, g2 = _frame(chord)
        Cg = (local[None, :, :1] * g1[:, None] + local[None, :, 1:2] * g2[:, None]
              + local[None, :, 2:] * chord[:, None])  # fmt: skip
        C = np.where(bridge[..., None], Cg, C)
        new_pts = P[:, None] + step * C
        score = np.array([b["score"] for b in beam])[:, None]
        val = np.where(ok, score + gain, -np.inf)
        val = np.where(bridge, score - cfg.gap_cost, val)  # ranked below supported steps
        flat = np.argsort(-val, axis=None)
        nxt, taken = [], []
        for f in flat:
            k, c = divmod(int(f), val.shape[1])
            if not np.isfinite(val[k, c]) or len(nxt) == cfg.beam:
                break
            q = new_pts[k, c]
            if any(np.linalg.norm(q - p) < 0.5 * step for p in taken):
                continue
            b = beam[k]
            d_new = C[k, c]
            turn = _turn(b["D"], d_new) if cfg.turn_span == 0 else b["turn"]
            on = bool(ok[k, c])
            nb = dict(pts=b["pts"] + [q], sup=b["sup"] + [float(sup[k, c])], D=d_new,
                      turn=turn,
                      score=float(val[k, c]) if on else b["score"],
                      gap=0.0 if on else b["gap"] + step,
                      last=len(b["pts"]) if on else b["last"])  # fmt: skip
            nxt.append(nb)
            taken.append(q)
        if nxt and cfg.recentre:
            nxt = _recentre(cams, Es, nxt, step, t, cfg.recentre)
        if cfg.turn_span > 0:
            for nb in nxt:
                nb["turn"] = _mean_turn(nb["pts"], cfg.turn_span)
        beam = nxt
        for nb in beam:
            if nb["gap"] == 0 and nb["score"] > best[0]:
                best = (nb["score"], list(nb["pts"]), list(nb["sup"]))
    score, pts, sups = best
    pts = np.asarray(pts)
    if len(pts) >= 2:  # the end refined to a quarter step along the last direction
        d = pts[-1] - pts[-2]
        d /= np.linalg.norm(d)
        fr = np.arange(1, 9) * 0.25 * step
        cand = pts[-1] + fr[:, None] * d
        ev = np.stack([_sample(E, project(c, cand)) for c, E in zip(cams, Es, strict=True)]).min(0)
        run = np.cumprod(ev >= cfg.support)
        if run.sum() > 0:
            pts = np.vstack([pts, cand[int(run.sum()) - 1]])
    pixels = [project(c, pts) for c in cams]
    return Trace3D(pts, pixels, [p[-1] for p in pixels], np.asarray(sups), float(score), step)


def _cut_and_refine(trace, backbone):
    """``trace`` (a :class:`jaxcr.segmentation.foreground.TubeTrace` with ``retrace``
    state) ending on ``backbone`` (n, 2) instead, its tip placed there as
    :func:`jaxcr.segmentation.foreground.plate_foreground` places it (the end face,
    docs/decisions.md S15; the end on the axis, S20)."""
    from dataclasses import replace

    from jaxcr.segmentation.foreground import _scaled, refine_tip_details

    ctx = trace.retrace
    tip, cap, d, hw = refine_tip_details(
        ctx.score, backbone, trace.width_px, _scaled(ctx.cfg, ctx.k)
    )
    return replace(trace, backbone=np.vstack([backbone[:-1], tip]), tip=tip, cap_px=cap,
                   end_dir=d, end_half_width_px=hw, junctions=[], departure=None)  # fmt: skip


def finish_on_path(cands, end_px, path_px, *, near_widths: float = 1.5):
    """One view's trace ending where the 3-D path ends (``end_px``, its projection; the
    path's projection ``path_px`` (n, 2)): of the view's traces ``cands`` (its trace and
    its alternatives, :func:`jaxcr.segmentation.foreground.trace_alternatives`), the one
    whose tip is nearest ``end_px`` when within ``near_widths`` tube widths of it (kept as
    it is); else the trace whose path passes nearest ``end_px`` (within half a width), cut
    there and its end placed again; else the path's own projection given an end there.
    Returns (the trace, how: ``"kept"``, ``"cut"`` or ``"path"``)."""
    end = np.asarray(end_px, np.float64)
    w = float(np.mean([c.width_px for c in cands]))
    dt = [float(np.linalg.norm(np.asarray(c.tip) - end)) for c in cands]
    i = int(np.argmin(dt))
    if dt[i] <= near_widths * w:
        return cands[i], "kept"
    best = None
    for c in cands:
        bb = np.asarray(c.backbone, np.float64)
        dd = np.linalg.norm(bb - end, axis=1)
        j = int(np.argmin(dd))
        if dd[j] <= 0.5 * w and j >= 2 and (best is None or dd[j] < best[0]):
            best = (dd[j], c, j)
    if best is not None:
        _, c, j = best
        return _cut_and_refine(c, np.asarray(c.backbone, np.float64)[: j + 1]), "cut"
    pp = np.asarray(path_px, np.float64)
    pp = pp[np.all(np.isfinite(pp), axis=1)]
    seg = np.linalg.norm(np.diff(pp, axis=0), axis=1)
    s = np.r_[0.0, np.cumsum(seg)]
    ss = np.arange(0.0, s[-1] + 1e-9, 2.0)
    dense = np.stack([np.interp(ss, s, pp[:, 0]), np.interp(ss, s, pp[:, 1])], 1)
    return _cut_and_refine(cands[0], dense), "path"


def _ahead_px(trace, widths: float = 3.0) -> np.ndarray:
    """The point of ``trace``'s backbone ``widths`` tube widths from its entry."""
    bb = np.asarray(trace.backbone, np.float64)
    s = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(bb, axis=0), axis=1))]
    return bb[min(int(np.searchsorted(s, widths * trace.width_px)), len(bb) - 1)]


def path_of_traces(cams, traces, cfg: Trace3DConfig = Trace3DConfig()) -> Trace3D:
    """:func:`trace_backbone_3d` on two views' traces
    (:class:`jaxcr.segmentation.foreground.TubeTrace` with ``retrace`` state): their
    full-resolution cue scores, entry pixels, mean width, the start direction from their
    first three widths, the foreground's ``high`` level."""
    return trace_backbone_3d(
        cams, [t.retrace.score for t in traces], [t.entry for t in traces],
        float(np.mean([t.width_px for t in traces])),
        ahead=[_ahead_px(t) for t in traces], high=traces[0].retrace.cfg.high, cfg=cfg,
    )  # fmt: skip
