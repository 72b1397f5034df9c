"""A pytest plugin that breaks refine_batch(mode="vmap") on purpose, to show that
tests/segmentation/test_refine.py::test_batch_vmap_matches_per_frame_quality fails for a broken
vmap mode (docs/decisions.md T5):

    BROKEN_VMAP=swap PYTHONPATH=.:experiments/segmentation python -m pytest -n 0 \\
        -p vmap_broken_plugin \\
        tests/segmentation/test_refine.py::test_batch_vmap_matches_per_frame_quality

BROKEN_VMAP=swap   frames 0 and 1 refined against each other's image (a frame axis mixed up)
BROKEN_VMAP=A,B    A and B solver steps per level instead of the config's (a lock-step loop
                   that stops early)
The same compiled program (steps are traced; the images are only reordered)."""

import os

import equinox as eqx
import jax.numpy as jnp

import jaxcr.segmentation.refine as R

_orig = R._refine_batch_jit
_MODE = os.environ["BROKEN_VMAP"]


def _broken(bases, cameras, images, backgrounds, config, inits, valid, mode, cams0, nums, *rest):
    if mode == "vmap":
        if _MODE == "swap":
            order = jnp.arange(images[0].shape[0]).at[0].set(1).at[1].set(0)
            images = tuple(im[order] for im in images)
            backgrounds = tuple(b[order] for b in backgrounds)
        else:
            steps = jnp.asarray([int(x) for x in _MODE.split(",")], jnp.int32)
            nums = eqx.tree_at(lambda n: n.steps, nums, steps)
    return _orig(
        bases, cameras, images, backgrounds, config, inits, valid, mode, cams0, nums, *rest
    )


R._refine_batch_jit = _broken
