"""Progressive object modelling, end to end (paper Fig. 3): sense, plan (Algorithm 1), move,
capture, register forward, close the loop, optimise globally (Algorithm 2), merge.

The sensor is any object with the :class:`jaxcr.synth.rgbd_tasks.RgbdSimulator` interface
(``K``, ``capture(T_world_cam)``, ``sense_obstacles(T_world_cam)``, ``true_mount()``,
``cfg``). The estimator only uses the images, the sensed obstacle points and the *nominal*
arm kinematics; the true poses (curvature scale and mount error applied) are recorded for
evaluation only.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field

import numpy as np

from jaxcr.registration.arm import ArmSpec, look_at_angles, tip_camera_pose
from jaxcr.registration.clouds import Cloud, voxel_downsample
from jaxcr.registration.clustering import ClusterMap
from jaxcr.registration.global_opt import GlobalResult, global_optimize
from jaxcr.registration.icp import DEFAULT_ICP, IcpConfig
from jaxcr.registration.metrics import pose_error
from jaxcr.registration.pairwise import (
    Frame,
    PairResult,
    RegistrationFailed,
    make_frame,
    median_depth,
    merge_models,
    register_pair,
)
from jaxcr.registration.planning import ArcPlanner, PlannerConfig
from jaxcr.registration.pose_graph import (
    GraphEdge,
    PoseGraphResult,
    optimize_pose_graph,
    point_information,
)


@dataclass
class Capture:
    run: str
    index: int
    frame: Frame
    T_nominal: np.ndarray  # world <- camera, nominal kinematics
    T_true: np.ndarray  # world <- camera, real arm (evaluation only)
    centreline: np.ndarray  # nominal arm centreline, world (N, 3)


@dataclass
class RunLog:
    name: str
    direction: int
    delta_s: float
    status: str = ""
    planning_time: float = 0.0
    planning_step_times: list[float] = field(default_factory=list)  # s, one per planner step
    events: list[str] = field(default_factory=list)
    arcs: list = field(default_factory=list)
    captures: list[Capture] = field(default_factory=list)
    pairs: list[PairResult] = field(default_factory=list)
    obstacles: np.ndarray | None = None
    closed_loop: bool = False
    ring_start: int = 0


@dataclass
class ModelResult:
    runs: list[RunLog]
    ring: list[tuple[int, int]]  # (run index, capture index) in loop order
    edges: list[PairResult]
    global_result: GlobalResult | None
    global_seconds: float
    merge: dict
    notes: list[str]
    alg2_result: GlobalResult | None = None  # Algorithm 2 (also when not the final result)
    alg2_seconds: float = 0.0
    extra: list[tuple[int, int, PairResult]] = field(default_factory=list)  # (i, j) ring pos.
    extra_seconds: float = 0.0
    pose_graph: PoseGraphResult | None = None
    # Views left out of the ring (captured before the loop's closing view), as (run, capture),
    # their pose-graph edges (i, j, pair) in node numbers (ring positions, then these views
    # from len(ring) on) and their optimised poses T_O,i (empty without a pose graph).
    outside: list[tuple[int, int]] = field(default_factory=list)
    outside_edges: list[tuple[int, int, PairResult]] = field(default_factory=list)
    outside_poses: list[np.ndarray] = field(default_factory=list)


@dataclass(frozen=True)
class PipelineConfig:
    voxel: float = 0.004
    cloud_size: int = 1024
    icp: IcpConfig = DEFAULT_ICP
    asift: bool = False
    min_fitness: float = 0.2
    loop_angle: float = np.deg2rad(300.0)
    max_steps: int = 40
    closure_gate_deg: float = 3.0
    closure_gate_m: float = 0.02
    # Drift gate of the loop closure against the chained forward registrations: the chain
    # of n registrations drifts ~sqrt(n) x the per-registration error (1 sigma, per
    # registration), so a closure more than 3 sigma sqrt(n) away from it is a slide, not
    # drift (fresh Task 1 seed 303: an ICP-alone closure 15.2 mm / 0.84 deg off the truth,
    # inside the 3 deg / 20 mm gate, while the chain of 12 drifted 1.45 mm; the global
    # optimisation spread it to 17.6 mm). 0.2 deg / 1 mm = ~2x the RMS error of the forward
    # registrations on seeds 303/304 (0.10 deg / 0.5 mm). A closure that passes the closure
    # gate but not this one is replaced by the chained estimate (:func:`check_closure`).
    closure_drift_deg: float = 0.2
    closure_drift_m: float = 0.001
    # Gate of the cross-route ring edges against the routes' chained registrations joined
    # by the nominal kinematics at their first views (:func:`route_estimates`), and of the
    # loop's consistency: ~3x the nominal drift over a whole loop (3.5 deg / 25 mm on Task
    # 1), so only gross failures (a cylinder registered half a face around) are caught.
    nominal_gate_deg: float = 10.0
    nominal_gate_m: float = 0.05
    association: str = "projective"  # ICP data association: "projective" or "nearest"
    # Full-resolution source pixels per frame (projective ICP). 8192 (was 4096): the ring
    # edges' mean error 0.129 -> ~0.11 deg on the synthetic tasks (finer sampling of the
    # sensor noise) at ~2x the ICP time, within the 0.5 s pairwise budget.
    sample_size: int = 8192
    # Dense colour term of the projective ICP, in the directions the geometry cannot observe
    # (a can's axis rotation): chromaticity, invariant to shading (None: keypoints only).
    photometric: str | None = "chromaticity"
    # Blur the nearer view's colour image so that both views' texture is blurred alike on
    # the surface before the colour term compares them (register_pair ``scale_match``;
    # :func:`jaxcr.registration.projective.scale_matching_blur`). Off: on the development
    # seeds' far/near pairs from the true pose it did not lower the error (mean 1.46 ->
    # 1.54 mm over 120 registrations, lower in 50; experiments/results/registration/
    # model_object_scale_match_edges.md).
    photometric_scale_match: bool = False
    # Global optimisation: "pose_graph" (weighted Gauss-Newton on SE(3) over the ring edges
    # plus the extra constraints below; :mod:`jaxcr.registration.pose_graph`) or "alg2"
    # (the paper's Algorithm 2 on the ring edges only). Algorithm 2 always runs (it seeds
    # and gates the extra registrations) and is reported either way.
    global_method: str = "pose_graph"
    # Extra constraints: ring views this many apart, registered and kept when consistent
    # with the Algorithm 2 poses (closure gate), plus the routes' own forward registrations
    # that are not ring edges. () = ring edges only. Gap 3 was measured too: its edges
    # (3 x the baseline) err ~2x more than gap 2's and, sharing the views' errors, made
    # the poses worse (experiments/results/registration/model_object_pose_graph.md).
    extra_gaps: tuple[int, ...] = (2,)
    # Edge weights of the pose graph: "calibrated" (each registration's information, see
    # ``edge_information``, then the covariance model scale * Omega^-1 + isotropic floor estimated from the
    # graph's own cycles by variance components / REML and the graph solved again:
    # :func:`jaxcr.registration.pose_graph.calibrate_edges`), "information" (that
    # information as stated; the ICP information of
    # :func:`jaxcr.registration.projective.projective_information` was optimistic ~5x in
    # scale and far too anisotropic, e^T Omega e medians ~100 against truth) or "points" (every edge the same point information, Algorithm 2's objective).
    edge_weights: str = "calibrated"
    # Source positions of the registrations' point-to-plane term
    # (:func:`jaxcr.registration.pairwise.geometric_sample`): "plane" (denoised) or "raw".
    # Raw points carry a depth-noise-induced bias, largest for the first view (0.6 m from
    # the object on Task 1): worst pose after the pose graph over Task 1/2 seeds 0-4
    # 2.24 -> 1.39 mm, mean of the ten worst 1.35 -> 0.88 mm (8 of 10 lower).
    geometric_points: str = "plane"
    # Footprint (m) of the plane fit behind "plane" (:func:`jaxcr.registration.clouds.
    # plane_points_scaled`: a per-pixel window of this size on the surface, 3-7 px); None:
    # a fixed 7-pixel window, whose footprint grows with depth.
    plane_footprint: float | None = None
    # Views left out of the ring (Task 1: those before the loop's closing view) join the pose
    # graph as nodes with their forward registrations and registrations to this many ring
    # views (the nearest by nominal viewing direction), instead of being chained from the
    # nearest ring view through one forward registration (fresh Task 1 seeds 310/313/314:
    # the chained first views erred 2.1-4.8 mm, every ring view <= 1.3 mm). 0 = chain them.
    outside_links: int = 4
    # Registrations of those views whose source is this much farther from the scene (median
    # depth ratio) than the target use the raw source points: the plane fit behind "plane"
    # has a fixed pixel window, so its footprint and model error grow with depth (fresh Task
    # 1 seeds 310/314, view 0 at 0.59-0.60 m to ring views at 0.25-0.47 m: view 0's pose
    # 2.4-5.4 mm off with denoised points in all 7 registrations, 0.8-2.8 mm raw; the raw
    # bias the denoising removes is that of views at similar depths). The run's forward
    # registration of such a pair is registered again this way.
    far_source_ratio: float = 1.15
    # The same rule for every other pose-graph edge (ring edges, including the loop closure and
    # the routes' seams, the routes' forward registrations, the extra gap edges): the loop
    # seam's view is the first capture, the farthest from the object (Task 1 0.59 m against
    # 0.22-0.36 m; dev Task 1 seed 6: its forward registration 0 -> 1 2.51 mm off with
    # denoised points, all its edges share that bias so no edge weighting can remove it).
    # False: only the outside-ring edges (the behaviour before 2026-12-02).
    far_source_all_edges: bool = True
    # How such an edge enters the graph: "replace" (the raw registration only) or "both"
    # (the denoised and the raw registration, each with half its information: the two
    # estimates come from the same images, and their biases, of either sign, partly cancel).
    far_source_mode: str = "both"
    # The same for the edges of the views left out of the ring (:func:`outside_view_edges`:
    # their forward registrations and their links to ring views): "both" (the denoised and
    # the raw registration of a far source, half information each, as ``far_source_mode``)
    # or "raw" (the raw one only, the behaviour before 2026-12-03). Dev Task 1 seeds 0-9,
    # the 21 registrations of a first capture (0.59 m) to nearer views, from their pipeline
    # estimates: error against the truth mean / RMS / max 1.28 / 1.43 / 2.63 mm raw, 0.98 /
    # 1.22 / 2.96 denoised, 0.86 / 0.98 / 2.00 for the mean of the two
    # (experiments/results/registration/model_object_outside_both.md).
    outside_far_mode: str = "both"
    # Cauchy-reweighted pose-graph solves after the calibrated one
    # (:func:`jaxcr.registration.pose_graph.optimize_pose_graph` ``robust_rounds``).
    robust_rounds: int = 0
    # SIFT on each frame's valid-depth bounding box grown by this many pixels
    # (:func:`jaxcr.registration.keypoints.detect` ``crop_margin``); None: the whole image
    # (before 2026-12-02). Issue 18: SIFT of the new frame was ~37 % of a pair's time
    # (bench_pairwise_profile_r5.md) while the object covers ~20-36 % of the 320x240 view.
    # Dev seeds 0-4, Tasks 1+2, 40 forward pairs (speed_r5.md): CPU ms/pair -17..-32 %, pose
    # error per pair within 0.010 deg / 0.049 mm of the whole-image SIFT's (another random
    # draw of the ICP's source pixels moves it by up to 0.12 deg / 0.53 mm); object
    # modelling, dev Task 1 seeds 0-4, worst pose 1.99 -> 1.91 mm
    # (model_object_dev_t1_crop16_reg25.md). 32 px measured too: less of the saving.
    keypoint_crop: int | None = 16
    # Errors-in-variables weight of the registrations' point-to-plane pairs
    # (``IcpConfig.noise_weight``: "none", "sensor" or "sensor+fit"). The source positions'
    # noise factor follows ``geometric_points`` (raw 1, denoised 0.2).
    noise_weight: str = "none"
    # The sensor's depth noise model (sigma0, sigma2, z0) (m, 1/m, m) of that weight:
    # sigma_z(z) = sigma0 + sigma2 (z - z0)^2; None: ``icp``'s (Nguyen et al. 2012, Kinect).
    # :func:`build_model` takes the one the scene declares (:meth:`with_sensor`).
    depth_noise: tuple[float, float, float] | None = None
    # Information of each registration, the pose graph's edge weight before calibration
    # (register_pair ``information``): "sandwich" (the covariance from the residuals' own
    # scatter, H^-1 (sum s s^T) H^-1 over clusters of ``information_tile`` x
    # ``information_tile`` source pixels: :func:`jaxcr.registration.covariance.
    # projective_sandwich_information`) or "hessian" (the ICP normal matrix over the mean
    # squared residual: independent residuals of one variance; the default before
    # 2026-12-04). Decision R3, development seeds 0-9 (model_object_r3_dev.md): per-residual
    # sandwich against "hessian", Task 1 run worst mean 1.14 -> 1.06 mm (lower in 9 of 10),
    # max 1.73 -> 1.69; Task 2 mean 0.77 -> 0.75, max 0.99 -> 0.98. With 8 x 8-pixel tiles
    # it was worse (Task 1 mean 1.31, Task 2 0.85).
    edge_information: str = "sandwich"
    # Tile (pixels) of the "sandwich" clusters; 1 (default): every residual its own cluster
    # (heteroscedasticity-robust).
    information_tile: int = 1

    def with_sensor(self, depth_noise: dict | None) -> PipelineConfig:
        """This configuration with the depth-noise model of a scene's ``depth_noise``
        declaration (keys ``sigma0``, ``sigma2``, ``z0``; missing keys keep the defaults);
        None or empty: as is."""
        if not depth_noise:
            return self
        icp = self.icp
        model = (
            float(depth_noise.get("sigma0", icp.depth_sigma0)),
            float(depth_noise.get("sigma2", icp.depth_sigma2)),
            float(depth_noise.get("z0", icp.depth_z0)),
        )
        return dataclasses.replace(self, depth_noise=model)

    def icp_config(self) -> IcpConfig:
        """The ICP settings of this configuration's registrations: ``icp``, with
        ``noise_weight`` on it the depth-noise model and the source noise factor of
        ``geometric_points`` (off: ``icp`` itself, so the programs compiled stay the same)."""
        if self.noise_weight == "none":
            return self.icp
        kw = {}
        if self.depth_noise is not None:
            names = ("depth_sigma0", "depth_sigma2", "depth_z0")
            kw = dict(zip(names, self.depth_noise, strict=True))
        return dataclasses.replace(
            self.icp,
            noise_weight=self.noise_weight,
            source_noise_factor=1.0 if self.geometric_points == "raw" else 0.2,
            **kw,
        )

    def register(self, src, tgt, K, prior, seed: int, prior_gate=None) -> PairResult:
        """:func:`register_pair` with this configuration's ICP, keypoint and colour options."""
        return register_pair(
            src,
            tgt,
            K,
            prior=prior,
            prior_gate=prior_gate,
            cfg=self.icp_config(),
            asift=self.asift,
            min_fitness=self.min_fitness,
            association=self.association,
            photometric=self.photometric or False,
            seed=seed,
            geometric_points=self.geometric_points,
            scale_match=self.photometric_scale_match,
            keypoint_crop=self.keypoint_crop,
            information=self.edge_information,
            information_tile=self.information_tile,
        )


