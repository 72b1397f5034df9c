"""``jaxcr fit ROBOT (--backbone FILE | --tips TIPS.json) -o OUT``: fit joint values (and the
base pose) to measurements of a real robot.

ROBOT is a robot.json, a dataset.json or a dataset folder. ``--backbone`` fits q to a measured
3-D backbone (points from base to tip, any spacing, in a declared unit: see
docs/dataset-format.md, "Measured backbones"); the points are taken in the robot frame unless
``--fit-pose`` also fits the base pose ``T_ref_robot`` (robot frame -> measurement frame).
``--tips`` fits q to tip pixels in the calibrated views of the dataset ROBOT; ``--fit-pose``
then fits a correction ``T_ref_robot`` of the robot frame the cameras see
(``T_cam_robot @ T_ref_robot``). Solver: Levenberg-Marquardt (Optimistix), joint limits by
reparametrisation (jaxcr.kinematics.fit).

Outputs, written atomically (temp file, then rename):

- ``OUT/fit.json`` (format ``jaxcr.fit/1``): ``kind``, ``mode``, ``q``, ``T_ref_robot`` (4x4,
  metres), ``errors`` (per point, metres, or per camera, pixels), ``rms``, ``max``,
  ``tip_error``, ``cost``, ``num_steps``, ``result``, ``ok``, ``input``.
- ``OUT/q.csv``: a header and one row of q, readable by ``jaxcr fk ROBOT OUT/q.csv``.
- With ``--frame ID`` (ROBOT a dataset): that frame's ``q`` in ROBOT's dataset.json is replaced
  by the fit and ``meta.fit`` records rms, max and the input; with ``--fit-pose`` every
  camera's inline ``T_cam_robot`` becomes ``T_cam_robot @ T_ref_robot`` (a camera taken from a
  stereo file, ``{"stereo": ..., "camera": N}``: its ``T_rig_robot``). dataset.json is
  rewritten atomically.

Exit code 0 when the fit converged, 1 when it did not (the outputs are written, ``ok`` false),
2 on bad input.
"""

from __future__ import annotations

import argparse
import os
import sys

import numpy as np

from jaxcr.errors import InputError

FORMAT = "jaxcr.fit/1"


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "fit",
        help="fit joint values (and base pose) to a measured backbone or tip pixels",
        description=__doc__.split("\n\n")[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=__doc__.split("\n\n", 1)[1],
    )
    p.add_argument("robot", help="robot.json, dataset.json or dataset folder")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--backbone", help="measured backbone: .csv/.txt, .json or .npy")
    src.add_argument("--tips", help='tip pixels {"tips": {"<camera>": [u, v]}} (needs a dataset)')
    p.add_argument(
        "--unit", choices=["m", "cm", "mm"], help="unit of the backbone file (if it declares none)"
    )
    p.add_argument("-o", "--out", required=True, help="output folder (created if missing)")
    p.add_argument("--fit-pose", action="store_true", help="also fit the base pose (SE(3))")
    p.add_argument(
        "--q0",
        help="comma-separated start joint values (default: see jaxcr.kinematics.fit.default_start)",
    )
    p.add_argument(
        "--tip-weight",
        type=float,
        default=1.0,
        help="weight of the measured-tip-to-model-tip term of a backbone fit (default %(default)s)",
    )
    p.add_argument(
        "--base-weight",
        type=float,
        default=1.0,
        help="weight of the measured-base-to-model-base term of a backbone fit (the first point "
        "is the base; 0: the model may start before it) (default %(default)s)",
    )
    p.add_argument(
        "--prior",
        type=float,
        default=0.0,
        help="weight of (q - q0), and of the pose twist with --fit-pose, in the residual, for "
        "under-determined fits such as tip pixels (default %(default)s)",
    )
    p.add_argument(
        "--starts",
        type=int,
        default=1,
        help="fit from this many starts (other bending planes, jaxcr.kinematics.fit.start_set) "
        "and keep the lowest cost; several sections' planes have local minima (default 1)",
    )
    p.add_argument(
        "--max-steps",
        type=int,
        default=100,
        help="Levenberg-Marquardt iterations (default %(default)s)",
    )
    p.add_argument(
        "--frame", help="dataset frame id whose q (and cameras, with --fit-pose) to update"
    )
    p.add_argument(
        "--in-camera",
        metavar="NAME",
        help="the backbone is in camera NAME's frame (ROBOT a dataset): map it into the "
        "dataset's robot frame by that camera's T_cam_robot before fitting",
    )
    p.set_defaults(func=run)


