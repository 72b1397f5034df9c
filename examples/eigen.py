# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
# ---

# %% [markdown]
# # Eigen-features: pose of a single-segment robot from a stereo pair
#
# Reiter et al.: the robot's end disc carries a coloured marker; its contour in each view is
# summarised by an angular histogram, the two histograms are projected on their principal
# components ("eigen-features"), and a thin-plate spline maps the configuration
# psi = (theta_L, delta) (radians, Reiter et al. eq. 1) to those features. Training samples
# that manifold; a query finds the nearest manifold points of a new pair's features and
# returns their inverse-distance mean of psi (eqs. 7-8).
#
# The data are two small synthetic IREP stereo sets (`jaxcr.synth.irep`, 160x120): one to
# train on, one with configurations the training never saw.

# %%
import os
import tempfile

import matplotlib.pyplot as plt
import numpy as np

import jaxcr as jcr
import jaxcr.eigen.pipeline
import jaxcr.synth.irep

OUT = os.environ.get("JAXCR_EXAMPLES_OUT", ".")  # where the figure is written
root = tempfile.mkdtemp()
jcr.synth.irep.generate_irep(f"{root}/train", 24, "train", seed=0, size=(160, 120),
                             progress=False)  # fmt: skip
jcr.synth.irep.generate_irep(f"{root}/test", 4, "test", seed=0, size=(160, 120), progress=False)
train_set, test_set = jcr.load_dataset(f"{root}/train"), jcr.load_dataset(f"{root}/test")
cameras = ("left", "right")

# %% [markdown]
# Descriptors: a colour model (k-means in CIELAB a*b* of one frame; the marker is the
# cluster nearest to lime green), each view's marker contour, and the stereo angular
# histograms (24 bins per view here) about fixed per-view centres.

# %%
config = jcr.eigen.TrainConfig(n_bins=24, variance=0.95, step=0.05, cameras=cameras)
colour = jcr.eigen.fit_colour_model(train_set.frames[0].load_image("left"), k=5)


def descriptors(dataset, centres=None):
    """Stereo histograms (n, 2 n_bins) of every frame, which frames have the marker in both
    views, and the fixed per-view histogram centres (from this set when not given)."""
    contours = jcr.eigen.pipeline.dataset_contours(dataset, colour, cameras, config.spacing)
    if centres is None:
        centres = jcr.eigen.view_centres(contours)  # (2, 2) pixels, one per view
    H, ok = jcr.eigen.stereo_histograms(contours, config.n_bins, config.normalise, centres)
    return H, ok, centres


H, ok, centres = descriptors(train_set)
psi = np.stack([np.asarray(f.q, np.float64) for f in train_set.frames])  # (n, 2) radians
print(f"{int(ok.sum())} of {len(ok)} training pairs have the marker in both views")

# %% [markdown]
# Train (PCA keeping 95 % of the variance, spline, resampling on a 0.05 rad grid), then
# estimate psi for the unseen test pairs: `jcr.eigen.estimate` for a batch, or
# `jcr.eigen.query` for one eigen-feature vector.

# %%
model = jcr.eigen.train(H[ok], psi[ok], colour, config, view_centres=centres)
print(f"{model.n_components} eigen-features, {model.manifold.psi.shape[0]} manifold points")

H_test, ok_test, _ = descriptors(test_set, model.view_centres)  # the training centres
psi_test = np.stack([np.asarray(f.q, np.float64) for f in test_set.frames])
estimates = jcr.eigen.estimate(model, H_test[ok_test])  # (m, 2) radians
features = jcr.eigen.model.eigen_features(model, H_test[ok_test][:1])  # (1, k)
one = jcr.eigen.query(model.manifold, features[0], b=config.b)  # (2,) radians
error_deg = np.degrees(np.abs(estimates - psi_test[ok_test]))
print("test error (deg), theta_L and delta per pair:\n", np.round(error_deg, 2))

# %% [markdown]
# The manifold (every resampled configuration) and the test pairs: truth and estimate.

# %%
fig, ax = plt.subplots(figsize=(5, 4))
grid = np.degrees(np.asarray(model.manifold.psi))
ax.plot(grid[:, 1], grid[:, 0], ".", color="0.8", ms=2, label="manifold")
ax.plot(np.degrees(psi[ok, 1]), np.degrees(psi[ok, 0]), "k+", label="training pairs")
ax.plot(np.degrees(psi_test[ok_test, 1]), np.degrees(psi_test[ok_test, 0]), "go", mfc="none",
        label="test: truth")  # fmt: skip
ax.plot(np.degrees(estimates[:, 1]), np.degrees(estimates[:, 0]), "rx", label="test: estimate")
ax.set_xlabel("delta (deg)")
ax.set_ylabel("theta_L (deg)")
ax.legend(fontsize=7)
fig.tight_layout()
fig.savefig(os.path.join(OUT, "eigen.png"), dpi=80)