def _winding(T: np.ndarray, centre: np.ndarray) -> float:
    return float(np.arctan2(T[1, 3] - centre[1], T[0, 3] - centre[0]))


def capture_frame(rgb, depth, K, cfg: PipelineConfig, seed: int, label: str):
    """One RGB-D capture as the pipeline registers it (:func:`make_frame` with ``cfg``'s voxel,
    cloud and sample sizes)."""
    return make_frame(
        rgb,
        depth,
        K,
        cfg.voxel,
        cfg.cloud_size,
        seed,
        label=label,
        sample_size=cfg.sample_size,
        plane_footprint=cfg.plane_footprint,
        plane_var=cfg.noise_weight == "sensor+fit",
    )


def run_arm_spec(sim, run: dict) -> ArmSpec:
    """The arm of one winding run: the scene's ``arm`` settings on the run's ``base``."""
    a = sim.cfg["arm"]
    return ArmSpec(
        int(a["n_sections"]),
        float(a["max_length"]),
        float(a["radius"]),
        float(a["height"]),
        tuple(run["base"]),
        float(a.get("max_kappa", 12.0)),
    )


def run_direction(sim, run: dict, cfg: PipelineConfig, progress=None, seed: int = 0) -> RunLog:
    """One winding run: Algorithm 1 with forward pairwise registration after every move."""
    scfg = sim.cfg
    spec = run_arm_spec(sim, run)
    model = spec.model()
    pcfg = PlannerConfig(
        direction=int(run["direction"]),
        delta_s=float(run["delta_s"]),
        view_radius=float(scfg["view_radius"]),
    )
    planner = ArcPlanner(spec, pcfg)
    log = RunLog(str(run["name"]), pcfg.direction, pcfg.delta_s)
    clusters = ClusterMap()
    object_pts: list[np.ndarray] = []
    kscale = float(scfg["truth"]["kappa_scale"])
    mount = sim.true_mount()
    aim_z = float(scfg.get("tilt_target_z", 0.0))
    # The target is marked in the first view: the camera initially faces it (the scene's
    # workspace centre is the operator's hint).
    centre = np.zeros(3)
    centre[2] = aim_z
    K = sim.K
    wound = 0.0
    last_w = None
    for step in range(cfg.max_steps):
        kap, lens = (
            planner.sections()
            if planner.state.arcs
            else (np.zeros(spec.n_sections), np.full(spec.n_sections, 1e-4))
        )
        T_tip, _ = tip_camera_pose(spec, kap, lens, 0.0, 0.0, model=model)
        T_tip = T_tip @ np.diag(
            [-1.0, -1.0, 1.0, 1.0]
        )  # back to the tip frame (camera_from_tip(0, 0) = Rz(pi))
        pan, tilt = look_at_angles(T_tip, centre)
        T_nom, line = tip_camera_pose(spec, kap, lens, pan, tilt, model=model)
        T_true, _ = tip_camera_pose(spec, kap * kscale, lens, pan, tilt, mount=mount, model=model)
        rgb, depth = sim.capture(T_true)
        frame = capture_frame(rgb, depth, K, cfg, seed + step, f"{log.name}:{step}")
        cap = Capture(log.name, step, frame, T_nom, T_true, line)
        if log.captures:
            prev = log.captures[-1]
            prior = np.linalg.inv(T_nom) @ prev.T_nominal
            log.pairs.append(cfg.register(prev.frame, frame, K, prior, seed + step))
        log.captures.append(cap)
        if progress is not None:
            progress(log, cap)
        pts_w = frame.cloud.points[::7] @ T_nom[:3, :3].T + T_nom[:3, 3]
        object_pts.append(pts_w)
        allp = np.concatenate(object_pts)
        centre = (
            np.array([*np.median(allp[:, :2], axis=0), aim_z]) if len(object_pts) > 2 else centre
        )
        w = _winding(T_nom, centre[:2])
        if last_w is not None:
            wound += pcfg.direction * np.angle(np.exp(1j * (w - last_w)))
        last_w = w
        # Loop closure: the last cloud overlaps the first one.
        if wound >= cfg.loop_angle and len(log.captures) >= 4:
            # Close on the earliest view that registers *consistently*: a closure whose
            # transform disagrees with the (roughly known) kinematics by more than the gate
            # is a false match, and Algorithm 2 would spread its error over the whole loop.
            # A closure with RANSAC keypoint consensus is preferred to one found by ICP alone
            # from the nominal seed: across the closure's wide baseline ICP can settle in a
            # wrong minimum that still passes the gate (Task 1 seed 2: 1.5 deg / 18 mm off,
            # fitness 0.29, when view 2 closed with 9 keypoint inliers at 0.2 deg / 1 mm).
            fallback = None
            drifted = None  # passes the closure gate but not the drift gate
            for k0 in range(min(6, len(log.captures) - 3)):
                first = log.captures[k0]
                prior = np.linalg.inv(first.T_nominal) @ T_nom
                try:
                    closure = cfg.register(frame, first.frame, K, prior, seed)
                except RegistrationFailed:
                    continue
                # Gate against the chained forward registrations (their drift is small; the
                # nominal kinematics drift more over a long arm: curvature errors add up).
                P = chain(log.pairs)
                chained = np.linalg.inv(P[k0]) @ P[-1]
                verdict, r_err, t_err, gate = check_closure(
                    closure.T, chained, len(log.pairs) - k0, cfg
                )
                if verdict == "reject":
                    log.events.append(
                        f"closure to view {k0} rejected ({r_err:.1f} deg, {1000 * t_err:.0f} mm "
                        "from the chained registrations)"
                    )
                    continue
                if verdict == "drift":
                    log.events.append(
                        f"closure to view {k0} inconsistent with the chain ({r_err:.2f} deg, "
                        f"{1000 * t_err:.1f} mm from the chained registrations, drift gate "
                        f"{gate[0]:.2f} deg / {1000 * gate[1]:.1f} mm)"
                    )
                    if drifted is None:
                        drifted = (k0, chained_closure(closure, chained))
                    continue
                if not closure.seeded_by_keypoints:
                    if fallback is None:
                        fallback = (k0, closure)
                    continue
                fallback = (k0, closure)
                break
            if fallback is None and drifted is not None:
                fallback = drifted
                log.events.append(
                    f"closure to view {drifted[0]}: the chained estimate is used (no closure "
                    "within the drift gate)"
                )
            if fallback is not None:
                k0, closure = fallback
                if not closure.seeded_by_keypoints and closure.n_matches > 0:
                    log.events.append(
                        f"closure to view {k0} by ICP alone (no keypoint consensus on any view)"
                    )
                log.pairs.append(closure)
                log.ring_start = k0
                log.closed_loop = True
                log.status = "loop closed"
                break
        # Sense the space ahead: the camera turns to the arm's heading.
        sense_T, _ = tip_camera_pose(spec, kap, lens, 0.0, 0.0, model=model)
        clusters.add(sim.sense_obstacles(sense_T))
        cloud = np.concatenate([clusters.points(), allp]) if len(clusters.points()) else allp
        status = planner.step(cloud, centre[:2])
        if status != "moving":
            log.status = status
            break
    else:
        log.status = "step limit"
    log.planning_time = planner.state.planning_time
    log.planning_step_times = list(planner.state.step_times)
    log.events = list(planner.state.events) + log.events
    log.arcs = list(planner.state.arcs)
    log.obstacles = clusters.points()
    return log