def _parse_q0(text: str | None, n: int) -> np.ndarray | None:
    if text is None:
        return None
    try:
        q = np.asarray([float(x) for x in text.split(",")], np.float64)
    except ValueError:
        raise InputError(
            f"expected {n} comma-separated numbers, got {text!r}", field="--q0"
        ) from None
    if q.shape != (n,) or not np.all(np.isfinite(q)):
        raise InputError(f"expected {n} finite comma-separated numbers, got {text!r}", field="--q0")
    return q


def _joint_names(model) -> list[str]:
    if model.kind == "constant_curvature":
        return [f"{j}_{i}" for i in range(model.n_sections) for j in model.joints]
    if model.kind == "single_segment":
        return ["theta_L", "delta"]
    n = model.n_tubes
    return [f"beta_{i + 1}" for i in range(n)] + [f"alpha_{i + 1}" for i in range(n)]


def _dataset_json(path: str) -> str:
    return os.path.join(path, "dataset.json") if os.path.isdir(path) else path


def _update_dataset(path: str, frame_id: str, q, T, record: dict, fit_pose: bool) -> None:
    from jaxcr.io.jsonfile import read_json
    from jaxcr.io.results import atomic_write_json

    jpath = _dataset_json(path)
    d = read_json(jpath)
    frames = d.get("frames") if isinstance(d, dict) else None
    idx = [
        i
        for i, f in enumerate(frames or [])
        if isinstance(f, dict) and str(f.get("id")) == frame_id
    ]
    if not idx:
        raise InputError(f"no frame with id {frame_id!r}", jpath, None, "--frame")
    fr = frames[idx[0]]
    fr["q"] = [float(x) for x in q]
    fr.setdefault("meta", {})["fit"] = record
    if fit_pose:
        for name, cam in d["cameras"].items():
            if isinstance(cam, dict) and "stereo" in cam:
                key = "T_rig_robot"
            else:
                key = "T_cam_robot"
            if not isinstance(cam, dict):
                raise InputError(
                    "camera given as a file: cannot apply the fitted pose (inline it, or apply "
                    "T_ref_robot from fit.json yourself)",
                    jpath,
                    frame_id,
                    f"cameras.{name}",
                )
            T0 = np.asarray(cam.get(key, np.eye(4)), np.float64)
            scale = {"m": 1.0, "cm": 100.0, "mm": 1000.0}.get(cam.get("unit", "m"), 1.0)
            Tm = np.array(T, np.float64)
            Tm[:3, 3] *= scale  # the fitted translation (m) in this entry's unit
            cam[key] = (T0 @ Tm).tolist()
    atomic_write_json(jpath, d)


