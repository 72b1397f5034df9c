"""Forward pairwise registration C_i -> C_j (paper Sec. IV.A): keypoints matched between the
colour images (SIFT, or ASIFT), RANSAC + Kabsch on their 3-D positions, then weighted ICP
seeded with that estimate (or with the caller's prior, identity by default, when there are
too few keypoint inliers). ICP associates by projection into the target depth image
(``association="projective"``, default; :mod:`jaxcr.registration.projective`, a random
sample of ``Frame.sample`` source pixels at full resolution) or by brute-force joint-space
nearest neighbours on the voxel clouds (``"nearest"``; :mod:`jaxcr.registration.icp`).

Degenerate inputs fail loudly: an empty cloud raises :class:`RegistrationFailed` before any
pose is produced, and so does a final overlap (ICP fitness) below ``min_fitness``: a pose
from clouds that do not overlap is garbage and is never returned.
"""

from __future__ import annotations

import copy
import time
from dataclasses import dataclass, field

import jax.numpy as jnp
import numpy as np

from jaxcr.registration import keypoints
from jaxcr.registration.clouds import (
    Cloud,
    organised_cloud,
    pad_cloud,
    plane_points,
    plane_points_scaled,
    voxel_downsample,
)
from jaxcr.registration.covariance import projective_sandwich_information_jit
from jaxcr.registration.icp import DEFAULT_ICP, CloudArrays, IcpConfig, Keypoints, icp_jit
from jaxcr.registration.keypoints import FrameFeatures, matched_features
from jaxcr.registration.metrics import pose_error
from jaxcr.registration.pose_graph import inverted_edge
from jaxcr.registration.projective import (
    DepthImage,
    blurred_image,
    depth_image,
    projective_icp_jit,
    projective_information_jit,
    scale_matching_blur,
)
from jaxcr.registration.ransac import estimate_transform, inlier_set


class RegistrationFailed(Exception):
    """Two frames could not be registered (no overlap, empty cloud)."""


@dataclass
class Frame:
    """One RGB-D capture: images, the camera-frame cloud, its padded voxel-downsampled
    arrays (nearest-neighbour ICP, Algorithm 2), the organised view (projective target) and
    a padded random sample of its full-resolution pixels (projective source)."""

    rgb: np.ndarray
    depth: np.ndarray
    cloud: Cloud
    arrays: CloudArrays
    label: str = ""
    image: DepthImage | None = None
    sample: CloudArrays | None = None
    # Denoised positions of the sample's pixels (clouds.plane_points), same rows: where the
    # photometric term predicts each source pixel lands in the target image.
    sample_plane: jnp.ndarray | None = None
    # Keypoint features of this frame by ``asift`` (:func:`frame_features`): computed at the
    # first registration the frame takes part in, reused by the others.
    features: dict = field(default_factory=dict, repr=False, compare=False)


def _arrays(p, c, n, m) -> CloudArrays:
    return CloudArrays(jnp.asarray(p), jnp.asarray(c), jnp.asarray(n), jnp.asarray(m))


def make_frame(
    rgb,
    depth,
    K,
    voxel: float = 0.003,
    size: int = 1536,
    seed: int = 0,
    label: str = "",
    sample_size: int = 4096,
    plane_footprint: float | None = None,
    plane_var: bool = False,
) -> Frame:
    """Build a :class:`Frame` (raises :class:`jaxcr.errors.InputError` for an all-invalid
    depth image). ``size``: padded voxel cloud; ``sample_size``: padded random sample of
    the full-resolution pixels (the projective ICP source); ``plane_footprint`` (m): the
    denoised positions' plane fit spans this much of the surface at every depth
    (:func:`jaxcr.registration.clouds.plane_points_scaled`), None: a fixed 7-pixel window;
    ``plane_var``: the organised view's plane-fit residual variance too
    (:func:`jaxcr.registration.projective.depth_image`)."""
    P, C, N, ok = organised_cloud(rgb, depth, K, frame=label or None)
    full = Cloud(P[ok], C[ok], N[ok])
    down = voxel_downsample(full, voxel)
    rng = np.random.default_rng(seed)
    arrays = _arrays(*pad_cloud(down, size, rng))
    rng_sample = copy.deepcopy(rng)  # the same draw for the denoised positions
    sample = _arrays(*pad_cloud(full, sample_size, rng))
    if plane_footprint is None:
        Pd = plane_points(P, N, ok)
    else:
        focal = float(np.sqrt(abs(K[0][0] * K[1][1])))
        Pd = plane_points_scaled(P, N, ok, focal, plane_footprint)
    plane = pad_cloud(Cloud(Pd[ok], C[ok], N[ok]), sample_size, rng_sample)[0]
    image = depth_image(P, C, N, ok, K, plane_var=plane_var)
    return Frame(
        np.asarray(rgb), np.asarray(depth), full, arrays, label, image, sample, jnp.asarray(plane)
    )


