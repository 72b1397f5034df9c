"""Kinematic-prior segmentation: refine delta-u so the projected tube explains the image.

Watson et al. (Sec. II): the kinematic model gives the nominal curvature u(s) = f(q); the
unknown is a small curvature change delta-u(s) (:mod:`jaxcr.segmentation.shape`), re-integrated from the
same base pose (eq. 1), drawn as a tube (eq. 7), projected (eqs. 3-4, :mod:`jaxcr.segmentation.silhouette`)
and scored by the region energy of eq. 5 with eq. 6 (:mod:`jaxcr.segmentation.energy`). This module
minimises that energy with Optimistix BFGS, coarse to fine over an image pyramid, for one
frame seen by one or several cameras (one delta-u explains all cameras: a 3-D estimate), and
for batches and sequences of frames.

Everything below ``refine_frame`` is pure and jit-compiled; a batch of frames with equal
image sizes and robot sampling is refined by one compiled call (``refine_batch``), compiled
once per shape. Solvers never raise: each frame carries ``status`` (Optimistix RESULTS as
int, 0 = success), ``num_steps``, ``ok`` and ``failure`` (:data:`FAILURES`).

Usage (notebook)::

    import jax, jax.numpy as jnp
    from jaxcr.segmentation.background import colour_mask
    from jaxcr.segmentation.refine import RefineConfig, refine_frame, refine_batch

    fk = robot.forward(q)                               # FkResult, .centreline in robot frame
    bg, img = colour_mask(image)                        # B (h, w) bool and I' = I o M
    cfg = RefineConfig()                                # weights, basis, pyramid, solver
    res = refine_frame(fk.centreline, camera, img, bg, cfg)
    res.masks[0]        # (h, w) bool: full projection of the refined robot (occluded parts too)
    res.centreline.p    # (N, 3) refined centreline, robot frame, metres
    res.coeffs, res.delta_u, res.energy, res.status, res.num_steps, res.ok

    # a dataset: stack frames (leading axis F) and refine in one compiled call
    cls = jax.vmap(robot.forward)(qs).centreline        # Centreline with leading axis F
    bgs, imgs = jax.vmap(colour_mask)(images)           # (F, h, w), (F, h, w, 3)
    out = refine_batch(cls, (camera,), (imgs,), (bgs,), cfg)   # RefineResult, axis F
    # sequences: warm start each frame from the previous delta-u
    out = refine_sequence(cls, (camera,), (imgs,), (bgs,), cfg)

Several cameras: pass tuples ``(cam_a, cam_b)``, ``(img_a, img_b)``, ``(bg_a, bg_b)``; the
energies are summed and ``masks`` holds one mask per camera.

Defaults (:class:`RefineConfig`) were chosen on seeds 0 and 1 of the four synthetic presets,
seed 3 held out, with no knowledge of the generator's colours. Each solve runs in
image-motion units (parameters scaled by the pixels their unit moves the projected
centreline, J scaled so that the first steepest-descent step moves it about 1 px) and stops
on an image-space convergence test (:class:`ImageSpaceBFGS`). The alternatives tried and the
measurements behind each default are in ``docs/decisions.md`` (records S1-S11).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable

import equinox as eqx
import jax
import jax.flatten_util
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from jaxcr._types import Array, Bool, Float, Int
from jaxcr.camera import Camera
from jaxcr.errors import InputError
from jaxcr.geometry import so3_exp, so3_log
from jaxcr.kinematics.cosserat import Centreline
from jaxcr.segmentation.energy import (
    RegionData,
    Weights,
    chan_vese_energy,
    chan_vese_soft,
    pyramid,
    region_data_from_level,
    region_terms,
    residual_variance,
)
from jaxcr.segmentation.least_squares import (
    band_normal_terms,
    damped_gauss_newton,
    winner_margins,
)
from jaxcr.segmentation.shape import delta_u_steps, n_axes, perturbed_centreline, regularisation
from jaxcr.segmentation.silhouette import (
    Band,
    TileGrid,
    TubeImage,
    band_margin,
    level_tube_padded,
    project_tube,
    select_band,
)

#: failure codes of :attr:`RefineResult.failure`
FAILURES = {
    0: "ok",
    1: "invalid input (non-finite joints/centreline or missing image)",
    2: "robot out of view (nominal projection misses every image)",
    3: "no data (every pixel is background)",
    4: "solver produced a non-finite result",
}


#: the warm schedule's J-change tolerance relative to ``ftol`` (:meth:`RefineConfig.warm`)
WARM_FTOL_FACTOR = 10.0


class RefineConfig(eqx.Module):
    """Settings of the refinement.

    A config is a hashable value of Python numbers (every field static). The compiled entry
    points (:func:`refine_frame_jit`, :func:`refine_batch`, :func:`refine_sequence`, and so
    ``jcr.refine``, ``jaxcr segment`` and ``jaxcr warmup``) pass its numeric settings traced,
    as array arguments of the program: ``steps``, ``tau``, ``g_in``, ``g_out``, ``g_reg``,
    ``g_pen``, ``xtol``, ``ftol``, ``robust`` (its value; ``robust > 0`` or ``== 0`` chooses
    the Welsch or the quadratic inside term, a structural switch), ``g_cam``, ``g_cam_rel``
    (its value; None or not is structural), ``gn_lambda`` and ``gn_max_px``. Configs
    differing only in those share one compiled program (in a process, and through the
    stored programs of :func:`jaxcr.io.exported.cached_call`); every other field (shapes,
    schedule lengths, switches, solver) is part of the program (docs/decisions.md S34).
    :func:`refine_frame` called inside a user's own ``jax.jit`` bakes the config in as
    constants.

    Parameters
    ----------
    n_coeffs : int
        Chebyshev coefficients per bending axis (:mod:`jaxcr.segmentation.shape`).
    torsion : bool
        also perturb the torsion (third axis); off by default.
    levels : tuple[int, ...]
        pyramid levels visited, coarse to fine (0 = full resolution).
    steps : tuple[int, ...]
        max BFGS steps per solve at each level.
    outer : tuple[int, ...]
        solves per level; the band is re-selected before each solve.
    tau : tuple[float, ...]
        soft-silhouette temperature (pixels of that level) per level.
    band_tiles : int
        tiles in the band at level 0 (halved per level, at least ``min_tiles``).
    min_tiles : int
        smallest band (tiles) at coarse levels.
    tile : int
        tile size in pixels.
    k_seg : int
        candidate segments per band tile during the solves (of the merged tube, see
        ``seg_merge``); the output masks use ``seg_merge * k_seg`` candidates of the
        unmerged tube.
    seg_merge : int
        consecutive centreline segments merged into one capsule while solving
        (times ``2**level`` at pyramid level ``level``, :func:`silhouette.level_tube`), so
        that ``k_seg`` candidates span a tile with fewer, longer capsules. The margin cost
        per pixel is proportional to ``k_seg``; the chord error of a merged capsule is
        ``L**2 / (8 R)`` for capsules of length L px on a bend of radius R px
        (docs/decisions.md S10).
    g_in, g_out, g_reg, g_pen : float
        gamma_1..4 of eq. 5 on the normalised terms
        (:mod:`jaxcr.segmentation.energy`).
    xtol : float
        convergence tolerance on the *image motion* of a step: a solve stops when
        its last accepted step moved every projected centreline point by less than
        ``xtol`` pixels of the current pyramid level (and changed J by less than
        ``ftol``), or when the line search cannot lower J with a step that small
        (see :class:`ImageSpaceBFGS`).
    ftol : float
        convergence tolerance on the change of the normalised objective J of an
        accepted step (J is in units of the tube's area, see :mod:`jaxcr.segmentation.energy`);
        ``WARM_FTOL_FACTOR`` times it for warm-started frames (:meth:`warm`).
    solver : str
        ``"bfgs"`` (:class:`ImageSpaceBFGS`, default), ``"lbfgs"``
        (:class:`ImageSpaceLBFGS`) or ``"gn"`` (Levenberg-Marquardt on the exact
        least-squares form of the band energy, :mod:`jaxcr.segmentation.least_squares`;
        ``steps`` is then its budget of linearisations), all with the image-space
        convergence test (docs/decisions.md S6).
    robust : float
        occlusion-robust inside term, Welsch scale in image colour std
        (:func:`jaxcr.segmentation.energy.region_terms`); 0 = the paper's quadratic eq. 6
        (the default, docs/decisions.md S4).
    data_var : str
        what normalises the data terms during the solves: ``"image"`` (the
        image's colour variance, :mod:`jaxcr.segmentation.energy`) or ``"residual"`` (the
        two-region model's own noise variance at the start of each solve,
        :func:`jaxcr.segmentation.energy.residual_variance`); ``"image"`` by default
        (docs/decisions.md S7).
    robust_envelope : bool
        with ``robust``, the solver's gradient does not flow through the
        robust mean's reweightings (envelope-theorem gradient, cheaper;
        :func:`jaxcr.segmentation.energy.region_terms`): the same value with a cheaper
        gradient (docs/decisions.md S8).
    local : bool
        mu_out over the band around the silhouette instead of the whole image
        (:func:`jaxcr.segmentation.energy.region_terms`; docs/decisions.md S3).
    camera_correction : bool
        also estimate a small per-camera pose correction (rotation about
        the optical centre and translation) so that camera calibration error is not
        absorbed by the shape; regularised by ``g_cam`` (units: 0.01 rad and 1 % of
        the robot's depth; docs/decisions.md S2).
    camera_correction_mode : str
        how the correction is shared between several cameras.
        ``"camera"``: an independent 6-DOF correction per camera. ``"rig"``: one shared
        correction E of the robot-to-rig transform, in camera 0's frame (regularised by
        ``g_cam``), so that camera i's corrected pose is ``T_i' = (T_i T_0^-1) E T_0``: the
        cameras keep their calibrated relative pose and their disparity measures depth,
        plus, if ``g_cam_rel`` is not None, a residual correction of each camera i >= 1 in
        its own frame (regularised by ``g_cam_rel``, same units as ``g_cam``). With one
        camera both modes are the same parameterisation.
    g_cam_rel : float | None
        weight of the residual per-camera corrections of the ``"rig"`` mode (a
        stereo rig's relative calibration is far better known than its registration to
        the robot); None = rigid rig (no residual). ``experiments/segmentation/table2.py``
        uses 0.3 (docs/decisions.md S9).
    hessian_memory : bool
        (``solver="bfgs"``) start each solve of a level after the first from the inverse
        Hessian the previous solve ended with (moved into the new solve's scaling), and a
        warm-started frame (``init_hessian`` of :func:`refine_frame`,
        :func:`refine_sequence`) from the previous frame's; otherwise every solve starts
        from the identity (steepest descent). Each new pyramid level starts from the
        identity. Off by default (docs/decisions.md S12): it cut tracking time to 0.55x and
        cold time to 0.71x at equal IoU on the benchmark scenes, but on the camera-correction
        scene of ``tests/segmentation/test_refine.py`` the refined IoU fell from > 0.8 to 0.69.
    gn_lambda : float
        (``solver="gn"``) initial Levenberg-Marquardt damping, relative to the diagonal of
        the Gauss-Newton matrix (:func:`jaxcr.segmentation.least_squares.damped_gauss_newton`).
    gn_max_px : float
        (``solver="gn"``) longest image motion (pixels of the level) of one step.
    share_levels : bool
        one compiled solve for every pyramid level (the coarse levels' data padded to the
        finest grid, traced level, band size and step budget; :func:`refine_frame`), or one
        per level. Sharing compiles faster (-20-26 % CPU) but a coarse step then costs about a
        fine one (+33-52 % CPU per frame at 640x480, package defaults); for long batch jobs
        ``False`` may be faster (experiments/results/segmentation/refine_compile_profile.md).

    Examples
    --------
    >>> import jaxcr as jcr
    >>> cfg = jcr.RefineConfig(levels=(0,), steps=(20,), outer=(1,), tau=(0.5,))
    >>> cfg.levels, cfg.camera_correction
    ((0,), True)
    >>> jcr.RefineConfig(levels=(2, 1, 0))  # steps, outer and tau need one entry per level
    Traceback (most recent call last):
    jaxcr.errors.InputError: ...
    """

    n_coeffs: int = eqx.field(static=True, default=4)
    torsion: bool = eqx.field(static=True, default=False)
    # half resolution then full resolution: the thinnest tube is ~3 px wide at 640x480, under
    # one pixel at level 2 (docs/decisions.md S1)
    levels: tuple[int, ...] = eqx.field(static=True, default=(1, 0))
    steps: tuple[int, ...] = eqx.field(static=True, default=(30, 30))
    outer: tuple[int, ...] = eqx.field(static=True, default=(2, 2))
    tau: tuple[float, ...] = eqx.field(static=True, default=(0.8, 0.5))
    band_tiles: int = eqx.field(static=True, default=384)
    min_tiles: int = eqx.field(static=True, default=48)
    tile: int = eqx.field(static=True, default=8)
    k_seg: int = eqx.field(static=True, default=4)
    seg_merge: int = eqx.field(static=True, default=2)
    g_in: float = eqx.field(static=True, default=1.0)
    g_out: float = eqx.field(static=True, default=1.0)
    g_reg: float = eqx.field(static=True, default=10.0)
    g_pen: float = eqx.field(static=True, default=4.0)
    xtol: float = eqx.field(static=True, default=0.1)
    ftol: float = eqx.field(static=True, default=1e-4)
    solver: str = eqx.field(static=True, default="bfgs")
    local: bool = eqx.field(static=True, default=True)
    robust: float = eqx.field(static=True, default=0.0)
    data_var: str = eqx.field(static=True, default="image")
    robust_envelope: bool = eqx.field(static=True, default=False)
    camera_correction: bool = eqx.field(static=True, default=True)
    g_cam: float = eqx.field(static=True, default=0.3)
    camera_correction_mode: str = eqx.field(static=True, default="camera")
    g_cam_rel: float | None = eqx.field(static=True, default=None)
    hessian_memory: bool = eqx.field(static=True, default=False)
    share_levels: bool = eqx.field(static=True, default=True)
    gn_lambda: float = eqx.field(static=True, default=1e-2)
    gn_max_px: float = eqx.field(static=True, default=4.0)

    def __check_init__(self):
        n = len(self.levels)
        if not (len(self.steps) == len(self.outer) == len(self.tau) == n) or n == 0:
            raise InputError(
                "levels, steps, outer and tau must have the same non-zero length",
                field="RefineConfig",
            )
        if self.n_coeffs < 1 or min(self.levels) < 0 or self.k_seg < 1 or self.seg_merge < 1:
            raise InputError(
                "n_coeffs, k_seg and seg_merge must be >= 1 and levels >= 0", field="RefineConfig"
            )
        if self.solver not in ("lbfgs", "bfgs", "gn"):
            raise InputError(
                f"solver must be 'bfgs', 'lbfgs' or 'gn', got {self.solver!r}",
                field="RefineConfig",
            )
        if not (self.xtol > 0 and self.ftol > 0):
            raise InputError("xtol and ftol must be > 0", field="RefineConfig")
        if self.camera_correction_mode not in ("camera", "rig"):
            raise InputError(
                "camera_correction_mode must be 'camera' or 'rig', got "
                f"{self.camera_correction_mode!r}",
                field="RefineConfig",
            )
        if self.data_var not in ("image", "residual"):
            raise InputError(
                f"data_var must be 'image' or 'residual', got {self.data_var!r}",
                field="RefineConfig",
            )
        if self.g_cam_rel is not None and not self.g_cam_rel > 0:
            raise InputError("g_cam_rel must be > 0 or None", field="RefineConfig")

    @property
    def weights(self) -> Weights:
        return Weights(self.g_in, self.g_out, self.g_reg, self.g_pen)

    @property
    def coeff_shape(self) -> tuple[int, int]:
        return (n_axes(self.torsion), self.n_coeffs)

    def tiles_at(self, level: int) -> int:
        return max(self.min_tiles, -(-self.band_tiles // (2**level)))

    def warm(self) -> RefineConfig:
        """The schedule for a warm start (:func:`refine_sequence`): the finest level only.

        The coarse levels exist to bring a cold start (delta-u = 0) into the basin of the
        fine energy; a warm start from the previous frame's answer is already there, and the
        coarse energy's minimum differs from the fine one by up to a coarse pixel, so a
        coarse solve from the answer walks away and back (docs/decisions.md S11).

        With several levels, the warm solves also stop on a J change ``WARM_FTOL_FACTOR``
        times ``ftol``: tracked frames otherwise ran 51-60 of their 60 steps, and the looser
        test cut them to ~40-44 at equal IoU (docs/decisions.md S18). A one-level config is
        its own warm schedule, so that :func:`refine_sequence` runs its cold first frame in
        the warm scan (one compiled program).
        """
        if len(self.levels) == 1:
            return self
        return dataclasses.replace(
            self,
            levels=self.levels[-1:],
            steps=self.steps[-1:],
            outer=self.outer[-1:],
            tau=self.tau[-1:],
            ftol=WARM_FTOL_FACTOR * self.ftol,
        )


DEFAULT_CONFIG = RefineConfig()


class _Numbers(eqx.Module):
    """The numeric settings of a :class:`RefineConfig` as arrays (scalars; ``tau`` and
    ``steps`` one per level): what the compiled entry points pass traced (:func:`_traced_apart`),
    so that configs differing only in these values run one compiled program."""

    steps: Int[Array, " L"]
    tau: Float[Array, " L"]
    g_in: Float[Array, ""]
    g_out: Float[Array, ""]
    g_reg: Float[Array, ""]
    g_pen: Float[Array, ""]
    xtol: Float[Array, ""]
    ftol: Float[Array, ""]
    robust: Float[Array, ""]
    g_cam: Float[Array, ""]
    g_cam_rel: Float[Array, ""] | None
    gn_lambda: Float[Array, ""]
    gn_max_px: Float[Array, ""]

    @property
    def weights(self) -> Weights:
        return Weights(self.g_in, self.g_out, self.g_reg, self.g_pen)


#: the fields of :class:`_Numbers` that are plain scalars of :class:`RefineConfig`
_SCALARS = ("g_in", "g_out", "g_reg", "g_pen", "xtol", "ftol", "robust", "g_cam", "gn_lambda",
            "gn_max_px")  # fmt: skip


def _numbers(config: RefineConfig, dtype=jnp.float32) -> _Numbers:
    """``config``'s numeric settings as arrays of ``dtype`` (the centreline's float type, so
    that a traced setting computes in the same precision as the constant it replaces)."""
    kw = {k: jnp.asarray(getattr(config, k), dtype) for k in _SCALARS}
    rel = None if config.g_cam_rel is None else jnp.asarray(config.g_cam_rel, dtype)
    return _Numbers(steps=jnp.asarray(config.steps, jnp.int32),
                    tau=jnp.asarray(config.tau, dtype), g_cam_rel=rel, **kw)  # fmt: skip


def _traced_apart(config: RefineConfig, dtype=jnp.float32) -> tuple[RefineConfig, _Numbers]:
    """``config`` with its numeric settings replaced by placeholders (the structure only: one
    value for every config of the same shape and switches), and the settings as arrays
    (:func:`_numbers`): the compiled entry points take the arrays as traced arguments, so that
    configs differing only in those values share one compiled program (and one trace, and one
    stored program of :func:`jaxcr.io.exported.cached_call`). Structural switches on the
    values stay in the placeholder: ``robust > 0`` (Welsch inside term) or 0 (eq. 6), and
    ``g_cam_rel`` None (rigid rig) or a number (residual per-camera corrections)."""
    n = len(config.levels)
    ph = dict.fromkeys(_SCALARS, 1.0)
    ph["robust"] = 1.0 if config.robust > 0 else 0.0
    ph["g_cam_rel"] = None if config.g_cam_rel is None else 1.0
    static = dataclasses.replace(config, steps=(1,) * n, tau=(1.0,) * n, **ph)
    return static, _numbers(config, dtype)


class RefineEnergy(eqx.Module):
    """Final terms of Watson et al. eq. 5 for one frame, summed over cameras (arrays with a
    leading frame axis from the batch functions).

    Attributes
    ----------
    e_in, e_out : float scalar array
        inside and outside region terms (eq. 6), full-resolution pixel units,
        hard mask.
    e_reg : float scalar array
        regularisation of delta-u (:func:`jaxcr.segmentation.shape.regularisation`).
    e_pen : float scalar array
        penalty term, full-resolution pixel units.
    total : float scalar array
        the normalised objective J at the refined shape (what the solver minimised).
    total_nominal : float scalar array
        J at delta-u = 0 (the nominal shape); ``total <= total_nominal`` when
        the solve improved on the kinematic model.

    Examples
    --------
    A refinement compiles for minutes, so this example is not run by the doctests;
    ``examples/refine_frame.py`` runs the same steps in the test suite.

    >>> res = jcr.refine(fk.centreline, camera, image, background)  # doctest: +SKIP
    >>> bool(res.energy.total <= res.energy.total_nominal)  # doctest: +SKIP
    True
    """

    e_in: Float[Array, ""]
    e_out: Float[Array, ""]
    e_reg: Float[Array, ""]
    e_pen: Float[Array, ""]
    total: Float[Array, ""]
    total_nominal: Float[Array, ""]


class RefineResult(eqx.Module):
    """Output of one frame (or, from the batch functions, arrays with a leading frame axis).

    Attributes
    ----------
    masks : tuple[bool array (h, w), ...]
        per camera, (h, w) bool full projection of the refined tube (the whole robot,
        occluded parts included, as in Watson et al.).
    nominal_masks : tuple[bool array (h, w), ...]
        per camera, the projection with delta-u = 0.
    centreline : Centreline
        refined :class:`Centreline` (robot frame, metres).
    coeffs : float array (a, k)
        (a, k) delta-u coefficients (:mod:`jaxcr.segmentation.shape`).
    delta_u : float array (m, 3)
        (N-1, 3) per-step curvature change (1/m).
    energy : RefineEnergy
        :class:`RefineEnergy`, the final eq. 5 terms ``e_in, e_out, e_reg, e_pen``
        (full-resolution pixel units, hard mask), ``total`` (normalised objective J) and
        ``total_nominal`` (J at delta-u = 0), all summed over cameras.
    status : int scalar array
        Optimistix RESULTS as int of the last solve (0 = successful).
    num_steps : int scalar array
        total solver steps over all levels.
    steps_per_level : int array (l,)
        (n_levels,) solver steps per pyramid level.
    ok : bool scalar array
        frame usable: no failure and finite output.
    failure : int scalar array
        code from :data:`FAILURES` (0 = none).
    band_exact : bool scalar array
        the final masks are exact rasterisations (band reached every boundary tile).
    camera_correction : float array (c, 6)
        (n_cameras, 6) estimated camera pose correction: rotation vector
        (rad, about the optical centre) and translation (m), camera frame; zeros unless
        ``config.camera_correction``. Masks use the corrected cameras. In the ``"rig"``
        mode each row is that camera's effective correction ``T_i' T_i^-1``.
    hessian_inv : float array (n, n)
        (n, n) the BFGS approximation of the inverse Hessian of the objective J with respect
        to the flattened parameters (``coeffs`` then the camera-correction parameters, in
        the units of :func:`refine_frame`'s solves before scaling) at the end of the last
        solve: solver state for warm-starting the next frame
        (:attr:`RefineConfig.hessian_memory`), not a calibrated covariance (the identity
        when no solve updated it).
    time_s : float scalar array
        wall time per frame in seconds (set by the Python entry points; 0 inside jit).

    Examples
    --------
    A refinement compiles for minutes, so this example is not run by the doctests;
    ``examples/refine_frame.py`` runs the same steps in the test suite.

    >>> res = jcr.refine(fk.centreline, camera, image, background)  # doctest: +SKIP
    >>> res.masks[0].shape == image.shape[:2], res.centreline.p.shape  # doctest: +SKIP
    (True, (64, 3))
    >>> bool(res.ok), jcr.segmentation.refine.FAILURES[int(res.failure)]  # doctest: +SKIP
    (True, 'ok')
    """

    masks: tuple[Bool[Array, "h w"], ...]
    nominal_masks: tuple[Bool[Array, "h w"], ...]
    centreline: Centreline
    coeffs: Float[Array, "a k"]
    delta_u: Float[Array, "m 3"]
    energy: RefineEnergy
    status: Int[Array, ""]
    num_steps: Int[Array, ""]
    steps_per_level: Int[Array, " l"]
    ok: Bool[Array, ""]
    failure: Int[Array, ""]
    band_exact: Bool[Array, ""]
    camera_correction: Float[Array, "c 6"]
    hessian_inv: Float[Array, "n n"]
    time_s: Float[Array, ""]


def _as_tuple(x):
    return tuple(x) if isinstance(x, (tuple, list)) else (x,)


def _straight(base: Centreline) -> Centreline:
    """A harmless straight replacement for a non-finite centreline (keeps shapes)."""
    n = base.s.shape[0]
    s = jnp.where(jnp.isfinite(base.s), base.s, jnp.linspace(0.0, 1.0, n, dtype=base.s.dtype))
    s = jnp.where(jnp.all(jnp.isfinite(base.s)), base.s, jnp.linspace(0, 0.1, n, dtype=s.dtype))
    p = jnp.zeros_like(base.p).at[:, 2].set(s)
    R = jnp.broadcast_to(jnp.eye(3, dtype=base.p.dtype), base.R.shape)
    return Centreline(s=s, p=p, R=R, u=jnp.zeros_like(base.u), rho=jnp.zeros_like(base.rho))


def _tube_area(tube: TubeImage, camera: Camera, size=None) -> Float[Array, ""]:
    """Approximate projected area (px) of the in-image part of the capsules (overlaps
    counted twice, joints ignored): a scale for normalising the energy. ``size``: the real
    (height, width) when the camera's is a padded one (shape buckets)."""
    mx, my = 0.5 * (tube.ax + tube.bx), 0.5 * (tube.ay + tube.by)
    h, w = (camera.height, camera.width) if size is None else size
    inside = (mx > -0.5) & (mx < w - 0.5) & (my > -0.5) & (my < h - 0.5)
    length = jnp.hypot(tube.bx - tube.ax, tube.by - tube.ay)
    a = (tube.ra + tube.rb) * length
    return jnp.sum(jnp.where(inside & tube.valid, a, 0.0))


def _hard_terms(tube: TubeImage, band: Band, data: RegionData, local: bool, robust: float, m=None):
    """Region terms of the hard mask; ``m``: the band's margins if already computed."""
    m = band_margin(tube, data.grid, band) if m is None else m
    return region_terms((m > 0).astype(m.dtype), band, data, local, robust)


STEP0_PX = 1.0  # image motion (px of the level) of the first trial step of each solve
CAM_ROT_UNIT = 0.01  # rad per unit of the camera-correction rotation parameters
CAM_T_UNIT = 0.01  # fraction of the robot's depth per unit of the translation parameters


def _corrected_camera(camera: Camera, p6: Float[Array, "6"], z_ref) -> Camera:
    """``camera`` with X_cam' = exp(w) X_cam + d, w = CAM_ROT_UNIT p6[:3] (rad) and
    d = CAM_T_UNIT z_ref p6[3:] (m)."""
    E = so3_exp(CAM_ROT_UNIT * p6[:3])
    d = CAM_T_UNIT * z_ref * p6[3:]
    T = camera.T_cam_robot
    top = jnp.concatenate([E @ T[:3, :3], (E @ T[:3, 3] + d)[:, None]], axis=1)
    return eqx.tree_at(lambda c: c.T_cam_robot, camera, jnp.concatenate([top, T[3:]], axis=0))


def _rigid_inv(T: Float[Array, "4 4"]) -> Float[Array, "4 4"]:
    R, t = T[:3, :3], T[:3, 3]
    top = jnp.concatenate([R.T, (-R.T @ t)[:, None]], axis=1)
    return jnp.concatenate([top, T[3:]], axis=0)


def _rig_cameras(cameras: tuple[Camera, ...], p, z_ref, residual: bool) -> tuple[Camera, ...]:
    """The ``"rig"`` correction (:class:`RefineConfig`): camera 0 gets E = ``p[0]``
    (:func:`_corrected_camera`), camera i ``T_i' = T_i + (T_i T_0^-1)(T_0' - T_0)``, which is
    ``(T_i T_0^-1) E T_0`` and exactly ``T_i`` at E = I; then, if ``residual``, its own
    correction ``p[i]`` in its frame."""
    cam0 = _corrected_camera(cameras[0], p[0], z_ref[0])
    T0 = cameras[0].T_cam_robot
    dT0 = cam0.T_cam_robot - T0
    out = [cam0]
    for i, cam in enumerate(cameras[1:], start=1):
        Ti = cam.T_cam_robot + (cam.T_cam_robot @ _rigid_inv(T0)) @ dT0
        ci = eqx.tree_at(lambda c: c.T_cam_robot, cam, Ti)
        out.append(_corrected_camera(ci, p[i], z_ref[i]) if residual else ci)
    return tuple(out)


def _phys_to_params(p6: Float[Array, "... 6"], z_ref) -> Float[Array, "... 6"]:
    """Physical correction (rad, m) -> parameter units of :func:`_corrected_camera`."""
    return jnp.concatenate([p6[..., :3] / CAM_ROT_UNIT, p6[..., 3:] / (CAM_T_UNIT * z_ref)], -1)


def _pose_delta(T_new: Float[Array, "4 4"], T: Float[Array, "4 4"]) -> Float[Array, "6"]:
    """Correction (rotation vector (rad), translation (m)) with ``T_new = E T``."""
    E = T_new @ _rigid_inv(T)
    return jnp.concatenate([so3_log(E[:3, :3]), E[:3, 3]])


def _rig_corrections_to_params(cameras, corr, z_ref, residual: bool) -> Float[Array, "r 6"]:
    """Inverse of the ``"rig"`` mode's output: effective per-camera corrections ``corr``
    (n_cameras, 6) (physical units, :attr:`RefineResult.camera_correction`) -> parameters of
    :func:`_rig_cameras`: row 0 is E = camera 0's correction; with ``residual``, row i is what
    is left of camera i's correction after the rig's motion (``T_i'' (A E T_0)^-1``)."""
    p0 = _phys_to_params(corr[:1], z_ref[0])
    if not residual:
        return p0
    shared = _rig_cameras(cameras, p0, z_ref, False)
    rows = [p0]
    for i in range(1, len(cameras)):
        target = _corrected_camera(cameras[i], _phys_to_params(corr[i], z_ref[i]), z_ref[i])
        res = _pose_delta(target.T_cam_robot, shared[i].T_cam_robot)
        rows.append(_phys_to_params(res, z_ref[i])[None])
    return jnp.concatenate(rows, axis=0)


#: tiles kept free between a region of interest's border and the output bands of a tracked
#: frame (:func:`refine_frame` ``roi``): a band tile within this many tiles of a border that is
#: not the image's own means the band may have been cut by the region, and the frame is
#: refined again on the full image. Two tiles, a heuristic margin (not a proof): the path
#: from a tile outside the region to its nearest silhouette point crosses the border ring,
#: whose tile there is at most about one tile diagonal farther from the silhouette, so with
#: two free rings an outside tile would hardly have entered the band.
ROI_FREE_TILES = 2

#: ``jaxcr segment --warm-start --roi auto`` (the default; :func:`roi_pays`) tracks on a region
#: of interest only for images of at least this many pixels (every camera) ...
ROI_AUTO_MIN_PIXELS = 2 * 640 * 480
#: ... and a region of at most this fraction of the image. The region saves the area-bound
#: part of a tracked frame's fixed cost and adds its own work (the whole image's variance,
#: crops, pasting the masks back; a second program to compile). Measured (decisions S21,
#: S28): a 288x480 region of 1280x720 (15 %) 0.76x / 0.83x CPU per tracked frame in the
#: library; 320x480 of 640x480 (50 %) 1.04x / 1.00x; through `jaxcr segment` on the
#: orthogonal synthetic sets at 1280x720, regions of 480-576 x 800 (42-50 %) were slower
#: than the whole image (1.10x tracked ms, +26 s CPU of compilation in a first process).
#: The pixel threshold is twice the largest size measured without a gain; the fraction a
#: quarter, between the 15 % measured with a gain and the 42 % measured without one.
ROI_AUTO_MAX_FRACTION = 0.25


def roi_pays(cameras, roi: tuple[int, int] | None) -> bool:
    """Whether tracking on the region of interest ``roi`` = (h, w) (e.g. from
    :func:`tracking_roi`) is expected to save time for images of these cameras' sizes: every
    camera has at least :data:`ROI_AUTO_MIN_PIXELS` pixels, and the region is at most
    :data:`ROI_AUTO_MAX_FRACTION` of each image (False for no region)."""
    if roi is None:
        return False
    area = roi[0] * roi[1]
    return all(
        c.height * c.width >= ROI_AUTO_MIN_PIXELS
        and area <= ROI_AUTO_MAX_FRACTION * c.height * c.width
        for c in _as_tuple(cameras)
    )


def _tube_box(tube: TubeImage) -> Float[Array, "4"]:
    """(x_min, y_min, x_max, y_max) in pixels of the valid capsules (with their radii)."""
    big = jnp.asarray(1e9, tube.ax.dtype)
    r = jnp.maximum(tube.ra, tube.rb)
    lo_x = jnp.where(tube.valid, jnp.minimum(tube.ax, tube.bx) - r, big)
    lo_y = jnp.where(tube.valid, jnp.minimum(tube.ay, tube.by) - r, big)
    hi_x = jnp.where(tube.valid, jnp.maximum(tube.ax, tube.bx) + r, -big)
    hi_y = jnp.where(tube.valid, jnp.maximum(tube.ay, tube.by) + r, -big)
    return jnp.stack([jnp.min(lo_x), jnp.min(lo_y), jnp.max(hi_x), jnp.max(hi_y)])


def _roi_origin(
    boxes: list[Array], roi: tuple[int, int], size: tuple[int, int], tile: int
) -> tuple[Int[Array, ""], Int[Array, ""]]:
    """Top-left (row, column) of the ``roi`` = (h, w) window centred on the union of
    ``boxes``, on the tile grid (so the region's tiles are the image's) and inside the image
    of ``size`` = (h, w)."""
    box = jnp.stack(boxes)
    cx = 0.5 * (jnp.min(box[:, 0]) + jnp.max(box[:, 2]))
    cy = 0.5 * (jnp.min(box[:, 1]) + jnp.max(box[:, 3]))
    cx = jnp.where(jnp.isfinite(cx), cx, 0.0)
    cy = jnp.where(jnp.isfinite(cy), cy, 0.0)

    def start(c, n, full):
        s = jnp.floor((c - 0.5 * n) / tile).astype(jnp.int32) * tile
        hi = (full - n) // tile * tile
        if not isinstance(hi, int):  # a traced real size (shape buckets)
            hi = jnp.maximum(hi, 0)
        return jnp.clip(s, 0, hi)

    return start(cy, roi[0], size[0]), start(cx, roi[1], size[1])


def _roi_camera(cam: Camera, r0, c0, roi: tuple[int, int]) -> Camera:
    """The camera of the ``roi`` window at (row ``r0``, column ``c0``): the principal point
    moved by the window's origin (exact for the pinhole and OpenCV distortion models, which
    distort normalised coordinates before the intrinsics)."""
    K = cam.K.at[0, 2].add(-c0.astype(cam.K.dtype)).at[1, 2].add(-r0.astype(cam.K.dtype))
    return dataclasses.replace(cam, K=K, width=roi[1], height=roi[0])


def _image_variance(image: Float[Array, "h w 3"], background: Bool[Array, "h w"], valid=None):
    """The data-weighted colour variance of a whole level-0 image, as
    :func:`energy.chan_vese_soft` computes it from :class:`RegionData` (its ``var``): the
    normalisation of J, kept from the full image when the data are a region of it.
    ``valid``: the real pixels of a padded image (the others weigh nothing)."""
    w = 1.0 - background.astype(image.dtype)
    if valid is not None:
        w = w * valid.astype(image.dtype)
    s0 = jnp.maximum(jnp.sum(w), 1e-6)
    centre = jnp.einsum("hw,hwc->c", w, image) / s0
    d = image - centre
    return jnp.sum(w * jnp.sum(d * d, axis=-1)) / s0


def _band_clear_of_border(band: Band, grid: TileGrid, r0, c0, size: tuple[int, int]):
    """No band tile within ``ROI_FREE_TILES`` of a region border that is not the image's."""
    row, col = grid.row_col(band.tiles)
    e = ROI_FREE_TILES
    top = (row < e) & (r0 > 0)
    left = (col < e) & (c0 > 0)
    bottom = (row >= grid.rows - e) & (r0 + grid.height < size[0])
    right = (col >= grid.cols - e) & (c0 + grid.width < size[1])
    return ~jnp.any(top | left | bottom | right)


def roi_shape(
    extent: tuple[float, float], size: tuple[int, int], *, tile: int = 8, margin: float = 64.0
) -> tuple[int, int] | None:
    """The region of interest (h, w) for tracking a tube whose silhouettes span at most
    ``extent`` = (h, w) pixels in images of ``size`` = (h, w): the extent plus ``margin``
    pixels on each side, rounded up to one of eight buckets per axis (multiples of an eighth
    of the image, in whole tiles: a few compiled shapes, not one per sequence). None when it
    would not be smaller than the image."""
    out = []
    for e, n in zip(extent, size, strict=True):
        step = -(-max(n // 8, tile) // tile) * tile
        need = -(-int(e + 2 * margin) // step) * step
        out.append(min(need, n))
    return None if tuple(out) == tuple(size) else tuple(out)


@eqx.filter_jit
def _nominal_boxes(bases: Centreline, camera) -> Float[Array, "f 4"]:
    """:func:`_tube_box` of every frame's nominal silhouette (one program per camera type and
    frame count, not one per call)."""
    return jax.vmap(lambda b: _tube_box(project_tube(camera, b)))(bases)


def tracking_roi(
    bases: Centreline, cameras, *, config: RefineConfig = DEFAULT_CONFIG, margin: float = 64.0
) -> tuple[int, int] | None:
    """The region of interest (:func:`roi_shape`) for tracking a sequence: the largest extent
    of the frames' nominal silhouettes (``bases``: (F, N) centrelines) over the cameras, plus
    ``margin`` pixels a side (the warm start's distance from the nominal shape and the band
    around it; a frame whose bands come closer to the border is refined on the whole image).
    None when no region would be smaller than the image, the cameras differ in size, or
    ``config`` has the whole image's outside mean (``local=False``: the region would change
    the energy)."""
    cameras = _as_tuple(cameras)
    sizes = {(c.height, c.width) for c in cameras}
    if len(sizes) != 1 or not config.local:
        return None
    ext = np.zeros(2)
    for cam in cameras:
        boxes = np.asarray(_nominal_boxes(bases, cam))
        ok = np.all(np.isfinite(boxes), axis=1) & (boxes[:, 2] >= boxes[:, 0])
        if not np.any(ok):
            return None
        spans = [(boxes[ok, 3] - boxes[ok, 1]).max(), (boxes[ok, 2] - boxes[ok, 0]).max()]
        ext = np.maximum(ext, spans)
    return roi_shape(tuple(ext), sizes.pop(), tile=config.tile, margin=margin)


def _mask(tube: TubeImage, band: Band, data: RegionData, m=None) -> Bool[Array, "h w"]:
    """The hard mask (h, w); ``m``: the band's margins if already computed."""
    grid = data.grid
    m = band_margin(tube, grid, band) if m is None else m
    tiles = jnp.broadcast_to(band.inside[:, None], (grid.n_tiles, grid.n_pix))
    hard = m > 0
    if band.active is not None:  # inactive slots keep their whole-tile class
        hard = jnp.where(band.active[:, None], hard, band.inside[band.tiles][:, None])
    return grid.from_tiles(tiles.at[band.tiles].set(hard))


def _image_space_stop(solver, y, state, new, options):
    """Replace ``new.terminate`` by the image-space test of :class:`ImageSpaceBFGS`."""
    jac = options["motion_jac"]
    d = jax.flatten_util.ravel_pytree(state.y_eval)[0] - jax.flatten_util.ravel_pytree(y)[0]
    uv = jac @ d  # (P, 2): displacement of each projected point by the trial step
    small_step = jnp.max(jnp.hypot(uv[:, 0], uv[:, 1])) < solver.xtol
    f_scale = options.get("f_scale", 1.0)
    small_df = jnp.abs(new.f_info.f - state.f_info.f) * f_scale < solver.ftol
    # the linear model's decrease for the trial: what the line search was asked to find
    g = jax.flatten_util.ravel_pytree(state.f_info.grad)[0]
    small_pred = jnp.abs(jnp.dot(g, d)) * f_scale < solver.ftol
    accepted = new.num_accepted_steps > state.num_accepted_steps
    converged = jnp.where(
        accepted, small_step & small_df & ~state.first_step, small_step & small_pred
    )
    return eqx.tree_at(lambda s: s.terminate, new, converged)


class _CountedState(eqx.Module):
    """A solver state with the number of steps taken: Optimistix counts steps in its loop,
    not in the state, and its ``max_steps`` is static; :class:`ImageSpaceBFGS` ends a solve
    after ``options["step_budget"]`` steps (a traced count), so that one compiled solve
    serves levels with different step budgets. Attributes of the inner state are readable
    on this one (``state.f_info``)."""

    inner: object
    num_steps: Int[Array, ""]

    def __getattr__(self, name):
        if name in ("inner", "num_steps") or name.startswith("__"):
            raise AttributeError(name)
        return getattr(self.inner, name)


def _budget_terminate(state: _CountedState, options):
    """(terminate, result) of the inner state, with Optimistix's own status for a solve that
    ran out of steps (``nonlinear_max_steps_reached``) once ``options["step_budget"]`` steps
    are taken without convergence."""
    term, result = state.inner.terminate, state.inner.result
    budget = options.get("step_budget")
    if budget is None:
        return term, result
    out = (state.num_steps >= budget) & ~term
    result = optx.RESULTS.where(out, optx.RESULTS.nonlinear_max_steps_reached, result)
    return term | out, result


class _ImageSpaceSteps:
    """The steps of :class:`ImageSpaceBFGS` and :class:`ImageSpaceLBFGS` (mixed in before the
    Optimistix solver): the inner solver's step followed by the image-space stopping test,
    counted in a :class:`_CountedState` so that ``options["step_budget"]`` can end the solve."""

    def step(self, fn, y, args, options, state, tags):
        y_new, new, aux = super().step(fn, y, args, options, state.inner, tags)
        new = _image_space_stop(self, y, state.inner, new, options)
        return y_new, _CountedState(new, state.num_steps + 1), aux

    def terminate(self, fn, y, args, options, state, tags):
        return _budget_terminate(state, options)

    def postprocess(self, fn, y, aux, args, options, state, tags, result):
        return super().postprocess(fn, y, aux, args, options, state.inner, tags, result)


class ImageSpaceBFGS(_ImageSpaceSteps, optx.BFGS):
    """Optimistix BFGS whose convergence test measures a step by the image motion it causes.

    Optimistix's own test (Cauchy: every parameter moved by less than ``atol + rtol |y|`` *and*
    ``|df| < atol + rtol |f|``) works in parameter units. Ours mixes dimensionless curvature
    coefficients (1 unit ~ 1 rad of bending, ~100 px of tip motion) with camera-pose
    corrections, several of whose combinations barely move the image (a small rotation about
    the optical centre against a sideways shift); those drift under the regulariser alone.
    With ``rtol = atol = 1e-4`` a step had to move the silhouette by ~0.01 px, below the
    resolution of a region energy on a pixel grid in float32, so no solve ever stopped
    (steps at the end of a solve still moved coefficients by 2e-3 to 7e-3 while the tube
    moved 0.005-0.2 px and J changed by its float32 rounding; measured with
    ``experiments/segmentation/refine_convergence_diag.py``).

    Here a step ``dy`` is measured as ``max_p |J_p dy|``: the largest displacement (pixels of
    the current pyramid level) of any projected centreline point p, with ``J_p`` the Jacobian
    of the projected points w.r.t. the flattened parameters at the start of the solve, passed
    as ``options["motion_jac"]`` with shape (P, 2, n). A solve stops (status successful) when

    * an accepted step (not the first evaluation) moved the tube by less than ``xtol`` px and
      changed J by less than ``ftol`` (the Cauchy test, in image space), or
    * a trial step moving the tube by less than ``xtol`` px, for which the gradient predicted
      a decrease of J below ``ftol``, was rejected by the Armijo line search: what is left to
      gain within the tolerance is below ``ftol`` even by the linear model (the line search
      otherwise halves the step until ``max_steps``, as it did at the end of every solve).

    A solve also ends (status ``nonlinear_max_steps_reached``, as at Optimistix's static
    ``max_steps``) after ``options["step_budget"]`` steps when given: a traced budget, so
    that the pyramid levels share one compiled solve (:func:`refine_frame`).

    Everything else (BFGS update, Newton descent, backtracking Armijo search) is
    ``optx.BFGS``.
    """

    xtol: float
    ftol: float

    def __init__(self, xtol: float, ftol: float):
        # the inherited Cauchy test is replaced in `step`; these values are never used
        super().__init__(rtol=0.0, atol=1.0)
        self.xtol = xtol
        self.ftol = ftol

    def init(self, fn, y, args, options, f_struct, aux_struct, tags):
        """Optimistix's init, starting from ``options["hessian_inv0"]`` ((n, n), the inverse
        Hessian in the solver's units, for a flat ``y`` of n) instead of the identity when
        given: the first BFGS direction is then ``-H0 g`` (a quasi-Newton step from what an
        earlier solve learnt) rather than steepest descent."""
        state = super().init(fn, y, args, options, f_struct, aux_struct, tags)
        h0 = options.get("hessian_inv0")
        if h0 is not None:
            state = eqx.tree_at(lambda s: s.f_info.hessian_inv.pytree, state, h0.astype(y.dtype))
        return _CountedState(state, jnp.asarray(0, jnp.int32))


class ImageSpaceLBFGS(_ImageSpaceSteps, optx.LBFGS):
    """:class:`ImageSpaceBFGS`'s stopping test on Optimistix L-BFGS, whose initial inverse
    Hessian at every step is ``gamma I`` with ``gamma = s.y / y.y`` from the last step
    (Nocedal & Wright eq. 7.20) instead of BFGS's fixed identity."""

    xtol: float
    ftol: float

    def __init__(self, xtol: float, ftol: float, history_length: int = 10):
        super().__init__(rtol=0.0, atol=1.0, history_length=history_length)
        self.xtol = xtol
        self.ftol = ftol

    def init(self, fn, y, args, options, f_struct, aux_struct, tags):
        state = super().init(fn, y, args, options, f_struct, aux_struct, tags)
        return _CountedState(state, jnp.asarray(0, jnp.int32))


def _pow2(x: Array) -> Array:
    """Nearest power of two (in log scale) of positive ``x``."""
    return jnp.exp2(jnp.round(jnp.log2(x)))


def _result_int(result) -> Int[Array, ""]:
    return jnp.asarray(result._value, jnp.int32)


class _Levels(eqx.Module):
    """The pyramid levels of a refinement as one pytree with a leading level axis L, so that
    one compiled solve serves every level (:func:`refine_frame`): per camera, the levels'
    :class:`RegionData` padded to the finest level's grid (zero weight on the padding), which
    tiles of that grid lie in the level's image (``tile_ok``) and the level's band size
    (``k_active`` of ``k_max`` slots); per level, the level, tau and the step budget; static,
    the capsule count of the drawn tube and the solver's ``max_steps`` (the largest budget, or
    None when the budgets are traced: see :func:`_level_tables`)."""

    datas: tuple[RegionData, ...]
    tile_ok: tuple[Bool[Array, "L n"], ...]
    k_active: tuple[Int[Array, " L"], ...]
    level: Int[Array, " L"]
    tau: Float[Array, " L"]
    steps: Int[Array, " L"]
    k_max: tuple[int, ...] = eqx.field(static=True)
    n_capsules: int = eqx.field(static=True)
    max_steps: int | None = eqx.field(static=True)


def _level_tables(
    pyramids,
    config: RefineConfig,
    n_seg: int,
    dtype,
    which: tuple[int, ...] | None = None,
    steps=None,
    sizes=None,
    tau=None,
) -> _Levels:
    """:class:`_Levels` of ``config``'s levels (those at indices ``which``; all if None), with
    the capsule count every level's merged tube is padded to
    (:func:`silhouette.level_tube_padded`). ``steps``: the per-level step budgets as an
    array (e.g. traced) instead of ``config.steps``; the solver's static ``max_steps`` is
    then None (no bound of its own: the traced budget ends every solve). ``tau``: the
    per-level temperatures as an array (e.g. traced) instead of ``config.tau``. ``sizes``: per
    camera the real (height, width) at level 0 (traced) of images padded to a shape bucket:
    only the tiles over real pixels of each level may enter a band, and a band has as many
    active tiles as on the unpadded image."""
    which = tuple(range(len(config.levels))) if which is None else which
    levels = [config.levels[i] for i in which]
    finest = min(levels)
    tile = config.tile
    datas, tile_ok, k_active, k_max = [], [], [], []
    for ci, pyr in enumerate(pyramids):
        hf, wf = pyr[finest][1].shape
        grid = TileGrid(hf, wf, tile)
        row = jnp.arange(grid.n_tiles) // grid.cols
        col = jnp.arange(grid.n_tiles) % grid.cols
        rds, oks, ks, ka = [], [], [], []
        for level in levels:
            img, w, b = pyr[level]
            h, wd = w.shape
            pad = ((0, hf - h), (0, wf - wd))
            rd = region_data_from_level(
                jnp.pad(img, pad + ((0, 0),)), jnp.pad(w, pad), jnp.pad(b, pad), level, tile
            )
            rds.append(eqx.tree_at(lambda d: d.pix_area, rd, jnp.asarray(4.0**level, dtype)))
            rows, cols = -(-h // tile), -(-wd // tile)
            ks.append(min(config.tiles_at(level), rows * cols))
            if sizes is None:
                oks.append((row < rows) & (col < cols))
                continue
            # the level's real size: downsample halves with the odd pixel kept (ceil)
            hr, wr = ((x + (2**level - 1)) // 2**level for x in sizes[ci])
            rr, cr = (hr + tile - 1) // tile, (wr + tile - 1) // tile
            oks.append((row < rr) & (col < cr))
            ka.append(jnp.minimum(config.tiles_at(level), rr * cr))
        datas.append(jax.tree.map(lambda *x: jnp.stack(x), *rds))
        tile_ok.append(jnp.stack(oks))
        k_active.append(jnp.asarray(ks, jnp.int32) if sizes is None else jnp.stack(ka))
        k_max.append(max(ks))
    return _Levels(
        datas=tuple(datas),
        tile_ok=tuple(tile_ok),
        k_active=tuple(k_active),
        level=jnp.asarray(levels, jnp.int32),
        tau=(
            jnp.asarray([config.tau[i] for i in which], dtype)
            if tau is None
            else jnp.asarray(tau, dtype)[jnp.asarray(which)]
        ),
        steps=(
            jnp.asarray([config.steps[i] for i in which], jnp.int32)
            if steps is None
            else jnp.asarray(steps, jnp.int32)[jnp.asarray(which)]
        ),
        k_max=tuple(k_max),
        n_capsules=-(-n_seg // (config.seg_merge * 2**finest)),
        max_steps=max(config.steps[i] for i in which) if steps is None else None,
    )


def refine_frame(
    base: Centreline,
    cameras: Camera | tuple[Camera, ...],
    images: Float[Array, "h w 3"] | tuple[Float[Array, "h w 3"], ...],
    backgrounds: Bool[Array, "h w"] | tuple[Bool[Array, "h w"], ...],
    config: RefineConfig = DEFAULT_CONFIG,
    init: Float[Array, "a k"] | None = None,
    valid: Bool[Array, ""] | bool = True,
    init_cam: Float[Array, "c 6"] | None = None,
    init_hessian: Float[Array, "n n"] | None = None,
    *,
    steps: Int[Array, " L"] | None = None,
) -> RefineResult:
    """Refine one frame (pure; jit it, or use :func:`refine_batch` / :func:`refine_frame_jit`).

    Args:
        base: nominal centreline from the robot model (robot frame, metres), N samples.
        cameras: one :class:`Camera` or a tuple (one per view).
        images: background-subtracted images I' (h, w, 3) in [0, 1], one per camera.
        backgrounds: B masks (h, w) bool, True on background, one per camera.
        config: :class:`RefineConfig`.
        init: warm-start coefficients (a, k) (e.g. the previous frame's); zeros if None.
        valid: False marks a frame known to be bad (e.g. missing image): it is skipped and
            reported with ``failure = 1``.
        init_cam: warm-start camera pose corrections (n_cameras, 6), in the physical units
            of :attr:`RefineResult.camera_correction` (e.g. the previous frame's; a
            calibration error persists across frames); zeros if None. Ignored unless
            ``config.camera_correction``.
        init_hessian: warm-start inverse Hessian (n, n) for the first solve (the previous
            frame's :attr:`RefineResult.hessian_inv`); identity if None or non-finite. Used
            only with ``config.hessian_memory`` and BFGS.
        steps: the per-level step budgets (one per ``config.levels``) as an integer array,
            used instead of ``config.steps``: traced, it makes configs that differ only in
            ``steps`` one compiled program (:func:`refine_frame_jit` and
            :func:`refine_batch` pass it so); the same solves either way.

    Returns:
        :class:`RefineResult` (see there).
    """
    return _refine_frame(
        base, cameras, images, backgrounds, config, init, valid, init_cam, init_hessian,
        steps=steps,
    )[0]  # fmt: skip


def _refine_frame(
    base: Centreline,
    cameras: Camera | tuple[Camera, ...],
    images: Float[Array, "h w 3"] | tuple[Float[Array, "h w 3"], ...],
    backgrounds: Bool[Array, "h w"] | tuple[Bool[Array, "h w"], ...],
    config: RefineConfig = DEFAULT_CONFIG,
    init: Float[Array, "a k"] | None = None,
    valid: Bool[Array, ""] | bool = True,
    init_cam: Float[Array, "c 6"] | None = None,
    init_hessian: Float[Array, "n n"] | None = None,
    *,
    steps: Int[Array, " L"] | None = None,
    roi: tuple[int, int] | None = None,
    sizes: Int[Array, "c 2"] | None = None,
    nums: _Numbers | None = None,
) -> tuple[RefineResult, Bool[Array, ""]]:
    """:func:`refine_frame`, optionally on a region of interest of a tracked frame.

    ``roi`` = (h, w) (static; one-level configs at level 0 only): the region data, band
    selections and output masks are computed in an h x w window of each image, on the tile
    grid, centred on the warm start's and the nominal shape's silhouettes (a camera whose
    principal point is moved by the window's origin); J keeps the whole image's colour
    variance and the nominal area, so with ``config.local`` (docs/decisions.md S3) the energy
    equals the full image's up to float rounding whenever the bands lie inside the window. The
    masks are returned at full size. Also returns ``fit``: every output band (refined and
    nominal shape) stays ``ROI_FREE_TILES`` clear of the window's inner borders; where it does
    not, the callers refine the frame again on the whole image (docs/decisions.md S21).
    Without ``roi``, ``fit`` is True.

    ``sizes`` (n_cameras, 2) int (traced): per camera the real (height, width) of an image
    padded at the bottom and right to the arrays' (and the cameras') larger size, a shape
    bucket (:mod:`jaxcr.segmentation.buckets`, docs/decisions.md S29). The padded pixels weigh
    nothing (:func:`jaxcr.segmentation.energy.pyramid` ``valid``), never enter a band, the
    projection is clamped and the silhouette area counted on the real image, and the masks
    are False there: the result equals the unpadded image's up to float rounding (sums over
    arrays of another shape), and every real size padded to one shape runs one program.

    ``nums``: the config's numeric settings as arrays (:func:`_traced_apart`, which gives
    ``config`` as placeholders; ``steps`` is then ignored): traced by the compiled entry
    points. None: ``config``'s own values (constants of the program).
    """
    cameras, images, backgrounds = _as_tuple(cameras), _as_tuple(images), _as_tuple(backgrounds)
    if not (len(cameras) == len(images) == len(backgrounds)):
        raise InputError("need one image and one background mask per camera", field="images")
    if steps is not None and jnp.shape(steps) != (len(config.levels),):
        raise InputError(
            f"steps needs one budget per level ({len(config.levels)}), got shape "
            f"{jnp.shape(steps)}",
            field="steps",
        )
    dtype = base.p.dtype
    # the numeric settings: read from ``num`` only (``config``'s may be placeholders)
    budgets_traced = nums is not None or steps is not None
    if nums is None:
        nums = _numbers(config, dtype)
        if steps is not None:
            nums = eqx.tree_at(lambda n: n.steps, nums, jnp.asarray(steps, jnp.int32))
    num = nums
    if sizes is None:
        real = (None,) * len(cameras)
    else:
        sizes = jnp.asarray(sizes, jnp.int32).reshape(len(cameras), 2)
        real = tuple((sizes[k, 0], sizes[k, 1]) for k in range(len(cameras)))
    finite_in = jnp.all(jnp.isfinite(base.p)) & jnp.all(jnp.isfinite(base.u))
    finite_in = finite_in & jnp.all(jnp.isfinite(base.R)) & jnp.all(jnp.isfinite(base.rho))
    finite_in = finite_in & jnp.asarray(valid)
    for im in images:
        finite_in = finite_in & jnp.all(jnp.isfinite(im))
    base = jax.tree.map(lambda a, b: jnp.where(finite_in, a, b), base, _straight(base))
    images = tuple(jnp.where(jnp.isfinite(im), im, 0.0).astype(dtype) for im in images)

    shape = config.coeff_shape
    n_cam = len(cameras)
    c0 = jnp.zeros(shape, dtype) if init is None else jnp.asarray(init, dtype).reshape(shape)
    c0 = jnp.where(jnp.all(jnp.isfinite(c0)), c0, 0.0)
    weights = num.weights
    # Welsch (robust > 0) or quadratic inside term: a structural switch, kept in the config;
    # the scale itself is traced (region_terms takes an array scale as the Welsch path)
    robust = num.robust if config.robust > 0 else 0.0
    z_ref = jax.lax.stop_gradient(tuple(jnp.mean(base.p @ cam.R[2] + cam.t[2]) for cam in cameras))

    rig = config.camera_correction_mode == "rig"
    residual = rig and config.g_cam_rel is not None and n_cam > 1

    def cameras_of(params):
        if not config.camera_correction:
            return cameras
        if rig:
            return _rig_cameras(cameras, params["cam"], z_ref, residual)
        return tuple(
            _corrected_camera(cam, params["cam"][i], z_ref[i]) for i, cam in enumerate(cameras)
        )

    def tubes_of(params):
        cl = perturbed_centreline(base, params["c"], config.torsion)
        cams = cameras_of(params)
        return cl, tuple(project_tube(c, cl, size=sz) for c, sz in zip(cams, real, strict=True))

    def reg_of(params):
        r = weights.g_reg * regularisation(params["c"], base.s, config.torsion)
        if config.camera_correction and residual:
            pc = params["cam"]
            r = r + num.g_cam * jnp.sum(pc[0] ** 2) + num.g_cam_rel * jnp.sum(pc[1:] ** 2)
        elif config.camera_correction:
            r = r + num.g_cam * jnp.sum(params["cam"] ** 2)
        return r

    def _tube_jacobian(params):
        """The projected tubes and their Jacobian (forward mode) w.r.t. the flat params:
        per camera a TubeImage of values and one whose float fields are (m, n) Jacobians.
        One forward-mode Jacobian serves both the motion Jacobian and the first gradient of
        each solve (:func:`_motion_jacobian`, ``g0``), so the centreline is differentiated
        once per solve set-up instead of twice (forward for the motion, reverse for ``g0``)."""
        flat, unravel = jax.flatten_util.ravel_pytree(jax.lax.stop_gradient(params))

        def fields(f):
            _, tubes = tubes_of(unravel(f))
            return tuple((t.ax, t.ay, t.bx, t.by, t.ra, t.rb) for t in tubes), tubes

        jacs, tubes = jax.jacfwd(fields, has_aux=True)(flat)
        return jax.lax.stop_gradient(tubes), jax.lax.stop_gradient(jacs)

    def _motion_jacobian(tubes, jacs, level):
        """(P, 2, n): d(projected centreline points, pixels of ``level``) / d(flat params);
        rows of points behind a camera are zero (see :class:`ImageSpaceBFGS`)."""
        out = []
        for t, (dax, day, dbx, dby, _, _) in zip(tubes, jacs, strict=True):
            ok = jnp.concatenate([t.valid, t.valid[-1:]])[:, None, None]
            jx = jnp.concatenate([dax, dbx[-1:]], axis=0)
            jy = jnp.concatenate([day, dby[-1:]], axis=0)
            out.append(jnp.where(ok, jnp.stack([jx, jy], axis=1), 0.0) * jnp.exp2(-level))
        return jax.lax.stop_gradient(jnp.concatenate(out, axis=0))

    params0 = {"c": c0}
    n_par = n_cam if (residual or not rig) else 1  # rows of params["cam"]
    z_par = jnp.stack(z_ref[:n_par])[:, None]
    if config.camera_correction:
        params0["cam"] = jnp.zeros((n_par, 6), dtype)
        if init_cam is not None:
            ic = jnp.asarray(init_cam, dtype).reshape(n_cam, 6)
            if rig:
                ic = _rig_corrections_to_params(cameras, ic, z_ref, residual)
            else:
                ic = _phys_to_params(ic, z_par)
            params0["cam"] = jnp.where(jnp.all(jnp.isfinite(ic)), ic, 0.0)
    zeros = jax.tree.map(jnp.zeros_like, params0)

    _, nominal_tubes = tubes_of(zeros)
    area_ref = sum(
        _tube_area(t, cam, sz) for t, cam, sz in zip(nominal_tubes, cameras, real, strict=True)
    )
    area_ref = jax.lax.stop_gradient(jnp.maximum(area_ref, 1.0))
    in_view = area_ref > 1.0
    full_size = tuple(im.shape[:2] for im in images)

    def valid_of(shape, sz):
        """The real pixels (True) of an array of ``shape`` whose real size is ``sz``."""
        if sz is None:
            return None
        return (jnp.arange(shape[0])[:, None] < sz[0]) & (jnp.arange(shape[1])[None, :] < sz[1])

    valids = tuple(valid_of(fs, sz) for fs, sz in zip(full_size, real, strict=True))
    real_full = tuple(fs if sz is None else sz for fs, sz in zip(full_size, real, strict=True))
    if roi is not None:
        if tuple(config.levels) != (0,) or not config.local:
            raise InputError(
                "roi (a region of interest) needs a one-level config at level 0 with the local "
                "outside mean (local=True)",
                field="roi",
            )
        # the window follows the warm start's and the nominal silhouettes; J keeps the whole
        # image's normalisation (colour variance; area_ref above)
        _, init_tubes = tubes_of(params0)
        rois = tuple((min(roi[0], h), min(roi[1], w)) for h, w in full_size)
        origins = tuple(
            _roi_origin([_tube_box(ti), _tube_box(tn)], rc, sz, config.tile)
            for ti, tn, rc, sz in zip(init_tubes, nominal_tubes, rois, real_full, strict=True)
        )
        roi_vars = tuple(
            _image_variance(im, bg, v)
            for im, bg, v in zip(images, backgrounds, valids, strict=True)
        )
        if sizes is not None:  # the real part of each window (all of it, unless past the image)
            real = tuple(
                (jnp.clip(sz[0] - r0, 0, rc[0]), jnp.clip(sz[1] - c0, 0, rc[1]))
                for sz, (r0, c0), rc in zip(real, origins, rois, strict=True)
            )
        images = tuple(
            jax.lax.dynamic_slice(im, (r0, c0, 0), rc + (3,))
            for im, (r0, c0), rc in zip(images, origins, rois, strict=True)
        )
        backgrounds = tuple(
            jax.lax.dynamic_slice(bg, (r0, c0), rc)
            for bg, (r0, c0), rc in zip(backgrounds, origins, rois, strict=True)
        )
        cameras = tuple(
            _roi_camera(cam, r0, c0, rc)
            for cam, (r0, c0), rc in zip(cameras, origins, rois, strict=True)
        )
        nominal_tubes = tubes_of(zeros)[1]
    # the arrays the solves see (a window of the image with roi) and their real pixels
    valids_in = tuple(valid_of(im.shape[:2], sz) for im, sz in zip(images, real, strict=True))

    def image_energy(tubes, args):
        """The data and penalty terms of J (everything but the regulariser) for the
        projected tubes of each camera."""
        bands, datas, lv, vars_, gathered = args
        J = 0.0
        for tube, band, data, var, gat in zip(tubes, bands, datas, vars_, gathered, strict=True):
            Jc, _ = chan_vese_energy(
                draw(tube, lv),
                band,
                data,
                0.0,
                weights,
                lv.tau,
                area_ref,
                config.local,
                robust,
                var,
                config.robust_envelope,
                gat,
            )
            J = J + Jc
        return J

    def objective(params, args):
        _, tubes = tubes_of(params)
        return reg_of(params) + image_energy(tubes, args)

    def first_gradient(params, tubes, jacs, args):
        """grad J at ``params`` by the chain rule through the tube Jacobian ``jacs``
        (:func:`_tube_jacobian`): the reverse pass runs through the image terms only, not
        through the centreline integration and projection again."""

        def of_fields(fs):
            ts = tuple(TubeImage(*f, t.valid) for f, t in zip(fs, tubes, strict=True))
            return image_energy(ts, args)

        fs = tuple((t.ax, t.ay, t.bx, t.by, t.ra, t.rb) for t in tubes)
        g_fields = jax.grad(of_fields)(fs)
        g = jax.flatten_util.ravel_pytree(jax.grad(reg_of)(params))[0]
        for gf, jf in zip(jax.tree.leaves(g_fields), jax.tree.leaves(jacs), strict=True):
            g = g + gf @ jf
        return g

    def gauss_newton_solve(params, tubes, tube_jacs, args, hinv, have_h):
        """One solve of ``solve`` by :func:`damped_gauss_newton` on the least-squares form of
        J (:mod:`jaxcr.segmentation.least_squares`); the inverse Hessian passes through."""
        bands, datas, lv, vars_, gathered = args
        flat0, unravel = jax.flatten_util.ravel_pytree(params)
        jac = _motion_jacobian(tubes, tube_jacs, lv.level)

        def reg_flat(y):
            return reg_of(unravel(y))

        # R is quadratic in the parameters: its Hessian is one constant matrix
        hess_reg = jax.hessian(reg_flat)(jnp.zeros_like(flat0))

        def drawn(y):
            _, ts = tubes_of(unravel(y))
            ds = tuple(draw(t, lv) for t in ts)
            return tuple(jnp.stack([t.ax, t.ay, t.bx, t.by, t.ra, t.rb]) for t in ds), ds

        def image_soft(softs):
            J = 0.0
            for soft, band, data, var, gat in zip(
                softs, bands, datas, vars_, gathered, strict=True
            ):
                J = J + chan_vese_soft(
                    soft, band, data, weights, area_ref, config.local, robust, var,
                    config.robust_envelope, gat,
                )[0]  # fmt: skip
            return J

        def linearise(y):
            # the drawn tubes' fields and their (6, m, n) Jacobians, then per band pixel the
            # margin's derivatives w.r.t. its winning capsule's fields (least_squares)
            field_jacs, ts = jax.jacfwd(drawn, has_aux=True)(y)
            wins = tuple(
                winner_margins(t, d.grid, bd) for t, d, bd in zip(ts, datas, bands, strict=True)
            )
            softs = tuple(jax.nn.sigmoid(w[0] / lv.tau) for w in wins)
            J_img, es = jax.value_and_grad(image_soft)(softs)
            J = J_img + reg_flat(y)
            g = hess_reg @ y
            G = hess_reg
            for (m, dfield, slot), fj, bd, e in zip(wins, field_jacs, bands, es, strict=True):
                gc, Gc = band_normal_terms(m, dfield, slot, fj, bd, e, lv.tau)
                g, G = g + gc, G + Gc
            return J, g, G

        out = damped_gauss_newton(
            linearise, flat0, jac, xtol=num.xtol, ftol=num.ftol, budget=lv.steps,
            lam0=num.gn_lambda, max_px=num.gn_max_px,
        )  # fmt: skip
        value = unravel(out.y)
        good = jnp.all(jnp.stack([jnp.all(jnp.isfinite(x)) for x in jax.tree.leaves(value)]))
        new = jax.tree.map(lambda a, b: jnp.where(good, a, b), value, params)
        result = optx.RESULTS.where(
            out.converged, optx.RESULTS.successful, optx.RESULTS.nonlinear_max_steps_reached
        )
        return (new, _result_int(result), hinv, have_h), out.num_steps

    if config.solver == "lbfgs":
        solver = ImageSpaceLBFGS(num.xtol, num.ftol)
    elif config.solver == "gn":
        solver = None
    else:
        solver = ImageSpaceBFGS(num.xtol, num.ftol)
    n_flat = jax.flatten_util.ravel_pytree(params0)[0].shape[0]
    memory = config.hessian_memory and config.solver == "bfgs"
    eye = jnp.eye(n_flat, dtype=dtype)
    if init_hessian is None:
        hinv, have_h = eye, jnp.asarray(False)
    else:
        hinv = jnp.asarray(init_hessian, dtype).reshape(n_flat, n_flat)
        have_h = jnp.all(jnp.isfinite(hinv))
        hinv = jnp.where(have_h, hinv, eye)
    pyramids = [
        pyramid(im, bg, max(config.levels) + 1, v)
        for im, bg, v in zip(images, backgrounds, valids_in, strict=True)
    ]
    data_ok = sum(jnp.sum(p[0][1]) for p in pyramids) > 0.5

    # One compiled solve serves every pyramid level (issue 18, config.share_levels): the
    # levels' data are padded to one shape and stacked, and a lax.scan over the schedule's
    # solves picks its level's slice (see _level_tables). Otherwise each level gets its own
    # one-level table and scan: the same body traced once per level, on unpadded arrays.
    def draw(tube, lv):
        return level_tube_padded(tube, lv.level, config.seg_merge, lv.n_capsules)

    def solve(carry, xs, tables):
        params, _, hinv, have_h = carry
        li, new_level = xs
        lv = jax.tree.map(lambda x: x[li], tables)
        # the coarse level's curvature (wider tau, coarser pixels) is not the fine one's
        hinv = jnp.where(new_level, eye, hinv)
        have_h = have_h & ~new_level
        datas = lv.datas
        tubes, tube_jacs = _tube_jacobian(params)
        bands = tuple(
            select_band(draw(t, lv), d.grid, k, config.k_seg, ok, ka)
            for t, d, k, ok, ka in zip(tubes, datas, lv.k_max, lv.tile_ok, lv.k_active, strict=True)
        )
        if config.data_var == "residual":
            vars_ = tuple(
                residual_variance(
                    chan_vese_energy(
                        draw(t, lv), bd, d, 0.0, weights, lv.tau, area_ref, config.local,
                        robust,
                    )[1]
                )
                for t, bd, d in zip(tubes, bands, datas, strict=True)
            )  # fmt: skip
        else:
            vars_ = (None,) * len(tubes) if roi is None else roi_vars
        # the band's pixels once per solve, not at every energy evaluation
        gathered = tuple(d.gather(bd.tiles) for d, bd in zip(datas, bands, strict=True))
        args = (bands, datas, lv, vars_, gathered)
        if config.solver == "gn":
            return gauss_newton_solve(params, tubes, tube_jacs, args, hinv, have_h)
        # solve in image-motion units (see ImageSpaceBFGS): z_i = scale_i * y_i with
        # scale_i the RMS motion (level px) of the projected points per unit of y_i, and
        # J divided by kappa so that the first, steepest-descent step moves the tube by
        # about STEP0_PX (quasi-Newton methods start from an identity Hessian, which in
        # parameter units made the first trial move it by 30-50 px: 4-5 rejected trials
        # per solve); L-BFGS is invariant to kappa after that first step
        flat0, unravel = jax.flatten_util.ravel_pytree(params)
        jac = _motion_jacobian(tubes, tube_jacs, lv.level)
        # Both factors are rounded to powers of two: scaling is then exact in floating
        # point, and rounding differences between compiled contexts (per frame, lax.map,
        # vmap) in the gradient behind kappa almost never change it
        scale = jnp.sqrt(jnp.mean(jnp.sum(jac * jac, axis=1), axis=0))
        scale = _pow2(jnp.maximum(scale, 1e-3 * jnp.max(scale) + 1e-12))
        g0 = first_gradient(jax.lax.stop_gradient(params), tubes, tube_jacs, args)
        uv0 = jac @ (g0 / scale**2)
        kappa = jnp.maximum(jnp.max(jnp.hypot(uv0[:, 0], uv0[:, 1])) / STEP0_PX, 1e-6)
        kappa = jax.lax.stop_gradient(_pow2(kappa))

        def scaled(z, args):
            return objective(unravel(z / scale), args) / kappa

        options = {"motion_jac": jac / scale, "f_scale": kappa, "step_budget": lv.steps}
        # the inverse Hessian is carried in J per (parameter unit)^2 and moved into this
        # solve's units (z = scale * y, J / kappa): H_z^-1 = kappa D H^-1 D, D = diag(scale)
        outer_scale = scale[:, None] * scale[None, :]
        if memory:
            hz = kappa * outer_scale * hinv
            use = have_h & jnp.all(jnp.isfinite(hz))
            options["hessian_inv0"] = jnp.where(use, hz, eye)
        sol = optx.minimise(
            scaled,
            solver,
            flat0 * scale,
            args=args,
            options=options,
            max_steps=lv.max_steps,
            throw=False,
        )
        value = unravel(sol.value / scale)
        good = jnp.all(jnp.stack([jnp.all(jnp.isfinite(x)) for x in jax.tree.leaves(value)]))
        new = jax.tree.map(lambda a, b: jnp.where(good, a, b), value, params)
        if memory:
            h_new = sol.state.inner.f_info.hessian_inv.pytree / (kappa * outer_scale)
            keep = good & jnp.all(jnp.isfinite(h_new))
            hinv = jnp.where(keep, h_new, hinv)
            have_h = have_h | keep
        return (new, _result_int(sol.result), hinv, have_h), sol.stats["num_steps"]

    n_levels = len(config.levels)
    groups = [tuple(range(n_levels))] if config.share_levels else [(i,) for i in range(n_levels)]
    carry = (params0, jnp.asarray(0, jnp.int32), hinv, have_h)
    n_solve = []
    for group in groups:
        tables = _level_tables(
            pyramids, config, base.p.shape[0] - 1, dtype, group,
            num.steps if budgets_traced else None, None if sizes is None else real, num.tau,
        )  # fmt: skip
        # the schedule: solve j runs at row k of the table (config.outer[li] solves of level
        # li = group[k]); each level after the first starts from the identity Hessian
        rows = [(k, li) for k, li in enumerate(group) for _ in range(config.outer[li])]
        new_level = [li > 0 and (j == 0 or rows[j - 1][1] != li) for j, (_, li) in enumerate(rows)]
        xs = (jnp.asarray([k for k, _ in rows], jnp.int32), jnp.asarray(new_level, bool))
        carry, n = jax.lax.scan(lambda c, x, t=tables: solve(c, x, t), carry, xs)
        n_solve.append(n)
    params, status, hinv, have_h = carry
    n_solve = jnp.concatenate(n_solve)
    ends = [sum(config.outer[: li + 1]) for li in range(len(config.levels))]
    steps = [jnp.sum(n_solve[e - n : e]) for e, n in zip(ends, config.outer, strict=True)]

    # final outputs at full resolution
    datas0 = tuple(region_data_from_level(*p[0], 0, config.tile) for p in pyramids)
    k0 = config.tiles_at(0)

    def tube_outputs(tubes):
        """Masks, exactness and hard terms (summed over cameras) of one shape's tubes, and
        whether their bands stay clear of the region of interest's borders."""
        masks, exact, fit = [], jnp.asarray(True), jnp.asarray(True)
        e = {"e_in": 0.0, "e_out": 0.0, "e_pen": 0.0, "J": 0.0}
        for i, (tube, data) in enumerate(zip(tubes, datas0, strict=True)):
            if sizes is None:
                band = select_band(tube, data.grid, k0, config.seg_merge * config.k_seg)
            else:  # tiles over real pixels only, as many as the unpadded image's band
                grid = data.grid
                rr, cr = ((x + config.tile - 1) // config.tile for x in real[i])
                row = jnp.arange(grid.n_tiles) // grid.cols
                col = jnp.arange(grid.n_tiles) % grid.cols
                band = select_band(
                    tube, grid, k0, config.seg_merge * config.k_seg,
                    (row < rr) & (col < cr), jnp.minimum(k0, rr * cr),
                )  # fmt: skip
            m = band_margin(tube, data.grid, band)  # once for the mask and the terms
            mask = _mask(tube, band, data, m)
            exact = exact & band.exact
            t = _hard_terms(tube, band, data, config.local, robust, m)
            if roi is None:
                var = data.total_s2 / jnp.maximum(data.total_w, 1e-6)
            else:
                var = roi_vars[i]
                r0, c0 = origins[i]
                fit = fit & _band_clear_of_border(band, data.grid, r0, c0, real_full[i])
                mask = jax.lax.dynamic_update_slice(jnp.zeros(full_size[i], bool), mask, (r0, c0))
            if valids[i] is not None:
                mask = mask & valids[i]
            masks.append(mask)
            e["e_in"] = e["e_in"] + t.e_in
            e["e_out"] = e["e_out"] + t.e_out
            e["e_pen"] = e["e_pen"] + t.e_pen
            e["J"] = (
                e["J"]
                + (weights.g_in * t.e_in + weights.g_out * (t.e_out - t.e_out_empty))
                / (area_ref * jnp.maximum(var, 1e-8))
                + weights.g_pen * t.e_pen / area_ref
            )
        return tuple(masks), exact, e, fit

    finite_out = jnp.all(jnp.stack([jnp.all(jnp.isfinite(x)) for x in jax.tree.leaves(params)]))
    params = jax.tree.map(lambda x: jnp.where(finite_out, x, 0.0), params)
    cl, tubes = tubes_of(params)
    # the refined and the nominal shape's outputs by one traced body (issue 18: the output
    # stage is a large part of the program; compiling it once instead of twice)
    pair = jax.tree.map(lambda a, b: jnp.stack([a, b]), tubes, nominal_tubes)
    masks2, exact2, e2, fit2 = jax.lax.map(tube_outputs, pair)
    masks = tuple(m[0] for m in masks2)
    nominal_masks = tuple(m[1] for m in masks2)
    exact = exact2[0]
    e = {k: v[0] for k, v in e2.items()}
    e["e_reg"] = regularisation(params["c"], base.s, config.torsion)
    e["J"] = e["J"] + reg_of(params)
    e_nom = {"J": e2["J"][1] + reg_of(zeros)}

    failure = jnp.where(
        ~finite_in,
        1,
        jnp.where(~in_view, 2, jnp.where(~data_ok, 3, jnp.where(~finite_out, 4, 0))),
    ).astype(jnp.int32)
    ok = failure == 0
    energy = RefineEnergy(
        e_in=e["e_in"],
        e_out=e["e_out"],
        e_reg=e["e_reg"],
        e_pen=e["e_pen"],
        total=e["J"],
        total_nominal=e_nom["J"],
    )
    if config.camera_correction and rig:
        # effective per-camera correction T_i' T_i^-1
        cams_c = cameras_of(params)
        cam_corr = jnp.stack(
            [
                _pose_delta(cc.T_cam_robot, cam.T_cam_robot)
                for cc, cam in zip(cams_c, cameras, strict=True)
            ]
        )
    elif config.camera_correction:
        cam_corr = jnp.concatenate(
            [
                CAM_ROT_UNIT * params["cam"][:, :3],
                CAM_T_UNIT * jnp.stack(z_ref)[:, None] * params["cam"][:, 3:],
            ],
            axis=1,
        )
    else:
        cam_corr = jnp.zeros((n_cam, 6), dtype)
    c = params["c"]
    result = RefineResult(
        masks=masks,
        nominal_masks=nominal_masks,
        centreline=cl,
        coeffs=c,
        delta_u=delta_u_steps(c, base.s, config.torsion),
        energy=energy,
        status=status,
        num_steps=sum(steps),
        steps_per_level=jnp.stack(steps),
        ok=ok,
        failure=failure,
        band_exact=exact,
        camera_correction=cam_corr,
        hessian_inv=hinv,
        time_s=jnp.asarray(0.0, dtype),
    )
    return result, jnp.all(fit2)


# The compiled entry points below take ``config`` as placeholders (static) and its numeric
# settings ``nums`` as traced arrays (:func:`_traced_apart`), so that configs differing only in
# step budgets, temperatures, weights or tolerances share one compiled program (and one trace).


@eqx.filter_jit
def _refine_frame_jit(
    base, cameras, images, backgrounds, config, init, valid, init_cam, init_h, nums
):
    return _refine_frame(
        base, cameras, images, backgrounds, config, init, valid, init_cam, init_h, nums=nums
    )[0]


@eqx.filter_jit
def _refine_frame_roi_jit(
    base, cameras, images, backgrounds, config, init, valid, init_cam, init_h, nums, roi
):
    return _refine_frame(
        base, cameras, images, backgrounds, config, init, valid, init_cam, init_h, roi=roi,
        nums=nums,
    )  # fmt: skip


def _direct(fn, *args):
    return fn(*args)


def bucket_cameras(cameras, images, shape_buckets: bool):
    """For ``shape_buckets``: the cameras re-sized to their image arrays (padded at the
    bottom/right to a shape bucket, :mod:`jaxcr.segmentation.buckets`) and the real sizes
    (n_cameras, 2) = (height, width) as an int32 array, passed traced so that every real size
    padded to one shape runs one compiled program (:func:`refine_frame`'s ``sizes``);
    otherwise ``(cameras, None)``. ``images``: per camera an array (..., H, W, 3)."""
    cameras = _as_tuple(cameras)
    if not shape_buckets:
        return cameras, None
    out, sizes = [], []
    for cam, im in zip(cameras, _as_tuple(images), strict=True):
        H, W = im.shape[-3], im.shape[-2]
        if H < cam.height or W < cam.width:
            raise InputError(
                f"shape buckets: the image array ({W}x{H}) is smaller than the camera's image "
                f"({cam.width}x{cam.height})",
                field="images",
            )
        out.append(dataclasses.replace(cam, height=int(H), width=int(W)))
        sizes.append((cam.height, cam.width))
    return tuple(out), jnp.asarray(sizes, jnp.int32)


def _cam_rows(config: RefineConfig, n_cam: int) -> int:
    """Rows of the camera-correction parameters (:func:`refine_frame`'s ``params["cam"]``)."""
    rig = config.camera_correction_mode == "rig"
    residual = rig and config.g_cam_rel is not None and n_cam > 1
    return n_cam if (residual or not rig) else 1


def _cam_init(init_cam, lead: tuple[int, ...], n_cam: int, dtype):
    return jnp.zeros(lead + (n_cam, 6), dtype) if init_cam is None else jnp.asarray(init_cam)


def refine_frame_jit(
    base: Centreline,
    cameras,
    images,
    backgrounds,
    config: RefineConfig = DEFAULT_CONFIG,
    init=None,
    valid=True,
    init_cam=None,
    init_hessian=None,
    *,
    roi: tuple[int, int] | None = None,
) -> RefineResult:
    """Jit-compiled :func:`refine_frame` (compiled once per shape/config) with wall time.

    ``roi`` = (h, w): refine a warm-started frame on a region of interest of that size around
    its warm start (one-level configs at level 0, e.g. ``RefineConfig().warm()``; sizes from
    :func:`roi_shape`); the frame is refined again on the whole image when its bands come
    near the region's border (see :func:`_refine_frame`, docs/decisions.md S21)."""
    cameras, images, backgrounds = _as_tuple(cameras), _as_tuple(images), _as_tuple(backgrounds)
    init = jnp.zeros(config.coeff_shape, base.p.dtype) if init is None else init
    init_cam = _cam_init(init_cam, (), len(cameras), base.p.dtype)
    config, nums = _traced_apart(config, base.p.dtype)
    args = (base, cameras, images, backgrounds, config, init, jnp.asarray(valid, bool), init_cam)
    t0 = time.perf_counter()
    fit = False
    if roi is not None:
        out, fit = _refine_frame_roi_jit(*args, init_hessian, nums, tuple(roi))
        fit = bool(fit)
    if not fit:
        out = _refine_frame_jit(*args, init_hessian, nums)
    jax.block_until_ready(out)
    return eqx.tree_at(lambda r: r.time_s, out, jnp.asarray(time.perf_counter() - t0))


@eqx.filter_jit
def _refine_batch_jit(
    bases, cameras, images, backgrounds, config, inits, valid, mode, cams0, nums, sizes=None
):
    def one(args):
        base, ims, bgs, init, v, cam0 = args
        return _refine_frame(
            base, cameras, ims, bgs, config, init, v, cam0, sizes=sizes, nums=nums
        )[0]

    args = (bases, images, backgrounds, inits, valid, cams0)
    if mode == "vmap":
        return jax.vmap(one)(args)
    return jax.lax.map(one, args)


def refine_batch(
    bases: Centreline,
    cameras,
    images,
    backgrounds,
    config: RefineConfig = DEFAULT_CONFIG,
    inits: Float[Array, "f a k"] | None = None,
    valid: Bool[Array, " f"] | None = None,
    mode: str = "map",
    init_cams: Float[Array, "f c 6"] | None = None,
    devices: int | None = None,
    jit_call: Callable | None = None,
    *,
    shape_buckets: bool = False,
) -> RefineResult:
    """Refine F independent frames in one compiled call.

    Args:
        bases: :class:`Centreline` with a leading frame axis F (e.g. ``jax.vmap(robot.forward)
            (qs).centreline``).
        cameras: one :class:`Camera` or a tuple, shared by all frames.
        images: per camera, (F, h, w, 3) background-subtracted images.
        backgrounds: per camera, (F, h, w) bool B masks.
        config: :class:`RefineConfig`.
        inits: optional (F, a, k) warm starts.
        valid: optional (F,) bool; False frames are skipped and reported failed.
        mode: ``"map"`` (``lax.map``: frames one after another inside the compiled call,
            fastest on CPU) or ``"vmap"`` (all frames in lock step; better on accelerators).
            Both give the per-frame result up to float32 rounding, which can only matter
            where the energy has several minima within reach (``tests/segmentation/test_refine_convergence.py``).
        init_cams: optional (F, n_cameras, 6) warm-start camera corrections
            (:func:`refine_frame`'s ``init_cam``).
        devices: local devices to spread the frames over (a 1-D mesh over frames,
            :func:`jaxcr.scale.devices.map_frames`; bit-identical per frame to one device).
            None: all local devices of the default backend (one on a usual machine: no
            sharding); 1: one device.
        jit_call: how the compiled function is called, ``jit_call(fn, *args)``; None calls
            ``fn(*args)``. ``jaxcr.io.exported.cached_call`` reuses the traced program of an
            earlier process (what ``jaxcr segment`` does).
        shape_buckets: the image arrays may be larger than the cameras' images, padded at
            the bottom and right (e.g. to :func:`jaxcr.segmentation.buckets.bucket_shape`,
            with :func:`~jaxcr.segmentation.buckets.pad_frames`); the program is compiled
            for the arrays' shape with the real sizes traced, so every size padded to one
            shape shares it, and the padding weighs nothing (:func:`refine_frame`; results
            equal to the unpadded images' up to float rounding; docs/decisions.md S29). The
            masks keep the arrays' shape, False beyond the real image: crop them to
            ``[:height, :width]``.

    Returns:
        :class:`RefineResult` with a leading frame axis; ``time_s`` is the batch wall time
        divided by F.
    """
    cameras, images, backgrounds = _as_tuple(cameras), _as_tuple(images), _as_tuple(backgrounds)
    if mode not in ("map", "vmap"):
        raise InputError(f"mode must be 'map' or 'vmap', got {mode!r}", field="mode")
    f = bases.p.shape[0]
    for im, bg in zip(images, backgrounds, strict=True):
        if im.shape[0] != f or bg.shape[0] != f:
            raise InputError(
                f"images/backgrounds need {f} frames, got {im.shape[0]}/{bg.shape[0]}",
                field="images",
            )
    dtype = bases.p.dtype
    inits = jnp.zeros((f,) + config.coeff_shape, dtype) if inits is None else inits
    valid = jnp.ones(f, bool) if valid is None else jnp.asarray(valid, bool)
    cams0 = _cam_init(init_cams, (f,), len(cameras), dtype)
    cameras, sizes = bucket_cameras(cameras, images, shape_buckets)
    from jaxcr.scale.devices import map_frames

    t0 = time.perf_counter()
    call = _direct if jit_call is None else jit_call

    config, nums = _traced_apart(config, dtype)

    def body(batched, cameras, config, mode, nums, *sizes):
        bases, images, backgrounds, inits, valid, cams0 = batched
        args = (bases, cameras, images, backgrounds, config, inits, valid, mode, cams0, nums)
        return call(_refine_batch_jit, *args, *sizes)

    batched = (bases, images, backgrounds, inits, valid, cams0)
    extra = () if sizes is None else (sizes,)
    out = map_frames(body, batched, cameras, config, mode, nums, *extra, devices=devices)
    jax.block_until_ready(out)
    dt = (time.perf_counter() - t0) / max(f, 1)
    return eqx.tree_at(lambda r: r.time_s, out, jnp.full((f,), dt, dtype))


@eqx.filter_jit
def _refine_sequence_jit(
    bases, cameras, images, backgrounds, config, warm_config, init, valid, cam0, h0, cold_first,
    roi=None, sizes=None,
):  # fmt: skip
    # config and warm_config: each (placeholders, traced numeric settings), _traced_apart
    n_levels = len(config[0].levels)

    def one(cfg, c_prev, cam_prev, h_prev, base, ims, bgs, v):
        # a region of interest serves the warm schedule only (a cold first frame has no
        # previous answer to centre it on)
        r_roi = roi if cfg is warm_config else None
        r, fit = _refine_frame(
            base, cameras, ims, bgs, cfg[0], c_prev, v, cam_prev, h_prev, roi=r_roi,
            sizes=sizes, nums=cfg[1],
        )  # fmt: skip
        # steps_per_level follows config's levels: levels a warm frame skips count 0 steps
        spl = r.steps_per_level
        pad = jnp.zeros((max(n_levels - spl.shape[0], 0),), spl.dtype)
        r = eqx.tree_at(lambda x: x.steps_per_level, r, jnp.concatenate([pad, spl]))
        c_next = jnp.where(r.ok, r.coeffs, c_prev)
        cam_next = jnp.where(r.ok, r.camera_correction, cam_prev)
        h_next = jnp.where(r.ok, r.hessian_inv, h_prev)
        return (c_next, cam_next, h_next), (r, fit)

    def step(prev, args):
        return one(warm_config, *prev, *args)

    seq = (bases, images, backgrounds, valid)
    if not cold_first:
        _, out = jax.lax.scan(step, (init, cam0, h0), seq)
    else:
        # the first frame has no previous answer: the full (coarse-to-fine) schedule
        first = jax.tree.map(lambda x: x[0], seq)
        prev, r0 = one(config, init, cam0, h0, *first)
        _, rest = jax.lax.scan(step, prev, jax.tree.map(lambda x: x[1:], seq))
        out = jax.tree.map(lambda a, b: jnp.concatenate([a[None], b]), r0, rest)
    # without a region the program's outputs are the results alone (as before the region)
    return out[0] if roi is None else out


def refine_sequence(
    bases: Centreline,
    cameras,
    images,
    backgrounds,
    config: RefineConfig = DEFAULT_CONFIG,
    init: Float[Array, "a k"] | None = None,
    valid: Bool[Array, " f"] | None = None,
    init_cam: Float[Array, "c 6"] | None = None,
    warm_config: RefineConfig | None = None,
    init_hessian: Float[Array, "n n"] | None = None,
    jit_call: Callable | None = None,
    *,
    roi: tuple[int, int] | str | None = None,
    shape_buckets: bool = False,
) -> RefineResult:
    """Refine a sequence, warm-starting frame t from frame t-1's delta-u and camera
    correction (in one compiled ``lax.scan``). A failed frame passes the last good values on.
    Arguments as :func:`refine_batch`; ``init`` and ``init_cam`` (:func:`refine_frame`)
    warm-start the first frame, with ``init_hessian`` (the last frame's
    :attr:`RefineResult.hessian_inv`; NaN = identity). ``jit_call`` as :func:`refine_batch`.

    Warm-started frames use ``warm_config`` (default ``config.warm()``: the finest pyramid
    level only, see :meth:`RefineConfig.warm`); the first frame uses ``config`` unless
    ``init`` is given (e.g. the last answer of the previous chunk of a long sequence).

    ``roi``: refine the warm-started frames on a region of interest of this (h, w) size around
    each frame's warm start (``"auto"``: :func:`tracking_roi` of ``bases``; one-level warm
    schedules at level 0, as ``config.warm()``): region data, band selection and output masks
    on the region only (docs/decisions.md S21). When a frame's bands come near the region's
    border, the whole sequence is refined again on the full images.

    ``shape_buckets``: images padded to a larger shape than the cameras', as
    :func:`refine_batch`'s (the region of interest, sized from the real cameras, is placed in
    the real image)."""
    cameras, images, backgrounds = _as_tuple(cameras), _as_tuple(images), _as_tuple(backgrounds)
    f = bases.p.shape[0]
    dtype = bases.p.dtype
    warm_config = config.warm() if warm_config is None else warm_config
    # A cold first frame differs from a warm one only in its schedule (and a zero start):
    # when config is its own warm schedule (one pyramid level, e.g. `jaxcr segment --levels
    # 1 --warm-start`), the first frame is one more step of the warm scan, so a sequence's
    # chunks (the first cold, the others warm-started) run one compiled program, not two
    cold_first = init is None and warm_config != config
    init = jnp.zeros(config.coeff_shape, dtype) if init is None else init
    valid = jnp.ones(f, bool) if valid is None else jnp.asarray(valid, bool)
    cam0 = _cam_init(init_cam, (), len(cameras), dtype)
    n_flat = config.coeff_shape[0] * config.coeff_shape[1] + (
        6 * _cam_rows(config, len(cameras)) if config.camera_correction else 0
    )
    # NaN = no Hessian yet (refine_frame falls back to the identity): one compiled shape
    h0 = jnp.full((n_flat, n_flat), jnp.nan, dtype) if init_hessian is None else init_hessian
    t0 = time.perf_counter()
    call = _direct if jit_call is None else jit_call
    if isinstance(roi, str):
        if roi != "auto":
            raise InputError(f"roi must be (h, w), 'auto' or None, got {roi!r}", field="roi")
        roi = tracking_roi(bases, cameras, config=warm_config)
    # the numeric settings of both schedules traced (_traced_apart): one program for configs
    # that differ only in them
    cfg_t, warm_t = _traced_apart(config, dtype), _traced_apart(warm_config, dtype)
    args = (bases, cameras, images, backgrounds, cfg_t, warm_t, init, valid, cam0, h0)
    bcams, sizes = bucket_cameras(cameras, images, shape_buckets)
    extra = () if sizes is None else (sizes,)
    if sizes is not None:
        args = (bases, bcams) + args[2:]
    fit = False
    if roi is not None:
        roi = tuple(int(x) for x in roi)
        out, fits = call(_refine_sequence_jit, *args, cold_first, roi, *extra)
        fit = bool(jnp.all(fits))
    if not fit:
        out = call(_refine_sequence_jit, *args, cold_first, *((None,) + extra if extra else ()))
    jax.block_until_ready(out)
    dt = (time.perf_counter() - t0) / max(f, 1)
    return eqx.tree_at(lambda r: r.time_s, out, jnp.full((f,), dt, dtype))
