"""The failing frames of the used fresh real_like sets, classified (issue 16 item 2, round
13): per frame whose ``trace_stereo`` tips are not both within 5 px, the worse view's error
class (5-10, 10-30, > 30 px), whether that view's one-view ``trace`` was already off (else a
two-view step moved it off), and whether the final tips are still flagged (over 5 px from
each other's epipolar lines). Reads the committed per-seed JSON of the reports; prints
Markdown (the class table, then one row per frame).

    python experiments/segmentation/real_like_fail_classes.py 8 9 10 11 12
"""

from __future__ import annotations

import collections
import json
import sys
from pathlib import Path

RESULTS = Path(__file__).resolve().parents[1] / "results" / "segmentation"


def _cls(x: float) -> str:
    return "5-10" if x <= 10 else "10-30" if x <= 30 else ">30"


def main(rounds) -> int:
    fails = []
    n = 0
    for r in rounds:
        d = json.loads((RESULTS / f"real_like_tip_r{r}_1280x720.json").read_text())
        for row in d["rows"]:
            n += 1
            e = [v["trace_stereo"]["err_px"] for v in row["views"]]
            if max(e) > 5.0:
                fails.append((r, row))
    table = collections.defaultdict(collections.Counter)
    lines = []
    for r, row in sorted(
        fails, key=lambda x: -max(v["trace_stereo"]["err_px"] for v in x[1]["views"])
    ):
        e = [v["trace_stereo"]["err_px"] for v in row["views"]]
        t = [v["trace"]["err_px"] for v in row["views"]]
        broke = any(ee > 5 and tt <= 5 for ee, tt in zip(e, t, strict=True))
        flag = row["epipolar_px"]["trace_stereo"] > 5.0
        c = _cls(max(e))
        for key in (c, "all"):
            table[key]["frames"] += 1
            table[key]["two-view" if broke else "one-view"] += 1
            table[key]["flagged" if flag else "consistent"] += 1
            table[key]["both views"] += sum(x > 5 for x in e) == 2
        act = row["views"][0]["trace_stereo"]["recheck"]
        br = [str(i + 1) for i, v in enumerate(row["views"]) if v["trace_stereo"].get("branch")]
        lines.append(
            f"| r{r} | {row['seed']} | {e[0]:.1f} / {e[1]:.1f} | {t[0]:.1f} / {t[1]:.1f} | "
            f"{row['epipolar_px']['trace_stereo']:.1f} | {act}"
            + (f"; branch {','.join(br)}" if br else "")
            + f" | {c} | {'two-view step' if broke else 'one-view trace'} |"
        )
    print(f"{len(fails)} failing of {n} frames\n")
    print("| class | frames | one-view trace not mended | broken by a two-view step | final flagged "
          "| final consistent | both views over 5 px |\n|---|---|---|---|---|---|---|")  # fmt: skip
    for key in (">30", "10-30", "5-10", "all"):
        c = table[key]
        print(f"| {key} | {c['frames']} | {c['one-view']} | {c['two-view']} | {c['flagged']} | "
              f"{c['consistent']} | {c['both views']} |")  # fmt: skip
    print()
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main([int(x) for x in sys.argv[1:]] or [8, 9, 10, 11, 12]))