def median_depth(frame: Frame) -> float:
    """Median depth (m) of the frame's valid pixels (its distance from the scene)."""
    d = np.asarray(frame.depth)
    d = d[np.isfinite(d) & (d > 0)]
    return float(np.median(d)) if len(d) else float("nan")


def frame_features(
    frame: Frame, *, asift: bool = False, crop_margin: int | None = None
) -> FrameFeatures:
    """The frame's SIFT keypoints, descriptors and smoothed depth
    (:func:`jaxcr.registration.keypoints.frame_features`), computed once per frame and
    ``asift`` setting and kept in ``frame.features``.

    Each capture of a run is the target of one forward registration and the source of the
    next, and the loop closure and the pose graph's extra edges register it again: without
    the cache its SIFT ran once per registration (44 % of a pair's time,
    experiments/results/registration/bench_pairwise_profile_r3.md). The entry remembers the
    ``rgb`` and ``depth`` arrays it was computed from and is recomputed if either attribute
    is replaced by another array (arrays are not expected to be modified in place).
    ``crop_margin``: :func:`jaxcr.registration.keypoints.detect` (part of the cache key)."""
    key = bool(asift) if crop_margin is None else (bool(asift), int(crop_margin))
    entry = frame.features.get(key)
    if entry is None or entry[0] is not frame.rgb or entry[1] is not frame.depth:
        feats = keypoints.frame_features(
            frame.rgb, frame.depth, asift=asift, crop_margin=crop_margin
        )
        entry = (frame.rgb, frame.depth, feats)
        frame.features[key] = entry
    return entry[2]


def keypoint_scale(ka, kb, T, upper: float) -> float:
    """Robust scale (m) of keypoint residuals across the target viewing rays, the residual
    the ICP keypoint term uses: ``T ka - kb`` with its component along ``kb`` removed. The
    2-D residuals of isotropic Gaussian noise sigma have a Rayleigh-distributed norm with
    median 1.1774 sigma; the weight width is 3 sigma (inliers keep their weight, gross
    matches within the RANSAC threshold are down-weighted), capped at ``upper``."""
    if len(ka) == 0:
        return float(upper)
    r = ka @ T[:3, :3].T + T[:3, 3] - kb
    ray = kb / np.maximum(np.linalg.norm(kb, axis=1, keepdims=True), 1e-12)
    perp = r - np.sum(r * ray, 1, keepdims=True) * ray
    sigma = float(np.median(np.linalg.norm(perp, axis=1))) / 1.1774
    return float(np.clip(3.0 * sigma, 1e-4, upper))


def _keypoint_arrays(ka, kb, T_kp, size: int = 256, upper: float = 0.005) -> Keypoints:
    """RANSAC inliers padded to ``size`` (no keypoints when RANSAC failed) with their robust
    residual scale (:func:`keypoint_scale`, at most ``upper``)."""
    s = np.zeros((size, 3), np.float32)
    t = np.zeros((size, 3), np.float32)
    m = np.zeros(size, bool)
    scale = upper
    if T_kp is not None:
        idx = np.flatnonzero(inlier_set(ka, kb, T_kp))[:size]
        s[: len(idx)], t[: len(idx)] = ka[idx], kb[idx]
        m[: len(idx)] = True
        scale = keypoint_scale(ka[idx], kb[idx], T_kp, upper)
    return Keypoints(jnp.asarray(s), jnp.asarray(t), jnp.asarray(m), jnp.float32(scale))


