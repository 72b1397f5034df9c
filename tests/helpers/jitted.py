"""Compiled versions of library functions that tests use only to build their inputs (scenes,
nominal and truth centrelines).

Called eagerly, ``integrate_centreline`` took ~20 s the first time in each test module (one
XLA compilation per primitive of its associative scan and SO(3) maps, redone in every module
because conftest drops compiled code after each one); compiled it takes ~2-3 s and gives the
same numbers (bit-identical on the 33-point scene of test_shape). Tests *of* these functions
(values, jit == eager, vmap == loop) keep calling the library functions directly.
"""

import jax

from jaxcr.kinematics.cosserat import integrate_centreline as _integrate_centreline
from jaxcr.segmentation.shape import perturbed_centreline as _perturbed_centreline

integrate_centreline = jax.jit(_integrate_centreline)
perturbed_centreline = jax.jit(_perturbed_centreline)
