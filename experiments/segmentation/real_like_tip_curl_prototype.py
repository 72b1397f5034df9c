"""Prototype for the next round of issue 16 item 2 (stop 37; measured, not in the product): a
tube end whose axis curls, fitted to one view's cue score.

Round 18's fresh failures (real_like 4470-4559, now released) are mostly tips that curl at
their end: the silhouette's end is the curl's apex and the tip lies beyond it, sideways or
back, where the end-direction refinement (``refine_tip_details``) and the capsule end fit
(``capsule_end``, straight end with a slight bend behind) cannot put it. Model here: from
an anchor on the traced path two tube widths behind its end (direction from the path), the
axis runs straight for ``L0`` then on an arc of curvature ``k`` for ``L1``; the silhouette is
the band of half width ``r`` round that axis (distance to the sampled axis,
``scipy.spatial.cKDTree``) and the half-ellipse end face of length ``a`` beyond its end,
drawn nearly sharp, blurred, scaled between a background and an inside level; fitted by
robust least squares (three starts: straight, and curving 0.8/r either way). The tip is the
axis' end. Per view it prints the one-view trace's tip error, the capsule fit's (None where
its gates refuse) and this fit's, against the rendered truth, and the same model fitted with ``k = 0`` (``straight``) and the
ratio of the curled fit's cost to the straight one's (a test that could choose between them).

    python experiments/segmentation/real_like_tip_curl_prototype.py 4501:1 4520:1 ...

(``SEED:VIEW``, view 0 or 1; frames from the caches of real_like_tip.py: /tmp/f37/cache for
seeds >= 4470, /tmp/f36/cache for 4380-4469, /tmp/dev/cache below.) Output of the stop-37
run: experiments/results/segmentation/real_like_tip_curl_prototype.md. About 7 s a view.
"""

import pickle
import sys

import numpy as np
from scipy import ndimage as ndi
from scipy.optimize import least_squares
from scipy.special import ndtr

from jaxcr.segmentation.capsule_end import fit_capsule_end
from jaxcr.segmentation.foreground import plate_foreground


def centreline(P0, th0, L0, k, L1, step=0.5):
    s0 = np.arange(0, L0 + 1e-9, step)
    pts = [P0 + s0[:, None] * np.array([np.cos(th0), np.sin(th0)])]
    E = P0 + L0 * np.array([np.cos(th0), np.sin(th0)])
    s1 = np.arange(step, L1 + 1e-9, step)
    if abs(k) < 1e-6:
        th = th0 + 0 * s1
        q = E + s1[:, None] * np.array([np.cos(th0), np.sin(th0)])
    else:
        th = th0 + k * s1
        q = E + np.stack([(np.sin(th) - np.sin(th0)) / k, -(np.cos(th) - np.cos(th0)) / k], 1)
    pts.append(q)
    bb = np.vstack(pts)
    th_end = th0 + k * L1
    return bb, th_end


def model_cover(p, P0, th0, U, V, step):
    L0, k, L1, r, a, sig, dth, doff = p[:8]
    n0 = np.array([-np.sin(th0), np.cos(th0)])
    bb, th_end = centreline(P0 + doff * n0, th0 + dth, L0, k, L1)
    X = np.stack([U.ravel(), V.ravel()], 1)
    from scipy.spatial import cKDTree

    dist, j = cKDTree(bb).query(X)
    e = bb[-1]
    de = np.array([np.cos(th_end), np.sin(th_end)])
    ne = np.array([-de[1], de[0]])
    x = (X - e) @ de
    y = (X - e) @ ne
    a = max(a, 1e-3)
    xp = np.maximum(x, 0)
    rho = np.sqrt((xp / a) ** 2 + (y / r) ** 2)
    grad = np.sqrt((xp / a**2) ** 2 + (y / r**2) ** 2) / np.maximum(rho, 1e-9)
    cap = np.where(x > 0, (rho - 1) / np.maximum(grad, 1e-9), np.abs(y) - r)
    band = np.where(j == len(bb) - 1, cap, dist - r)
    sd = band.reshape(U.shape)
    cover = ndtr(-sd / 0.25)
    return ndi.gaussian_filter(cover, max(sig, 0.3) / step, mode="nearest"), bb[-1]