def geometric_sample(frame: Frame, points: str = "plane") -> CloudArrays:
    """The projective-ICP source sample of ``frame`` with the positions the point-to-plane
    term uses: ``"raw"``, the measured back-projections (``Frame.sample``), or ``"plane"``,
    the same pixels at their denoised positions (``Frame.sample_plane``: moved along their
    own viewing rays onto the local plane fit, :func:`jaxcr.registration.clouds.plane_points`;
    colours, normals and mask unchanged; raw when the frame has none).

    Why denoised (measured, mechanism not isolated): with raw points the geometric term
    is biased by the depth noise itself. Task 1 seed 3, ring views re-rendered at their true
    poses, 6 noise draws of one view, ICP from the true pose without keypoints or colour:
    edge 4->6 mean error 3.3 mm (along z) with raw points, 0.12 mm denoised; the first
    view's edges (that view 0.6 m from the object, 4.4k object pixels; the others 0.2-0.33 m,
    12-30k) 1.4 / 1.9 mm sideways raw against 0.19 / 0.03 mm without depth noise. A likely
    cause: the association, the radius gate and the robust weights are non-linear in each
    point's own noise near face boundaries (silhouettes, creases); associating with the
    denoised positions but keeping the raw residual removed only part of it. The plane
    fit's own error (a window straddling a crease, a curved surface) is the price: it grows
    with the window's footprint, i.e. with depth and with the object's size in pixels (the
    first view's edges ~1 mm along the viewing axis; a noise-free 2.5k-pixel box corner
    0.86 mm against 0.12 mm raw, tests/registration/test_registration_pairwise.py). The residuals of
    denoised points are correlated over the window: the ICP information then overstates
    the precision (the pose graph's calibrated weights rescale it)."""
    if points not in ("plane", "raw"):
        raise ValueError(f"points must be 'plane' or 'raw', got {points!r}")
    s = frame.sample
    if points == "raw" or frame.sample_plane is None or s is None:
        return s
    return CloudArrays(
        jnp.asarray(frame.sample_plane, s.points.dtype), s.colours, s.normals, s.mask
    )


@dataclass
class PairResult:
    T: np.ndarray  # target <- source (camera frames)
    n_matches: int
    n_inliers: int
    seeded_by_keypoints: bool
    fitness: float
    rmse: float
    seconds: float
    # Information (6, 6) of T on its left perturbation in the target frame, order (v, w)
    # (projective association; :func:`projective_information`), None when not computed.
    information: np.ndarray | None = None

    def reversed(self) -> PairResult:
        """The same registration read the other way (``T^-1``, source <- target), its
        information carried to the source frame
        (:func:`jaxcr.registration.pose_graph.inverted_edge`)."""
        T, info = np.linalg.inv(self.T), None
        if self.information is not None:
            T, info = inverted_edge(self.T, self.information)
        return PairResult(
            T,
            self.n_matches,
            self.n_inliers,
            self.seeded_by_keypoints,
            self.fitness,
            self.rmse,
            self.seconds,
            info,
        )


