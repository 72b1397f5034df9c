"""The float64 finite-difference scene of the band-energy tests and its energy, compiled once.

tests/segmentation/test_energy.py (gradient of the band energy vs central differences) and
tests/segmentation/test_least_squares.py (the least-squares form against the BFGS energy's
gradient) check the same energy on the same kind of scene: a 12 cm tube seen at pyramid
level 1 of a smooth 96x72 image (smooth so the energy is smooth at the difference step),
x64. The scene is an argument of the compiled functions (closed-over arrays would be
constants of each program), so every scene, in both modules, runs one compiled
``value_and_grad`` program per (local, robust) pair: the run's compilation cache serves the
second module. Call everything here inside ``jax.enable_x64(True)``.
"""

import cv2
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from jaxcr.camera import Camera
from jaxcr.segmentation.energy import Weights, chan_vese_energy
from jaxcr.segmentation.shape import perturbed_centreline
from jaxcr.segmentation.silhouette import project_tube, scale_tube
from tests.helpers.jitted import integrate_centreline, prepare_region_data, select_band

W, H = 96, 72
TAU = 1.5
AREA = 500.0


def smooth_scene(u, background_cols: int = 10):
    """``(centreline, camera, region data, band)`` in float64: the 33-point tube of constant
    curvature ``u`` (3,) 1/m, the camera 0.3 m in front (fx = 120 px), a blurred random
    image with a horizontal red ramp, the first ``background_cols`` columns background, the
    region data and the band (30 tiles, 8 candidates) at level 1."""
    # the inputs as numpy arrays and the tube drawn by one compiled program: built op by op
    # in x64, every primitive was an XLA compilation of its own (~40 per module)
    n = 33
    s = np.linspace(0.0, 0.12, n)
    u = np.tile(np.asarray(u, np.float64), (n - 1, 1))
    R0 = np.array([[0.0, 0, 1], [0, 1, 0], [-1, 0, 0]])
    cl = integrate_centreline(s, u, np.full(n, 4e-3), np.array([-0.05, 0.0, 0.0]), R0)
    cam = Camera.look_at([0, 0, -0.3], [0, 0, 0], [0, -1, 0], fx=120.0, size=(W, H))
    cam = jax.tree.map(
        lambda x: jnp.asarray(np.asarray(x, np.float64)) if hasattr(x, "dtype") else x, cam
    )
    rng = np.random.default_rng(4)
    img = cv2.GaussianBlur(rng.random((H, W, 3)), (0, 0), 3).astype(np.float64)
    img[..., 0] += np.linspace(0, 0.5, W)[None]
    bg = np.zeros((H, W), bool)
    bg[:, :background_cols] = True  # background pixels: e_p = g_pen/A > 0 there
    d = prepare_region_data(jnp.asarray(img), jnp.asarray(bg), 1, 8)
    band = select_band(_level1_tube(cam, cl), d.grid, 30, 8)
    return cl, cam, d, band


@eqx.filter_jit
def _level1_tube(cam, cl):
    return scale_tube(project_tube(cam, cl), 1)


def level_tube(scene, c):
    """The tube of ``perturbed_centreline(centreline, c)`` on the level-1 grid."""
    cl, cam, _, _ = scene
    return scale_tube(project_tube(cam, perturbed_centreline(cl, c)), 1)


def band_energy(scene, c, reg_weight, local=False, robust=0.0):
    """chan_vese_energy's J at ``c`` (Weights(), tau 1.5 px, reference area 500 px) with
    ``reg_weight * sum(c**2)`` as E_reg; reg_weight = 0 is what the BFGS solver minimises
    without its regulariser."""
    _, _, d, band = scene
    reg = reg_weight * jnp.sum(c**2)
    return chan_vese_energy(
        level_tube(scene, c), band, d, reg, Weights(), TAU, AREA, local, robust
    )[0]


#: (J, dJ/dc) in one program per (local, robust); its value also serves the central
#: differences, so no separate program computes J alone
energy_value_and_grad = eqx.filter_jit(jax.value_and_grad(band_energy, argnums=1))
