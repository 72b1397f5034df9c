"""CPU per frame of `jaxcr segment`'s chunk with and without shape buckets, in one process
(docs/decisions.md S29): the Segmenter's own chunk (kinematics, background, refinement,
covariance; no overlays, files written to a temporary folder) on the first ``--batch`` frames
of DATASET, the two modes alternating ``--repeats`` times after one warm-up chunk each.
Process CPU seconds (``time.process_time``, all threads) per chunk / frames, and the
refinement's wall ``time_s``; medians. Run it on a cache that holds both modes' programs.

    python experiments/segmentation/shape_buckets_cpu.py DATASET --repeats 6 --name NAME
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import time
from pathlib import Path

OUT = Path(__file__).resolve().parents[2] / "experiments" / "results" / "segmentation"


def main() -> int:
    p = argparse.ArgumentParser()
    p.add_argument("dataset")
    p.add_argument("--repeats", type=int, default=6)
    p.add_argument("--batch", type=int, default=4)
    p.add_argument("--name", default="shape_buckets_cpu_s29")
    p.add_argument("--commit", default="?")
    a = p.parse_args()
    from jaxcr.cli import segment
    from jaxcr.io.compile_cache import enable_compile_cache
    from jaxcr.segmentation.batch import Segmenter

    enable_compile_cache()  # as the CLI: $JAXCR_CACHE_DIR
    parser = argparse.ArgumentParser()
    segment.add_parser(parser.add_subparsers())
    args = parser.parse_args(["segment", a.dataset, "-o", "unused"])
    ds = segment.load(a.dataset)
    cfg = segment.refine_config(args)
    segs = {}
    tmp = tempfile.mkdtemp(prefix="bucket-cpu-")
    for mode in ("off", "on"):
        segs[mode] = Segmenter(ds, ["main"], cfg, "colour", os.path.join(tmp, mode),
                               overlays=False, batch_size=a.batch,
                               shape_buckets=mode == "on")  # fmt: skip
    seg0 = segs["off"]
    ids = [f for f in seg0.frame_ids if f not in ds.bad_frames][: a.batch]
    chunk = [(f, seg0._check_frame(f)[0]) for f in ids]
    cpu = {m: [] for m in segs}
    wall = {m: [] for m in segs}
    loads = []
    for rep in range(a.repeats + 1):
        for mode in ("off", "on") if rep % 2 == 0 else ("on", "off"):
            t0 = time.process_time()
            recs = list(segs[mode]._process_chunk(chunk))
            dt = time.process_time() - t0
            if rep:  # the first round loads the programs
                cpu[mode].append(1e3 * dt / len(chunk))
                wall[mode].append(1e3 * statistics.median(r["time_s"] for r in recs))
        loads.append(os.getloadavg()[0])
    h, w = ds.cameras["main"].height, ds.cameras["main"].width
    lines = [f"# Shape buckets (S29): CPU per frame at {w}x{h}, buckets off vs on, one process",
             "", f"Commit {a.commit}; command: `python experiments/segmentation/"
             f"shape_buckets_cpu.py DATASET --repeats {a.repeats} --batch {a.batch} --name "
             f"{a.name}`; DATASET: `jaxcr synth --preset orthogonal --size {w}x{h} --frames 8 "
             f"--seed 11`. Load (1-min) per round: {', '.join(f'{x:.1f}' for x in loads)}.", "",
             "| buckets | chunk CPU ms per frame (median; all) | refinement time_s ms/frame "
             "(median; all) |", "|---|---|---|"]  # fmt: skip
    for m in ("off", "on"):
        lines.append(f"| {m} | **{statistics.median(cpu[m]):.1f}**; "
                     f"{', '.join(f'{x:.0f}' for x in cpu[m])} | "
                     f"{statistics.median(wall[m]):.1f}; {', '.join(f'{x:.0f}' for x in wall[m])} |")  # fmt: skip
    ratio = statistics.median(cpu["on"]) / statistics.median(cpu["off"])
    lines += ["", f"CPU ratio on / off: **{ratio:.3f}**."]
    (OUT / f"{a.name}.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