def register_pair(
    src: Frame,
    tgt: Frame,
    K: np.ndarray,
    *,
    prior: np.ndarray | None = None,
    cfg: IcpConfig = DEFAULT_ICP,
    asift: bool = False,
    min_fitness: float = 0.2,
    seed: int = 0,
    association: str = "projective",
    photometric: bool | str = False,
    prior_gate: tuple[float, float] | None = None,
    geometric_points: str = "raw",
    scale_match: bool = False,
    keypoint_crop: int | None = None,
    information: str = "hessian",
    information_tile: int = 8,
) -> PairResult:
    """Register two RGB-D frames: ``T`` with ``tgt ~ T src`` (``jcr.registration.register_pair``;
    paper Sec. IV.A, see the module docstring).

    Keypoints matched between the colour images seed RANSAC + Kabsch on their 3-D
    positions; weighted ICP then refines from that estimate (or from ``prior`` when there are
    too few keypoint inliers, e.g. a textureless scene).

    Parameters
    ----------
    src, tgt : Frame
        The two captures (:func:`make_frame`: RGB (H, W, 3), depth (H, W) in metres, camera
        frame, and their padded clouds).
    K : (3, 3) array
        Camera intrinsics (pixels), the same for both frames.
    prior : (4, 4) array, optional
        Initial guess of ``T`` (target <- source, metres), e.g. from the arm's kinematics;
        identity when None. The ICP starts here when the keypoints do not give an estimate.
    cfg : IcpConfig, optional
        ICP settings (iterations, distance gates and robust scales in metres); the default
        ``DEFAULT_ICP`` is degeneracy-aware (a dense colour term acts only in the directions
        the geometry cannot observe).
    asift : bool, optional
        Affine-SIFT keypoints (more matches under strong viewpoint change, slower).
    min_fitness : float, optional
        Smallest accepted ICP overlap (fraction of source points with a target match); below
        it :class:`RegistrationFailed` is raised rather than a garbage pose returned.
    seed : int, optional
        Seed of RANSAC's sampling (results are deterministic for a seed).
    association : {"projective", "nearest"}, optional
        ICP data association: projection into the target depth image (default; a random
        sample of ``Frame.sample`` source pixels at full resolution) or brute-force
        joint-space nearest neighbours on the voxel clouds.
    photometric : {False, "chromaticity", "intensity"}, optional
        Dense colour term (projective association only; True means ``"intensity"``),
        :func:`jaxcr.registration.projective.photometric_terms`.
    prior_gate : (float, float), optional
        (degrees, metres): a keypoint estimate farther than this from ``prior`` is taken for
        a false RANSAC consensus and dropped (ICP then starts from the prior without the
        keypoint term).
    geometric_points : {"raw", "plane"}, optional
        Source positions of the point-to-plane term (projective association only): the
        measured back-projections (``"raw"``, default) or the denoised
        ``Frame.sample_plane`` (:func:`jaxcr.registration.clouds.plane_points`); see
        :func:`geometric_sample`.
    scale_match : bool, optional
        With ``photometric``: blur the nearer view's colour image so that both views' texture
        is blurred alike on the surface (:func:`jaxcr.registration.projective.
        scale_matching_blur` from the views' median depths, :func:`median_depth`), so a
        far view's coarser pixels are not read as motion by the colour term.
    keypoint_crop : int, optional
        SIFT on each frame's valid-depth bounding box grown by this many pixels
        (:func:`jaxcr.registration.keypoints.detect` ``crop_margin``); None: the whole image.
    information : {"hessian", "sandwich"}, optional
        The returned ``information`` (projective association): the normal matrix over the
        residual variance (:func:`jaxcr.registration.projective.projective_information`,
        default) or the cluster-robust sandwich estimate from the residuals' scatter over
        ``information_tile`` x ``information_tile``-pixel tiles
        (:func:`jaxcr.registration.covariance.projective_sandwich_information`).
    information_tile : int, optional
        The sandwich's cluster size in pixels (default 8; 1: each residual its own cluster,
        the heteroscedasticity-robust form the pipeline uses, decision R3).

    Returns
    -------
    PairResult
        ``T`` (4, 4) target <- source (camera frames, metres), ``n_matches`` keypoint
        matches, ``n_inliers`` RANSAC inliers, ``seeded_by_keypoints``, ``fitness`` (ICP
        overlap), ``rmse`` (m), ``seconds``, and ``information`` (6, 6) of ``T``
        (projective association) for the pose graph.

    Raises
    ------
    RegistrationFailed
        An empty cloud, or a final overlap below ``min_fitness`` (the frames do not overlap).
    ValueError
        An unknown ``association``, ``photometric`` or ``geometric_points``.

    Examples
    --------
    Two 64 x 48 views of a pyramid-shaped surface (depth in metres, NaN = no depth), the
    source camera moved 3 mm along x:

    >>> import numpy as np
    >>> import jaxcr as jcr
    >>> from jaxcr.registration.pairwise import make_frame
    >>> K = np.array([[60.0, 0, 31.5], [0, 60.0, 23.5], [0, 0, 1]])
    >>> def pyramid(cx):  # depth of z = 0.3 + 0.5 |X| + 0.5 |Y| seen from (cx, 0, 0)
    ...     v, u = np.mgrid[0:48, 0:64]
    ...     x, y = (u - 31.5) / 60, (v - 23.5) / 60
    ...     t = [(0.3 + 0.5 * a * cx) / (1 - 0.5 * a * x - 0.5 * b * y)
    ...          for a in (-1, 1) for b in (-1, 1)]
    ...     return np.max(t, axis=0).astype(np.float32)
    >>> grey = np.full((48, 64, 3), 0.5, np.float32)
    >>> src = make_frame(grey, pyramid(0.003), K, size=512, sample_size=512)
    >>> tgt = make_frame(grey, pyramid(0.0), K, size=512, sample_size=512)
    >>> src.cloud.points.shape[1], int(src.arrays.mask.sum()) <= 512
    (3, True)

    Options are checked before any work:

    >>> try:
    ...     jcr.registration.register_pair(src, tgt, K, association="kdtree")
    ... except ValueError as err:
    ...     print(err)
    association must be 'projective' or 'nearest', got 'kdtree'

    The registration itself compiles the ICP (20-30 s on a loaded 2-core machine), so it is
    not run as a doctest; tests/registration/test_registration_pairwise.py recovers known
    poses this way:

    >>> result = jcr.registration.register_pair(src, tgt, K, prior=np.eye(4))  # doctest: +SKIP
    >>> result.T.shape, result.seeded_by_keypoints  # doctest: +SKIP
    ((4, 4), False)
    """
    if geometric_points not in ("plane", "raw"):
        raise ValueError(f"geometric_points must be 'plane' or 'raw', got {geometric_points!r}")
    if association not in ("projective", "nearest"):
        raise ValueError(f"association must be 'projective' or 'nearest', got {association!r}")
    if information not in ("hessian", "sandwich"):
        raise ValueError(f"information must be 'hessian' or 'sandwich', got {information!r}")
    if photometric is True:
        photometric = "intensity"
    if photometric not in (False, None, "intensity", "chromaticity"):
        raise ValueError(
            f"photometric must be False, 'intensity' or 'chromaticity', got {photometric!r}"
        )
    t0 = time.perf_counter()
    for f in (src, tgt):
        if not bool(np.asarray(f.arrays.mask).any()):
            raise RegistrationFailed(f"frame {f.label or '?'} has an empty point cloud")
    fa, fb = (frame_features(f, asift=asift, crop_margin=keypoint_crop) for f in (src, tgt))
    ka, kb = matched_features(fa, fb, K)
    T_kp, n_in = estimate_transform(ka, kb, seed=seed) if len(ka) else (None, 0)
    if T_kp is not None and prior is not None and prior_gate is not None:
        r_err, t_err = pose_error(T_kp, prior)
        if r_err > prior_gate[0] or t_err > prior_gate[1]:
            T_kp = None
    T0 = T_kp if T_kp is not None else (np.eye(4) if prior is None else prior)
    kp = _keypoint_arrays(ka, kb, T_kp, upper=cfg.sigma_keypoint)
    T0 = jnp.asarray(T0, jnp.float32)
    src_image, tgt_image = src.image, tgt.image
    if photometric and scale_match:
        e_src, e_tgt = scale_matching_blur(median_depth(src), median_depth(tgt))
        src_image, tgt_image = blurred_image(src_image, e_src), blurred_image(tgt_image, e_tgt)
    # data association and photometric options shared by the ICP and its information
    proj_kw = dict(
        window=0,
        src_image=src_image if photometric else None,
        photometric=photometric or "intensity",
        photo_points=src.sample_plane if photometric else None,
    )
    src_sample = geometric_sample(src, geometric_points)
    if association == "projective":
        res = projective_icp_jit(src_sample, tgt_image, T0, cfg, kp, **proj_kw)
    else:
        res = icp_jit(src.arrays, tgt.arrays, T0, cfg, kp)
    T = np.asarray(res.T, np.float64)
    fitness = float(res.fitness)
    info = None
    if association == "projective" and np.all(np.isfinite(T)):
        if information == "sandwich":
            info, _ = projective_sandwich_information_jit(
                res.T, src_sample, tgt_image, cfg, kp, tile=int(information_tile), **proj_kw
            )
        else:
            info, _ = projective_information_jit(res.T, src_sample, tgt_image, cfg, kp, **proj_kw)
        info = np.asarray(info, np.float64)
    if not np.all(np.isfinite(T)) or fitness < min_fitness:
        raise RegistrationFailed(
            f"no overlap between frames {src.label or '?'} and {tgt.label or '?'} "
            f"(ICP fitness {fitness:.2f} < {min_fitness}; {len(ka)} keypoint matches, "
            f"{n_in} RANSAC inliers)"
        )
    return PairResult(
        T,
        len(ka),
        n_in,
        T_kp is not None,
        fitness,
        float(res.rmse),
        time.perf_counter() - t0,
        info,
    )


