"""``jaxcr segment DATASET -o OUT``: kinematic-prior segmentation (Watson et al.) of a dataset.

For every frame: nominal kinematics (the robot model's forward kinematics, batched), background
subtraction (Sec. II-A), refinement of delta-u against the region energy of eq. 5
(:func:`jaxcr.segmentation.refine.refine_batch`, compiled once per shape), then the output files of
:mod:`jaxcr.io.results` are written frame by frame, crash-safe, so ``--resume`` continues an
interrupted run. Frames that cannot be processed (bad frames reported by the loader, NaN
joints, missing or unreadable images, kinematics failure, robot out of view, an image that is
all background) are recorded as failed with a reason; the run goes on.

Exit code: 0 when every frame succeeded, 1 when some failed, 2 on bad usage or input.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import math
import platform
import shutil
import sys
from pathlib import Path

import numpy as np

from jaxcr.cli._common import check_robot_placed
from jaxcr.cli._common import seed as _seed
from jaxcr.cli._plate import add_plate_arguments, plate_config, plate_flags_given
from jaxcr.errors import InputError
from jaxcr.io import results as R

HELP = "segment a dataset with the kinematic prior (Watson et al.)"
BACKGROUNDS = ("colour", "gmm", "plate", "none")


def add_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "segment",
        help=HELP,
        description=__doc__.split("\n\n")[0].replace("``", "")
        + " Writes OUT/results.jsonl, masks, overlays.",
    )
    p.add_argument("dataset", help="dataset folder (containing dataset.json) or dataset.json")
    p.add_argument("-o", "--out", required=True, help="output folder")
    p.add_argument(
        "--camera",
        action="append",
        default=None,
        metavar="NAME",
        help="camera(s) to use (repeat for several; default: all cameras of the dataset)",
    )
    p.add_argument(
        "--background",
        choices=BACKGROUNDS,
        default="colour",
        help="background subtraction: colour mask (paper's choice, default), per-pixel GMM "
        "fitted to the dataset's background images, plate (the first background image of "
        "each camera, aligned to every frame, cues beyond the key colour, the tube traced "
        "from the projected nominal base with gap bridging; see the --plate-... flags), or "
        "none",
    )
    p.add_argument(
        "--robot-hsv",
        action="append",
        default=None,
        metavar="H0,H1,S0,S1,V0,V1",
        help="colour mask: an HSV box of robot colours (hue in degrees 0-360, wrapping when "
        "H0 > H1; saturation and value 0-1); repeat for several boxes; pixels in none of them "
        "are background. Default: greys/metals/whites, 0,360,0,0.3,0.06,1 (for a coloured "
        "robot, e.g. a blue sheath: 190,250,0.3,1,0.1,1)",
    )
    p.add_argument(
        "--basis",
        type=int,
        default=None,
        metavar="N",
        help="Chebyshev coefficients per bending axis of delta-u (default: core's)",
    )
    p.add_argument(
        "--levels",
        type=int,
        default=None,
        metavar="L",
        help="number of pyramid levels, coarse to fine (default: core's)",
    )
    p.add_argument(
        "--max-steps",
        type=int,
        default=None,
        metavar="K",
        help="scale the solver's per-level step budget so the finest level has K "
        "steps (default: core's)",
    )
    p.add_argument(
        "--camera-correction",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="also estimate a small per-camera pose correction so calibration error is not "
        "absorbed by the shape (default: core's, on)",
    )
    p.add_argument(
        "--camera-correction-mode",
        choices=["camera", "rig"],
        default=None,
        help="with several cameras: an independent pose correction per camera (camera), or one "
        "shared correction of the robot-to-rig transform that keeps the cameras' calibrated "
        "relative poses, so their disparity measures depth (rig) (default: core's, camera)",
    )
    p.add_argument(
        "--g-cam-rel",
        type=float,
        default=None,
        metavar="G",
        help="rig mode: also estimate a residual correction of each further camera, "
        "regularised by G (default: core's)",
    )
    p.add_argument(
        "--prior-weight",
        type=float,
        default=None,
        metavar="G",
        help="gamma_3 of eq. 5, the weight of the curvature-change prior |delta-u|^2: larger "
        "keeps the shape nearer the kinematic model where the images say little (e.g. depth "
        "in one camera) (default: core's)",
    )
    p.add_argument(
        "--mu-out",
        choices=["local", "global"],
        default=None,
        help="outside mean colour over the band around the robot (local) or the whole "
        "image (global, the paper's eq. 6) (default: core's, local)",
    )
    p.add_argument(
        "--batch-size",
        type=int,
        default=4,
        metavar="B",
        help="frames per compiled call (the last chunk is padded; default 4)",
    )
    p.add_argument(
        "--warm-start",
        action="store_true",
        help="treat the frames as a sequence: warm-start each frame from the "
        "previous frame's delta-u",
    )
    p.add_argument(
        "--roi",
        choices=("auto", "on", "off"),
        default=None,
        help="with --warm-start: refine each tracked frame on a region of interest around its "
        "warm start (region data, bands and masks computed there; a frame whose band nears "
        "the region's border is refined on the whole image): 'on', 'off', or 'auto' = on for "
        "images of at least 2 x 640 x 480 pixels whose region is at most a quarter of the "
        "image, where it measurably saves time (docs/decisions.md S21, S28). Default: auto; "
        "a resumed run keeps its recorded choice (off for a run written before this option)",
    )
    p.add_argument(
        "--shape-buckets",
        choices=("on", "off"),
        default=None,
        help="pad each camera's frames at the bottom/right to a standard size (each side "
        "rounded up to the ladder 32, 40, 48, 64, 80, 96, 120, 128, 160, 192, 240, 256, 320, "
        "384, 480, 512, 640, 720, 800, 960, 1080, 1280, 1440, 1600, 1920, 2160, 2560, 3072, "
        "3840, 4096, then multiples of 1024), so that a new image size reuses the programs "
        "compiled for its bucket (600x450 runs 640x480's); the padding weighs nothing and "
        "every output keeps the real size (docs/decisions.md S29). Default: on; a resumed "
        "run keeps its recorded choice (off for a run written before this option)",
    )
    p.add_argument(
        "--resume",
        action="store_true",
        help="continue an interrupted run in OUT (skips frames in results.jsonl)",
    )
    p.add_argument(
        "--retry-failed",
        action="store_true",
        help="with --resume (implied): also re-run the frames whose last record failed, e.g. "
        "after fixing their images (the new record supersedes the failed one)",
    )
    p.add_argument(
        "--overwrite", action="store_true", help="delete previous results in OUT and start again"
    )
    p.add_argument("--no-overlays", action="store_true", help="do not write overlay PNGs")
    p.add_argument(
        "--limit",
        type=int,
        default=None,
        metavar="N",
        help="process at most N new frames, then stop (no DONE marker; continue with --resume)",
    )
    p.add_argument(
        "--seed",
        type=_seed,
        default=0,
        help="random seed (recorded; the refinement itself is deterministic)",
    )
    p.add_argument(
        "--depth-warning-factor",
        type=float,
        default=None,
        metavar="F",
        help="warn (once per run on stderr, and flag 'depth_ambiguous' in every such "
        "frame's record) when the tip's 1-sigma uncertainty along a camera's optical axis "
        "exceeds F times its 1-sigma uncertainty in that camera's image plane (default 3: "
        "about what a stereo pair with 20 degrees of vergence gives; docs/uncertainty.md)",
    )
    p.add_argument(
        "--no-uncertainty",
        action="store_true",
        help="skip the per-frame Laplace covariance of the refined shape (no 'uncertainty' "
        "entry in results.jsonl, no depth warning)",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    from jaxcr.scale.executor import add_executor_arguments
    from jaxcr.scale.shards import add_shard_argument

    add_shard_argument(p)
    add_executor_arguments(p, "--batch-size frames")
    add_plate_arguments(p, "--background plate")
    p.set_defaults(func=run)
    return p


# --------------------------------------------------------------------------- configuration


def refine_config(args):
    """The :class:`jaxcr.segmentation.refine.RefineConfig` for the CLI options (None = core default)."""
    import dataclasses

    from jaxcr.segmentation.refine import RefineConfig

    base = RefineConfig()
    kw = {}
    if args.basis is not None:
        if args.basis < 1:
            raise InputError("--basis must be >= 1", field="basis")
        kw["n_coeffs"] = args.basis
    # per-level schedules: every tuple field as long as ``levels`` (steps, outer, tau, ...)
    n_lev = len(base.levels)
    sched = {
        f.name: tuple(getattr(base, f.name))
        for f in dataclasses.fields(base)
        if isinstance(getattr(base, f.name), tuple) and len(getattr(base, f.name)) == n_lev
    }
    if args.levels is not None:
        n = args.levels
        if n < 1:
            raise InputError("--levels must be >= 1", field="levels")
        # keep the core's schedule for its finest n levels; extend coarser ones if asked
        if n <= n_lev:
            sched = {k: v[-n:] for k, v in sched.items()}
        else:
            extra = n - n_lev
            top = max(base.levels)
            sched = {k: (v[0],) * extra + v for k, v in sched.items()}
            sched["levels"] = tuple(range(top + extra, top, -1)) + tuple(base.levels)
    if args.max_steps is not None:
        from jaxcr.limits import MAX_STEPS, check_count

        check_count(args.max_steps, "max-steps", 1, MAX_STEPS)
        steps = sched["steps"]
        scale = args.max_steps / steps[-1]
        sched["steps"] = tuple(max(1, round(s * scale)) for s in steps)
    kw.update(sched)
    if getattr(args, "camera_correction", None) is not None:
        kw["camera_correction"] = bool(args.camera_correction)
    if getattr(args, "camera_correction_mode", None) is not None:
        kw["camera_correction_mode"] = args.camera_correction_mode
    if getattr(args, "g_cam_rel", None) is not None:
        from jaxcr.limits import check_number

        kw["g_cam_rel"] = check_number(args.g_cam_rel, "g-cam-rel", 0.0)  # NaN was accepted
    if getattr(args, "mu_out", None) is not None:
        kw["local"] = args.mu_out == "local"
    if getattr(args, "prior_weight", None) is not None:
        if not (args.prior_weight >= 0 and math.isfinite(args.prior_weight)):
            raise InputError("--prior-weight must be a finite number >= 0", field="prior-weight")
        kw["g_reg"] = float(args.prior_weight)
    return RefineConfig(**kw)


def _hsv_tuple(r) -> tuple[float, ...]:
    return (r.h_lo, r.h_hi, r.s_lo, r.s_hi, r.v_lo, r.v_hi)


def robot_hsv_ranges(args):
    """The ``--robot-hsv`` boxes as :class:`jaxcr.segmentation.background.HSVRange` (None = the default
    :data:`jaxcr.segmentation.background.ROBOT_HSV`)."""
    texts = getattr(args, "robot_hsv", None)
    if not texts:
        return None
    if args.background != "colour":
        raise InputError("--robot-hsv needs --background colour", field="robot-hsv")
    from jaxcr.segmentation.background import HSVRange

    out = []
    for text in texts:
        try:
            v = [float(x) for x in text.split(",")]
        except ValueError:
            v = []
        ok = len(v) == 6 and all(math.isfinite(x) for x in v)
        ok = ok and 0 <= v[0] <= 360 and 0 <= v[1] <= 360
        ok = ok and 0 <= v[2] <= v[3] <= 1 and 0 <= v[4] <= v[5] <= 1
        if not ok:
            raise InputError(
                f"--robot-hsv {text!r}: need six numbers H0,H1,S0,S1,V0,V1 with hue in "
                "[0, 360] and 0 <= S0 <= S1 <= 1, 0 <= V0 <= V1 <= 1",
                field="robot-hsv",
            )
        out.append(HSVRange(*v))
    return tuple(out)


def dataclasses_asdict(cfg) -> dict:
    import dataclasses

    return dataclasses.asdict(cfg)


def config_dict(cfg) -> dict:
    import dataclasses

    return {f.name: getattr(cfg, f.name) for f in dataclasses.fields(cfg)}


def versions() -> dict:
    import importlib.metadata as md

    out = {"python": platform.python_version(), "platform": platform.platform()}
    for pkg in (
        "jaxcr",
        "jax",
        "jaxlib",
        "equinox",
        "optimistix",
        "numpy",
        "opencv-python-headless",
    ):
        try:
            out[pkg] = md.version(pkg)
        except md.PackageNotFoundError:
            pass
    root = _source_root()
    out["git_commit"] = None if root is None else _head_commit(root)
    # modified tracked files under jaxcr/ (the code that ran differs from the commit), asked
    # with --no-optional-locks: a plain `git status` refreshes the index under .git/index.lock,
    # a write into the user's checkout
    dirty = None if root is None else _git(root, "status", "--porcelain", "--untracked-files=no",
                                           "--", "jaxcr")  # fmt: skip
    out["git_dirty"] = (
        None if dirty is None else sorted(line[3:] for line in dirty.splitlines() if line.strip())
    )
    return out


def _source_root(module_file: str | None = None) -> Path | None:
    """The git checkout jaxcr runs from (an editable install), or None (a wheel installed in
    site-packages: its version is the package version alone)."""
    root = Path(module_file or __file__).resolve().parents[2]
    if "site-packages" in root.parts or "dist-packages" in root.parts:
        return None
    if not (root / ".git").exists() or not (root / "pyproject.toml").is_file():
        return None
    return root


def _git_dir(root: Path) -> tuple[Path, Path] | None:
    """(git dir, common dir) of the checkout at ``root``; a worktree's ``.git`` is a file
    ``gitdir: PATH`` and its shared refs live in the ``commondir``."""
    dot = root / ".git"
    try:
        if dot.is_file():
            text = dot.read_text(encoding="utf-8").strip()
            if not text.startswith("gitdir:"):
                return None
            gdir = Path(text[7:].strip())
            gdir = gdir if gdir.is_absolute() else (root / gdir)
        else:
            gdir = dot
        common = gdir
        if (gdir / "commondir").is_file():
            c = Path((gdir / "commondir").read_text(encoding="utf-8").strip())
            common = c if c.is_absolute() else (gdir / c)
        return gdir, common
    except (OSError, UnicodeDecodeError):
        return None


def _head_commit(root: Path) -> str | None:
    """The commit checked out at ``root``, read from ``.git/HEAD`` and the refs files (loose
    or packed) without running git: nothing in the checkout is locked or written."""
    dirs = _git_dir(root)
    if dirs is None:
        return None
    gdir, common = dirs
    try:
        head = (gdir / "HEAD").read_text(encoding="utf-8").strip()
        if not head.startswith("ref:"):
            return head if _is_sha(head) else None  # detached HEAD
        ref = head[4:].strip()
        for base in (gdir, common):
            if (base / ref).is_file():
                sha = (base / ref).read_text(encoding="utf-8").strip()
                return sha if _is_sha(sha) else None
        packed = common / "packed-refs"
        if packed.is_file():
            for line in packed.read_text(encoding="utf-8").splitlines():
                parts = line.split()
                if len(parts) == 2 and parts[1] == ref and _is_sha(parts[0]):
                    return parts[0]
    except (OSError, UnicodeDecodeError):
        return None
    return None


def _is_sha(text: str) -> bool:
    return len(text) in (40, 64) and all(c in "0123456789abcdef" for c in text)


def _git(root: Path, *args: str) -> str | None:
    import os
    import subprocess

    try:
        r = subprocess.run(
            ["git", "--no-optional-locks", "-C", str(root), *args],
            capture_output=True,
            text=True,
            timeout=5,
            check=False,
            env={**os.environ, "GIT_OPTIONAL_LOCKS": "0"},
        )
        return r.stdout.rstrip("\n") if r.returncode == 0 else None
    except (OSError, subprocess.SubprocessError):
        return None


# --------------------------------------------------------------------------- dataset access


def load(path: str):
    """Load a dataset with :func:`jaxcr.io.dataset.load_dataset` (InputError on bad input)."""
    from jaxcr.io.dataset import load_dataset

    p = Path(path)
    if not p.exists():
        raise InputError("dataset not found", file=path)
    return load_dataset(p)


def select_cameras(ds, names: list[str] | None) -> list[str]:
    available = list(ds.cameras)
    if not names:
        return available
    for n in names:
        if n not in ds.cameras:
            raise InputError(
                f"no camera '{n}' in the dataset (available: {', '.join(available)})",
                field="camera",
            )
    return list(dict.fromkeys(names))


# --------------------------------------------------------------------------- output folder


PRODUCTS = ("masks", "nominal", "background", "overlays", "centrelines", "centrelines_nominal")


def prepare_output(
    out: Path, resume: bool, overwrite: bool, run_info: dict, shard=None
) -> list[dict]:
    """Check/prepare OUT (``shard``: a :class:`jaxcr.scale.shards.Shard`, whose bookkeeping
    goes to ``OUT/shards/I-of-N``); return the records already there that this run skips (its
    own with ``--resume``, and always those of other shards / an unsharded run)."""
    from jaxcr.io import outdir
    from jaxcr.scale import shards as S

    log_dir = None if shard is None else S.shard_dir(out, shard)
    layout = R.OutputLayout(out, log_dir=log_dir)
    if resume and overwrite:
        raise InputError("--resume and --overwrite exclude each other")

    # Never write into (or --overwrite) a folder that holds something else, e.g. the dataset
    # itself: its masks/<cam>/<id>.png ground truth would be replaced by our predictions; and
    # never beside another process writing the same OUT (the lock, held until exit).
    lock = S.claim_output(out, "segment", shard, marker=R.RUN_FILE)
    try:
        return _prepare_claimed(out, layout, resume, overwrite, run_info, shard)
    except BaseException:
        outdir.release(lock)  # refused: the folder is free again (library callers)
        raise


_SAME_JOB_KEYS = (
    "results_format",
    "dataset",
    "cameras",
    "background",
    "robot_hsv",
    "plate",
    "config",
    "roi",
    "shape_buckets",
)

#: the value of a run.json key absent from a run written before the key existed (its
#: behaviour then): such a run resumes with that value
_ABSENT = {"roi": "off", "shape_buckets": "off"}
#: the defaults of the options whose resume keeps the recorded choice
_DEFAULTS = {"roi": "auto", "shape_buckets": "on"}


def _roi_mode(args, out: Path, shard, key: str = "roi") -> str:
    """``--roi`` (or the option ``key``) as given; else the choice recorded in this job's
    run.json (a resume or another shard: :data:`_ABSENT` for a run written before the
    option); else :data:`_DEFAULTS`."""
    given = getattr(args, key, None)
    if given is not None:
        return given
    from jaxcr.scale import shards as S

    own = out / R.RUN_FILE if shard is None else S.shard_dir(out, shard) / R.RUN_FILE
    paths = [out / R.RUN_FILE] + [d / R.RUN_FILE for _, d in S.shard_dirs(out)]
    for path in dict.fromkeys(paths):
        if args.overwrite and (shard is None or path == own):
            continue  # deleted by --overwrite before the run starts
        if path.exists():
            return R.read_run(path).get(key, _ABSENT[key])
    return _DEFAULTS[key]


def _check_same_job(path: Path, run_info: dict, what: str) -> None:
    """Refuse to continue (or add a shard to) the run of ``path`` (a run.json) with other
    options."""
    prev = R.read_run(path)
    for key in _SAME_JOB_KEYS:
        a = R.to_jsonable(prev.get(key, _ABSENT.get(key)))
        b = R.to_jsonable(run_info.get(key, _ABSENT.get(key)))
        if a != b:
            if isinstance(a, dict) and isinstance(b, dict):  # name only what differs
                diff = sorted(k for k in set(a) | set(b) if a.get(k, "?") != b.get(k, "?"))
                change = ", ".join(
                    f"{k}: {a.get(k, '(absent)')!r} -> {b.get(k, '(absent)')!r}" for k in diff
                )
            else:
                change = f"{a!r} -> {b!r}"
            raise InputError(
                f"cannot {what}: '{key}' differs from the run in this folder ({change}); "
                "use the same options (or --overwrite, or a new -o)",
                file=str(path),
            )


def _prepare_claimed(out, layout, resume, overwrite, run_info, shard=None) -> list[dict]:
    from jaxcr.scale import shards as S

    has_results = layout.results.exists() and layout.results.stat().st_size > 0
    if has_results and not (resume or overwrite):
        raise InputError(
            "output folder already has results; use --resume to continue or --overwrite",
            file=str(out if shard is None else layout.log_root),
        )
    if overwrite and out.exists():
        if shard is None:  # the whole run: every shard's bookkeeping too (none runs: locked)
            for name in (*PRODUCTS, S.SHARDS_DIR):
                shutil.rmtree(out / name, ignore_errors=True)
        for f in (layout.results, layout.summary, layout.done, layout.run):
            f.unlink(missing_ok=True)
    # the run.json of every other part of this job (OUT's own, other shards'): same options
    others = [out / R.RUN_FILE] + [d / R.RUN_FILE for _, d in S.shard_dirs(out)]
    for path in others:
        if path.exists() and path != layout.run:
            _check_same_job(path, run_info, "add to the runs in this folder")
    records: list[dict] = []
    if resume and layout.run.exists():
        _check_same_job(layout.run, run_info, "resume")
        try:
            records = R.read_results(layout.results)
        except ValueError as err:
            raise InputError(str(err)) from None
    # frames recorded by the other parts of the job are done (a shard never redoes another
    # shard's frame; an unsharded --resume after shards finishes only what is missing)
    try:
        own = {str(r["frame"]) for r in records}
        for f in S.results_files(out):
            if f != layout.results:
                records += [r for r in R.read_results(f) if str(r["frame"]) not in own]
    except ValueError as err:
        raise InputError(str(err)) from None
    out.mkdir(parents=True, exist_ok=True)
    layout.log_root.mkdir(parents=True, exist_ok=True)
    layout.done.unlink(missing_ok=True)
    layout.summary.unlink(missing_ok=True)
    if not (resume and layout.run.exists()):
        R.atomic_write_json(layout.run, run_info)
    return records


# --------------------------------------------------------------------------- the run


def _check_limits(args, ds, cams) -> None:
    """--levels, --basis and --batch-size against this dataset (jaxcr.limits), before any
    work: a --levels 30 run compiled for minutes and then hung on a 1-pixel pyramid level."""
    from jaxcr.limits import (
        MEMORY_BUDGET,
        MIN_LEVEL_SIDE,
        SEGMENT_BYTES_PER_PIXEL,
        check_count,
        max_levels,
    )

    short = min(min(ds.cameras[c].width, ds.cameras[c].height) for c in cams)
    if args.levels is not None:
        most = max_levels(short)
        check_count(args.levels, "levels", 1, most, f"the coarsest level of a {short}-px side "
                    f"must keep {MIN_LEVEL_SIDE} px")  # fmt: skip
    n_points = getattr(ds.robot, "n_points", None)
    if args.basis is not None and n_points:
        # more Chebyshev coefficients than centreline samples are not determined by them
        check_count(args.basis, "basis", 1, int(n_points), f"the robot has {n_points} "
                    "centreline samples")  # fmt: skip
    pixels = sum(ds.cameras[c].width * ds.cameras[c].height for c in cams)
    most = max(1, MEMORY_BUDGET // (SEGMENT_BYTES_PER_PIXEL * pixels))
    check_count(args.batch_size, "batch-size", 1, most, f"{SEGMENT_BYTES_PER_PIXEL} bytes per "
                f"pixel of {len(cams)} view(s) within {MEMORY_BUDGET >> 30} GiB")  # fmt: skip


def run(args) -> int:
    ds = load(args.dataset)
    if not ds.frames and not ds.bad_frames:  # else a DONE run of 0/0 frames, exit 0
        raise InputError(
            "the dataset has no frames: nothing to segment",
            file=str(Path(ds.root) / "dataset.json"),
            field="frames",
        )
    cams = select_cameras(ds, args.camera)
    check_robot_placed(ds, cams)
    _check_limits(args, ds, cams)
    if args.limit is not None and args.limit < 0:
        raise InputError("--limit must be >= 0", field="limit")
    if args.retry_failed:
        if args.overwrite:
            raise InputError("--retry-failed and --overwrite exclude each other")
        args.resume = True
    cfg = refine_config(args)
    ranges = robot_hsv_ranges(args)
    given = plate_flags_given(args)
    if given and args.background != "plate":
        raise InputError(f"{given[0]} needs --background plate", field=given[0][2:])
    plate_cfg = plate_config(args) if args.background == "plate" else None
    from jaxcr.scale.executor import WorkerSpec, executor_config
    from jaxcr.scale.shards import parse_shard, shard_dir

    shard = parse_shard(args.shard)
    executor = executor_config(args)
    if executor.kind == "ray" and args.warm_start:
        raise InputError("--warm-start needs the frames as one sequence in one process: use "
                         "--executor local (shards each start their sequence cold)",
                         field="warm-start")  # fmt: skip
    factor = args.depth_warning_factor
    if factor is not None and not (math.isfinite(factor) and factor >= 1.0):
        raise InputError(
            "--depth-warning-factor must be a finite number >= 1", field="depth-warning-factor"
        )
    out = Path(args.out)
    from jaxcr.segmentation.uncertainty import DEPTH_FACTOR

    run_info = {
        "format": R.RUN_FORMAT,
        "results_format": R.RESULTS_FORMAT,
        "dataset": str(Path(ds.root).resolve()),
        "dataset_name": ds.name,
        "cameras": cams,
        "background": args.background,
        "robot_hsv": None if ranges is None else [list(_hsv_tuple(r)) for r in ranges],
        "plate": None if plate_cfg is None else dataclasses_asdict(plate_cfg),
        "warm_start": bool(args.warm_start),
        "roi": _roi_mode(args, out, shard),
        "shape_buckets": _roi_mode(args, out, shard, "shape_buckets"),
        "batch_size": args.batch_size,
        "seed": args.seed,
        "uncertainty": None
        if args.no_uncertainty
        else {"depth_warning_factor": DEPTH_FACTOR if factor is None else factor},
        "config": config_dict(cfg),
        "shard": None if shard is None else str(shard),
        "started": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
        "command": " ".join(sys.argv),
        "versions": versions(),
    }
    previous = prepare_output(out, args.resume, args.overwrite, run_info, shard)
    from jaxcr.segmentation.batch import Segmenter, build_segmenter

    seg_kwargs = dict(
        overlays=not args.no_overlays,
        warm_start=args.warm_start,
        roi=run_info["roi"],
        shape_buckets=run_info["shape_buckets"] == "on",
        batch_size=args.batch_size,
        colour_ranges=ranges,
        plate_config=plate_cfg,
        log_dir=None if shard is None else shard_dir(out, shard),
        uncertainty=not args.no_uncertainty,
        depth_factor=factor,
        warn=lambda msg: print(f"jaxcr segment: warning: {msg}", file=sys.stderr, flush=True),
    )
    seg = Segmenter(ds, cams, cfg, args.background, out, **seg_kwargs)
    spec = WorkerSpec(build_segmenter, (str(ds.root), cams, cfg, args.background, str(out)),
                      seg_kwargs)  # fmt: skip
    scope = seg.frame_ids if shard is None else shard.select(seg.frame_ids)
    done = R.done_frame_ids(previous, retry_failed=args.retry_failed)
    todo = [f for f in scope if f not in done]
    if args.limit is not None:
        todo = todo[: args.limit]
    stopped_early = len({f for f in scope if f in done}) + len(todo) < len(scope)

    stats = seg.run(todo, progress=not args.quiet, executor=executor, spec=spec)
    new_records = stats.records

    from jaxcr.scale.shards import read_all_records

    in_scope = set(scope)
    all_records = [r for r in read_all_records(out) if str(r["frame"]) in in_scope]
    n_failed = sum(1 for r in all_records if not r.get("ok"))
    what = "" if shard is None else f" (shard {shard})"
    if stopped_early:
        print(
            f"jaxcr segment: stopped after {len(new_records)} new frames (--limit){what}; "
            f"{len(scope) - len(all_records)} left, continue with --resume",
            file=sys.stderr,
        )
        return 1 if n_failed else 0
    summary = {
        "format": R.RESULTS_FORMAT,
        "frames": len(all_records),
        "ok": len(all_records) - n_failed,
        "failed": n_failed,
        "failures": {r["frame"]: r.get("reason") for r in all_records if not r.get("ok")},
        "shard": None if shard is None else str(shard),
        "executor": stats.executor,
        "compile_s": seg.compile_s,
        "run_s": seg.run_s,
        "median_time_s": _median(r.get("time_s") for r in all_records if r.get("ok")),
        "median_uncertainty_time_s": _median(
            (r.get("uncertainty") or {}).get("time_s") for r in all_records if r.get("ok")
        ),
        "depth_ambiguous": [
            r["frame"] for r in all_records if (r.get("uncertainty") or {}).get("depth_ambiguous")
        ],
        "finished": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
    }
    layout = seg.layout
    R.atomic_write_json(layout.summary, summary)
    R.atomic_write_text(layout.done, summary["finished"] + "\n")
    print(
        f"jaxcr segment: {summary['ok']}/{summary['frames']} frames ok{what}"
        + (f", {n_failed} failed (reasons in {layout.summary})" if n_failed else "")
        + (
            f", {len(summary['depth_ambiguous'])} depth-ambiguous"
            if summary["depth_ambiguous"]
            else ""
        )
        + f" -> {out}"
    )
    return 1 if n_failed else 0


def _median(values) -> float | None:
    v = [x for x in values if x is not None and math.isfinite(x)]
    return float(np.median(v)) if v else None
