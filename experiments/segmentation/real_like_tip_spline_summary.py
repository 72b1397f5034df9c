"""Summary of ``real_like_tip_spline.py eval`` rows (round 13): per variant the frames with
both tips within 5 px and the views within 5 px, the frames where a variant differs from
``ref`` (px, view 1 / view 2), and CPU seconds of the two-view steps.

    python experiments/segmentation/real_like_tip_spline_summary.py ROWS.json
"""

from __future__ import annotations

import json
import sys

import numpy as np


def main(path: str) -> int:
    rows = {r["seed"]: r for r in json.loads(open(path).read())["rows"]}  # one per seed
    rows = [rows[s] for s in sorted(rows)]
    names = [k for k in rows[0] if k not in ("seed", "n_alts")]
    print(f"{len(rows)} frames: {', '.join(str(r['seed']) for r in rows)}\n")
    # Frames where a branch choice ran (the spline score's fits took time there).
    ran = [r for r in rows if r.get("spline", {}).get("cpu_s", 0.0) > 0.05]
    print("| variant | frames with both views within 5 px | views within 5 px | CPU s a frame "
          f"where the branch choice ran ({len(ran)} frames; median / max, two-view steps) |"
          "\n|---|---|---|---|")  # fmt: skip
    for n in names:
        ok = sum(max(r[n]["err_px"]) <= 5 for r in rows)
        v = sum(x <= 5 for r in rows for x in r[n]["err_px"])
        cpu = [r[n]["cpu_s"] for r in ran if "cpu_s" in r[n]]
        c = f"{np.median(cpu):.2f} / {max(cpu):.1f}" if cpu else ""
        print(f"| {n} | {ok} of {len(rows)} | {v} of {2 * len(rows)} | {c} |")
    fail = [r for r in rows if max(r["ref"]["err_px"]) > 5]
    reach = (
        [r["seed"] for r in fail if max(r["oracle"]["err_px"]) <= 5] if "oracle" in names else []
    )
    print(
        f"\n`ref` fails {len(fail)} frames; a candidate pair (end-face tips, before the tip "
        f"step) has both tips within 5 px in {len(reach)} of them: {reach}\n"
    )
    for n in names:
        if n == "ref":
            continue
        diff = [
            f"{r['seed']} {r['ref']['err_px'][0]:.1f} / {r['ref']['err_px'][1]:.1f} -> "
            f"{r[n]['err_px'][0]:.1f} / {r[n]['err_px'][1]:.1f}"
            for r in rows
            if max(abs(a - b) for a, b in zip(r["ref"]["err_px"], r[n]["err_px"], strict=True))
            > 0.05
        ]
        print(f"- `{n}` differs from `ref` on {len(diff)}: " + "; ".join(diff))
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1]))
