"""A pytest plugin that breaks the refinement on purpose, to show that test_refine's
tolerances still fail for the bugs they guard (docs/decisions.md T5):

    BROKEN_VMAP=swap PYTHONPATH=.:experiments/segmentation python -m pytest -n 0 \\
        -p vmap_broken_plugin \\
        tests/segmentation/test_refine.py::test_batch_vmap_matches_per_frame_quality

BROKEN_VMAP=swap   refine_batch(mode="vmap"): frames 0 and 1 refined against each other's
                   image (a frame axis mixed up)
BROKEN_VMAP=A,B    refine_batch(mode="vmap"): A and B solver steps per level instead of the
                   config's (a lock-step loop that stops early)
BROKEN_FRAME=A,B   refine_frame_jit: A and B solver steps per level (a per-frame solve that
                   stops early; test_recovers_known_delta_u)
The same compiled programs (steps are traced; the images are only reordered)."""

import dataclasses
import os

import equinox as eqx
import jax.numpy as jnp

import jaxcr.segmentation.refine as R

_orig = R._refine_batch_jit
_orig_frame = R.refine_frame_jit
_MODE = os.environ.get("BROKEN_VMAP", "")
_FRAME = os.environ.get("BROKEN_FRAME", "")


def _broken(bases, cameras, images, backgrounds, config, inits, valid, mode, cams0, nums, *rest):
    if mode == "vmap" and _MODE:
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


def _broken_frame(base, cameras, images, backgrounds, config=R.DEFAULT_CONFIG, *args, **kw):
    steps = tuple(int(x) for x in _FRAME.split(","))
    config = dataclasses.replace(config, steps=steps)
    return _orig_frame(base, cameras, images, backgrounds, config, *args, **kw)


R._refine_batch_jit = _broken
if _FRAME:
    R.refine_frame_jit = _broken_frame
