"""Interleaved A/B of jaxcr.colour.rgb_to_lab: the previous implementation (matmul over the
trailing colour axis, jnp.cbrt, pow; up to commit 85d65a8) vs the current one (channel by channel,
exp/log + one Newton step), jitted on CPU.

  python experiments/segmentation/colour_bench.py

Times (median [IQR] of 30 alternating calls, ms): the conversion alone at 320x240 and 640x480,
and the motion pipeline's tracked segmentation step (jaxcr.motion.superpixels.segment_track at
the motion bench's default shape: 640x480 frame, 320x240 working, 20 working px, 2 iterations)
with the old, the new and no Lab conversion (rgb * 100, to bound the conversion's share).
Writes experiments/results/segmentation/colour_bench.md. About 30 s.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import cv2
import jax
import jax.numpy as jnp
import numpy as np

import jaxcr.motion.superpixels as sp
from jaxcr import colour

OUT = Path(__file__).parent.parent / "results" / "segmentation" / "colour_bench.md"


def old_rgb_to_lab(rgb):
    """jaxcr.colour.rgb_to_lab before this change."""
    rgb = jnp.clip(rgb, 0.0, 1.0)
    lin = jnp.where(rgb > 0.04045, ((rgb + 0.055) / 1.055) ** 2.4, rgb / 12.92)
    M = jnp.asarray(colour._RGB2XYZ, rgb.dtype)
    xyz = (lin @ M.T) / jnp.asarray(colour._WHITE, rgb.dtype)
    eps = colour._EPS
    f = jnp.where(xyz > eps, jnp.cbrt(jnp.maximum(xyz, eps)), 7.787 * xyz + 16.0 / 116.0)
    L = jnp.where(xyz[..., 1] > eps, 116.0 * f[..., 1] - 16.0, 903.3 * xyz[..., 1])
    return jnp.stack([L, 500.0 * (f[..., 0] - f[..., 1]), 200.0 * (f[..., 1] - f[..., 2])], -1)


def load() -> str:
    return " ".join(f"{v:.1f}" for v in os.getloadavg())


def interleaved(calls: dict, n: int = 30) -> dict[str, str]:
    for f in calls.values():
        jax.block_until_ready(f())
    ts: dict[str, list[float]] = {k: [] for k in calls}
    for _ in range(n):
        for k, f in calls.items():
            t = time.perf_counter()
            jax.block_until_ready(f())
            ts[k].append(1e3 * (time.perf_counter() - t))
    return {
        k: f"{np.median(v):.2f} [{np.percentile(v, 25):.2f}, {np.percentile(v, 75):.2f}]"
        for k, v in ts.items()
    }


def smooth_image(h: int, w: int, rng) -> np.ndarray:
    img = cv2.GaussianBlur(rng.random((h, w, 3), dtype=np.float32), (0, 0), 6)
    return ((img - img.min()) / (img.max() - img.min())).astype(np.float32)


def main() -> None:
    rng = np.random.default_rng(0)
    lines = [
        "# jaxcr.colour.rgb_to_lab: previous vs current (interleaved A/B)",
        "",
        f"jax {jax.__version__}, CPU; load average (1, 5, 15 min) {load()} at the start",
        "",
        "| what | previous (ms) | current (ms) | no Lab (ms) |",
        "|---|---|---|---|",
    ]
    f_old, f_new = jax.jit(old_rgb_to_lab), jax.jit(colour.rgb_to_lab)
    for h, w in [(240, 320), (480, 640)]:
        x = jnp.asarray(smooth_image(h, w, rng))
        r = interleaved({"old": lambda x=x: f_old(x), "new": lambda x=x: f_new(x)})
        lines.append(f"| rgb_to_lab alone, {w}x{h} | {r['old']} | {r['new']} | - |")

    h, w, step = 240, 320, 20
    x = jnp.asarray(smooth_image(h, w, rng))
    lbl0 = sp.grid_labels(h, w, step)
    n_seg = int(np.asarray(lbl0).max()) + 1
    flow = jnp.zeros((h, w, 2), jnp.float32)
    statics = ("n_segments", "step", "n_iter", "scale", "height", "width")
    kw = dict(n_segments=n_seg, step=step, compactness=10.0, n_iter=2, scale=2)
    kw.update(height=480, width=640)
    current = sp.rgb_to_lab
    fns, labels = {}, {}
    try:
        for name, impl in (("old", old_rgb_to_lab), ("new", current), ("none", lambda r: r * 100)):
            sp.rgb_to_lab = impl  # looked up when segment_track is traced

            # A fresh function object per variant: jax caches traces per function, so jitting
            # segment_track.__wrapped__ itself again would reuse the first variant's trace.
            def fresh(*a, **k):
                return sp.segment_track.__wrapped__(*a, **k)

            f = jax.jit(fresh, static_argnames=statics)
            labels[name] = np.asarray(f(lbl0, flow, x, **kw)[0])
            fns[name] = lambda f=f: f(lbl0, flow, x, **kw)
    finally:
        sp.rgb_to_lab = current
    r = interleaved(fns)
    lines.append(
        f"| segment_track (working 320x240, 20 px, 2 iterations) | {r['old']} | {r['new']} "
        f"| {r['none']} |"
    )
    same = int((labels["old"] != labels["new"]).sum())
    # Guard: the no-Lab variant must really be a different program (different labels).
    assert (labels["none"] != labels["old"]).any(), "variants share one trace"
    lines += [
        "",
        f"Load average at the end: {load()}. Median [IQR] of 30 alternating calls after a "
        "compile call; smooth random image.",
        f"segment_track labels, previous vs current Lab: {same} of {labels['old'].size} pixels "
        "differ.",
    ]
    OUT.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
