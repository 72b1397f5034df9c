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

from jaxtyping import Array, Bool, Float

from jaxcr.camera import Camera
from jaxcr.kinematics.cosserat import Centreline
from jaxcr.segmentation import refine as _refine
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

    Parameters:
        base: nominal :class:`~jaxcr.kinematics.cosserat.Centreline` (N samples, robot frame,
            metres), e.g. ``robot.forward(q).centreline``.
        cameras: one :class:`~jaxcr.camera.Camera` or a tuple (multi-view).
        images: per camera, the (h, w, 3) float image after background subtraction (the
            second output of :func:`jaxcr.colour_mask`).
        backgrounds: per camera, the (h, w) bool background mask B.
        config: :class:`RefineConfig` (default ``RefineConfig()``).
        init: (a, k) warm-start delta-u coefficients (default zeros).
        valid: False skips the frame (reported failed).
        init_cam: (n_cameras, 6) warm-start camera corrections.

    Returns:
        :class:`RefineResult`: ``centreline`` (N samples), ``coeffs``, ``ok``, ``failure``,
        ``num_steps``, ``energy`` terms, ``camera_correction``, ``time_s``.
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
) -> RefineResult:
    """Refine F independent frames in one compiled call (shared cameras).

    Parameters:
        bases: :class:`~jaxcr.kinematics.cosserat.Centreline` with a leading frame axis F
            (``jax.vmap(robot.forward)(qs).centreline``).
        cameras, images, backgrounds: as :func:`refine`, with a leading F axis on the arrays.
        config: :class:`RefineConfig` (default ``RefineConfig()``).
        inits: (F, a, k) warm starts; valid: (F,) bool; init_cams: (F, n_cameras, 6).
        mode: ``"map"`` (frames in sequence inside the compiled call; fastest on CPU) or
            ``"vmap"`` (lock step).

    Returns:
        :class:`RefineResult` with a leading F axis.
    """
    return _refine.refine_batch(
        bases,
        cameras,
        images,
        backgrounds,
        config or DEFAULT_CONFIG,
        inits,
        valid,
        mode,
        init_cams,
    )
