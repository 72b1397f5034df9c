# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
# ---

# %% [markdown]
# # Stereo shape sensing
#
# The backbone of a concentric-tube robot from one calibrated stereo pair (Shape Sensing of
# Tubular Continuum Robots using Stereo Vision): chroma-key segmentation, thinning, ordering,
# matching along epipolar lines, triangulation and a base frame from ArUco markers.
#
# The pair comes from `jaxcr stereo synth` (the same as `jcr.synth.stereo_ctr.generate_stereo_set`),
# a small 320x240 set with the true backbone stored beside the images: three tubes bent in
# general directions (`kinds=("general",)`), the kind of scene docs/your-own-rig.md's
# example rig is drawn from.

# %%
import os
import tempfile

import matplotlib.pyplot as plt
import numpy as np

import jaxcr as jcr
import jaxcr.io.stereo_dataset
import jaxcr.synth.stereo_ctr

OUT = os.environ.get("JAXCR_EXAMPLES_OUT", ".")  # where the figure is written
folder = jcr.synth.stereo_ctr.generate_stereo_set(
    tempfile.mkdtemp(), n_frames=1, seed=4, size=(320, 240), kinds=("general",), n_tubes=3
)
ds = jcr.io.stereo_dataset.load_stereo_dataset(folder)  # calibration, config, frames
frame = ds["frames"][0]
image1, image2 = (
    jcr.io.stereo_dataset.read_rgb(ds["root"] / frame["images"][c]) for c in ("cam1", "cam2")
)
truth = np.load(ds["root"] / frame["truth"])  # p: (n, 3) true backbone, base frame, metres

# %% [markdown]
# One call: `jcr.stereo.reconstruct` returns a `StereoReconstruction` (numpy arrays, base
# frame, metres): arc length `s`, backbone `p`, fused tube diameter, segments, ...

# %%
rec = jcr.stereo.reconstruct(image1, image2, ds["cam1"], ds["cam2"], config=ds["config"])
print(f"{len(rec.p)} backbone points, {len(rec.segments)} segment(s), "
      f"length {1e3 * rec.s[-1]:.1f} mm (true {1e3 * truth['s'][-1]:.1f} mm)")  # fmt: skip

# %% [markdown]
# The reconstruction against the truth (side view, base frame) and the skeleton it was
# triangulated from, in camera 1.

# %%
fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(7, 3))
ax1.plot(1e3 * truth["p"][:, 0], 1e3 * truth["p"][:, 2], "k-", lw=3, alpha=0.3, label="truth")
ax1.plot(1e3 * rec.p[:, 0], 1e3 * rec.p[:, 2], "r-", lw=1, label="stereo")
ax1.set_xlabel("x (mm)")
ax1.set_ylabel("z (mm)")
ax1.set_aspect("equal")
ax1.legend(fontsize=6)
ax2.imshow(image1)
ax2.plot(*np.asarray(rec.skeleton_rc[0])[:, ::-1].T, "r.", ms=1)
ax2.set_title("camera 1 and its skeleton", fontsize=8)
fig.savefig(os.path.join(OUT, "stereo.png"), dpi=80)