def merge_models(
    model_a: Cloud,
    model_b: Cloud,
    T_init: np.ndarray,
    size: int = 2048,
    voxel: float = 0.003,
    seed: int = 0,
    min_fitness: float = 0.2,
) -> tuple[np.ndarray, float]:
    """Register partial model A to partial model B by ICP from ``T_init`` (paper Sec. IV.C:
    the change of the robot's initial pose between routes); returns (T_B<-A, fitness)."""
    rng = np.random.default_rng(seed)
    arrs = []
    for m in (model_a, model_b):
        if len(m) == 0:
            raise RegistrationFailed("cannot merge an empty partial model")
        p, c, n, k = pad_cloud(voxel_downsample(m, voxel), size, rng)
        arrs.append(CloudArrays(jnp.asarray(p), jnp.asarray(c), jnp.asarray(n), jnp.asarray(k)))
    cfg = IcpConfig(iterations=40, max_dist=0.03, min_dist=0.005)
    res = icp_jit(arrs[0], arrs[1], jnp.asarray(T_init, jnp.float32), cfg)
    if float(res.fitness) < min_fitness:
        raise RegistrationFailed(
            f"partial models do not overlap (fitness {float(res.fitness):.2f})"
        )
    return np.asarray(res.T, np.float64), float(res.fitness)
