"""Variant of the accuracy experiment: the paper's raw point counts instead of normalised
histograms (120 bins, 90 %, smoothing 1e-3, the paper's per-frame region centroid), from the
contour cache of eigen_accuracy.py.

    taskset -c 1 python experiments/eigen/eigen_rawcounts.py /tmp/irep experiments/results/eigen/eigen_rawcounts.json
"""

import json
import sys

import jax.numpy as jnp
import numpy as np
from eigen_common import _load, angle_errors

from jaxcr.eigen.colour import ColourModel
from jaxcr.eigen.model import TrainConfig, estimate, train
from jaxcr.eigen.pipeline import stereo_histograms
from jaxcr.io.dataset import load_dataset

DATA = sys.argv[1] if len(sys.argv) > 1 else "/tmp/irep"
c = DATA + "/cache/"
tr, te, to = (_load(c + f"contours_{n}.npz") for n in ("train", "test", "test_occluded"))
P = {
    n: np.array([f.q for f in load_dataset(DATA + "/" + n).frames])
    for n in ("train", "test", "test_occluded")
}
print(
    "marker px median occluded",
    np.median(to.views[0].marker_pixels),
    "unoccluded",
    np.median(te.views[0].marker_pixels),
    flush=True,
)
cm = ColourModel(jnp.zeros((5, 2)), jnp.asarray(0))
H, ok = stereo_histograms(tr, 120, False)
m = train(
    H,
    P["train"],
    cm,
    TrainConfig(n_bins=120, variance=0.9, smoothing=1e-3, normalise=False, centre="region"),
)
out = {}
for name, sc in (("test", te), ("test_occluded", to)):
    Ht, okt = stereo_histograms(sc, 120, False)
    out[name] = angle_errors(estimate(m, Ht), P[name])
    print(
        "raw counts",
        m.n_components,
        name,
        {k: round(v, 3) for k, v in out[name].items()},
        flush=True,
    )
json.dump(
    {"dims": m.n_components, **out},
    open(sys.argv[2] if len(sys.argv) > 2 else "eigen_rawcounts.json", "w"),
)
