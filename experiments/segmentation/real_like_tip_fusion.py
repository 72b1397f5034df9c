"""Round 17a (issue 16 item 2, docs/decisions.md S40): the two views' consistent tips fused
along the tube by a Mahalanobis triangulation (:mod:`jaxcr.stereo.tip_fusion`), on stored
development traces, beside this tree's method in the same run.

Per seed: ``ref`` -- this tree's :func:`jaxcr.stereo.pipeline.traced_stereo_tips` with
``calibration=REAL_LIKE_CALIBRATION`` (fusion off); where its tip step says
``"consistent"`` (the tips within the rig's epipolar tolerance), each variant
``<output>_<along>_<across>_<gate>`` replaces the tips by :func:`jaxcr.stereo.tip_fusion.fuse_tips`'s, with
the along-tube standard deviation

* ``cN``: N px in both views (equal weights);
* ``fK``: ``sqrt(1 + (K * falloff)^2)`` px, ``falloff`` the 20-80 % distance of the cue's
  fall-off at the end (:func:`jaxcr.stereo.tip_fusion.end_falloff_px`; 8 px where the
  profile has no step);

the gate ``g0`` (none), ``s3`` (both end lines at least asin 0.3 from the epipolar
lines), ``x9`` (chi-square at most 9), ``s3x9`` (both), and the output ``n`` (each tip
minus its placement error's estimate, the calibration's share of the residual left) or
``r`` (the end's reprojections): ``<output>_<along>_<across>_<gate>``. Elsewhere a variant is
``ref``. ``mT_cN``: ``n_cN_a1_g0`` where the chi-square of the tight model (both
views along and across 1 px: two right tips) is over ``T`` (the residual is improbable for
two right tips), ``ref`` elsewhere.
``pipeline`` -- this tree's ``traced_stereo_tips(..., fuse_ends=True)`` (the hook, with its
defaults: equal to ``n_c8_a1_s1``, the variant chosen on the even seeds).

    python experiments/segmentation/real_like_tip_fusion.py --seeds 4000-4100 \\
        --store /tmp/tip34/traces --out ROWS
    python experiments/segmentation/real_like_tip_fusion.py --summary ROWS.json [ROWS2.json]
"""

from __future__ import annotations

import json
import re
import time
from pathlib import Path

import numpy as np
from tip_harness import along_across as _along_across
from tip_harness import (
    dev_seeds,
    harness_parser,
    resumed_rows,
    stored_alternatives,
    stored_records,
    write_rows,
)
from tip_harness import tip_errors as _errs

from jaxcr.stereo import pipeline
from jaxcr.stereo.epipolar_tolerance import REAL_LIKE_CALIBRATION
from jaxcr.stereo.tip_fusion import end_falloff_px, fuse_tips

#: the branch step and end placement as they were when the rows were made (stop 35, before
#: S41 ``run_on`` and S42 ``end_fit`` were on by default): ``ref`` is that tree's method
BEFORE_S41_S42 = {"run_on": False, "end_fit": False}

ALONG = {"c1": 1.0, "c2": 2.0, "c3": 3.0, "c5": 5.0, "c8": 8.0, "c12": 12.0, "f1": 1.0, "f2": 2.0}
ACROSS = {"a0.5": 0.5, "a1": 1.0}
GATES = {"g0": (0.0, np.inf), "s1": (0.1, np.inf), "s3": (0.3, np.inf), "x9": (0.0, 9.0)}
OUTPUTS = {"n": "noise_removed", "r": "reprojected"}
NO_STEP_PX = 8.0
TIGHT_CHI2 = (2.7, 4.0, 6.6)
VARIANTS = [(a, c, g, o) for o in OUTPUTS for a in ALONG for c in ACROSS for g in GATES]


def sigma_along(name: str, falloff) -> list[float]:
    if name.startswith("c"):
        return [ALONG[name]] * 2
    k = ALONG[name]
    return [float(np.hypot(1.0, k * (f if np.isfinite(f) else NO_STEP_PX))) for f in falloff]


