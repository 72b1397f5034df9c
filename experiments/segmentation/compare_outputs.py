"""Compare two ``jaxcr segment`` output folders, timings aside: every field of results.jsonl
(numbers: the largest absolute and relative difference per field path; other values: equal or
not) and every mask/centreline file byte for byte. Used to check that a compile-option change
(docs/decisions.md S22) leaves the results as they were.

Run: ``python experiments/segmentation/compare_outputs.py OUT_A OUT_B``; prints a summary.
"""

from __future__ import annotations

import json
import sys
from collections import defaultdict
from pathlib import Path

SKIP = {"time_s", "compile_s"}


def _walk(a, b, path, diffs, unequal):
    if isinstance(a, dict) and isinstance(b, dict):
        for k in sorted(set(a) | set(b)):
            if k in SKIP:
                continue
            _walk(a.get(k), b.get(k), f"{path}.{k}", diffs, unequal)
    elif isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
        for x, y in zip(a, b, strict=True):
            _walk(x, y, f"{path}[]", diffs, unequal)
    elif isinstance(a, (int, float)) and isinstance(b, (int, float)) and not isinstance(a, bool):
        d = abs(a - b)
        rel = d / max(abs(a), abs(b), 1e-300)
        old = diffs[path]
        diffs[path] = (max(old[0], d), max(old[1], rel if d else 0.0))
    elif a != b:
        unequal[path] += 1


def main(a: str, b: str) -> int:
    ra = [json.loads(x) for x in (Path(a) / "results.jsonl").read_text().splitlines() if x]
    rb = [json.loads(x) for x in (Path(b) / "results.jsonl").read_text().splitlines() if x]
    ra.sort(key=lambda r: r["frame"])
    rb.sort(key=lambda r: r["frame"])
    diffs: dict = defaultdict(lambda: (0.0, 0.0))
    unequal: dict = defaultdict(int)
    _walk(ra, rb, "", diffs, unequal)
    files = sorted(p.relative_to(a) for p in Path(a).rglob("*") if p.suffix in (".png", ".npy"))
    differ = [f for f in files if (Path(a) / f).read_bytes() != (Path(b) / f).read_bytes()]
    moved = {k: v for k, v in diffs.items() if v[0] > 0}
    print(f"{len(ra)} vs {len(rb)} records; {len(diffs)} numeric fields, {len(moved)} differ; "
          f"{sum(unequal.values())} other values differ; {len(files)} mask/centreline files, "
          f"{len(differ)} differ")  # fmt: skip
    for k, (d, rel) in sorted(moved.items(), key=lambda kv: -kv[1][1]):
        print(f"  {k}: max |diff| {d:.3g}, max relative {rel:.3g}")
    for k, n in unequal.items():
        print(f"  {k}: {n} unequal")
    for f in differ[:10]:
        print(f"  file differs: {f}")
    return 0


if __name__ == "__main__":
    sys.exit(main(*sys.argv[1:3]))
