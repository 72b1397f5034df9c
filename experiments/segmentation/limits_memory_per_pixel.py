"""Peak memory per pixel of each synthetic renderer, the basis of jaxcr.limits.MAX_PIXELS.

Each renderer draws one frame (motion: its 6-frame minimum; model-object: one RGB-D view) at
320x240 and at 640x480 in a fresh process, after a warm-up frame at 160x120 (imports and
compilations are then not counted). The peak memory traced by ``tracemalloc`` (numpy arrays
report their buffers to it; XLA's own buffers are not traced) is divided by the pixels at
640x480: that figure includes the fixed part, so it over-estimates the per-pixel cost at
larger sizes and the ceiling derived from it is conservative. The slope between the two
sizes is reported beside it.

Reproduce (about 5 minutes on one core):
    PYTHONPATH=$PWD python experiments/segmentation/limits_memory_per_pixel.py
writes experiments/results/segmentation/limits_memory_per_pixel.md and .json.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
import tracemalloc
from pathlib import Path

import numpy as np

KINDS = ["synth", "stereo synth", "motion synth", "manifold synth", "model-object"]
SIZES = [(320, 240), (640, 480)]


def render(kind: str, size: tuple[int, int], d: str) -> None:
    shutil.rmtree(d, ignore_errors=True)
    if kind == "synth":
        from jaxcr.synth.generate import generate

        generate("orthogonal", d, seed=0, frames=1, size=size, progress=False)
    elif kind == "stereo synth":
        from jaxcr.synth.stereo_ctr import generate_stereo_set

        generate_stereo_set(d, 1, 0, size, "green", progress=False)
    elif kind == "motion synth":
        from jaxcr.synth.motion_scenes import generate_motion_video

        generate_motion_video(d, "pushed_static", seed=0, size=size, n_frames=6)
    elif kind == "manifold synth":
        from jaxcr.synth.irep import generate_irep

        generate_irep(d, 1, "train", 0, size, progress=False)
    else:
        from jaxcr.synth.rgbd_tasks import RgbdSimulator, generate_task

        generate_task(d, "1", 0, size)
        T = np.eye(4)
        T[:3, :3] = [[1, 0, 0], [0, 0, 1], [0, -1, 0]]  # looking along +y at the target
        T[:3, 3] = [0, -0.3, 0.1]
        RgbdSimulator(d).capture(T)


def measure(kind: str) -> dict:
    tmp = tempfile.mkdtemp(prefix="jaxcr_limits_")
    try:
        render(kind, (160, 120), os.path.join(tmp, "warm"))
        peaks = {}
        for w, h in SIZES:
            tracemalloc.start()
            render(kind, (w, h), os.path.join(tmp, f"{w}x{h}"))
            peaks[f"{w}x{h}"] = tracemalloc.get_traced_memory()[1]
            tracemalloc.stop()
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    (a, b), (pa, pb) = peaks.values(), [w * h for w, h in SIZES]
    return {"peak_bytes": peaks, "bytes_per_pixel_640x480": b / pb,
            "slope_bytes_per_pixel": (b - a) / (pb - pa)}  # fmt: skip


def main() -> None:
    if len(sys.argv) == 2:  # child: one renderer in a fresh process
        print(json.dumps(measure(sys.argv[1])))
        return
    from jaxcr import limits

    res = {}
    for kind in KINDS:
        out = subprocess.run([sys.executable, __file__, kind], capture_output=True, text=True,
                             check=True, env={**os.environ, "JAX_PLATFORMS": "cpu"})  # fmt: skip
        res[kind] = json.loads(out.stdout.strip().splitlines()[-1])
    lines = [
        "# Peak memory per pixel of the synthetic renderers (jaxcr.limits)",
        "",
        "Command: `PYTHONPATH=$PWD python experiments/segmentation/limits_memory_per_pixel.py`",
        "",
        "| renderer | peak 320x240 (MB) | peak 640x480 (MB) | bytes/px at 640x480 | slope "
        "(bytes/px) | jaxcr.limits bytes/px | ceiling (MP) |",
        "|---|---|---|---|---|---|---|",
    ]
    for kind, r in res.items():
        p = r["peak_bytes"]
        lines.append(
            f"| {kind} | {p['320x240'] / 1e6:.1f} | {p['640x480'] / 1e6:.1f} | "
            f"{r['bytes_per_pixel_640x480']:.0f} | {r['slope_bytes_per_pixel']:.0f} | "
            f"{limits.RENDER_BYTES_PER_PIXEL[kind]} | {limits.MAX_PIXELS[kind] / 1e6:.1f} |"
        )
    lines += ["", f"Budget: {limits.MEMORY_BUDGET >> 30} GiB; ceiling = budget / bytes per pixel "
              "at 640x480 (includes the fixed part: conservative)."]  # fmt: skip
    root = Path(__file__).parent.parent / "results" / "segmentation"
    root.mkdir(exist_ok=True)
    (root / "limits_memory_per_pixel.md").write_text("\n".join(lines) + "\n")
    (root / "limits_memory_per_pixel.json").write_text(json.dumps(res, indent=1) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
