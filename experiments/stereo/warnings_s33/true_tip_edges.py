"""True tips' distance to the image border in real_like views, without rendering:
the preset's cameras and robot for SEED (render_real_like_frame's first draws).
Usage: true_tip_edges.py FIRST LAST (development seeds 4000-4199 only)."""

import sys

import numpy as np

from jaxcr.stereo.aruco import MarkerLayout
from jaxcr.synth import real_like as rl

lo, hi = int(sys.argv[1]), int(sys.argv[2])
assert hi < 4200
edges, lengths = [], []
for seed in range(lo, hi + 1):
    rng = np.random.default_rng([seed, 16])
    layout = MarkerLayout()
    cams = rl.stereo_cameras((1280, 720), layout, rng)
    robot = rl.sample_robot(rng, "general", layout, cams)
    fine = rl.cc_backbone(robot, 1e-3)
    for cam in cams:
        bb = rl._project(cam, fine["p"])
        lengths.append(float(np.sum(np.linalg.norm(np.diff(bb, axis=0), axis=1))))
        u, v = bb[-1]
        edges.append(min(u, v, cam.width - 1 - u, cam.height - 1 - v))
edges = np.array(edges)
print(
    f"seeds {lo}-{hi}: {len(edges)} views; true tip to border px: min {edges.min():.1f}, "
    f"5th pct {np.percentile(edges, 5):.1f}, median {np.median(edges):.1f}; "
    f"under 40 px: {int(np.sum(edges < 40))}, under 20: {int(np.sum(edges < 20))}, outside: {int(np.sum(edges < 0))}"
)
lengths = np.array(lengths)
print(
    f"projected backbone length px: min {lengths.min():.1f}, 5th pct {np.percentile(lengths, 5):.1f}, "
    f"median {np.median(lengths):.1f}; under 100 px: {int(np.sum(lengths < 100))}"
)