def check_closure(
    T_closure: np.ndarray, T_chained: np.ndarray, n_chained: int, cfg: PipelineConfig
) -> tuple[str, float, float, tuple[float, float]]:
    """Verdict on a loop-closure registration ``T_closure`` against the chained estimate
    ``T_chained`` of the same transform (``n_chained`` forward registrations): "reject"
    outside the closure gate (a false match), "drift" inside it but further from the chain
    than 3 sigma sqrt(n) of the expected drift (``cfg.closure_drift_*``; a slide the global
    optimisation would spread over the loop), else "ok". Returns (verdict, rotation error
    deg, translation error m, the drift gate (deg, m))."""
    r_err, t_err = pose_error(T_closure, T_chained)
    k = 3.0 * np.sqrt(max(int(n_chained), 1))
    gate = (
        min(cfg.closure_gate_deg, k * cfg.closure_drift_deg),
        min(cfg.closure_gate_m, k * cfg.closure_drift_m),
    )
    if r_err > cfg.closure_gate_deg or t_err > cfg.closure_gate_m:
        return "reject", r_err, t_err, gate
    if r_err > gate[0] or t_err > gate[1]:
        return "drift", r_err, t_err, gate
    return "ok", r_err, t_err, gate


def chained_closure(closure: PairResult, T_chained: np.ndarray) -> PairResult:
    """The closure replaced by the chained estimate: a nominal-weight edge (no matches, no
    information; :func:`graph_edges` gives it 1/100 of a registration's weight), so the
    ring composes to the identity and the global optimisation keeps the chain."""
    return dataclasses.replace(
        closure,
        T=np.asarray(T_chained, np.float64).copy(),
        n_matches=0,
        n_inliers=0,
        seeded_by_keypoints=False,
        rmse=float("nan"),
        information=None,
    )


