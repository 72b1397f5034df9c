"""The public API (``import jaxcr as jcr``): every name resolves and is documented, optional
arguments are keyword-only (as dm_pix's api_test.py enforces), ``import jaxcr`` stays cheap,
and the new entry points agree with the functions they front."""

import ast
import inspect
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import jaxcr as jcr

# the subpackage entry points a notebook uses, beside the flat names of jaxcr.__all__
SUBPACKAGE_API = [
    ("stereo", "reconstruct"),
    ("eigen", "train"),
    ("eigen", "query"),
    ("eigen", "estimate"),
    ("motion", "segment"),
    ("registration", "register_pair"),
]


def _public_callables():
    for name in jcr.__all__:
        obj = getattr(jcr, name)
        if inspect.isfunction(obj):
            yield f"jcr.{name}", obj
    for pkg, name in SUBPACKAGE_API:
        yield f"jcr.{pkg}.{name}", getattr(getattr(jcr, pkg), name)


def test_all_names_resolve_and_are_documented():
    assert set(jcr.__all__) == set(jcr._NAMES) | set(jcr._SUBPACKAGES)
    for name in jcr.__all__:
        obj = getattr(jcr, name)
        if name == "TEST_CTR":
            assert obj["kind"] == "ctr"
            continue
        assert inspect.getdoc(obj), name
    for pkg, name in SUBPACKAGE_API:
        assert name in getattr(jcr, pkg).__all__, (pkg, name)
        assert inspect.getdoc(getattr(getattr(jcr, pkg), name)), (pkg, name)
    with pytest.raises(AttributeError):
        jcr.no_such_name  # noqa: B018


# ids are the public names only: a function's repr carries its address, which differs
# between pytest-xdist workers and makes them collect different tests
_CALLABLES = list(_public_callables())


@pytest.mark.parametrize("label,fn", _CALLABLES, ids=[label for label, _ in _CALLABLES])
def test_optional_arguments_are_keyword_only(label, fn):
    for p in inspect.signature(fn).parameters.values():
        if p.default is not inspect.Parameter.empty:
            assert p.kind is inspect.Parameter.KEYWORD_ONLY, f"{label}({p.name}=...) is positional"


def test_import_is_cheap():
    # a notebook's first line must not pay for JAX, OpenCV or matplotlib
    code = "import sys, jaxcr; print(sorted(m for m in ('jax', 'cv2', 'matplotlib') if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


#: the robot and chunk of tests/scale/test_ray_equality.py's `jaxcr fk --chunk 2` (also
#: tests/cli/test_cli_fk.py's robot): jcr.forward below runs the very same compiled batch
#: program (run_chunk, 2 rows of this 9-sample robot), so it loads it from the run's
#: compilation cache instead of compiling its own (the default 64 samples made another)
SS = {"kind": "single_segment", "length": 0.04, "radius": 0.002, "n_points": 9}


def test_forward_matches_a_loop_and_gives_reasons():
    """jcr.forward == a Python loop of model.forward (same float32 arithmetic per row, so equal
    to float32 rounding of the batched vs unbatched XLA kernels: 1e-6 m on 0.04 m), with the
    failure reason of a non-finite row as data and the padded last chunk discarded."""
    import equinox as eqx

    robot = jcr.robot_from_dict(SS)
    rng = np.random.default_rng(0)
    q = rng.uniform(-0.8, 0.8, (5, robot.n_joints))
    q[3] = np.nan
    fk = jcr.forward(robot, q, chunk=2)  # chunks 2, 2, 1 (padded)
    assert isinstance(fk, jcr.BatchFk)
    assert fk.p.shape == (5, robot.n_points, 3) and fk.ok.shape == (5,)
    one = eqx.filter_jit(lambda m, qi: m.forward(qi))
    for i in (0, 1, 2, 4):
        ref = one(robot, q[i].astype(np.float32))
        np.testing.assert_allclose(fk.p[i], np.asarray(ref.centreline.p), atol=1e-6)
        assert fk.ok[i] and fk.reasons[i] == ""
    assert not fk.ok[3] and fk.reasons[3] == "non-finite joint values"


