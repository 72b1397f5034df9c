"""jcr.refine / jcr.refine_batch (the keyword-only front doors of jaxcr/segmentation/api.py)
give exactly what the solvers they call give, on one rendered frame (bit-identical: same
compiled function, same inputs)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxcr as jcr
from jaxcr.segmentation.refine import RefineConfig, refine_batch, refine_frame_jit
from tests.helpers.tube_render import arc_base, front_camera, tube_frames

pytestmark = pytest.mark.slow  # compiles the refinement (minutes on a loaded machine)

W, H = 160, 120
# One pyramid level: the front doors pass the config through untouched, so any config tests
# them; each level is one more BFGS solve in the compiled program, which two compilations
# here (per frame and the F = 1 batch) would pay for twice.
CFG = RefineConfig(n_coeffs=3, levels=(0,), steps=(5,), outer=(1,), tau=(0.5,), band_tiles=96,
                   min_tiles=24, local=False, camera_correction=False)  # fmt: skip


def test_refine_front_door_equals_refine_frame_jit():
    base, cam = arc_base(2.5e-3), front_camera(200.0, (W, H))
    (f,) = tube_frames(
        base, cam, [np.array([[0.3, -0.1, 0.0], [0.0, 0.0, 0.0]], np.float32)], (W, H)
    )
    got = jcr.refine(base, cam, f["img"], f["bg"], config=CFG)
    want = refine_frame_jit(base, cam, f["img"], f["bg"], CFG)
    assert isinstance(got, jcr.RefineResult)
    np.testing.assert_array_equal(np.asarray(got.coeffs), np.asarray(want.coeffs))
    np.testing.assert_array_equal(np.asarray(got.centreline.p), np.asarray(want.centreline.p))
    # the batch front door on F = 1 stacked frame == refine_batch itself
    bases = jax.tree.map(lambda a: a[None], base)
    gb = jcr.refine_batch(bases, cam, f["img"][None], f["bg"][None], config=CFG)
    wb = refine_batch(bases, cam, f["img"][None], f["bg"][None], CFG)
    np.testing.assert_array_equal(np.asarray(gb.coeffs), np.asarray(wb.coeffs))
    assert gb.coeffs.shape == (1,) + CFG.coeff_shape
    assert jnp.isfinite(gb.coeffs).all()
