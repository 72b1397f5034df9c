"""The canonical refinement setup of the suite: one image size, one camera, one nominal arc and
one :class:`RefineConfig`, imported by every module that does not need a setup of its own.

Why shared: compiling a refinement program costs ~40 s of CPU here (two pyramid levels), and
the run-wide persistent compilation cache (tests/conftest.py) serves a program to every later
process and module only when it is the very same program: same image size, config, camera
count, batch size F and the same jitted function. tests/segmentation/test_refine.py compiles
:func:`jaxcr.segmentation.refine.refine_frame_jit` and ``refine_batch(..., mode="map")`` on
F = 2 frames with this setup, and calls the public front doors (jcr.refine, jcr.refine_batch)
on the same shapes in the same module (no reload of both programs from the run's cache).
tests/segmentation/test_refine_convergence.py runs the per-frame program and test_refine's
vmap program (VMAP_BATCH frames) with a config that differs from CFG only in ``steps``, which
the compiled entry points take as a traced argument: the same programs.
Change nothing here without re-deriving the thresholds of the modules that import it.
"""

from jaxcr.segmentation.refine import RefineConfig
from tests.helpers.tube_render import arc_base, front_camera

W, H = 160, 120
#: two pyramid levels, 3 Chebyshev coefficients, no camera correction (the scenes have an
#: exact camera and a uniform background; the correction has its own tests)
CFG = RefineConfig(
    n_coeffs=3,
    levels=(1, 0),
    steps=(30, 15),
    outer=(2, 1),
    tau=(1.0, 0.8),
    band_tiles=96,
    min_tiles=24,
    g_reg=0.5,
    local=False,
    camera_correction=False,
)
#: the batch size of the shared ``refine_batch`` program
BATCH = 2
#: the batch size of the shared ``refine_batch(..., mode="vmap")`` program: test_refine's
#: batch of good and bad frames; tests/segmentation/test_refine_convergence.py runs the same
#: program (its config differs from CFG only in ``steps``, which refine_frame_jit and
#: refine_batch pass as a traced argument, so it is the same compiled program)
VMAP_BATCH = 5


def base():
    """The nominal arc (radius 2.5 mm) of tests/helpers/tube_render.py."""
    return arc_base(2.5e-3)


def camera():
    """The front camera, fx = 200 px, W x H."""
    return front_camera(200.0, (W, H))


#: the suite's two-camera refinement program: one full-resolution level, the rig-level camera
#: correction (tests/segmentation/test_refine_multicam.py). test_refine's two-camera test runs
#: it too, at the same image size, with the same argument structure (``eqx.filter_jit(
#: refine_frame)(base, (cam_a, cam_b), images, backgrounds, RIG_CFG, init, True, init_cam)``):
#: one compiled program for both modules (the run's compilation cache serves the second)
RIG_CFG = RefineConfig(
    n_coeffs=3,
    levels=(0,),
    steps=(40,),
    outer=(1,),
    tau=(0.8,),
    band_tiles=96,
    min_tiles=24,
    g_reg=0.5,
    local=False,
    camera_correction=True,
    camera_correction_mode="rig",
)

#: the suite's small one-level per-frame program with camera correction:
#: ``refine_frame_jit`` on a 96x72 frame of the arc seen by the front camera at fx = 120 px,
#: with a config of this structure (the numbers -- weights, tolerances, tau, steps -- are
#: traced arguments of refine_frame_jit, docs/decisions.md S34, so they may differ).
#: tests/segmentation/test_refine_traced.py compiles it (its traced per-frame program) and
#: test_refine.test_camera_correction_recovers_a_calibration_error runs it: one program for
#: both modules (the run's compilation cache serves the second; docs/decisions.md T3)
SMALL_W, SMALL_H = 96, 72
SMALL_CFG = RefineConfig(
    n_coeffs=3,
    levels=(0,),
    steps=(20,),
    outer=(1,),
    tau=(0.7,),
    band_tiles=48,
    min_tiles=16,
    local=False,
    camera_correction=True,
)


def small_camera():
    """The front camera at fx = 120 px, SMALL_W x SMALL_H."""
    return front_camera(120.0, (SMALL_W, SMALL_H))
