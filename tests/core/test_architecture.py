"""The import rule of docs/ARCHITECTURE.md, checked on the source (ast, so in-function imports
and calls count too):

1. Nothing in the library (jaxcr/ outside jaxcr/cli/ and jaxcr/__main__.py) imports the CLI,
   experiments or tests.
2. Core modules (the jitted numerical core and the pure model code) import no cv2 and no
   jaxcr.io / jaxcr.cli, and access no files (open, np.load/np.save*, json.load/dump,
   Path.read_*/write_*, os.replace/remove/makedirs, mkdir, ...). Files, images, video and
   every file format live in jaxcr/io/ (and the CLI); drivers that read or write (the batch
   segmenter, the per-video motion driver, synth's dataset writers) are not core.

3. No library module prints (``print``, ``sys.stdout/stderr.write``, ``pprint``): results are
   returned as data and warnings go to the ``jaxcr`` logger, which the CLI prints on stderr
   (jaxcr.cli.main). The one exception is the progress reporter (:data:`PRINTS`).

Which modules are core is decided per package below; a module outside core is listed with the
reason, so a new module is core by default and this test fails if it does I/O.
"""

import ast
from pathlib import Path

import pytest

PKG = Path(__file__).resolve().parents[2] / "jaxcr"

CORE_PACKAGES = ("kinematics", "segmentation", "eigen", "stereo", "motion", "registration")
CORE_TOP = ("_types.py", "errors.py", "geometry.py", "camera.py", "colour.py", "_timing.py")
NOT_CORE = {
    # drivers and front doors that call io/ by design
    "segmentation/batch.py": "batch driver: reads frames and writes results through jaxcr.io",
    "segmentation/evaluate.py": "evaluation driver: reads segment outputs and ground truth",
    "motion/run.py": "per-video driver over a MotionDataset (jaxcr.io.motion_dataset)",
    "motion/api.py": "front door of motion/run.py (type-only import of the dataset)",
    "motion/batch.py": "writes one video's outputs and a batch's records (jaxcr.io)",
    # OpenCV as a numerical library on host numpy arrays, outside jit (not file I/O)
    "motion/flow.py": "OpenCV pyramidal Lucas-Kanade on a grid (the M-L paper's tracker)",
    "motion/baseline.py": "the paper's baseline: frame differencing + OpenCV grabCut",
    "motion/superpixels.py": "cv2.resize INTER_AREA for the working resolution (host side)",
    "registration/keypoints.py": "OpenCV ORB/ASIFT keypoints and descriptor matching",
    "registration/projective.py": "cv2.GaussianBlur of the intensity image (host side)",
    "registration/clouds.py": "cv2 box filters / min-max filters on depth images (host side)",
    "stereo/aruco.py": "OpenCV ArUco marker detection (the base frame)",
    "stereo/calibration.py": "OpenCV calibrateCamera/stereoCalibrate and target detectors",
    "stereo/base_locate.py": "OpenCV flood fill, Canny and Hough (paper's base detection)",
    "stereo/overlay.py": "drawing on images for the overlays (cv2 drawing primitives)",
    "stereo/pipeline.py": "end-to-end driver of one pair: cv2 morphology/projectPoints/fillPoly",
    "stereo/base_frame.py": "cv2.undistortPoints/projectPoints for the markerless base (host side)",
    "stereo/tip_consistency.py": "cv2.undistortPoints/projectPoints for the two views' tips (host side)",
    "stereo/single_view.py": "one-camera driver: cv2 projectPoints/morphology (host side)",
}

FILE_CALLS = {
    "open", "np.load", "numpy.load", "np.save", "np.savez", "np.savez_compressed", "np.loadtxt",
    "np.savetxt", "np.fromfile", "json.load", "json.dump", "os.replace", "os.remove",
    "os.makedirs", "os.rename", "os.listdir", "os.scandir", "shutil.rmtree", "shutil.copy",
    "shutil.copyfile", "shutil.move", "pickle.load", "pickle.dump",
}  # fmt: skip
FILE_METHODS = {"read_text", "read_bytes", "write_text", "write_bytes", "mkdir", "unlink",
                "iterdir", "glob", "rglob", "imread", "imwrite", "VideoCapture"}  # fmt: skip


# library modules allowed to write to the terminal, with the reason
PRINTS = {
    "progress.py": "the progress reporter: the progress lines on stderr (or the caller's "
    "file; JAXCR_PROGRESS=off or silent=True turns them off), as tqdm does",
}
PRINT_CALLS = {"print", "pprint", "pprint.pprint", "sys.stdout.write", "sys.stderr.write",
               "sys.__stdout__.write", "sys.__stderr__.write"}  # fmt: skip