def fit_curl(score, tr, w, step=1.0, straight=False):
    bb = np.asarray(tr.backbone, float)
    seg = np.r_[0, np.cumsum(np.linalg.norm(np.diff(bb, axis=0), axis=1))]
    back = 2.0 * w
    i0 = int(np.searchsorted(seg, seg[-1] - back))
    P0 = bb[i0]
    i1 = min(i0 + 3, len(bb) - 1)
    d = bb[i1] - bb[max(i0 - 3, 0)]
    th0 = np.arctan2(d[1], d[0])
    c = (P0 + bb[-1]) / 2
    R = 0.5 * back + 2.0 * w
    xs = np.arange(-R, R + 1e-9, step)
    U, V = np.meshgrid(c[0] + xs, c[1] + xs)
    g = ndi.map_coordinates(score, [V, U], order=1, mode="nearest")
    s_in = np.percentile(g, 95)
    s_bg = np.median(g)
    best = None
    L = seg[-1] - seg[i0]
    for k0 in (0.0,) if straight else (0.0, 0.8 / (w / 2), -0.8 / (w / 2)):
        for frac in (0.6,):
            p0 = np.array(
                [frac * L, k0, (1 - frac) * L + 0.5 * w, w / 2, w / 4, 1.2, 0.0, 0.0, s_in, s_bg]
            )
            kmax = 1e-9 if straight else 2.0 / (w / 2)  # straight: the same model, k = 0
            lo = [0, -kmax, 0.5, 0.3 * w, 0.05, 0.3, -0.5, -w / 2, -np.inf, -np.inf]
            hi = [2 * L + w, kmax, 3 * w, 0.8 * w, w / 2, 3.0, 0.5, w / 2, np.inf, np.inf]

            def res(p):
                cov, _ = model_cover(p, P0, th0, U, V, step)
                return (p[9] + (p[8] - p[9]) * cov - g).ravel()

            try:
                sol = least_squares(
                    res,
                    np.clip(p0, lo, hi),
                    bounds=(lo, hi),
                    loss="soft_l1",
                    f_scale=0.1 * (s_in - s_bg),
                    max_nfev=40,
                )
            except Exception:
                continue
            if best is None or sol.cost < best.cost:
                best = sol
    _, tip = model_cover(best.x, P0, th0, U, V, step)
    return tip, best


def main() -> int:
    for a in sys.argv[1:]:
        s, vi = map(int, a.split(":"))
        cache = (
            "/tmp/f37/cache" if s >= 4470 else ("/tmp/f36/cache" if s >= 4380 else "/tmp/dev/cache")
        )
        fr = pickle.load(open(f"{cache}/real_like_1280x720_{s}.pkl", "rb"))
        v = fr.views[vi]
        tr = plate_foreground(v.image, v.plate, v.entry_px, v.entry_dir_px)
        w = tr.width_px
        tip, sol = fit_curl(tr.score, tr, w)
        tip0, sol0 = fit_curl(tr.score, tr, w, straight=True)
        hw = tr.end_half_width_px if tr.end_half_width_px > 0 else 0.5 * w
        cf = (
            fit_capsule_end(tr.score, tr.tip, tr.end_dir, hw, cap=tr.cap_px)
            if np.any(tr.end_dir)
            else None
        )
        print(
            s,
            vi + 1,
            "w",
            round(w, 1),
            "trace",
            np.linalg.norm(tr.tip - v.tip_px).round(1),
            "capsule",
            None if cf is None else np.linalg.norm(cf.tip - v.tip_px).round(1),
            "curl",
            np.linalg.norm(tip - v.tip_px).round(1),
            "straight",
            np.linalg.norm(tip0 - v.tip_px).round(1),
            "cost_ratio",
            round(sol.cost / max(sol0.cost, 1e-12), 3),
            "k*r",
            round(sol.x[1] * w / 2, 2),
            "L1",
            round(sol.x[2], 1),
            flush=True,
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
