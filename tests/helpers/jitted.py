"""Compiled versions of library functions that tests use only to build their inputs (scenes,
nominal and truth centrelines).

Called eagerly, ``integrate_centreline`` took ~20 s the first time in each test module (one
XLA compilation per primitive of its associative scan and SO(3) maps, redone in every module
because conftest drops compiled code after each one); compiled it takes ~2-3 s and gives the
same numbers (bit-identical on the 33-point scene of test_shape). Tests *of* these functions
(values, jit == eager, vmap == loop) keep calling the library functions directly.
"""

import equinox as eqx
import jax

from jaxcr.kinematics.cosserat import integrate_centreline as _integrate_centreline
from jaxcr.segmentation.background import colour_mask as _colour_mask
from jaxcr.segmentation.energy import prepare_region_data as _prepare_region_data
from jaxcr.segmentation.shape import perturbed_centreline as _perturbed_centreline
from jaxcr.segmentation.silhouette import band_margin as _band_margin
from jaxcr.segmentation.silhouette import rasterise_dense as _rasterise_dense
from jaxcr.segmentation.silhouette import select_band as _select_band

integrate_centreline = jax.jit(_integrate_centreline)
perturbed_centreline = jax.jit(_perturbed_centreline)


# The band-energy inputs of the segmentation tests (region data, band, margins, dense masks),
# shared by several modules so the run's compilation cache serves one module's programs to
# the next: op by op, each primitive was its own compilation per image size (~250 programs
# in test_energy alone). Non-array arguments (ints, bools, TileGrid) are static.
prepare_region_data = eqx.filter_jit(_prepare_region_data)
select_band = eqx.filter_jit(_select_band)
band_margin = eqx.filter_jit(_band_margin)
rasterise_dense = eqx.filter_jit(_rasterise_dense)

# the background mask of the rendered test images (tests/helpers/tube_render.py and the
# refinement tests' own renders): one program per image size instead of its primitives
colour_mask = eqx.filter_jit(_colour_mask)