def test_stereo_result_fields_cover_reconstruct_pair():
    """StereoReconstruction names every key reconstruct_pair returns (read from its source,
    so a key added there without a field here fails this test instead of landing in extra)."""
    from jaxcr.stereo import api, pipeline

    tree = ast.parse(Path(pipeline.__file__).read_text())
    fn = next(
        n for n in tree.body if isinstance(n, ast.FunctionDef) and n.name == "reconstruct_pair"
    )
    ret = [n for n in ast.walk(fn) if isinstance(n, ast.Return) and isinstance(n.value, ast.Dict)]
    keys = {k.value for r in ret for k in r.value.keys}
    fields = {f for f in api.StereoReconstruction.__dataclass_fields__} - {"extra"}
    assert keys and keys == fields


def test_enable_compile_cache_returns_the_folder(tmp_path, monkeypatch):
    import jax

    before = jax.config.jax_compilation_cache_dir
    try:
        assert jcr.enable_compile_cache(path=tmp_path / "c") == os.fspath(tmp_path / "c")
        assert jax.config.jax_compilation_cache_dir == os.fspath(tmp_path / "c")
        monkeypatch.delenv("JAXCR_CACHE_DIR", raising=False)  # the test run sets it (conftest)
        monkeypatch.setenv("JAXCR_JAX_CACHE", "")
        assert jcr.enable_compile_cache() is None
    finally:
        jax.config.update("jax_compilation_cache_dir", before)


# ---------------------------------------------------------------- docstrings (numpydoc style)


def _documented_objects():
    """Every public object with a docstring of its own: the flat names (TEST_CTR is a dict,
    documented in jaxcr's module docstring) and the subpackage entry points."""
    for name in sorted(jcr._NAMES):
        if name != "TEST_CTR":
            yield f"jcr.{name}", getattr(jcr, name)
    for pkg, name in SUBPACKAGE_API:
        yield f"jcr.{pkg}.{name}", getattr(getattr(jcr, pkg), name)


_DOCUMENTED = list(_documented_objects())


def _sections(doc: str) -> list[str]:
    """numpydoc section headers: a line followed by a dashed underline of its length."""
    lines = doc.splitlines()
    return [
        a.strip()
        for a, b in zip(lines, lines[1:], strict=False)
        if a.strip() and set(b.strip()) == {"-"} and len(b.strip()) == len(a.strip())
    ]


@pytest.mark.parametrize("label,obj", _DOCUMENTED, ids=[label for label, _ in _DOCUMENTED])
def test_public_docstrings_have_numpydoc_sections(label, obj):
    """scikit-image / numpydoc reference style: functions document Parameters, Returns and
    Examples; classes their constructor Parameters or their Attributes, and Examples. An
    Examples section holds at least one doctest line (run by the next test)."""
    doc = inspect.getdoc(obj)
    assert doc, label
    sections = _sections(doc)
    if inspect.isclass(obj):
        assert {"Parameters", "Attributes"} & set(sections), (label, sections)
    else:
        assert {"Parameters", "Returns"} <= set(sections), (label, sections)
    assert "Examples" in sections, (label, sections)
    assert ">>> " in doc.split("Examples\n--------", 1)[1], label
    # every parameter of a function is documented by name
    if not inspect.isclass(obj):
        params = doc.split("Parameters\n----------", 1)[1].split("\n\n", 1)[0]
        documented = {n.strip() for line in params.splitlines() if not line.startswith(" ")
                      for n in line.split(" : ")[0].split(",")}  # fmt: skip
        assert set(inspect.signature(obj).parameters) <= documented, (label, documented)


def test_public_docstring_examples_run():
    """The Examples of the public names and the subpackage entry points run as doctests and
    print what they show. Steps that compile for minutes (a refinement, the stereo and
    motion pipelines, the ICP) are marked +SKIP; examples/ runs the refinement and stereo
    steps (tests/core/test_examples.py); each entry point's example still calls it on a
    cheap path (a failure reason, an option check) or runs it whole (eigen)."""
    import doctest

    finder = doctest.DocTestFinder(recurse=False)
    runner = doctest.DocTestRunner(optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    ran = 0
    for label, obj in _DOCUMENTED:
        for test in finder.find(obj, label, globs={}):
            report: list[str] = []
            result = runner.run(test, out=report.append)
            assert result.failed == 0, "".join(report)
            ran += result.attempted
    assert ran >= 20  # the cheap examples did run (not all skipped)
