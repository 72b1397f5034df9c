"""Keyword-only entry points of kinematic-prior segmentation, re-exported as ``jcr.refine``
and ``jcr.refine_batch``.

They call the compiled solvers of :mod:`jaxcr.segmentation.refine` (``refine_frame_jit``,
``refine_batch``) unchanged; only the optional arguments are keyword-only, so a notebook reads
``jcr.refine(base, camera, image, background, config=cfg)``.

Example (one frame, one camera)::

    import jax.numpy as jnp
    import jaxcr as jcr

    robot = jcr.robot_from_dict(jcr.TEST_CTR)
    base = robot.forward(q).centreline                  # nominal shape for joint values q
    background, image = jcr.colour_mask(jnp.asarray(rgb, jnp.float32) / 255)
    res = jcr.refine(base, camera, image, background)   # RefineResult
    res.centreline.p                                    # (N, 3) refined centreline, metres
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from jaxcr.camera import Camera
from jaxcr.kinematics.cosserat import Centreline
from jaxcr.segmentation import refine as _refine
from jaxcr.segmentation.buckets import bucket_shape, pad_frames
from jaxcr.segmentation.refine import DEFAULT_CONFIG, RefineConfig, RefineResult


def refine(
    base: Centreline,
    cameras: Camera | tuple[Camera, ...],
    images: Float[Array, "h w 3"] | tuple[Float[Array, "h w 3"], ...],
    backgrounds: Bool[Array, "h w"] | tuple[Bool[Array, "h w"], ...],
    *,
    config: RefineConfig | None = None,
    init: Float[Array, "a k"] | None = None,
    valid: Bool[Array, ""] | bool = True,
    init_cam: Float[Array, "c 6"] | None = None,
) -> RefineResult:
    """Refine one frame's centreline against its images (Watson et al. eq. 5), compiled once
    per shape and config.

    Parameters
    ----------
    base : Centreline
        nominal :class:`~jaxcr.kinematics.cosserat.Centreline` (N samples, robot frame,
        metres), e.g. ``robot.forward(q).centreline``.
    cameras : Camera | tuple[Camera, ...]
        one :class:`~jaxcr.camera.Camera` or a tuple (multi-view).
    images : float array (h, w, 3) | tuple[float array (h, w, 3), ...]
        per camera, the (h, w, 3) float image after background subtraction (the
        second output of :func:`jaxcr.colour_mask`).
    backgrounds : bool array (h, w) | tuple[bool array (h, w), ...]
        per camera, the (h, w) bool background mask B.
    config : RefineConfig | None
        :class:`RefineConfig` (default ``RefineConfig()``).
    init : float array (a, k) | None
        (a, k) warm-start delta-u coefficients (default zeros).
    valid : bool scalar array | bool
        False skips the frame (reported failed).
    init_cam : float array (c, 6) | None
        (n_cameras, 6) warm-start camera corrections.

    Returns
    -------
    RefineResult
        ``masks`` (per camera (h, w) bool), ``centreline`` (N samples, robot frame, metres),
        ``coeffs``, ``ok``, ``failure``, ``num_steps``, ``energy``
        (:class:`RefineEnergy`), ``camera_correction``, ``time_s``.

    Examples
    --------
    A refinement compiles for minutes, so this example is not run by the doctests;
    ``examples/refine_frame.py`` runs it in the test suite.

    >>> import jaxcr as jcr
    >>> robot = jcr.robot_from_dict(jcr.TEST_CTR)  # doctest: +SKIP
    >>> background, image = jcr.colour_mask(rgb)  # rgb: (h, w, 3) float in [0, 1]  # doctest: +SKIP
    >>> res = jcr.refine(robot.forward(q).centreline, camera, image, background)  # doctest: +SKIP
    >>> res.centreline.p.shape, bool(res.ok)  # doctest: +SKIP
    ((64, 3), True)
    """
    return _refine.refine_frame_jit(
        base, cameras, images, backgrounds, config or DEFAULT_CONFIG, init, valid, init_cam
    )


def refine_batch(
    bases: Centreline,
    cameras: Camera | tuple[Camera, ...],
    images: Float[Array, "f h w 3"] | tuple[Float[Array, "f h w 3"], ...],
    backgrounds: Bool[Array, "f h w"] | tuple[Bool[Array, "f h w"], ...],
    *,
    config: RefineConfig | None = None,
    inits: Float[Array, "f a k"] | None = None,
    valid: Bool[Array, " f"] | None = None,
    mode: str = "map",
    init_cams: Float[Array, "f c 6"] | None = None,
    shape_buckets: bool = False,
) -> RefineResult:
    """Refine F independent frames in one compiled call (shared cameras).

    Parameters
    ----------
    bases : Centreline
        :class:`~jaxcr.kinematics.cosserat.Centreline` with a leading frame axis F
        (``jax.vmap(robot.forward)(qs).centreline``).
    cameras, images, backgrounds : Camera | tuple[Camera, ...]
        as :func:`refine`, with a leading F axis on the arrays.
    config : RefineConfig | None
        :class:`RefineConfig` (default ``RefineConfig()``).
    inits : float array (f, a, k) | None
        (F, a, k) warm-start delta-u coefficients (default zeros).
    valid : bool array (f,) | None
        False skips that frame (reported failed); default all True.
    mode : str
        ``"map"`` (frames in sequence inside the compiled call; fastest on CPU) or
        ``"vmap"`` (lock step).
    init_cams : float array (f, c, 6) | None
        (F, n_cameras, 6) warm-start camera corrections.
    shape_buckets : bool
        pad each camera's frames at the bottom and right to its image-size bucket
        (:func:`jaxcr.segmentation.buckets.bucket_shape`; the padding weighs nothing) so that
        every size of a bucket shares one compiled program, as ``jaxcr segment
        --shape-buckets on`` does (docs/decisions.md S29); the masks are cropped back to the
        cameras' sizes. Results equal the unpadded call's up to float rounding, which a
        solve can amplify to a few pixels of mask. Off by default.

    Returns
    -------
    RefineResult
        every field with a leading frame axis F.

    Examples
    --------
    A refinement compiles for minutes, so this example is not run by the doctests;
    ``examples/refine_frame.py`` runs it in the test suite.

    >>> import jaxcr as jcr
    >>> robot = jcr.robot_from_dict(jcr.TEST_CTR)  # doctest: +SKIP
    >>> background, image = jcr.colour_mask(rgb)  # rgb: (h, w, 3) float in [0, 1]  # doctest: +SKIP
    >>> qs = jnp.stack([q0, q1])  # doctest: +SKIP
    >>> bgs, imgs = jax.vmap(jcr.colour_mask)(rgbs)  # rgbs: (F, h, w, 3)  # doctest: +SKIP
    >>> out = jcr.refine_batch(jax.vmap(robot.forward)(qs).centreline, camera, imgs, bgs)  # doctest: +SKIP
    >>> out.ok.shape  # doctest: +SKIP
    (2,)
    """
    if not shape_buckets:
        return _refine.refine_batch(
            bases, cameras, images, backgrounds, config or DEFAULT_CONFIG, inits, valid, mode,
            init_cams,
        )  # fmt: skip
    cams = _refine._as_tuple(cameras)
    sizes = [(c.height, c.width) for c in cams]
    shapes = [bucket_shape(*hw) for hw in sizes]
    imgs = _refine._as_tuple(images)
    bgs = _refine._as_tuple(backgrounds)
    imgs = tuple(
        jnp.asarray(pad_frames(np.asarray(x), sh)) for x, sh in zip(imgs, shapes, strict=True)
    )
    bgs = tuple(
        jnp.asarray(pad_frames(np.asarray(b), sh, fill=True))
        for b, sh in zip(bgs, shapes, strict=True)
    )
    out = _refine.refine_batch(
        bases, cameras, imgs, bgs, config or DEFAULT_CONFIG, inits, valid, mode, init_cams,
        shape_buckets=True,
    )  # fmt: skip

    def crop(masks):
        return tuple(m[:, :h, :w] for m, (h, w) in zip(masks, sizes, strict=True))

    return eqx.tree_at(
        lambda r: (r.masks, r.nominal_masks), out, (crop(out.masks), crop(out.nominal_masks))
    )