def run(args) -> int:
    import jax.numpy as jnp

    from jaxcr.io.backbone import read_backbone, read_tips
    from jaxcr.io.exported import cached_call  # the stored traced programs (K4)
    from jaxcr.io.results import atomic_write_json, atomic_write_text
    from jaxcr.io.robot import load_robot
    from jaxcr.kinematics.fit import fit_backbone, fit_tip_pixels, pose_start

    if args.max_steps < 1:
        raise InputError(f"must be >= 1, got {args.max_steps}", field="--max-steps")
    if not 1 <= args.starts <= 1000:
        raise InputError(f"must be 1 to 1000, got {args.starts}", field="--starts")
    for name in ("tip_weight", "base_weight", "prior"):
        v = getattr(args, name)
        if not np.isfinite(v) or v < 0:
            raise InputError(
                f"must be finite and >= 0, got {v}", field="--" + name.replace("_", "-")
            )
    if args.unit is not None and args.backbone is None:
        raise InputError("--unit applies to --backbone only", field="--unit")
    if args.in_camera is not None and args.backbone is None:
        raise InputError("--in-camera applies to --backbone only", field="--in-camera")
    is_dataset = os.path.isdir(args.robot) or os.path.basename(args.robot) == "dataset.json"
    if args.frame is not None and not is_dataset:
        raise InputError("--frame needs ROBOT to be a dataset folder or dataset.json", args.robot)
    if args.in_camera is not None and not is_dataset:
        raise InputError(
            "--in-camera needs ROBOT to be a dataset folder or dataset.json", args.robot
        )
    model = load_robot(args.robot)
    q0 = _parse_q0(args.q0, model.n_joints)
    opts = dict(q0=q0, fit_pose=args.fit_pose, prior_weight=args.prior, max_steps=args.max_steps)
    if args.backbone is not None:
        points = read_backbone(args.backbone, args.unit)
        if args.in_camera is not None:
            from jaxcr.io.dataset import load_dataset

            cams = load_dataset(args.robot).cameras
            if args.in_camera not in cams:
                raise InputError(
                    f"unknown camera {args.in_camera!r} (cameras: {sorted(cams)})",
                    args.robot,
                    field="--in-camera",
                )
            Tcr = np.asarray(cams[args.in_camera].T_cam_robot, np.float64)
            points = (points - Tcr[:3, 3]) @ Tcr[:3, :3]  # camera frame -> robot frame
        if args.fit_pose:
            opts["T0"] = jnp.asarray(pose_start(points), jnp.float32)
        res = _best_of_starts(
            lambda o: fit_backbone(
                model,
                jnp.asarray(points, jnp.float32),
                tip_weight=args.tip_weight,
                base_weight=args.base_weight,
                jit_call=cached_call,
                **o,
            ),
            model,
            opts,
            args.starts,
        )
        mode, unit, source = "backbone", "m", args.backbone
        labels = [f"point {i}" for i in range(points.shape[0])]
    else:
        if not is_dataset:
            raise InputError("--tips needs ROBOT to be a dataset (its cameras)", args.robot)
        from jaxcr.io.dataset import load_dataset

        ds = load_dataset(args.robot)
        tips = read_tips(args.tips, list(ds.cameras))
        names = list(tips)
        from jaxcr.cli._common import check_robot_placed

        check_robot_placed(ds, names)
        cams = tuple(ds.cameras[c] for c in names)
        uv = jnp.asarray([tips[c] for c in names], jnp.float32)
        res = _best_of_starts(
            lambda o: fit_tip_pixels(model, cams, uv, jit_call=cached_call, **o),
            model,
            opts,
            args.starts,
        )
        mode, unit, source = "tips", "px", args.tips
        labels = names

    q = np.asarray(res.q, np.float64)
    T = np.asarray(res.T_ref_robot, np.float64)
    errors = np.asarray(res.errors, np.float64)
    ok = bool(res.ok)
    record = {
        "format": FORMAT,
        "kind": model.kind,
        "mode": mode,
        "input": source,
        "joints": _joint_names(model),
        "q": q.tolist(),
        "T_ref_robot": T.tolist(),
        "fit_pose": bool(args.fit_pose),
        "error_unit": unit,
        "errors": errors.tolist(),
        "rms": float(res.rms),
        "max": float(res.max),
        "tip_error": float(res.tip_error),
        "cost": float(res.cost),
        "num_steps": int(res.num_steps),
        "result": _result_text(res.result),
        "ok": ok,
        "starts": int(args.starts),
    }
    os.makedirs(args.out, exist_ok=True)
    atomic_write_json(os.path.join(args.out, "fit.json"), record)
    header = ",".join(_joint_names(model))
    row = ",".join(repr(float(x)) for x in q)
    atomic_write_text(os.path.join(args.out, "q.csv"), f"{header}\n{row}\n")
    if args.frame is not None:
        summary = {k: record[k] for k in ("mode", "input", "rms", "max", "error_unit", "ok")}
        _update_dataset(args.robot, args.frame, q, T, summary, args.fit_pose)

    scale, shown = (1000.0, "mm") if unit == "m" else (1.0, "px")
    worst = int(np.argmax(errors))
    print(
        f"fit {model.kind} to {mode} ({len(errors)} {'points' if mode == 'backbone' else 'views'}): "
        f"rms {errors_rms(errors) * scale:.3g} {shown}, max {errors[worst] * scale:.3g} {shown} "
        f"({labels[worst]}), tip {float(res.tip_error) * scale:.3g} {shown}, "
        f"{int(res.num_steps)} steps, {record['result']}"
    )
    print("q = " + ", ".join(f"{n}={v:.6g}" for n, v in zip(record["joints"], q, strict=True)))
    if not ok:
        print(f"jaxcr fit: fit did not converge ({record['result']})", file=sys.stderr)
        return 1
    return 0


def _best_of_starts(fit, model, opts: dict, n: int):
    """``fit(opts)`` from each start of :func:`jaxcr.kinematics.fit.start_set` (the first is
    ``--q0`` or the default); the converged result of lowest cost (any result if none
    converged). Its ``prior`` stays anchored at each start's own q0."""
    from jaxcr.kinematics.fit import start_set

    best = None
    for q0 in start_set(model, n, q0=opts.get("q0")):
        res = fit({**opts, "q0": q0})
        key = (not bool(res.ok), float(res.cost))
        if best is None or key < best[0]:
            best = (key, res)
    return best[1]


def errors_rms(errors: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(errors))))


def _result_text(result) -> str:
    import optimistix as optx

    return "successful" if result == optx.RESULTS.successful else optx.RESULTS[result]