def chain(pairs: list[PairResult]) -> list[np.ndarray]:
    """Poses of captures 0..n in the frame of capture 0 from forward transforms T_{i+1<-i}."""
    poses = [np.eye(4)]
    for p in pairs:
        poses.append(poses[-1] @ np.linalg.inv(p.T))
    return poses


def partial_model(captures: list[Capture], poses: list[np.ndarray], voxel: float) -> Cloud:
    parts = [c.frame.cloud.transformed(P) for c, P in zip(captures, poses, strict=False)]
    merged = Cloud(
        *(np.concatenate([getattr(p, k) for p in parts]) for k in ("points", "colours", "normals"))
    )
    return voxel_downsample(merged, voxel)


def build_model(
    sim, cfg: PipelineConfig = PipelineConfig(), progress=None, seed: int = 0
) -> ModelResult:
    """Run every winding direction of the scene, then close the loop and optimise."""
    cfg = cfg.with_sensor(sim.cfg.get("depth_noise"))
    runs = [
        run_direction(sim, r, cfg, progress, seed=seed + 100 * k)
        for k, r in enumerate(sim.cfg["runs"])
    ]
    return model_from_runs(runs, sim.K, cfg, seed=seed)


def model_from_runs(
    runs: list[RunLog], K: np.ndarray, cfg: PipelineConfig = PipelineConfig(), seed: int = 0
) -> ModelResult:
    """The second half of :func:`build_model`: the ring, its edges and the global
    optimisation from the recorded winding runs (no sensor needed; camera matrix ``K``)."""
    notes: list[str] = []
    merge: dict = {}
    if len(runs) == 1:
        log = runs[0]
        if not log.closed_loop:
            notes.append(f"run {log.name}: loop not closed ({log.status}); partial model only")
            return ModelResult(
                runs, [(0, i) for i in range(len(log.captures))], log.pairs, None, 0.0, merge, notes
            )
        k0 = log.ring_start
        ring = [(0, i) for i in range(k0, len(log.captures))]
        edges = list(log.pairs[k0:])  # forward pairs from the closing view, plus the closure
    else:
        # Several routes: merge the partial models by ICP seeded with the change of the
        # robot's initial pose, then order all views by azimuth around the object and close
        # the ring through the views of both routes.
        A, B = runs[0], runs[1]
        PA, PB = chain(A.pairs), chain(B.pairs)
        mA = partial_model(A.captures, PA, cfg.voxel)
        mB = partial_model(B.captures, PB, cfg.voxel)
        init = np.linalg.inv(B.captures[0].T_nominal) @ A.captures[0].T_nominal
        t0 = time.perf_counter()
        T_BA, fit = merge_models(mA, mB, init, seed=seed)
        merge = {"fitness": fit, "seconds": time.perf_counter() - t0, "T_B_A": T_BA.tolist()}
        # Estimated pose of every capture in B's first camera frame (for the ring order and
        # the initial estimates of the cross-route edges).
        est = {(0, i): T_BA @ P for i, P in enumerate(PA)}
        est.update({(1, i): P for i, P in enumerate(PB)})
        # The reference that gates the cross-route registrations: each route's chained
        # forward registrations, joined at the routes' first views by the nominal
        # kinematics (the arm is short there). Not the nominal kinematics at both ends:
        # their curvature errors add up along each route (fresh Task 2 seed 300: the
        # nominal relative poses of the far cross-route edges were 9.7-11.6 deg off the
        # truth, the registrations 0.02-0.07 deg, the chains <= 0.4 deg; the 10 deg gate
        # rejected right registrations, the edges took the nominal and the loop composed
        # to 35 deg / 386 mm). Not the merged estimate either: the merge of two partial
        # models of a cylinder can slide around its axis (seed 300: 1.5 deg).
        ref = route_estimates(PA, PB, init)
        nominal = {
            (r, i): c.T_nominal for r, lg in enumerate(runs) for i, c in enumerate(lg.captures)
        }
        centre = np.mean([T[:3, 3] for T in nominal.values()], axis=0)
        order = sorted(nominal, key=lambda k: _winding(nominal[k], centre))
        ring = order
        edges = []
        for j, a in enumerate(ring):
            b = ring[(j + 1) % len(ring)]
            if a[0] == b[0] and b[1] == a[1] + 1:
                edges.append(runs[a[0]].pairs[a[1]])
                continue
            if a[0] == b[0] and a[1] == b[1] + 1:
                edges.append(runs[a[0]].pairs[b[1]].reversed())
                continue
            fa, fb = _capture(runs, a).frame, _capture(runs, b).frame
            pair = cross_route_edge(
                cfg,
                fa,
                fb,
                K,
                np.linalg.inv(est[b]) @ est[a],
                np.linalg.inv(ref[b]) @ ref[a],
                seed + j,
                notes,
                f"ring edge {a}->{b}",
            )
            edges.append(pair)
    # Loop consistency: the product of the ring's registrations must be near the identity
    # (its residual is the drift Algorithm 2 spreads); a gross residual means a wrong edge,
    # and spreading it would turn every pose into garbage.
    loop = np.eye(4)
    for e in edges:
        loop = e.T @ loop
    r_err, t_err = pose_error(loop, np.eye(4))
    if r_err > cfg.nominal_gate_deg or t_err > cfg.nominal_gate_m:
        notes.append(
            f"loop inconsistent: the ring's registrations compose to {r_err:.1f} deg / "
            f"{1000 * t_err:.0f} mm (gate {cfg.nominal_gate_deg:.0f} deg / "
            f"{1000 * cfg.nominal_gate_m:.0f} mm); Algorithm 2 not run, partial models only"
        )
        return ModelResult(runs, ring, edges, None, 0.0, merge, notes)
    clouds = ring_clouds(runs, ring)
    if cfg.global_method not in ("pose_graph", "alg2"):
        raise ValueError(f"global_method must be 'pose_graph' or 'alg2', got {cfg.global_method!r}")
    t0 = time.perf_counter()
    g = global_optimize(clouds, [e.T for e in edges], seed=seed)
    t_alg2 = time.perf_counter() - t0
    result = ModelResult(runs, ring, edges, g, t_alg2, merge, notes, g, t_alg2)
    if cfg.global_method == "alg2":
        return result
    return optimize_pose_graph_stage(result, K, cfg, seed=seed)


