"""jcr.refine / jcr.refine_batch (the keyword-only front doors of jaxcr/segmentation/api.py)
give exactly what the solvers they call give, on rendered frames (bit-identical: same
compiled function, same inputs)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxcr as jcr
from jaxcr.segmentation.refine import refine_batch, refine_frame_jit
from tests.helpers import refine_scene
from tests.helpers.tube_render import tube_frames

pytestmark = pytest.mark.slow  # compiles the refinement (minutes on a loaded machine)

# The suite's canonical setup (tests/helpers/refine_scene.py): the front doors pass the config
# through untouched, so any config tests them, and with this one both programs called here
# (refine_frame_jit on one frame, the map batch on F = 2) are the ones
# tests/segmentation/test_refine.py compiles: the run's compilation cache serves them instead
# of two more compilations.
W, H, CFG = refine_scene.W, refine_scene.H, refine_scene.CFG
COEFFS = [
    np.array([[0.3, -0.1, 0.0], [0.0, 0.0, 0.0]], np.float32),
    np.array([[-0.2, 0.1, 0.0], [0.0, 0.0, 0.0]], np.float32),
]


def test_refine_front_door_equals_refine_frame_jit():
    base, cam = refine_scene.base(), refine_scene.camera()
    frames = tube_frames(base, cam, COEFFS, (W, H))
    f = frames[0]
    got = jcr.refine(base, cam, f["img"], f["bg"], config=CFG)
    want = refine_frame_jit(base, cam, f["img"], f["bg"], CFG)
    assert isinstance(got, jcr.RefineResult)
    np.testing.assert_array_equal(np.asarray(got.coeffs), np.asarray(want.coeffs))
    np.testing.assert_array_equal(np.asarray(got.centreline.p), np.asarray(want.centreline.p))
    # the batch front door on F = 2 stacked frames == refine_batch itself
    F = refine_scene.BATCH
    bases = jax.tree.map(lambda *a: jnp.stack(a), *[base] * F)
    imgs = jnp.stack([g["img"] for g in frames[:F]])
    bgs = jnp.stack([g["bg"] for g in frames[:F]])
    gb = jcr.refine_batch(bases, cam, imgs, bgs, config=CFG)
    wb = refine_batch(bases, cam, imgs, bgs, CFG)
    np.testing.assert_array_equal(np.asarray(gb.coeffs), np.asarray(wb.coeffs))
    np.testing.assert_array_equal(np.asarray(gb.centreline.p), np.asarray(wb.centreline.p))
    assert gb.coeffs.shape == (F,) + CFG.coeff_shape
    assert jnp.isfinite(gb.coeffs).all()
