# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
# ---

# %% [markdown]
# # Kinematics and projection
#
# A concentric-tube robot (`jcr.TEST_CTR`, three tubes), its forward kinematics for a few
# joint vectors in one compiled, vmapped call, and the centrelines projected into a camera.
# Everything a notebook needs comes from `import jaxcr as jcr`.
#
# Joint values q = (beta_1, beta_2, beta_3, alpha_1, alpha_2, alpha_3): translations (m,
# beta_1 <= beta_2 <= beta_3 <= 0) and rotations (rad) of the tubes at the actuation unit.

# %%
import os

import equinox as eqx
import jax
import jax.numpy as jnp
import matplotlib.pyplot as plt
import numpy as np

import jaxcr as jcr

OUT = os.environ.get("JAXCR_EXAMPLES_OUT", ".")  # where the figure is written

robot = jcr.robot_from_dict(jcr.TEST_CTR)
qs = jnp.array(
    [
        [-0.10, -0.05, -0.02, 0.0, 0.0, 0.0],
        [-0.10, -0.05, -0.02, 0.0, 1.0, 2.0],
        [-0.10, -0.05, -0.02, 0.3, -1.0, 2.0],
        [-0.12, -0.06, -0.01, 0.0, 3.0, -1.5],
    ]
)
# The model is a pytree (an equinox Module): pass it to the compiled function as an argument
# rather than closing over it, so one compiled program serves every robot of the same
# structure (other tube lengths, stiffnesses, precurvatures: no recompile)
fk = eqx.filter_jit(lambda m, q: jax.vmap(m.forward)(q))(robot, qs)  # leading axis B = 4
centrelines = fk.centreline.p  # (B, N, 3), robot frame, metres
print("converged:", np.asarray(fk.ok), "tips (mm):\n", np.round(1e3 * centrelines[:, -1], 2))

# %% [markdown]
# The same in one call with failure reasons as data (`jcr.forward`, no jit/vmap to write):

# %%
batch = jcr.forward(robot, np.asarray(qs))
print(batch.reasons)  # "" for every converged row

# %% [markdown]
# A 160x120 camera 0.7 m from the robot's axis, looking at its middle, and every centreline
# sample projected to pixels (`jcr.project_points`: pinhole + OpenCV distortion).

# %%
mid = float(centrelines[..., 2].mean())
camera = jcr.Camera.look_at(
    eye=[0.7, 0.0, mid], target=[0.0, 0.0, mid], up=[0.0, 0.0, 1.0], fx=120.0, size=(160, 120)
)
uv, valid = jax.vmap(jcr.project_points, in_axes=(None, 0))(camera, centrelines)  # (B, N, 2)

fig, ax = plt.subplots(figsize=(4, 3))
for b in range(len(qs)):
    ax.plot(uv[b, :, 0], uv[b, :, 1], label=f"q{b}")
ax.set_xlim(0, camera.width)
ax.set_ylim(camera.height, 0)  # image rows run downwards
ax.set_aspect("equal")
ax.legend(fontsize=6)
ax.set_title("TEST_CTR centrelines in the camera")
fig.savefig(os.path.join(OUT, "kinematics_projection.png"), dpi=80)