def optimize_pose_graph_stage(
    result: ModelResult, K: np.ndarray, cfg: PipelineConfig, seed: int = 0
) -> ModelResult:
    """The pose-graph stage of :func:`model_from_runs`, after Algorithm 2
    (``result.alg2_result``): register the extra constraints (:func:`extra_edges`) and the
    views left out of the ring (:func:`outside_view_edges`), solve the weighted pose graph
    (anchor: the last ring view) and set ``result.global_result`` (ring poses, frame O =
    the last ring view), ``result.outside_poses`` and ``result.pose_graph``. Returns
    ``result``."""
    ring, g = result.ring, result.alg2_result
    t0 = time.perf_counter()
    result.extra = extra_edges(result, K, cfg, seed=seed)
    result.outside, outside_init, result.outside_edges = outside_view_edges(
        result, K, cfg, seed=seed
    )
    result.extra_seconds = time.perf_counter() - t0
    t0 = time.perf_counter()
    ring_edges = [(k, (k + 1) % len(ring), e) for k, e in enumerate(result.edges)]
    if cfg.far_source_all_edges:
        # registered with the denoised points by the run (ring edges, the routes' forward
        # registrations) or by extra_edges (gap edges): a far source is registered again
        n_ring = len(ring_edges)
        fixed = far_source_edges(result, ring_edges + result.extra, K, cfg, seed=seed)
        ring_edges, result.extra = fixed[:n_ring], fixed[n_ring:]  # "both": raw ones in extra
    graph = graph_edges(
        result,
        ring_edges + result.extra + result.outside_edges,
        _graph_weights(cfg.edge_weights),
        nodes=ring + result.outside,
    )
    pg = optimize_pose_graph(
        list(g.poses) + outside_init,
        graph,
        anchor=len(ring) - 1,
        calibrate=cfg.edge_weights == "calibrated",
        robust_rounds=cfg.robust_rounds,
    )
    result.pose_graph = pg
    # Frame O = the last ring view exactly (it is the anchor; re-anchor against float32).
    anchor = np.linalg.inv(pg.poses[len(ring) - 1])
    poses = [anchor @ P for P in pg.poses]
    result.outside_poses = poses[len(ring) :]
    result.global_result = GlobalResult(
        poses[: len(ring)], g.initial, pg.iterations, pg.step_norm < 1e-5
    )
    result.global_seconds = time.perf_counter() - t0
    return result


