"""``jaxcr synth --preset NAME -o OUT``: write synthetic continuum-robot datasets.

Scenes reproduce the evaluation of Watson et al. (kinematic prior): a concentric-tube robot
above tissue-like texture, seen orthogonally or endoscopically, with or without a
laparoscopic instrument occluding it. Images are ray cast (exact tube surfaces, depth test,
metallic shading, anti-aliased edges, camera blur and noise). The robot and camera used to
render differ from the nominal ones written to dataset.json by a model error (precurvature,
stiffness, joint offsets, tip load, camera pose), so projecting the nominal model misses the
robot as in the paper.

Presets: orthogonal, orthogonal_occluded, endoscopic, endoscopic_occluded (20 frames each at
640x480). With --all, one sub-dataset per preset is written to OUT/<preset>/.

Examples:
  jaxcr synth --all -o data/synth
  jaxcr synth --preset orthogonal --frames 5 --size 320x240 -o /tmp/ortho --seed 3
  jaxcr synth --preset endoscopic --stereo -o /tmp/endo_stereo
  jaxcr synth --preset orthogonal --preview docs/images -o /tmp/ortho
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time

from jaxcr.cli._common import seed as _seed
from jaxcr.errors import InputError


def add_parser(subparsers) -> None:
    from jaxcr.synth.presets import PRESETS

    p = subparsers.add_parser(
        "synth",
        help="generate synthetic CTR datasets (ray-cast images, masks, true centrelines)",
        description=__doc__.split("\n\n")[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=__doc__.split("\n\n", 1)[1],
    )
    p.add_argument(
        "--preset", action="append", default=[], choices=sorted(PRESETS), help="preset (repeatable)"
    )
    p.add_argument("--all", action="store_true", help="every preset, one sub-folder each")
    p.add_argument(
        "-o",
        "--out",
        required=True,
        help="output folder: new, empty, or an earlier jaxcr synth dataset (replaced)",
    )
    p.add_argument("--seed", type=_seed, default=0, help="random seed (default %(default)s)")
    p.add_argument("--frames", type=int, default=None, help="frames per preset (default 20)")
    p.add_argument("--size", default=None, help="image size WIDTHxHEIGHT (default 640x480)")
    p.add_argument(
        "--model-error",
        type=float,
        default=None,
        metavar="SCALE",
        help="scale of every model-error source (default 1; 0 = nominal model is exact)",
    )
    p.add_argument(
        "--robot",
        default=None,
        metavar="ROBOT.json",
        help="render this robot (any kind) instead of the presets' concentric-tube robot",
    )
    p.add_argument("--stereo", action="store_true", help="a two-camera rig (left, right)")
    p.add_argument("--cameras", type=int, default=None, help="number of cameras in the rig")
    p.add_argument(
        "--preview",
        default=None,
        metavar="DIR",
        help="also write example_frame.png, example_mask.png, example_nominal_overlay.png "
        "of the first dataset's first frame to DIR",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def _is_synth_dataset(out) -> bool:
    """True when OUT holds a dataset this command wrote (a rerun replaces it); written before
    output folders carried an owner file (:mod:`jaxcr.io.outdir`)."""
    import json

    ds = os.path.join(out, "dataset.json")
    try:
        with open(ds, encoding="utf-8-sig") as fh:
            gen = (json.load(fh).get("meta") or {}).get("generator")
    except (OSError, ValueError, AttributeError):
        return False
    return gen == "jaxcr synth"


def _check_out(out: str) -> None:
    """OUT may be new, empty, or a dataset this command wrote (it is then replaced); never a
    user's folder, a dataset from elsewhere or a run's output folder, whose files would be
    overwritten. Takes OUT's lock (:func:`jaxcr.io.outdir.claim`) until the command ends."""
    from jaxcr.io import outdir

    outdir.claim(out, "synth", recognise=_is_synth_dataset)


def run(args) -> int:
    from jaxcr.synth.generate import generate, parse_size
    from jaxcr.synth.presets import PRESETS

    names = list(PRESETS) if args.all else list(dict.fromkeys(args.preset))
    if not names:
        raise InputError("give --preset NAME (repeatable) or --all", field="preset")
    size = None if args.size is None else parse_size(args.size)
    from jaxcr.limits import MAX_PIXELS, check_count, check_frames

    if args.frames is not None:
        check_frames(args.frames, "frames")
    if args.model_error is not None and not 0 <= args.model_error < math.inf:
        raise InputError(
            f"model-error scale must be finite and >= 0, got {args.model_error}",
            field="model-error",
        )
    n_cameras = args.cameras
    if args.stereo:
        if n_cameras is not None and n_cameras < 2:
            raise InputError("--stereo needs at least 2 cameras", field="cameras")
        n_cameras = n_cameras or 2
    if n_cameras is not None and n_cameras < 1:
        raise InputError(f"need at least one camera, got {n_cameras}", field="cameras")
    if n_cameras is not None:
        # the views of one frame are rendered, stored and segmented together: together they
        # count against the renderer's pixel ceiling (jaxcr.limits)
        w, h = size or (640, 480)
        most = max(1, MAX_PIXELS["synth"] // (w * h))
        check_count(n_cameras, "cameras", 1, most, f"{most} views of {w}x{h} fit the "
                    f"{MAX_PIXELS['synth']}-pixel ceiling of one frame")  # fmt: skip
    robot = None
    if args.robot is not None:
        from jaxcr.io.robot import load_robot
        from jaxcr.kinematics.robots import robot_to_dict

        robot = robot_to_dict(load_robot(args.robot))
    several = len(names) > 1 or args.all
    if args.preview:
        from jaxcr.cli._common import check_writable_folder

        check_writable_folder(args.preview, "preview folder")
    for name in names:
        _check_out(os.path.join(args.out, name) if several else args.out)
    t0 = time.perf_counter()
    written = []
    for name in names:
        out = os.path.join(args.out, name) if several else args.out
        path = generate(
            name,
            out,
            seed=args.seed,
            frames=args.frames,
            size=size,
            progress=not args.quiet,
            model_error_scale=args.model_error,
            n_cameras=n_cameras,
            robot=robot,
        )
        written.append(path)
        print(f"{name}: {path}", file=sys.stderr if args.quiet else sys.stdout)
    if args.preview:
        from jaxcr.synth.preview import write_preview

        for p in write_preview(written[0].parent, args.preview):
            print(f"preview: {p}")
    print(f"wrote {len(written)} dataset(s) in {time.perf_counter() - t0:.1f} s")
    return 0
