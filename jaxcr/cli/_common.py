"""CLI subcommands: one module per command (see ``jaxcr.cli``)."""


def seed(text: str) -> int:
    """argparse type of ``--seed``: a non-negative integer (numpy's generators reject negative
    seeds, which was a traceback deep inside numpy)."""
    import argparse

    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a non-negative integer, got {text!r}") from None
    from jaxcr.limits import MAX_SEED

    if value < 0:
        raise argparse.ArgumentTypeError(f"expected a non-negative integer, got {value}")
    if value > MAX_SEED:
        raise argparse.ArgumentTypeError(
            f"expected a non-negative integer <= {MAX_SEED}, got {value}"
        )
    return value


def check_robot_placed(ds, cams) -> None:
    """Refuse (InputError naming ``cameras.<c>.T_cam_robot``) a camera of the loaded dataset
    ``ds`` whose robot base sits exactly at its optical centre: ``T_cam_robot`` without
    translation, the default when a dataset never placed the robot (e.g. a stereo entry
    without ``T_rig_robot`` before ``jaxcr fit --fit-pose``). No robot is seen from there:
    ``segment`` failed its frames after the compile with "no data (every pixel is
    background)", ``fit --tips`` ran out of steps at hundreds of pixels (audit r31)."""
    from pathlib import Path

    import numpy as np

    from jaxcr.errors import InputError

    for c in cams:
        if not np.any(np.asarray(ds.cameras[c].T_cam_robot, np.float64)[:3, 3]):
            raise InputError(
                f"camera {c!r}: the robot's base is at the camera's optical centre "
                "(T_cam_robot has no translation: the robot was never placed in the cameras); "
                "give T_cam_robot (a stereo entry: T_rig_robot) or fit it: jaxcr fit DATASET "
                "--backbone FILE --in-camera NAME --fit-pose --frame ID "
                "(docs/your-own-rig.md, step 4)",
                file=str(Path(ds.root) / "dataset.json"),
                field=f"cameras.{c}.T_cam_robot",
            )


def check_writable_folder(path: str, what: str) -> None:
    """Create folder ``path`` if needed and check a file can be written there, before any
    long work (an InputError naming it otherwise)."""
    import os
    import tempfile

    from jaxcr.errors import InputError

    if os.path.exists(path) and not os.path.isdir(path):
        raise InputError(f"{what} exists and is not a folder", file=path)
    try:
        os.makedirs(path, exist_ok=True)
        with tempfile.TemporaryFile(dir=path):
            pass
    except OSError as err:
        raise InputError(f"{what} is not writable ({err.strerror or err})", file=path) from None