def cross_route_edge(
    cfg: PipelineConfig,
    fa: Frame,
    fb: Frame,
    K: np.ndarray,
    prior: np.ndarray,
    reference: np.ndarray,
    seed: int,
    notes: list[str],
    label: str,
) -> PairResult:
    """A ring edge ``T_{b <- a}`` between two routes' views: registered from ``prior`` (the
    merged-model estimate), then from ``reference`` (the chained registrations,
    :func:`route_estimates`), and kept only when it agrees with ``reference`` within
    ``cfg.nominal_gate_*``; else ``reference`` itself as a nominal-weight edge. Rejections
    are appended to ``notes`` (prefixed ``label``)."""
    nom = reference
    # Seed with the merged-model estimate, then with the chained reference (dropping
    # keypoint estimates outside the gate: a false RANSAC consensus); keep a result only if
    # it agrees with the reference within the gate (a merge of two partial models of a
    # cylinder can slide around its axis, a repeated texture can match).
    pair, why = None, ""
    gate = (cfg.nominal_gate_deg, cfg.nominal_gate_m)
    for pr, pg in ((prior, None), (nom, gate)):
        try:
            cand = cfg.register(fa, fb, K, pr, seed, prior_gate=pg)
        except RegistrationFailed as e:
            why = str(e)
            continue
        r_err, t_err = pose_error(cand.T, nom)
        if r_err <= cfg.nominal_gate_deg and t_err <= cfg.nominal_gate_m:
            pair = cand
            break
        why = (
            f"{r_err:.1f} deg / {1000 * t_err:.0f} mm from the chained registrations "
            f"(gate {cfg.nominal_gate_deg:.0f} deg / {1000 * cfg.nominal_gate_m:.0f} mm)"
        )
        notes.append(f"{label}: registration rejected ({why})")
    if pair is None:
        # No registration agrees with the reference (e.g. a wide baseline with no keypoints:
        # ICP on a cylinder slides to the largest overlap): the edge keeps the reference's
        # relative pose, and Algorithm 2 treats it like any other.
        notes.append(
            f"{label}: no consistent registration ({why}); "
            "the chained registrations are used for this edge"
        )
        pair = PairResult(nom, 0, 0, False, 0.0, float("nan"), 0.0)
    return pair


def route_estimates(
    PA: list[np.ndarray], PB: list[np.ndarray], T_B0_A0: np.ndarray
) -> dict[tuple[int, int], np.ndarray]:
    """Poses of the captures of two routes in the frame of route B's first camera, keyed
    (route, capture): each route's chained forward registrations (``PA``, ``PB``: poses in
    the frame of the route's first capture, :func:`chain`) joined by ``T_B0_A0`` (A's
    first camera -> B's, from the nominal kinematics)."""
    out = {(0, i): T_B0_A0 @ P for i, P in enumerate(PA)}
    out.update({(1, i): np.asarray(P) for i, P in enumerate(PB)})
    return out


def _graph_weights(edge_weights: str) -> str:
    """``graph_edges`` weighting of a ``PipelineConfig.edge_weights`` value ("calibrated"
    starts from the stated information)."""
    if edge_weights not in ("calibrated", "information", "points"):
        raise ValueError(
            f"edge_weights must be 'calibrated', 'information' or 'points', got {edge_weights!r}"
        )
    return "information" if edge_weights == "calibrated" else edge_weights


def graph_edges(
    result: ModelResult,
    edges: list[tuple[int, int, PairResult]],
    weights: str = "information",
    nodes: list[tuple[int, int]] | None = None,
) -> list[GraphEdge]:
    """Pose-graph constraints from registrations ``(i, j, pair)`` between ring positions
    (``pair.T = T_{j <- i}``). ``weights="information"``: each registration's ICP
    information (:func:`jaxcr.registration.projective.projective_information`); a
    registration without one (nearest association, or the nominal kinematics standing in
    for a failed edge) gets the point information of its source cloud scaled to the
    median registration's trace, divided by 100 for a nominal edge (~10x the error).
    ``"points"``: every edge the point information of its source cloud (Algorithm 2's
    weighting). ``nodes``: the (run, capture) of every node number (default: the ring)."""
    nodes = result.ring if nodes is None else nodes
    if weights not in ("information", "points"):
        raise ValueError(f"weights must be 'information' or 'points', got {weights!r}")

    def usable(x):
        return x is not None and np.all(np.isfinite(x)) and np.trace(x) > 0

    infos = [_psd(e.information) for _, _, e in edges if usable(e.information)]
    ref = float(np.median([np.trace(x) for x in infos])) if infos else 1.0
    out = []
    for i, j, e in edges:
        if weights == "information" and usable(e.information):
            # float32 normal matrices: clip round-off negative eigenvalues
            info = _psd(e.information)
        else:
            f = _capture(result.runs, nodes[i]).frame
            p = np.asarray(f.arrays.points)[np.asarray(f.arrays.mask)]
            info = point_information(p @ e.T[:3, :3].T + e.T[:3, 3])
            if weights == "information":
                info = (
                    info
                    * ref
                    / np.trace(info)
                    / (100.0 if e.n_matches == 0 and not np.isfinite(e.rmse) else 1.0)
                )
        out.append(GraphEdge(i, j, e.T, info))
    return out


def _psd(info: np.ndarray) -> np.ndarray:
    """Symmetric part of ``info`` with negative eigenvalues (round-off) set to zero."""
    lam, V = np.linalg.eigh(0.5 * (info + info.T))
    return (V * np.maximum(lam, 0.0)) @ V.T


