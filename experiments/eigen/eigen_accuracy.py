"""Reiter et al. reproduction on the synthetic IREP sets: Table I (dimensions kept),
pose accuracy (120 bins, 90 % variance; unoccluded and occluded), Fig. 7 (error vs fraction
of training data, 3 random trials each) and the 3-DOF tip-position manifold.

    taskset -c 1 python experiments/eigen/eigen_accuracy.py --data /tmp/irep --validation /tmp/irep

``--data`` holds ``train``, ``test``, ``test_occluded`` from experiments/eigen/eigen_generate.py;
``--validation`` (optional) holds ``val`` and ``val_occluded`` (``eigen_generate.py --sets
val,val_occluded``: 300 new configurations from the *training* random stream, without and
with the instrument), on which the histogram centre (fixed per view vs the paper's
per-frame region centroid) was chosen. The thin-plate smoothing is chosen on a held-out
15 % of the training set (no test data is used for any choice). Main results use the fixed
centre (jaxcr default); the paper's per-frame centroid is reported beside it. Writes experiments/results/eigen/eigen_accuracy.{md,json} and
eigen_fig7.png.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from eigen_common import RESULTS, angle_errors, colour_model, contours, metadata, write_json  # noqa: E402

from jaxcr.eigen.model import TrainConfig, estimate, train  # noqa: E402
from jaxcr.eigen.pca import components_for_variance, fit_pca  # noqa: E402
from jaxcr.eigen.pipeline import stereo_histograms, view_centres  # noqa: E402

PAPER_TABLE1 = {
    72: {0.65: 2, 0.85: 5, 0.95: 19},
    120: {0.65: 2, 0.85: 8, 0.95: 39},
    360: {0.65: 3, 0.85: 39, 0.95: 200},
}
PAPER_ACC = {"unoccluded": (0.98, 1.28, 1.16), "occluded": (1.04, 2.06, 1.46)}
VARIANCES = (0.65, 0.85, 0.90, 0.95)
BINS = (72, 120, 360)


def fit_eval(Htr, Ptr, tests, colour, centres=None, **cfg):
    c = TrainConfig(centre="fixed" if centres is not None else "region", **cfg)
    t0 = time.perf_counter()
    model = train(Htr, Ptr, colour, c, view_centres=centres)
    dt = time.perf_counter() - t0
    return model, {k: estimate(model, H) for k, H in tests.items()}, dt


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--data", default="/tmp/irep")
    ap.add_argument("--validation", default=None, help="folder with val, val_occluded")
    ap.add_argument("--cache", default=None, help="contour cache folder (default DATA/cache)")
    ap.add_argument("--fractions", default="0.15,0.25,0.35,0.5,0.65,0.8,1.0")
    ap.add_argument("--trials", type=int, default=3)
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    data = Path(a.data)
    cache = Path(a.cache) if a.cache else data / "cache"
    rec: dict = {"meta": metadata()}
    colour = colour_model(data / "train", a.seed)
    sets = {}
    for name in ("train", "test", "test_occluded"):
        sc, psi, tips, dt = contours(data / name, colour, cache)
        sets[name] = (sc, psi, tips)
        rec.setdefault("descriptor_s_per_frame", {})[name] = dt
        print(
            f"{name}: {len(psi)} frames, {int((~sc.ok).sum())} without markers, contours {dt * 1e3:.1f} ms/frame"
        )
    rec["failed_frames"] = {k: int((~v[0].ok).sum()) for k, v in sets.items()}
    rec["marker_pixels_left_median"] = {
        k: float(np.median(v[0].views[0].marker_pixels)) for k, v in sets.items()
    }
    centres = view_centres(sets["train"][0])
    rec["view_centres_px"] = centres.tolist()

    # Table I: components for each variance fraction.
    table1 = {}
    hist = {}
    for nb in BINS:
        hist[nb] = {k: stereo_histograms(v[0], nb, True, centres) for k, v in sets.items()}
        Htr, ok = hist[nb]["train"]
        pca = fit_pca(Htr[ok])
        table1[nb] = {v: components_for_variance(pca, v) for v in VARIANCES}
        print("Table I", nb, table1[nb])
    rec["table1"] = table1

    sc_tr, psi_tr, tips_tr = sets["train"]
    ok_tr = sc_tr.ok
    # Smoothing chosen on a held-out 15 % of the training set (120 bins, 90 %).
    rng = np.random.default_rng(a.seed)
    idx = np.nonzero(ok_tr)[0]
    perm = rng.permutation(idx)
    nval = int(0.15 * len(perm))
    val, fit = perm[:nval], perm[nval:]
    H120 = hist[120]["train"][0]
    region = {k: stereo_histograms(v[0], 120) for k, v in sets.items()}  # paper's centre
    Hreg = region["train"][0]

    def select(H, c):
        sel = {}
        for s in (0.0, 1e-5, 1e-4, 1e-3, 1e-2):
            _, est, _ = fit_eval(
                H[fit],
                psi_tr[fit],
                {"val": H[val]},
                colour,
                c,
                n_bins=120,
                variance=0.9,
                smoothing=s,
            )
            sel[s] = angle_errors(est["val"], psi_tr[val])["combined"]
            print(
                f"smoothing {s:g} ({'fixed' if c is not None else 'region'}): held-out {sel[s]:.3f} deg"
            )
        return sel

    sel = select(H120, centres)
    smoothing = min(sel, key=sel.get)
    rec["smoothing_selection"] = {"held_out_combined_deg": sel, "chosen": smoothing}
    sel_r = select(Hreg, None)
    smoothing_r = min(sel_r, key=sel_r.get)
    rec["smoothing_selection_region"] = {"held_out_combined_deg": sel_r, "chosen": smoothing_r}

    # The paper's per-frame region centroid, 120 bins, 90 %, on the test sets.
    tests_r = {k: region[k][0][region[k][1]] for k in ("test", "test_occluded")}
    model, est, _ = fit_eval(
        Hreg[ok_tr],
        psi_tr[ok_tr],
        tests_r,
        colour,
        None,
        n_bins=120,
        variance=0.9,
        smoothing=smoothing_r,
    )
    rec["region_centre"] = {"dims": model.n_components, "smoothing": smoothing_r}
    for k in tests_r:
        rec["region_centre"][k] = angle_errors(est[k], sets[k][1][sets[k][0].ok])
    print("region centre", {k: rec["region_centre"][k]["combined"] for k in tests_r})

    # Validation sets (training stream, new configurations): the data the centre was chosen on.
    if a.validation:
        vroot = Path(a.validation)
        vres = {}
        for name in ("val", "val_occluded"):
            sc, psi_v, _, _ = contours(vroot / name, colour, cache)
            vres[name] = {"frames": len(psi_v)}
            for label, c, Htr_, sm in (
                ("fixed", centres, H120, smoothing),
                ("region", None, Hreg, smoothing_r),
            ):
                Hv, okv = stereo_histograms(sc, 120, True, c)
                _, est, _ = fit_eval(
                    Htr_[ok_tr],
                    psi_tr[ok_tr],
                    {"v": Hv[okv]},
                    colour,
                    c,
                    n_bins=120,
                    variance=0.9,
                    smoothing=sm,
                )
                vres[name][label] = angle_errors(est["v"], psi_v[okv])
            print(
                "validation",
                name,
                {k: v["combined"] for k, v in vres[name].items() if k != "frames"},
            )
        rec["validation"] = vres

    # Accuracy for every bins x variance, unoccluded and occluded.
    acc = {}
    for nb in BINS:
        for v in VARIANCES:
            Htr = hist[nb]["train"][0]
            tests = {k: hist[nb][k][0][hist[nb][k][1]] for k in ("test", "test_occluded")}
            model, est, dt = fit_eval(
                Htr[ok_tr],
                psi_tr[ok_tr],
                tests,
                colour,
                centres,
                n_bins=nb,
                variance=v,
                smoothing=smoothing,
            )
            r = {
                "dims": model.n_components,
                "train_s": dt,
                "manifold_points": int(model.manifold.psi.shape[0]),
            }
            for k in tests:
                okk = sets[k][0].ok
                r[k] = angle_errors(est[k], sets[k][1][okk])
            acc[f"{nb}/{v}"] = r
            print(nb, v, r["dims"], {k: round(r[k]["combined"], 3) for k in tests})
    rec["accuracy"] = acc

    # Fig. 7: fraction of the training data (120 bins, 90 %), 3 random trials each.
    fracs = [float(x) for x in a.fractions.split(",")]
    fig7 = {}
    tests = {k: hist[120][k][0][hist[120][k][1]] for k in ("test", "test_occluded")}
    for f in fracs:
        trials = []
        for t in range(a.trials if f < 1.0 else 1):
            r = np.random.default_rng(1000 * a.seed + 17 * t + int(f * 100))
            sub = r.choice(idx, int(round(f * len(idx))), replace=False) if f < 1.0 else idx
            _, est, _ = fit_eval(
                H120[sub],
                psi_tr[sub],
                tests,
                colour,
                centres,
                n_bins=120,
                variance=0.9,
                smoothing=smoothing,
            )
            trials.append({k: angle_errors(est[k], sets[k][1][sets[k][0].ok]) for k in tests})
        fig7[f] = {
            k: {
                m: float(np.mean([tr[k][m] for tr in trials]))
                for m in ("delta", "theta_L", "combined")
            }
            for k in tests
        }
        fig7[f]["n_train"] = int(round(f * len(idx)))
        print("fig7", f, fig7[f])
    rec["fig7"] = fig7
    fig, ax = plt.subplots(figsize=(6, 4))
    xs = [100 * f for f in fracs]
    ax.plot(xs, [fig7[f]["test"]["delta"] for f in fracs], "b-o", label="delta")
    ax.plot(xs, [fig7[f]["test"]["theta_L"] for f in fracs], "r-o", label="theta_L")
    ax.plot(xs, [fig7[f]["test"]["combined"] for f in fracs], "k--", label="combined")
    ax.set_xlabel("training data used (%)")
    ax.set_ylabel("median error (deg), mean of trials")
    ax.set_title("Fig. 7 (synthetic IREP, 120 bins, 90 % variance)")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(RESULTS / "eigen_fig7.png", dpi=120)

    # 3-DOF tip-position manifold (120 bins, 90 %). Its smoothing is chosen separately on
    # the same held-out training frames: lambda has units of the parameters (metres here,
    # radians above), so the angle manifold's value does not carry over.
    sel_p = {}
    for s in (0.0, 1e-7, 1e-6, 1e-5, 1e-4, 1e-3):
        _, est, _ = fit_eval(
            H120[fit],
            tips_tr[fit],
            {"val": H120[val]},
            colour,
            centres,
            n_bins=120,
            variance=0.9,
            smoothing=s,
            params="position",
        )
        sel_p[s] = float(np.median(np.linalg.norm(est["val"] - tips_tr[val], axis=1)) * 1e3)
        print(f"position smoothing {s:g}: held-out {sel_p[s]:.3f} mm")
    smoothing_p = min(sel_p, key=sel_p.get)
    rec["smoothing_selection_position"] = {"held_out_median_mm": sel_p, "chosen": smoothing_p}
    pos = {}
    model, est, dt = fit_eval(
        H120[ok_tr],
        tips_tr[ok_tr],
        tests,
        colour,
        centres,
        n_bins=120,
        variance=0.9,
        smoothing=smoothing_p,
        params="position",
    )
    for k in tests:
        e = np.linalg.norm(est[k] - sets[k][2][sets[k][0].ok], axis=1) * 1e3
        pos[k] = {
            "median_mm": float(np.median(e)),
            "p90_mm": float(np.percentile(e, 90)),
            "manifold_points": int(model.manifold.psi.shape[0]),
            "train_s": dt,
        }
        print("position", k, pos[k])
    rec["position"] = pos
    write_json("eigen_accuracy.json", rec)
    write_markdown(rec, smoothing)


def write_markdown(rec, smoothing) -> None:
    m = rec["meta"]
    L = [
        "# Eigen-feature pose estimation (Reiter et al.) on synthetic IREP stereo data",
        "",
        f"Commit {m['commit']}, {m['date']}, jax {m['jax']}, {m['machine']}. Data: "
        "`experiments/eigen/eigen_generate.py` (train 2296, test 806, occluded test 806 frames, 512x384 stereo); "
        "run: `taskset -c 1 python experiments/eigen/eigen_accuracy.py --data /tmp/irep --validation /tmp/irep` "
        "(validation sets: `taskset -c 1 python experiments/eigen/eigen_generate.py --out /tmp/irep --size 512x384 --sets val,val_occluded --tag _val`).",
        "",
        "Histogram centre: **fixed per view** (the mean region centroid over the training frames, "
        f"left/right = {', '.join(f'({c[0]:.1f}, {c[1]:.1f})' for c in rec['view_centres_px'])} px), "
        "a deviation from the paper's per-frame region centroid, which a partial occlusion moves "
        "and thereby re-bins every contour point (see jaxcr/eigen/descriptor.py). The paper's "
        "centre is reported beside it.",
        f"Smoothing lambda = {smoothing:g}, chosen on 15 % of the training set held out "
        f"(held-out combined errors: {', '.join(f'{k:g}: {v:.3f} deg' for k, v in rec['smoothing_selection']['held_out_combined_deg'].items())}). "
        f"Frames without marker pixels (reported failed, not estimated): {rec['failed_frames']}.",
        "",
        "## Table I: dimensions kept",
        "",
        "| bins | 65 % (paper) | 85 % (paper) | 90 % | 95 % (paper) |",
        "|---|---|---|---|---|",
    ]
    for nb, row in rec["table1"].items():
        p = PAPER_TABLE1[nb]
        L.append(
            f"| {nb} | {row[0.65]} ({p[0.65]}) | {row[0.85]} ({p[0.85]}) | {row[0.9]} | {row[0.95]} ({p[0.95]}) |"
        )
    a = rec["accuracy"]["120/0.9"]
    L += [
        "",
        "## Accuracy, 120 bins, 90 % variance (median absolute error, deg)",
        "",
        f"Eigen-feature dimension: {a['dims']} (paper: 16).",
        "",
        "| set | delta (paper) | theta_L (paper) | combined (paper) | combined: median of per-frame mean | median of norm | 90th pct. pooled |",
        "|---|---|---|---|---|---|---|",
    ]
    for k, pk in (("test", "unoccluded"), ("test_occluded", "occluded")):
        e, p = a[k], PAPER_ACC[pk]
        L.append(
            f"| {pk} ({e['n']} frames) | {e['delta']:.2f} ({p[0]}) | {e['theta_L']:.2f} ({p[1]}) | {e['combined']:.2f} ({p[2]}) | {e['combined_mean']:.2f} | {e['combined_norm']:.2f} | {e['p90_combined']:.2f} |"
        )
    rc = rec["region_centre"]
    for k, pk in (("test", "unoccluded"), ("test_occluded", "occluded")):
        e, p = rc[k], PAPER_ACC[pk]
        L.append(
            f"| {pk}, paper's per-frame centroid ({rc['dims']} dims, lambda {rc['smoothing']:g}) | {e['delta']:.2f} ({p[0]}) | {e['theta_L']:.2f} ({p[1]}) | {e['combined']:.2f} ({p[2]}) | {e['combined_mean']:.2f} | {e['combined_norm']:.2f} | {e['p90_combined']:.2f} |"
        )
    L += [
        "",
        '"combined" pools the absolute errors of both angles and takes the median.',
        "",
        "## All bins x variance (combined median error, deg; dims)",
        "",
        "| bins | variance | dims | unoccluded | occluded |",
        "|---|---|---|---|---|",
    ]
    for key, r in rec["accuracy"].items():
        nb, v = key.split("/")
        L.append(
            f"| {nb} | {float(v):.0%} | {r['dims']} | {r['test']['combined']:.2f} | {r['test_occluded']['combined']:.2f} |"
        )
    L += [
        "",
        "## Fig. 7: error vs training data used (mean over 3 random trials of the median error, deg)",
        "",
        "![fig7](eigen_fig7.png)",
        "",
        "| fraction | frames | delta | theta_L | combined | occluded combined |",
        "|---|---|---|---|---|---|",
    ]
    for f, r in rec["fig7"].items():
        L.append(
            f"| {float(f):.0%} | {r['n_train']} | {r['test']['delta']:.2f} | {r['test']['theta_L']:.2f} | {r['test']['combined']:.2f} | {r['test_occluded']['combined']:.2f} |"
        )
    L += [
        "",
        'Paper: with 15 % (345/2296) of the training data the results stay "reasonable" (Fig. 7).',
        "",
        "## 3-DOF tip-position manifold (120 bins, 90 %)",
        "",
        f"Smoothing lambda = {rec['smoothing_selection_position']['chosen']:g} (metres), chosen on the same held-out "
        "training frames (held-out median tip errors: "
        + ", ".join(
            f"{k:g}: {v:.2f} mm"
            for k, v in rec["smoothing_selection_position"]["held_out_median_mm"].items()
        )
        + ").",
        "",
        "| set | median tip error (mm) | 90th pct. (mm) | paper |",
        "|---|---|---|---|",
    ]
    for k, r in rec["position"].items():
        L.append(
            f"| {k} | {r['median_mm']:.2f} | {r['p90_mm']:.2f} | {'0.97' if k == 'test' else '-'} |"
        )
    mp = rec["marker_pixels_left_median"]
    L += [
        "",
        "## Notes",
        "",
        f"- Occlusion level: median labelled marker pixels (left view) {mp['test_occluded']:.0f} in the "
        f"occluded test set vs {mp['test']:.0f} unoccluded (the instrument crosses 10-25 mm in front of "
        "the segment at a random image angle). The paper does not quantify its occlusions.",
        "- Why the fixed centre: with the per-frame region centroid, the centroid of the "
        "occluded frames moves by 3.5 px (median; 90th pct. 10 px) from the same configuration "
        "unoccluded (measured on the paired test sets while diagnosing; the choice itself was "
        "made on the validation sets), which rotates the angle of every contour point; with a fixed point only the "
        "bins of the hidden and newly cut contour change (tests/eigen/test_eigen_contour.py "
        "checks this exactly). It also removes centroid jitter from the descriptor, presumably "
        "why fewer PCA components hold the same variance (Table I).",
        "- Generation time and descriptor extraction: see experiments/results/eigen/eigen_generate.json "
        "(512x384: ~0.5 s/frame unoccluded, ~1 s/frame occluded on one shared core).",
    ]
    (RESULTS / "eigen_accuracy.md").write_text("\n".join(L) + "\n")


if __name__ == "__main__":
    main()
