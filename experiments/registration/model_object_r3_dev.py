"""Decision R3 (issue 17 item 10): the pipeline's variants on the development seeds, each run by
the fresh-seed harness (``model_object_fresh_seeds.py``, one JSON-lines log per variant), compared
run by run. Development seeds 0-9 only.

    python experiments/registration/model_object_fresh_seeds.py --seeds 0-9 --tasks 1 2 \
        --scratch /tmp/r3/base --log /tmp/r3/base.jsonl --out /tmp/r3/out --name base
    python experiments/registration/model_object_fresh_seeds.py --seeds 0-9 --tasks 1 2 \
        --scratch /tmp/r3/sw --log /tmp/r3/sw.jsonl --out /tmp/r3/out --name sw \
        --set edge_information=sandwich
    python experiments/registration/model_object_r3_dev.py --base /tmp/r3/base.jsonl \
        --variant sandwich=/tmp/r3/sw.jsonl

Writes experiments/results/registration/model_object_r3_dev.md (+ .json); the text below the
tables is written by hand.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

OUT = Path(__file__).parent.parent / "results" / "registration"
GOAL_MM, GOAL_DEG = 2.0, 1.0


def read(path: Path) -> dict:
    out = {}
    for line in path.read_text().splitlines():
        if line.strip():
            r = json.loads(line)
            out[(r["task"], r["seed"])] = r
    return out


def view_key(v: dict) -> tuple:
    return (v["run"], v["index"])


def summary(recs: list[dict]) -> dict:
    ok = [r for r in recs if r["status"] == "ok"]
    worst = [r["worst_trans_mm"] for r in ok]
    return {
        "runs": len(recs),
        "ok": len(ok),
        "worst_max": max(worst) if worst else float("nan"),
        "worst_mean": float(np.mean(worst)) if worst else float("nan"),
        "median_median": float(np.median([r["median_trans_mm"] for r in ok])) if ok else 0,
        "goal": sum(r["worst_trans_mm"] <= GOAL_MM and r["worst_rot_deg"] <= GOAL_DEG for r in ok),
        "worst_deg": max(r["worst_rot_deg"] for r in ok) if ok else float("nan"),
    }


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--base", required=True, help="harness log of the defaults")
    ap.add_argument("--variant", action="append", default=[], metavar="NAME=LOG")
    ap.add_argument("--out", default=str(OUT))
    ap.add_argument("--name", default="model_object_r3_dev")
    a = ap.parse_args()
    base = read(Path(a.base))
    variants = {}
    for item in a.variant:
        name, _, path = item.partition("=")
        variants[name] = read(Path(path))
    commit = subprocess.run(
        ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True
    ).stdout.strip()
    cmd = "python experiments/registration/model_object_r3_dev.py " + " ".join(sys.argv[1:])
    md = [
        "# Object modelling: edge information and frames per capture on the development seeds (decision R3, issue 17 item 10)",
        "",
        f"Report written at commit {commit} by `{cmd}` from the harness logs named there. "
        "Errors of every view's camera pose after global optimisation against the truth, "
        "frame O = the last ring view (the anchor left out). Development seeds 0-9 only.",
        "",
    ]
    for name, var in variants.items():
        keys = sorted(set(base) & set(var))
        md += [
            f"## defaults -> {name}",
            "",
            "| task | seed | worst mm | worst view | median mm | worst deg | far first capture mm "
            "| views changed > 0.1 mm (up / down) |",
            "|---|---|---|---|---|---|---|---|",
        ]
        deltas = []
        firsts: dict[str, list[tuple[float, float]]] = {}
        for k in keys:
            b, v = base[k], var[k]
            if b["status"] != "ok" or v["status"] != "ok":
                md.append(f"| {k[0]} | {k[1]} | {b['status']} -> {v['status']} | | | | | |")
                continue
            bv = {view_key(x): x for x in b["views"]}
            vv = {view_key(x): x for x in v["views"]}
            common = [x for x in bv if x in vv]
            d = [vv[x]["trans_mm"] - bv[x]["trans_mm"] for x in common]
            deltas += d
            first = [x for x in common if x[1] == 0]
            anchor = len([x for x in b["views"] if x["ring_position"] is not None]) - 1
            firsts.setdefault(k[0], []).extend(
                (bv[x]["trans_mm"], vv[x]["trans_mm"])
                for x in first
                if bv[x]["ring_position"] != anchor and vv[x]["ring_position"] != anchor
            )
            fc = " ; ".join(
                f"{bv[x]['trans_mm']:.2f} -> {vv[x]['trans_mm']:.2f}" for x in sorted(first)
            )
            up = sum(x > 0.1 for x in d)
            down = sum(x < -0.1 for x in d)
            md.append(
                f"| {k[0]} | {k[1]} | {b['worst_trans_mm']:.2f} -> {v['worst_trans_mm']:.2f} | "
                f"{b['worst_view']} -> {v['worst_view']} | {b['median_trans_mm']:.2f} -> "
                f"{v['median_trans_mm']:.2f} | {b['worst_rot_deg']:.3f} -> {v['worst_rot_deg']:.3f} "
                f"| {fc} | {up} / {down} |"
            )
        md += [
            "",
            "| task | runs | worst max mm | mean of run worst mm | median of run medians mm | goal met | worst deg |",
            "|---|---|---|---|---|---|---|",
        ]
        for task in sorted({k[0] for k in keys}):
            sb = summary([base[k] for k in keys if k[0] == task])
            sv = summary([var[k] for k in keys if k[0] == task])
            md.append(
                f"| {task} | {sb['runs']} | {sb['worst_max']:.2f} -> {sv['worst_max']:.2f} | "
                f"{sb['worst_mean']:.2f} -> {sv['worst_mean']:.2f} | {sb['median_median']:.2f} -> "
                f"{sv['median_median']:.2f} | {sb['goal']} -> {sv['goal']} of {sb['ok']} | "
                f"{sb['worst_deg']:.3f} -> {sv['worst_deg']:.3f} |"
            )
        for task, pairs in sorted(firsts.items()):
            fa = np.asarray(pairs)
            md.append(
                f"\nTask {task}, the routes' first captures (capture 0, the anchor left out; "
                f"{len(fa)}): mean {fa[:, 0].mean():.2f} -> {fa[:, 1].mean():.2f} mm, max "
                f"{fa[:, 0].max():.2f} -> {fa[:, 1].max():.2f} mm, lower in "
                f"{int(np.sum(fa[:, 1] < fa[:, 0]))}."
            )
        if deltas:
            dd = np.asarray(deltas)
            md += [
                "",
                f"Every view (anchor included, {len(dd)}): change mean {dd.mean():+.3f} mm, "
                f"median {np.median(dd):+.3f}, largest increase {dd.max():+.2f}, largest "
                f"decrease {dd.min():+.2f} mm.",
                "",
            ]
    out = Path(a.out)
    (out / f"{a.name}.md").write_text("\n".join(md) + "\n")
    (out / f"{a.name}.json").write_text(
        json.dumps(
            {
                "command": cmd,
                "commit": commit,
                "base": [base[k] for k in sorted(base)],
                "variants": {n: [v[k] for k in sorted(v)] for n, v in variants.items()},
            },
            indent=1,
        )
    )
    print("\n".join(md))


if __name__ == "__main__":
    main()