def evaluate(seeds, store: Path, out: Path) -> None:
    rows = resumed_rows(out)
    for seed, rec in stored_records(seeds, store, rows):
        cams, truth = rec["calib"], rec["truth"]
        with stored_alternatives(rec):
            t0 = time.process_time()
            tips, _, res, chosen = pipeline.traced_stereo_tips(
                cams, rec["traces"], calibration=REAL_LIKE_CALIBRATION, **BEFORE_S41_S42
            )
            ref_cpu = time.process_time() - t0
            t0 = time.process_time()
            hook = pipeline.traced_stereo_tips(
                cams,
                rec["traces"],
                calibration=REAL_LIKE_CALIBRATION,
                fuse_ends=True,
                **BEFORE_S41_S42,
            )[0]
            hook_cpu = time.process_time() - t0
        action = None if res is None else res.action
        row = {"seed": seed, "action": action, "ref": {"err_px": _errs(tips, truth), "cpu_s": ref_cpu},
               "pipeline": {"err_px": _errs(hook, truth), "cpu_s": hook_cpu}}  # fmt: skip
        dirs = [np.asarray(t.end_dir, np.float64) for t in chosen]
        row["ref"]["along_across"] = [
            _along_across(d, p, g) for d, p, g in zip(dirs, tips, truth, strict=True)
        ]
        if action == "consistent":
            t0 = time.process_time()
            falloff = [end_falloff_px(t.score, p, d, t.end_half_width_px)
                       if t.score is not None and t.end_half_width_px > 0 else float("nan")
                       for t, p, d in zip(chosen, tips, dirs, strict=True)]  # fmt: skip
            row["falloff_px"] = falloff
            row["falloff_cpu_s"] = time.process_time() - t0
            for an, cn, gn, on in VARIANTS:
                sa = sigma_along(an, falloff)
                ms, mx = GATES[gn]
                t0 = time.process_time()
                f = fuse_tips(cams, tips, dirs, sigma_along=sa, calibration=REAL_LIKE_CALIBRATION,
                              sigma_across=ACROSS[cn], min_sin=ms, max_chi2=mx,
                              output=OUTPUTS[on])  # fmt: skip
                cpu = time.process_time() - t0
                new = tips if f is None else f.tips
                row[f"{on}_{an}_{cn}_{gn}"] = {
                    "err_px": _errs(new, truth), "cpu_s": cpu,
                    "reason": None if f is None else f.reason,
                    "chi2": None if f is None else f.chi2,
                    "sin": None if f is None else [float(x) for x in f.sin],
                    "moved_px": None if f is None else [float(x) for x in f.moved_px],
                    "along_across": [_along_across(d, p, g) for d, p, g in
                                     zip(dirs, new, truth, strict=True)],
                }  # fmt: skip
            # The two-hypothesis variants: fused (along N px, across 1 px) only where the
            # tips' residual is improbable for two right tips (along 1 px, across 1 px):
            # chi-square of that tight model over T.
            tight = fuse_tips(cams, tips, dirs, sigma_along=[1.0, 1.0],
                              calibration=REAL_LIKE_CALIBRATION, sigma_across=1.0)  # fmt: skip
            row["chi2_tight"] = None if tight is None else tight.chi2
            for t in TIGHT_CHI2:
                for an in ("c3", "c5", "c8"):
                    base = row[f"n_{an}_a1_g0"]
                    use = tight is not None and tight.chi2 > t
                    row[f"m{t:g}_{an}"] = base if use else {"err_px": row["ref"]["err_px"],
                                                            "along_across": row["ref"]["along_across"]}  # fmt: skip
        rows.append(row)
        print(seed, action, [round(x, 1) for x in row["ref"]["err_px"]],
              [round(x, 1) for x in row.get("n_f1_a0.5_g0", row["ref"])["err_px"]], flush=True)  # fmt: skip
        write_rows(out, rows)


def _variant(r, name):
    return r[name] if name in r else r["ref"]


def _table(rows, names, title):
    n_cons = sum(r["action"] == "consistent" for r in rows)
    print(f"\n{title} ({len(rows)} frames, {n_cons} consistent)\n")
    print("| variant | frames both views <= 5 px | views <= 5 px | fixed | broken "
          "| median err (consistent views) | ref's right views (<= 2 px, consistent): "
          "median / p90 err after, over 3 px |\n|---|---|---|---|---|---|---|")  # fmt: skip
    for n in names:
        errs = [(r["ref"]["err_px"], _variant(r, n)["err_px"], r["action"]) for r in rows]
        ok = sum(max(b) <= 5 for _, b, _ in errs)
        v = sum(x <= 5 for _, b, _ in errs for x in b)
        fx = [r["seed"] for r, (a, b, _) in zip(rows, errs, strict=True) if max(a) > 5 >= max(b)]
        br = [r["seed"] for r, (a, b, _) in zip(rows, errs, strict=True) if max(a) <= 5 < max(b)]
        med = np.median([x for _, b, c in errs if c == "consistent" for x in b])
        # The precision cost on right tips: views within 2 px in ref, consistent frames.
        rb = np.array([y for a, b, c in errs if c == "consistent"
                       for x, y in zip(a, b, strict=True) if x <= 2])  # fmt: skip
        print(f"| {n} | {ok} | {v} of {2 * len(rows)} | {len(fx)} {fx} | {len(br)} {br} | "
              f"{med:.2f} | {np.median(rb):.2f} / {np.percentile(rb, 90):.2f} / "
              f"{int(np.sum(rb > 3))} of {len(rb)} |")  # fmt: skip


