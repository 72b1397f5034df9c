"""Benchmarks of the eigen-feature manifold (Reiter et al.): training (PCA + thin-plate
spline fit + dense resampling) on 2296 samples and the batched query per sample, each
beside the reference a user would otherwise reach for, in the same run:

* PCA: ``numpy.linalg.svd``;
* spline fit + resampling: ``scipy.interpolate.RBFInterpolator(kernel="thin_plate_spline")``;
* query: ``scipy.spatial.cKDTree`` (build + k=3 query) + numpy inverse-distance weights.

    taskset -c 1 python experiments/eigen_bench.py --data /tmp/irep

Uses the real training/test descriptors (120 bins, 90 % variance) from the contour cache
of experiments/eigen_accuracy.py if present, else synthetic ones of the same shapes.
Median and spread over repeats after a warm-up; compile time reported separately.
Writes experiments/results/eigen_bench.{md,json}.
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

        from jaxcr.eigen.pipeline import stereo_histograms
        from jaxcr.io.dataset import load_dataset

        tr = _load(cache / "contours_train.npz")
        te = _load(cache / "contours_test.npz")
        H, ok = stereo_histograms(tr, 120)
        Ht, okt = stereo_histograms(te, 120)
        psi = np.array([f.q for f in load_dataset(data / "train").frames])
        return H[ok], psi[ok], Ht[okt], "real (synthetic IREP renders)"
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
    return H.astype(np.float32), psi, H[:806].astype(np.float32), "synthetic smooth descriptors"


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--data", default="/tmp/irep")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--smoothing", type=float, default=1e-4)
    a = ap.parse_args()
    H, psi, Htest, source = load_inputs(Path(a.data))
    n = len(H)
    rec = {"meta": metadata(), "source": source, "n_train": n, "n_query": len(Htest)}
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

    # Query: batched JAX brute force vs cKDTree + numpy IDW.
    m = Manifold(jnp.asarray(grid, jnp.float32), jnp.asarray(feats, jnp.float32))
    Lt = jnp.asarray((jnp.asarray(Htest) - E.mean) @ E.components)
    t0 = time.perf_counter()
    jax.block_until_ready(query_batch(m, Lt, 3))
    rec["query_compile_s"] = time.perf_counter() - t0
    rec["query_jax_batch"] = timeit(lambda: query_batch(m, Lt, 3), R)
    Ltn = np.asarray(Lt, np.float64)

    def ref_query():
        tree = cKDTree(feats)
        d, i = tree.query(Ltn, k=3)
        d = np.maximum(d, 1e-12)
        w = (1 / d) / (1 / d).sum(1, keepdims=True)
        return np.einsum("nb,nbd->nd", w, grid[i])

    tree = cKDTree(feats)

    def ref_query_only():
        d, i = tree.query(Ltn, k=3)
        d = np.maximum(d, 1e-12)
        w = (1 / d) / (1 / d).sum(1, keepdims=True)
        return np.einsum("nb,nbd->nd", w, grid[i])

    rec["query_ckdtree_build_and_query"] = timeit(ref_query, R)
    rec["query_ckdtree_query_only"] = timeit(ref_query_only, R)
    agree = np.abs(np.asarray(query_batch(m, Lt, 3)) - ref_query_only()).max()
    rec["query_max_abs_diff_rad"] = float(agree)
    write_json("eigen_bench.json", rec)
    nq = len(Htest)

    def row(name, ours, ref, per=1):
        return f"| {name} | {ours[0] / per * 1e3:.3f} ({ours[1] / per * 1e3:.3f}-{ours[2] / per * 1e3:.3f}) | {ref[0] / per * 1e3:.3f} | {ref[0] / ours[0]:.2f} |"

    md = [
        "# Eigen-feature manifold benchmarks",
        "",
        f"Commit {rec['meta']['commit']}, {rec['meta']['date']}, jax {rec['meta']['jax']}, {rec['meta']['machine']}, one core (`taskset -c 1`, shared machine: absolute times vary with load). "
        f"Inputs: {source}; {n} training samples, 120 bins, 90 % variance -> {k} dims; {len(grid)} resampled points (0.5 deg grid); {nq} queries, b = 3. "
        f"Median (min-max) of {R} runs after a warm-up; first-call (compile) times separate. Command: `taskset -c 1 python experiments/eigen_bench.py --data /tmp/irep`.",
        "",
        "| step | jaxcr (ms) | reference (ms) | reference / jaxcr |",
        "|---|---|---|---|",
        row("PCA (SVD) vs numpy.linalg.svd", rec["pca_jax"], rec["pca_numpy"]),
        row("thin-plate fit vs scipy RBFInterpolator", rec["tps_fit_jax"], rec["tps_fit_scipy"]),
        row("resampling vs RBFInterpolator.__call__", rec["resample_jax"], rec["resample_scipy"]),
        row(
            "query per sample, batched vs cKDTree build+query+IDW",
            rec["query_jax_batch"],
            rec["query_ckdtree_build_and_query"],
            nq,
        ),
        row(
            "query per sample, batched vs cKDTree query+IDW (prebuilt tree)",
            rec["query_jax_batch"],
            rec["query_ckdtree_query_only"],
            nq,
        ),
        "",
        f"Training total (PCA + fit + resampling, jaxcr): {(rec['pca_jax'][0] + rec['tps_fit_jax'][0] + rec['resample_jax'][0]):.2f} s; "
        f"reference: {(rec['pca_numpy'][0] + rec['tps_fit_scipy'][0] + rec['resample_scipy'][0]):.2f} s. "
        f"First calls (compile included): PCA {rec['pca_first_call_s']:.2f} s, fit {rec['tps_fit_first_call_s']:.2f} s, resampling {rec['resample_first_call_s']:.2f} s, query {rec['query_compile_s']:.2f} s. "
        f"Max |jaxcr - reference| of the query estimates: {agree:.2e} rad.",
    ]
    (RESULTS / "eigen_bench.md").write_text("\n".join(md) + "\n")
    print("\n".join(md))


if __name__ == "__main__":
    main()