def _dotted(node):
    if isinstance(node, ast.Name):
        return node.id
    if isinstance(node, ast.Attribute):
        base = _dotted(node.value)
        return f"{base}.{node.attr}" if base else None
    return None


def _imports(tree):
    for n in ast.walk(tree):
        if isinstance(n, ast.Import):
            yield from (a.name for a in n.names)
        elif isinstance(n, ast.ImportFrom) and not n.level:
            yield n.module or ""


def _file_access(tree):
    for n in ast.walk(tree):
        if isinstance(n, ast.Call):
            name = _dotted(n.func)
            if name in FILE_CALLS:
                yield name
            elif isinstance(n.func, ast.Attribute) and n.func.attr in FILE_METHODS:
                yield f".{n.func.attr}()"


def _prints(tree):
    for n in ast.walk(tree):
        if isinstance(n, ast.Call) and _dotted(n.func) in PRINT_CALLS:
            yield f"{_dotted(n.func)}() line {n.lineno}"


def _modules():
    return sorted(p.relative_to(PKG).as_posix() for p in PKG.rglob("*.py"))


def _core_modules():
    core = [m for m in _modules() if m in CORE_TOP]
    for pkg in CORE_PACKAGES:
        core += [m for m in _modules() if m.startswith(f"{pkg}/") and m not in NOT_CORE]
    return core


def _parse(rel):
    return ast.parse((PKG / rel).read_text(), filename=rel)


@pytest.mark.parametrize("rel", [m for m in _modules() if not m.startswith("cli/")])
def test_library_does_not_import_cli_experiments_or_tests(rel):
    if rel == "__main__.py":  # `python -m jaxcr` is the CLI's entry point
        return
    for mod in _imports(_parse(rel)):
        top = mod.split(".")
        assert not (top[0] == "jaxcr" and len(top) > 1 and top[1] in ("cli", "commands")), (
            f"jaxcr/{rel} imports {mod}"
        )
        assert top[0] not in ("experiments", "tests", "benchmarks"), f"jaxcr/{rel} imports {mod}"


@pytest.mark.parametrize("rel", _core_modules())
def test_core_has_no_cv2_io_or_file_access(rel):
    tree = _parse(rel)
    bad = [m for m in _imports(tree) if m.split(".")[0] == "cv2" or m.startswith("jaxcr.io")]
    bad += list(_file_access(tree))
    assert not bad, f"jaxcr/{rel} (core) uses {sorted(set(bad))}; move it to jaxcr/io/"


@pytest.mark.parametrize(
    "rel", [m for m in _modules() if not m.startswith("cli/") and m != "__main__.py"]
)
def test_library_does_not_print(rel):
    if rel in PRINTS:
        assert list(_prints(_parse(rel))), f"{rel} prints nothing now: remove it from PRINTS"
        return
    found = list(_prints(_parse(rel)))
    assert not found, (
        f"jaxcr/{rel} prints ({found}): return the data, or warn on the jaxcr logger "
        "(logging.getLogger(__name__)); the CLI prints"
    )


def test_exception_list_is_current():
    """Every NOT_CORE entry exists and really needs its exception (a module that became clean
    leaves the list, so the list only shrinks)."""
    for rel in NOT_CORE:
        assert (PKG / rel).exists(), rel
        tree = _parse(rel)
        uses = [m for m in _imports(tree) if m.split(".")[0] == "cv2" or m.startswith("jaxcr.io")]
        assert uses or list(_file_access(tree)), f"{rel} is clean now: remove it from NOT_CORE"


def test_checker_finds_violations():
    # the checker itself: each kind of violation in a snippet is reported
    snippet = ast.parse(
        "import cv2\nfrom jaxcr.io.images import read_image\n"
        "def f(p):\n    import json\n    with open(p) as fh:\n        return json.load(fh)\n"
        "def g(p):\n    return p.read_text(), np.load(p)\n"
    )
    assert [m for m in _imports(snippet) if m in ("cv2", "jaxcr.io.images")] == [
        "cv2",
        "jaxcr.io.images",
    ]
    assert sorted(_file_access(snippet)) == [".read_text()", "json.load", "np.load", "open"]
    printing = ast.parse("import sys\nprint(1)\nsys.stderr.write('x')\nlog.warning('y')\n")
    assert [p.split("(")[0] for p in _prints(printing)] == ["print", "sys.stderr.write"]
