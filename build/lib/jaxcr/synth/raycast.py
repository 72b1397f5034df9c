"""Exact ray-primitive intersections for the scene renderer (numpy, independent of jaxcr's
estimators: no projection of model points is used to draw anything).

Every function takes ``M`` rays with origins ``o`` (M, 3) and unit directions ``d`` (M, 3)
in one frame (the renderer uses the camera frame, metres) and returns the ray parameter
``t`` (M,) of the first intersection in front of the origin (``t > 0``; distance in metres
along a unit direction) or ``inf`` where the ray misses, plus the outward unit surface
normal (M, 3) at the hit (zeros where missed).
"""

from __future__ import annotations

import numpy as np

INF = np.inf


def ray_sphere(
    o: np.ndarray, d: np.ndarray, centre: np.ndarray, radius: float
) -> tuple[np.ndarray, np.ndarray]:
    """First intersection of rays with a sphere (closed form of |o + t d - c|^2 = r^2)."""
    oc = o - centre
    b = np.einsum("ij,ij->i", oc, d)
    c = np.einsum("ij,ij->i", oc, oc) - radius * radius
    h = b * b - c
    ok = h >= 0.0
    sq = np.sqrt(np.where(ok, h, 0.0))
    t0 = -b - sq
    t1 = -b + sq
    t = np.where(t0 > 0.0, t0, t1)  # origin inside: exit point (the renderer never needs it)
    ok &= t > 0.0
    t = np.where(ok, t, INF)
    p = o + np.where(ok, t, 0.0)[:, None] * d
    n = np.where(ok[:, None], (p - centre) / radius, 0.0)
    return t, n


def ray_capsule(
    o: np.ndarray, d: np.ndarray, a: np.ndarray, b: np.ndarray, radius: float
) -> tuple[np.ndarray, np.ndarray]:
    """First intersection of rays with the capsule {x : dist(x, segment ab) <= radius}.

    Closed form: the infinite cylinder about ``ab`` gives a quadratic in ``t``; if its entry
    point projects inside the segment it is the hit, otherwise the ray can only enter through
    the hemispherical cap on that side (the capsule lies inside the infinite cylinder), which
    is a sphere quadratic. Rays starting inside the capsule are reported as misses.
    """
    ba = b - a
    oa = o - a
    baba = float(ba @ ba)
    if baba <= (1e-9 * radius) ** 2:  # degenerate segment: a sphere
        return ray_sphere(o, d, 0.5 * (a + b), radius)
    bard = d @ ba
    baoa = oa @ ba
    rdoa = np.einsum("ij,ij->i", d, oa)
    oaoa = np.einsum("ij,ij->i", oa, oa)
    qa = baba - bard * bard
    qb = baba * rdoa - baoa * bard
    qc = baba * oaoa - baoa * baoa - radius * radius * baba
    h = qb * qb - qa * qc
    hit_inf = h >= 0.0
    # Ray parallel to the axis (qa ~ 0): the body cannot be entered, only the caps.
    par = qa <= 1e-12 * baba
    safe_qa = np.where(par, 1.0, qa)
    t_body = (-qb - np.sqrt(np.where(hit_inf, h, 0.0))) / safe_qa
    y = baoa + t_body * bard
    body = hit_inf & ~par & (y > 0.0) & (y < baba)
    # Cap: the side where the cylinder entry left the segment (parallel rays: pick by bard).
    y_side = np.where(par, -bard, y)
    cap_centre_is_a = y_side <= 0.0
    oc = np.where(cap_centre_is_a[:, None], oa, o - b)
    cb = np.einsum("ij,ij->i", d, oc)
    cc = np.einsum("ij,ij->i", oc, oc) - radius * radius
    ch = cb * cb - cc
    cap = (hit_inf | par) & ~body & (ch >= 0.0)
    t_cap = -cb - np.sqrt(np.where(cap, ch, 0.0))
    t = np.where(body, t_body, np.where(cap, t_cap, INF))
    t = np.where(t > 0.0, t, INF)
    hit = np.isfinite(t)
    p = o + np.where(hit, t, 0.0)[:, None] * d
    w = np.clip(((p - a) @ ba) / baba, 0.0, 1.0)
    n = (p - (a + w[:, None] * ba)) / radius
    n = np.where(hit[:, None], n, 0.0)
    return t, n


def ray_box(
    o: np.ndarray,
    d: np.ndarray,
    centre: np.ndarray,
    axes: np.ndarray,
    half: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """First intersection of rays with an oriented box (slab method).

    ``axes`` (3, 3) holds the box's unit axes as columns; ``half`` (3,) the half extents.
    """
    lo = (o - centre) @ axes  # origins in the box frame
    ld = d @ axes
    m = len(ld)
    t_near = np.full(m, -np.inf)
    t_far = np.full(m, np.inf)
    face = np.zeros(m, np.int64)
    face_sign = np.zeros(m)
    for k in range(3):
        dk = ld[:, k]
        ok = np.abs(dk) > 1e-15
        inv = 1.0 / np.where(ok, dk, 1.0)
        t1 = (-half[k] - lo[:, k]) * inv
        t2 = (half[k] - lo[:, k]) * inv
        # A ray parallel to the slab is inside it for all t, or never.
        inside = np.abs(lo[:, k]) <= half[k]
        tmin = np.where(ok, np.minimum(t1, t2), np.where(inside, -np.inf, np.inf))
        tmax = np.where(ok, np.maximum(t1, t2), np.where(inside, np.inf, -np.inf))
        upd = tmin > t_near
        t_near = np.where(upd, tmin, t_near)
        face = np.where(upd, k, face)
        face_sign = np.where(upd, -np.sign(dk), face_sign)
        t_far = np.minimum(t_far, tmax)
    hit = (t_near <= t_far) & (t_near > 0.0)
    t = np.where(hit, t_near, INF)
    n = axes[:, face].T * face_sign[:, None]
    n = np.where(hit[:, None], n, 0.0)
    return t, n


def ray_plane(
    o: np.ndarray, d: np.ndarray, point: np.ndarray, normal: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Intersection of rays with an infinite plane (hit only from its front side)."""
    denom = d @ normal
    front = denom < -1e-9
    t = np.where(front, ((point - o) @ normal) / np.where(front, denom, -1.0), INF)
    t = np.where(t > 0.0, t, INF)
    n = np.where(np.isfinite(t)[:, None], normal[None, :], 0.0)
    return t, n