def extra_edges(
    result: ModelResult, K: np.ndarray, cfg: PipelineConfig, seed: int = 0
) -> list[tuple[int, int, PairResult]]:
    """Constraints beyond the ring edges, as (i, j, pair) with ring positions i, j and
    ``pair.T = T_{j <- i}``: the routes' own forward registrations that are not ring edges
    (free: registered while moving), and every pair of ring views ``cfg.extra_gaps`` apart
    (across the loop seam too) registered from the Algorithm 2 poses. A registration is
    kept only when it agrees with the Algorithm 2 poses within the closure gate (a false
    keypoint consensus or an ICP slide would otherwise pull the graph); pairs that do not
    overlap (:class:`RegistrationFailed`) are skipped."""
    ring, m = result.ring, len(result.ring)
    if result.alg2_result is None:
        return []
    poses = result.alg2_result.poses
    pos = {k: n for n, k in enumerate(ring)}
    have = {frozenset((n, (n + 1) % m)) for n in range(m)}
    out: list[tuple[int, int, PairResult]] = []
    for r, run in enumerate(result.runs):
        for k, pair in enumerate(run.pairs[: len(run.captures) - 1]):
            a, b = (r, k), (r, k + 1)
            if a in pos and b in pos and frozenset((pos[a], pos[b])) not in have:
                have.add(frozenset((pos[a], pos[b])))
                out.append((pos[a], pos[b], pair))
    gate = (cfg.closure_gate_deg, cfg.closure_gate_m)
    for gap in cfg.extra_gaps:
        for i in range(m):
            j = (i + gap) % m
            if i == j or frozenset((i, j)) in have:
                continue
            have.add(frozenset((i, j)))
            prior = np.linalg.inv(poses[j]) @ poses[i]
            try:
                pair = cfg.register(
                    _capture(result.runs, ring[i]).frame,
                    _capture(result.runs, ring[j]).frame,
                    K,
                    prior,
                    seed + 1000 + i,
                    prior_gate=gate,
                )
            except RegistrationFailed:
                continue
            r_err, t_err = pose_error(pair.T, prior)
            if r_err <= gate[0] and t_err <= gate[1]:
                out.append((i, j, pair))
    return out


def register_views(
    cfg: PipelineConfig, fa: Frame, fb: Frame, K: np.ndarray, prior, seed: int, prior_gate=None
) -> PairResult:
    """``T_{b <- a}`` by ``cfg.register``, with the raw source points when ``fa`` is more
    than ``cfg.far_source_ratio`` farther from the scene (median depth) than ``fb`` (the
    plane fit behind the denoised points has a fixed pixel window, biased at depth: see
    ``PipelineConfig.far_source_ratio``)."""
    far = median_depth(fa) > cfg.far_source_ratio * median_depth(fb)
    if cfg.geometric_points == "plane" and far:
        cfg = dataclasses.replace(cfg, geometric_points="raw")
    return cfg.register(fa, fb, K, prior, seed, prior_gate=prior_gate)


def far_source_edges(
    result: ModelResult,
    edges: list[tuple[int, int, PairResult]],
    K: np.ndarray,
    cfg: PipelineConfig,
    seed: int = 0,
    nodes: list[tuple[int, int]] | None = None,
) -> list[tuple[int, int, PairResult]]:
    """``edges`` (i, j, pair) with every registration whose source view i is more than
    ``cfg.far_source_ratio`` farther from the scene than its target j registered again
    with the raw source points (:func:`register_views`), seeded by its own estimate and
    kept when it agrees with it within the closure gate (else, or when it fails, the edge
    is unchanged). An edge whose registration has no matches (a nominal or chained stand-in)
    is left alone. ``cfg.far_source_mode == "both"``: such an edge is kept too, and the raw
    one is appended, each with half its information (the same images twice, not two
    independent measurements). ``nodes``: the (run, capture) of every node number (default:
    the ring)."""
    if cfg.far_source_mode not in ("replace", "both"):
        raise ValueError(
            f"far_source_mode must be 'replace' or 'both', got {cfg.far_source_mode!r}"
        )
    if cfg.geometric_points != "plane":
        return list(edges)
    nodes = result.ring if nodes is None else nodes
    gate = (cfg.closure_gate_deg, cfg.closure_gate_m)
    out, added = [], []
    for n, (i, j, pair) in enumerate(edges):
        fa, fb = _capture(result.runs, nodes[i]).frame, _capture(result.runs, nodes[j]).frame
        if pair.n_matches > 0 and median_depth(fa) > cfg.far_source_ratio * median_depth(fb):
            try:
                cand = register_views(cfg, fa, fb, K, pair.T, seed + 4000 + n, gate)
            except RegistrationFailed:
                cand = None  # keep the registration as it was
            if cand is not None and all(
                x <= g for x, g in zip(pose_error(cand.T, pair.T), gate, strict=True)
            ):
                if cfg.far_source_mode == "replace":
                    pair = cand
                elif pair.information is not None and cand.information is not None:
                    pair = dataclasses.replace(pair, information=0.5 * pair.information)
                    added.append(
                        (i, j, dataclasses.replace(cand, information=0.5 * cand.information))
                    )
        out.append((i, j, pair))
    return out + added


def chained_view_pose(
    result: ModelResult, ring_poses: list[np.ndarray], key: tuple[int, int]
) -> np.ndarray | None:
    """Pose T_O,i of the view ``key`` = (run, capture) chained from the nearest ring view of
    its run (``ring_poses`` in ring order) through the run's forward registrations
    (T_{i+1 <- i}); the ring view's own pose for a ring view; None when the run has no ring
    view."""
    pos = {k: j for j, k in enumerate(result.ring)}
    if key in pos:
        return np.asarray(ring_poses[pos[key]], np.float64)
    r, i = key
    log = result.runs[r]
    members = [k for k in range(len(log.captures)) if (r, k) in pos]
    if not members:
        return None
    j = min(members, key=lambda k: abs(k - i))
    T = np.asarray(ring_poses[pos[(r, j)]], np.float64)
    lo, hi = min(i, j), max(i, j)
    T_hi_lo = np.eye(4)  # T_{hi <- lo} from the forward pairs lo..hi-1
    for k in range(lo, hi):
        T_hi_lo = np.asarray(log.pairs[k].T, np.float64) @ T_hi_lo
    return T @ (T_hi_lo if i < j else np.linalg.inv(T_hi_lo))


