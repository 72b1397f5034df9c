"""Benchmarks of the eigen-feature manifold (Reiter et al.): training (PCA + thin-plate
spline fit + dense resampling) on 2296 samples and the batched query per sample, each
beside the reference a user would otherwise reach for, in the same run:

* PCA: ``numpy.linalg.svd``;
* spline fit + resampling: ``scipy.interpolate.RBFInterpolator(kernel="thin_plate_spline")``;
* query: ``scipy.spatial.cKDTree`` (k=3 query on a prebuilt tree, and build + query) +
  numpy inverse-distance weights. jaxcr's query is the exact pruned search of
  :mod:`jaxcr.eigen.knn_index` (its leaf index is built once at training, like the tree);
  the jitted brute-force query (:func:`jaxcr.eigen.manifold.query_batch`) is listed too.

    taskset -c 1 python experiments/eigen/eigen_bench.py --data /tmp/irep

Uses the real training/test/occluded-test descriptors (120 bins, 90 % variance, fixed
histogram centre) from the contour cache of experiments/eigen/eigen_accuracy.py if present,
else synthetic ones of the same shapes.
Median and spread over repeats after a warm-up; compile time reported separately.
Writes experiments/results/eigen/eigen_bench.{md,json}.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from eigen_common import RESULTS, metadata, write_json
from scipy.interpolate import RBFInterpolator
from scipy.spatial import cKDTree

from jaxcr.eigen.knn_index import build_index, knn_batch, query_batch_indexed
from jaxcr.eigen.manifold import Manifold, _min_dist, grid_points, query_batch
from jaxcr.eigen.model import DEFAULT_STEP
from jaxcr.eigen.pca import components_for_variance, fit_pca
from jaxcr.eigen.tps import evaluate_tps, fit_tps


def timeit(f, repeats):
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(f())
        ts.append(time.perf_counter() - t0)
    return float(np.median(ts)), float(np.min(ts)), float(np.max(ts))


def load_inputs(data: Path):
    cache = data / "cache"
    if (cache / "contours_train.npz").exists():
        from eigen_common import _load

        from jaxcr.eigen.pipeline import stereo_histograms, view_centres
        from jaxcr.io.dataset import load_dataset

        tr = _load(cache / "contours_train.npz")
        c = view_centres(tr)
        H, ok = stereo_histograms(tr, 120, True, c)
        psi = np.array([f.q for f in load_dataset(data / "train").frames])
        tests = {}
        for name in ("test", "test_occluded"):
            if (cache / f"contours_{name}.npz").exists():
                Ht, okt = stereo_histograms(_load(cache / f"contours_{name}.npz"), 120, True, c)
                tests[name] = Ht[okt]
        return H[ok], psi[ok], tests, "real (synthetic IREP renders)"
    rng = np.random.default_rng(0)
    psi = np.stack([rng.uniform(0.09, 1.31, 2296), rng.uniform(0, np.pi, 2296)], 1)
    ang = np.linspace(0, 2 * np.pi, 120, endpoint=False)
    H = np.concatenate(
        [
            np.exp(np.cos(ang[None] - psi[:, 1:]) * psi[:, :1]),
            np.exp(np.cos(ang[None] - 0.5 * psi[:, 1:])),
        ],
        1,
    )
    tests = {"test": H[:806].astype(np.float32)}
    return H.astype(np.float32), psi, tests, "synthetic smooth descriptors"


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--data", default="/tmp/irep")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--smoothing", type=float, default=1e-4)
    a = ap.parse_args()
    H, psi, tests, source = load_inputs(Path(a.data))
    n = len(H)
    rec = {"meta": metadata(), "source": source, "n_train": n, "n_query": len(tests["test"])}
    R = a.repeats

    # PCA.
    Hj = jnp.asarray(H)
    t0 = time.perf_counter()
    pca = fit_pca(Hj)
    jax.block_until_ready(pca.components)
    rec["pca_first_call_s"] = time.perf_counter() - t0
    rec["pca_jax"] = timeit(lambda: fit_pca(Hj).components, R)
    rec["pca_numpy"] = timeit(lambda: np.linalg.svd(H - H.mean(0), full_matrices=False), R)
    k = components_for_variance(pca, 0.9)
    E = pca.truncate(k)
    L = np.asarray((Hj - E.mean) @ E.components)
    rec["dims"] = k

    # Spline fit.
    x32 = jnp.asarray(psi, jnp.float32)
    L32 = jnp.asarray(L, jnp.float32)
    t0 = time.perf_counter()
    sp = fit_tps(x32, L32, a.smoothing)
    jax.block_until_ready(sp.weights)
    rec["tps_fit_first_call_s"] = time.perf_counter() - t0
    rec["tps_fit_jax"] = timeit(lambda: fit_tps(x32, L32, a.smoothing).weights, R)
    rec["tps_fit_scipy"] = timeit(
        lambda: RBFInterpolator(psi, L, kernel="thin_plate_spline", smoothing=a.smoothing),
        max(1, R // 2),
    )

    # Resampling (grid 0.5 deg, kept within 3 x median spacing of the samples).
    step = np.full(2, DEFAULT_STEP["angles"])
    grid = grid_points(psi.min(0), psi.max(0), step)
    keep = _min_dist(grid, psi) <= np.deg2rad(3.0)
    grid = grid[keep]
    g32 = jnp.asarray(grid, jnp.float32)
    t0 = time.perf_counter()
    jax.block_until_ready(evaluate_tps(sp, g32))
    rec["resample_first_call_s"] = time.perf_counter() - t0
    rec["resample_points"] = int(len(grid))
    rec["resample_jax"] = timeit(lambda: evaluate_tps(sp, g32), R)
    rbf = RBFInterpolator(psi, L, kernel="thin_plate_spline", smoothing=a.smoothing)
    rec["resample_scipy"] = timeit(lambda: rbf(grid), max(1, R // 2))
    feats = np.asarray(evaluate_tps(sp, g32))

    # Query: exact pruned search (jaxcr default) and jitted brute force vs cKDTree + IDW.
    m = Manifold(jnp.asarray(grid, jnp.float32), jnp.asarray(feats, jnp.float32))
    t0 = time.perf_counter()
    index = build_index(feats)
    rec["index_build_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    cKDTree(feats)
    rec["ckdtree_build_s"] = time.perf_counter() - t0
    tree = cKDTree(feats)
    q = {}
    for name, Ht in tests.items():
        Lt = np.asarray((jnp.asarray(Ht) - E.mean) @ E.components, np.float32)
        Ltn = Lt.astype(np.float64)
        r = {"n": len(Lt)}
        t0 = time.perf_counter()
        query_batch_indexed(m, index, Lt, 3)
        r["pruned_first_call_s"] = time.perf_counter() - t0
        r["pruned"] = timeit(lambda Lt=Lt: query_batch_indexed(m, index, Lt, 3), R)
        stats: dict = {}
        knn_batch(index, m.features, Lt, 3, stats=stats)
        r["pruned_passes"] = stats
        Lj = jnp.asarray(Lt)
        t0 = time.perf_counter()
        jax.block_until_ready(query_batch(m, Lj, 3))
        r["brute_first_call_s"] = time.perf_counter() - t0
        r["brute"] = timeit(lambda Lj=Lj: query_batch(m, Lj, 3), R)

        def ref_query(Ltn=Ltn, build=False):
            t = cKDTree(feats) if build else tree
            d, i = t.query(Ltn, k=3)
            d = np.maximum(d, 1e-12)
            w = (1 / d) / (1 / d).sum(1, keepdims=True)
            return np.einsum("nb,nbd->nd", w, grid[i])

        r["ckdtree_query_only"] = timeit(ref_query, R)
        r["ckdtree_build_and_query"] = timeit(lambda f=ref_query: f(build=True), R)
        est = query_batch_indexed(m, index, Lt, 3)
        r["max_abs_diff_vs_ckdtree_rad"] = float(np.abs(est - ref_query()).max())
        r["max_abs_diff_vs_brute_rad"] = float(
            np.abs(est - np.asarray(query_batch(m, Lj, 3))).max()
        )
        q[name] = r
    rec["query"] = q
    write_json("eigen_bench.json", rec)

    def row(name, ours, ref, per=1):
        return f"| {name} | {ours[0] / per * 1e3:.3f} ({ours[1] / per * 1e3:.3f}-{ours[2] / per * 1e3:.3f}) | {ref[0] / per * 1e3:.3f} | {ref[0] / ours[0]:.2f} |"

    import os

    load = os.getloadavg()
    md = [
        "# Eigen-feature manifold benchmarks",
        "",
        f"Commit {rec['meta']['commit']}, {rec['meta']['date']}, jax {rec['meta']['jax']}, {rec['meta']['machine']}, one core (`taskset -c 1`; shared machine, load average at the end of the run {load[0]:.1f} / {load[1]:.1f} / {load[2]:.1f}: absolute times vary with load, the ratios much less). "
        f"Inputs: {source}; {n} training samples, 120 bins, 90 % variance -> {k} dims; {len(grid)} resampled points (0.5 deg grid); b = 3. "
        f"Median (min-max) of {R} runs after a warm-up; first-call (compile) times separate. Command: `taskset -c 1 python experiments/eigen/eigen_bench.py --data /tmp/irep`.",
        "",
        "| step | jaxcr (ms) | reference (ms) | reference / jaxcr |",
        "|---|---|---|---|",
        row("PCA (SVD) vs numpy.linalg.svd", rec["pca_jax"], rec["pca_numpy"]),
        row("thin-plate fit vs scipy RBFInterpolator", rec["tps_fit_jax"], rec["tps_fit_scipy"]),
        row("resampling vs RBFInterpolator.__call__", rec["resample_jax"], rec["resample_scipy"]),
    ]
    for name, r in q.items():
        nq = r["n"]
        md += [
            row(
                f"query per sample ({name}, {nq}), pruned exact vs cKDTree query+IDW (prebuilt tree)",
                r["pruned"],
                r["ckdtree_query_only"],
                nq,
            ),
            row(
                f"query per sample ({name}), pruned exact vs cKDTree build+query+IDW",
                r["pruned"],
                r["ckdtree_build_and_query"],
                nq,
            ),
            row(
                f"query per sample ({name}), jitted brute force vs cKDTree query+IDW",
                r["brute"],
                r["ckdtree_query_only"],
                nq,
            ),
        ]
    md += [
        "",
        f"Training total (PCA + fit + resampling + leaf index, jaxcr): {(rec['pca_jax'][0] + rec['tps_fit_jax'][0] + rec['resample_jax'][0] + rec['index_build_s']):.2f} s "
        f"(leaf index {rec['index_build_s']:.2f} s); "
        f"reference: {(rec['pca_numpy'][0] + rec['tps_fit_scipy'][0] + rec['resample_scipy'][0] + rec['ckdtree_build_s']):.2f} s (cKDTree build {rec['ckdtree_build_s']:.2f} s). "
        f"First calls (compile included): PCA {rec['pca_first_call_s']:.2f} s, fit {rec['tps_fit_first_call_s']:.2f} s, resampling {rec['resample_first_call_s']:.2f} s, "
        + ", ".join(
            f"query {k} {r['pruned_first_call_s']:.2f} s (brute {r['brute_first_call_s']:.2f} s)"
            for k, r in q.items()
        )
        + ".",
        "",
        "Pruned search passes (queries certified exact in pass 1 (32 leaves of 16 points), pass 2 "
        "(128 leaves), answered by brute force): "
        + "; ".join(
            f"{k}: {r['pruned_passes']['pass1']} / {r['pruned_passes']['pass2']} / {r['pruned_passes']['brute']}"
            for k, r in q.items()
        )
        + ". Max |jaxcr - cKDTree| of the estimates: "
        + ", ".join(f"{k} {r['max_abs_diff_vs_ckdtree_rad']:.2e} rad" for k, r in q.items())
        + "; vs jaxcr brute force: "
        + ", ".join(f"{k} {r['max_abs_diff_vs_brute_rad']:.2e} rad" for k, r in q.items())
        + ".",
    ]
    (RESULTS / "eigen_bench.md").write_text("\n".join(md) + "\n")
    print("\n".join(md))


if __name__ == "__main__":
    main()