def summary(paths, half: str = "both", only: str | None = None) -> None:
    rows = {}
    for p in paths:
        for r in json.loads(Path(p).read_text())["rows"]:
            rows.setdefault(r["seed"], r)
    rows = [rows[s] for s in sorted(rows)]
    names = ["ref"] + [f"{o}_{a}_{c}_{g}" for a, c, g, o in VARIANTS]
    names += [f"m{t:g}_{a}" for t in TIGHT_CHI2 for a in ("c3", "c5", "c8")] + ["pipeline"]
    if only:
        names = [n for n in names if n in ("ref", "pipeline") or re.search(only, n)]
    even = [r for r in rows if r["seed"] % 2 == 0]
    odd = [r for r in rows if r["seed"] % 2 == 1]
    if half in ("even", "both"):
        _table(even, names, "even seeds (design)")
    if half in ("odd", "both"):
        _table(odd, names, "odd seeds (test)")
    rows = {"even": even, "odd": odd, "both": rows}[half]
    cons = [r for r in rows if r["action"] == "consistent"]
    # Calibration of the along-tube model: ref's along error over its falloff (z-score).
    al = np.array([a[0] for r in cons for a in r["ref"]["along_across"]])
    ac = np.array([a[1] for r in cons for a in r["ref"]["along_across"]])
    fo = np.array([f for r in cons for f in r["falloff_px"]])
    print(f"\nconsistent views: {len(al)}; |along| median {np.nanmedian(np.abs(al)):.2f} p90 "
          f"{np.nanpercentile(np.abs(al), 90):.2f}; |across| median {np.nanmedian(np.abs(ac)):.2f} "
          f"p90 {np.nanpercentile(np.abs(ac), 90):.2f}; falloff median {np.nanmedian(fo):.2f} "
          f"p10 {np.nanpercentile(fo, 10):.2f} p90 {np.nanpercentile(fo, 90):.2f}, no step {int(np.sum(~np.isfinite(fo)))}")  # fmt: skip
    big = np.abs(al) > 3
    for lo, hi in ((0, 2), (2, 4), (4, 8), (8, 1e9)):
        sel = np.isfinite(fo) & (fo >= lo) & (fo < hi)
        if sel.any():
            print(f"falloff {lo}-{hi} px: {int(sel.sum())} views, |along| median "
                  f"{np.median(np.abs(al[sel])):.2f}, RMS {np.sqrt(np.mean(al[sel] ** 2)):.2f}, "
                  f"over 3 px {int(np.sum(big & sel))}")  # fmt: skip
    sins = np.array(
        [min(r["n_c3_a0.5_g0"]["sin"]) for r in cons if r["n_c3_a0.5_g0"]["sin"] is not None]
    )
    print(
        f"min sine per consistent frame: median {np.median(sins):.2f}, under 0.3: {int(np.sum(sins < 0.3))}"
    )
    for name in ("ref", "pipeline"):
        c = [r[name]["cpu_s"] for r in rows]
        print(f"{name} CPU s a frame: median {np.median(c):.3f}, max {max(c):.2f}")
    c = [r["n_f1_a0.5_g0"]["cpu_s"] + r["falloff_cpu_s"] for r in cons]
    print(
        f"fusion (fall-off + fuse_tips) CPU s a consistent frame: median {np.median(c):.4f}, max {max(c):.3f}"
    )


def main() -> int:
    ap = harness_parser(__doc__, "/tmp/real_like_tip_fusion")
    ap.add_argument("more", nargs="*", type=Path, help="further rows files for --summary")
    ap.add_argument("--only", help="--summary: the variants matching this regular expression")
    ap.add_argument("--half", choices=("even", "odd", "both"), default="both",
                    help="--summary: the even (design) seeds, the odd (test) ones or both")  # fmt: skip
    args = ap.parse_args()
    if args.summary is not None:
        summary([args.summary, *args.more], args.half, args.only)
        return 0
    evaluate(dev_seeds(ap, args), args.store, args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