def outside_view_edges(
    result: ModelResult, K: np.ndarray, cfg: PipelineConfig, seed: int = 0
) -> tuple[list[tuple[int, int]], list[np.ndarray], list[tuple[int, int, PairResult]]]:
    """Pose-graph nodes and edges of the views left out of the ring (captured before the
    loop's closing view). Returns (their (run, capture) keys, their initial poses T_O,i
    chained from the Algorithm 2 ring poses, edges (i, j, pair) with ``pair.T = T_{j <- i}``
    in node numbers: ring positions, then these views from ``len(ring)`` on). The edges are
    the run's forward registrations that touch them and registrations of each to up to
    ``cfg.outside_links`` ring views nearest to it in nominal viewing direction, seeded from
    the chained poses, kept when they agree with them within the closure gate (like
    :func:`extra_edges`) and have keypoint consensus (ICP-alone ones only when none has). A view thus rests on several registrations, not on the one
    forward registration its chain starts with. A registration whose source is more than
    ``cfg.far_source_ratio`` farther from the scene than its target uses the raw source
    points (:func:`register_views`); with ``cfg.outside_far_mode == "both"`` the denoised
    one (for a forward edge: the run's own registration) joins it, each with half its
    information, when the two agree within the closure gate. No views, no Algorithm 2 result or
    ``cfg.outside_links <= 0``: nothing (such views stay chained in the evaluation)."""
    ring, m = result.ring, len(result.ring)
    pos = {k: n for n, k in enumerate(ring)}
    outside = [
        (r, i)
        for r, run in enumerate(result.runs)
        for i in range(len(run.captures))
        if (r, i) not in pos and any(k[0] == r for k in ring)
    ]
    if not outside or cfg.outside_links <= 0 or result.alg2_result is None:
        return [], [], []
    ring_poses = result.alg2_result.poses

    if cfg.outside_far_mode not in ("raw", "both"):
        raise ValueError(f"outside_far_mode must be 'raw' or 'both', got {cfg.outside_far_mode!r}")

    def is_far(a, b):
        fa, fb = _capture(result.runs, a).frame, _capture(result.runs, b).frame
        return cfg.geometric_points == "plane" and median_depth(fa) > (
            cfg.far_source_ratio * median_depth(fb)
        )

    def register(a, b, prior, seed_ab, gate=None):
        """T_{b <- a}: raw source points when a is much farther than b (see cfg)."""
        fa, fb = _capture(result.runs, a).frame, _capture(result.runs, b).frame
        return register_views(cfg, fa, fb, K, prior, seed_ab, gate)

    def halves(na, nb, raw, denoised):
        """Edges (na, nb) of a far source: the raw registration, and with
        ``outside_far_mode == "both"`` the denoised one too (when it agrees with the raw one
        within the closure gate), each with half its information (the same images twice)."""
        if (
            cfg.outside_far_mode == "raw"
            or denoised is None
            or raw.information is None
            or denoised.information is None
            or not all(x <= g for x, g in zip(pose_error(denoised.T, raw.T), gate, strict=True))
        ):
            return [(na, nb, raw)]
        return [
            (na, nb, dataclasses.replace(p, information=0.5 * p.information))
            for p in (raw, denoised)
        ]

    gate = (cfg.closure_gate_deg, cfg.closure_gate_m)

    node = dict(pos)
    node.update({k: m + n for n, k in enumerate(outside)})
    init = [chained_view_pose(result, ring_poses, k) for k in outside]
    poses = list(ring_poses) + init
    edges: list[tuple[int, int, PairResult]] = []
    linked = set()
    for r, run in enumerate(result.runs):
        for k, pair in enumerate(run.pairs[: len(run.captures) - 1]):
            a, b = (r, k), (r, k + 1)
            if a in node and b in node and (a not in pos or b not in pos):
                new = [(node[a], node[b], pair)]
                if is_far(a, b):
                    try:
                        # the run's registration (denoised source) is the other half
                        raw = register(a, b, pair.T, seed + 3000 + k)
                        new = halves(node[a], node[b], raw, pair)
                    except RegistrationFailed:
                        pass  # keep the run's registration
                edges += new
                linked.add(frozenset((node[a], node[b])))
    for n, key in enumerate(outside):
        cap = _capture(result.runs, key)
        # nearest ring views by the angle between the nominal optical axes
        axis = cap.T_nominal[:3, 2]
        order = sorted(
            range(m), key=lambda j: -float(axis @ _capture(result.runs, ring[j]).T_nominal[:3, 2])
        )
        # Links with keypoint consensus are preferred (as for the loop closure): ICP alone
        # across these wide baselines can settle in a wrong minimum inside the gate (fresh
        # Task 1 seed 310, view 0: 0.8-1.3 mm with keypoints, 2.7 / 4.7 mm by ICP alone).
        # Up to 2 x outside_links candidates are tried; ICP-alone links only when none has
        # keypoints.
        seeded, alone = [], []
        for j in [j for j in order if frozenset((m + n, j)) not in linked][: 2 * cfg.outside_links]:
            if len(seeded) >= cfg.outside_links:
                break
            prior = np.linalg.inv(poses[j]) @ poses[m + n]
            try:
                pair = register(key, ring[j], prior, seed + 2000 + 100 * n + j, gate)
            except RegistrationFailed:
                continue
            r_err, t_err = pose_error(pair.T, prior)
            if r_err <= gate[0] and t_err <= gate[1]:
                denoised = None
                if cfg.outside_far_mode == "both" and is_far(key, ring[j]):
                    try:
                        denoised = cfg.register(
                            cap.frame,
                            _capture(result.runs, ring[j]).frame,
                            K,
                            prior,
                            seed + 2000 + 100 * n + j,
                            prior_gate=gate,
                        )
                    except RegistrationFailed:
                        pass
                link = halves(m + n, j, pair, denoised)
                (seeded if pair.seeded_by_keypoints else alone).append(link)
        for link in seeded or alone[: cfg.outside_links]:
            edges += link
    return outside, init, edges


def ring_clouds(
    runs: list[RunLog], ring: list[tuple[int, int]]
) -> list[tuple[np.ndarray, np.ndarray]]:
    """The padded clouds (points (n, 3), mask (n,)) of the ring views, in ring order: the
    input of :func:`jaxcr.registration.global_opt.global_optimize`."""
    out = []
    for k in ring:
        arrays = _capture(runs, k).frame.arrays
        out.append((np.asarray(arrays.points), np.asarray(arrays.mask)))
    return out


def _capture(runs: list[RunLog], key: tuple[int, int]) -> Capture:
    return runs[key[0]].captures[key[1]]
