# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
# ---

# %% [markdown]
# # Refining one frame
#
# Kinematic-prior segmentation (Watson et al.): the robot's forward kinematics gives a nominal
# centreline from the joint values; it is wrong by the model error (tube precurvature,
# stiffness, ...). `jcr.refine` bends it, with a smooth curvature correction, until its
# rendered silhouette matches the image. The refined silhouette is the segmentation.
#
# The frame comes from `jaxcr synth` (preset "orthogonal", 320x240, the first of two frames):
# a ray-cast image of the robot over tissue, with the true robot mask beside it.

# %%
import os
import tempfile

import jax
import jax.numpy as jnp
import matplotlib.pyplot as plt
import numpy as np

import jaxcr as jcr
import jaxcr.kinematics.batch
import jaxcr.synth.generate

OUT = os.environ.get("JAXCR_EXAMPLES_OUT", ".")  # where the figure is written
path = jcr.synth.generate.generate(
    "orthogonal", tempfile.mkdtemp(), seed=0, frames=2, size=(320, 240), progress=False
)
ds = jcr.load_dataset(path)
frame = ds.frames[0]
cam_name = ds.camera_names[0]
camera = ds.cameras[cam_name]
rgb = frame.load_image(cam_name)  # (240, 320, 3) float32 in [0, 1]
truth = frame.load_mask(cam_name)  # (240, 320) bool: the robot's true silhouette

# %% [markdown]
# The nominal shape from the joint values, the image after background subtraction
# (`jcr.colour_mask`: background mask B and the subtracted image), and one refinement.
# A small configuration (the full-resolution level only, few steps) keeps the compile short:
# a coarse pyramid level helps when the nominal silhouette is far from the tube; here it is
# close enough for the fine level alone.

# %%
# the forward model, compiled: jcr.kinematics.batch.forward_batch is one jitted vmap of
# robot.forward over a batch of joint vectors (here the dataset's two frames), with the robot
# an argument -- the very program `jaxcr synth` ran for this robot and batch, so it is not
# compiled again (run op by op, the solver's loops would compile hundreds of small programs
# instead)
qs = jnp.asarray([f.q for f in ds.frames], jnp.float32)
fk = jaxcr.kinematics.batch.forward_batch(ds.robot, qs)
base = jax.tree.map(lambda x: x[0], fk.centreline)  # (N, 3) samples of the first frame
background, image = jcr.colour_mask(jnp.asarray(rgb))
config = jcr.RefineConfig(levels=(0,), steps=(30,), outer=(1,), tau=(0.5,))
result = jcr.refine(base, camera, image, background, config=config)
print("ok:", bool(result.ok), "steps:", int(result.num_steps))

# %% [markdown]
# The silhouettes of the nominal and the refined centreline (part of the result), against
# the true mask (intersection over union).

# %%
nominal_mask = np.asarray(result.nominal_masks[0])  # (h, w) bool, delta-u = 0
refined_mask = np.asarray(result.masks[0])  # (h, w) bool, the refined tube


def iou(a, b):
    return float((a & b).sum() / max((a | b).sum(), 1))


iou_nominal, iou_refined = iou(nominal_mask, truth), iou(refined_mask, truth)
print(f"IoU nominal {iou_nominal:.3f} -> refined {iou_refined:.3f}")
fig, axes = plt.subplots(1, 3, figsize=(8, 2.2))
titles = ("truth", f"nominal {iou_nominal:.2f}", f"refined {iou_refined:.2f}")
for ax, m, title in zip(axes, (truth, nominal_mask, refined_mask), titles, strict=True):
    ax.imshow(rgb)
    ax.contour(m, levels=[0.5], colors="y", linewidths=0.8)
    ax.set_title(title, fontsize=8)
    ax.axis("off")
fig.savefig(os.path.join(OUT, "refine_frame.png"), dpi=80)
jax.clear_caches()
