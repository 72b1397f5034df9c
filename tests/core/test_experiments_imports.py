"""Every experiment script's imports resolve on this tree: each ``import m`` / ``from m import
name`` of experiments/<paper>/*.py (read with ast, so in-function imports count too) imports,
and each imported name exists. A move or rename in jaxcr/ that an experiment was not updated
for fails here, without running the experiment (issue 15: the results must reproduce after
the moves; experiments/REPRODUCED.md). Also: no script edits sys.path to reach the checkout
except the one listed, and none names an absolute checkout path."""

import ast
import importlib
from pathlib import Path

import pytest

EXPERIMENTS = Path(__file__).resolve().parents[2] / "experiments"
SCRIPTS = sorted(EXPERIMENTS.rglob("*.py"))
# optional extras the scripts handle being absent (open3d: the [bench] extra)
OPTIONAL = {"open3d"}
# scripts still editing sys.path, with the reason
SYS_PATH = {
    "scale/bench_scale.py": "imports tests.helpers.scale_data (make_segment_dataset) from the "
    "repository root",
    "segmentation/static_args_s34.py": "measures archived trees side by side (--tree "
    "NAME=PATH): each child puts its tree first",
}


def _edits_sys_path(tree) -> bool:
    """A call on sys.path (insert, append, extend, ...) or an assignment to it."""
    for n in ast.walk(tree):
        target = n.func if isinstance(n, ast.Call) else None
        if isinstance(n, (ast.Assign, ast.AugAssign)):
            targets = n.targets if isinstance(n, ast.Assign) else [n.target]
            if any(ast.unparse(t).startswith("sys.path") for t in targets):
                return True
        if target is not None and ast.unparse(target).startswith("sys.path."):
            return True
    return False


def _imports(tree):
    for n in ast.walk(tree):
        if isinstance(n, ast.Import):
            for a in n.names:
                yield a.name, []
        elif isinstance(n, ast.ImportFrom) and n.module and not n.level:
            yield n.module, [a.name for a in n.names]


@pytest.mark.parametrize(
    "path", SCRIPTS, ids=[p.relative_to(EXPERIMENTS).as_posix() for p in SCRIPTS]
)
def test_experiment_imports_resolve(path, monkeypatch):
    rel = path.relative_to(EXPERIMENTS).as_posix()
    source = path.read_text()
    # a script run as `python experiments/<paper>/x.py` has its folder first on sys.path
    monkeypatch.syspath_prepend(str(path.parent))
    missing = []
    tree = ast.parse(source, filename=rel)
    for module, names in _imports(tree):
        if module.split(".")[0] in OPTIONAL:
            continue
        try:
            mod = importlib.import_module(module)
        except ImportError as err:
            missing.append(f"import {module}: {err}")
            continue
        for name in names:
            if name == "*" or hasattr(mod, name):
                continue
            try:  # a submodule imported by name
                importlib.import_module(f"{module}.{name}")
            except ImportError:
                missing.append(f"from {module} import {name}")
    assert not missing, f"experiments/{rel}: {missing}"
    assert "/work/" not in source, f"experiments/{rel} names an absolute checkout path"
    if rel not in SYS_PATH:
        assert not _edits_sys_path(tree), f"experiments/{rel} edits sys.path"


def test_sys_path_list_is_current():
    for rel in SYS_PATH:
        tree = ast.parse((EXPERIMENTS / rel).read_text())
        assert _edits_sys_path(tree), f"{rel} no longer edits sys.path: remove it from SYS_PATH"


def test_checker_finds_a_missing_name_and_sys_path_edits():
    tree = ast.parse("import json\nfrom jaxcr.kinematics import no_such_name\n")
    found = list(_imports(tree))
    assert found == [("json", []), ("jaxcr.kinematics", ["no_such_name"])]
    assert not hasattr(importlib.import_module("jaxcr.kinematics"), "no_such_name")
    assert _edits_sys_path(ast.parse("import sys\nsys.path.insert(0, 'x')\n"))
    assert _edits_sys_path(ast.parse("import sys\nsys.path = ['x']\n"))
    assert not _edits_sys_path(ast.parse("import sys\nprint(sys.path)  # sys.path\n"))
