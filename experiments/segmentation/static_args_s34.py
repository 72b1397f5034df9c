"""Does a changed numeric setting of ``RefineConfig`` compile the refinement again? (issue 18,
"static arguments minimised"; docs/decisions.md S34.) Trees side by side (``git archive``
folders or ``.``), each in processes of its own.

    python experiments/segmentation/static_args_s34.py --tree before=/tmp/x/before --tree after=.
        [--repeat 1] [--out experiments/results/segmentation/static_args_s34]

Per tree, three parts:

- ``frame``: one process, no persistent cache; ``refine_frame_jit`` on one 96x72 frame (one
  pyramid level) with a base config, then with ``g_reg``, ``ftol``, ``tau``, ``robust`` (> 0,
  then another > 0 scale), ``xtol`` and ``g_in`` changed in turn: per call the XLA compilations
  (``/jax/core/compile/backend_compile_duration`` events), their seconds, and the process CPU
  seconds of the call (``time.process_time``, both cores).
- ``stored``: one process, a fresh persistent cache; ``refine_batch(..., jit_call=cached_call)``
  (F = 2) with the base config, then ``g_reg`` changed, then ``ftol``: compilations and the
  stored traced programs written (``exported/*.jaxexport`` files) per call.
- ``cli``: ``jaxcr segment`` on the tiny 96x72 dataset of ``tests/cli/test_cli_segment.py`` in
  two processes sharing a fresh cache, the second with ``--prior-weight 5`` (``g_reg``): its
  ``compile_s`` (summary.json), new cache entries, wall and CPU seconds.

The outputs (refined coefficients, J, IoU against the true mask) of every call are saved and
compared between the trees.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

OUT = "experiments/results/segmentation/static_args_s34"
W, H = 96, 72


def _base_cfg():
    from jaxcr.segmentation.refine import RefineConfig

    return RefineConfig(
        n_coeffs=3, levels=(0,), steps=(20,), outer=(1,), tau=(0.8,), band_tiles=48,
        min_tiles=16, g_reg=0.5, local=False, camera_correction=False,
    )  # fmt: skip


def _variants():
    import dataclasses

    base = _base_cfg()
    return [
        ("base", base),
        ("g_reg", dataclasses.replace(base, g_reg=2.0)),
        ("ftol", dataclasses.replace(base, ftol=1e-3)),
        ("tau", dataclasses.replace(base, tau=(0.6,))),
        ("robust", dataclasses.replace(base, robust=2.0)),
        ("robust2", dataclasses.replace(base, robust=3.0)),
        ("xtol", dataclasses.replace(base, xtol=0.05)),
        ("g_in", dataclasses.replace(base, g_in=1.5)),
    ]


def _scene():
    import jax.numpy as jnp

    from jaxcr.segmentation.shape import perturbed_centreline
    from tests.helpers.tube_render import arc_base, front_camera, render_tube

    base = arc_base(2.5e-3)
    cam = front_camera(120.0, (W, H))
    true = jnp.asarray([[0.3, -0.1, 0.05], [0.0, 0.0, 0.0]], jnp.float32)
    img, mask = render_tube(perturbed_centreline(base, true), cam, 0, (W, H))
    bg = np.zeros((H, W), bool)  # the whole image is data (the red background is data too)
    return base, cam, jnp.asarray(img), jnp.asarray(bg), mask


class _Compiles:
    def __init__(self):
        import jax

        self.events = []
        jax.monitoring.register_event_duration_secs_listener(self._on)

    def _on(self, event, duration, **kw):
        if event == "/jax/core/compile/backend_compile_duration":
            self.events.append((kw.get("fun_name", "?"), duration))


def _out_record(res, mask) -> dict:
    m = np.asarray(res.masks[0]).reshape(-1, H, W)[0]
    inter, union = np.sum(m & mask), np.sum(m | mask)
    return {
        "coeffs": np.asarray(res.coeffs).reshape(-1, *np.shape(res.coeffs)[-2:])[0].tolist(),
        "J": float(np.asarray(res.energy.total).reshape(-1)[0]),
        "iou": float(inter / max(union, 1)),
        "num_steps": int(np.asarray(res.num_steps).reshape(-1)[0]),
    }


def child_frame() -> dict:
    from jaxcr.segmentation.refine import refine_frame_jit

    base, cam, img, bg, mask = _scene()
    rec = _Compiles()
    rows = []
    for name, cfg in _variants():
        n0, c0, t0 = len(rec.events), time.process_time(), time.perf_counter()
        res = refine_frame_jit(base, cam, img, bg, cfg)
        ev = rec.events[n0:]
        rows.append({"config": name, "compiles": len(ev),
                     "compile_s": round(sum(d for _, d in ev), 2),
                     "big": [f"{n}:{d:.1f}" for n, d in ev if d > 0.5],
                     "cpu_s": round(time.process_time() - c0, 2),
                     "wall_s": round(time.perf_counter() - t0, 2), **_out_record(res, mask)})  # fmt: skip
    return {"rows": rows}


def child_stored(cache: str) -> dict:
    import jax

    from jaxcr.io.compile_cache import enable_compile_cache
    from jaxcr.io.exported import cached_call
    from jaxcr.segmentation.refine import refine_batch

    enable_compile_cache(path=cache)
    base, cam, img, bg, mask = _scene()
    bases = jax.tree.map(lambda x: np.stack([x, x]), base)
    imgs, bgs = np.stack([img, img]), np.stack([bg, bg])
    rec = _Compiles()
    rows = []
    for name, cfg in _variants()[:3]:
        n0, c0 = len(rec.events), time.process_time()
        files0 = set(Path(cache).glob("exported/*.jaxexport"))
        res = refine_batch(bases, cam, imgs, bgs, cfg, jit_call=cached_call)
        ev = rec.events[n0:]
        new = sorted(
            p.name.rsplit("-", 1)[0] for p in set(Path(cache).glob("exported/*.jaxexport")) - files0
        )
        rows.append({"config": name, "compiles": len(ev),
                     "compile_s": round(sum(d for _, d in ev), 2),
                     "big": [f"{n}:{d:.1f}" for n, d in ev if d > 0.5],
                     "exported_new": new, "cpu_s": round(time.process_time() - c0, 2),
                     **_out_record(res, mask)})  # fmt: skip
    return {"rows": rows}


SEGMENT = ["--levels", "1", "--max-steps", "4", "--basis", "2", "--no-camera-correction",
           "--batch-size", "2", "--quiet", "--no-overlays"]  # fmt: skip


def _entries(folder: Path) -> set[str]:
    return {p.relative_to(folder).as_posix() for p in folder.rglob("*")
            if p.is_file() and not p.name.endswith("-atime")}  # fmt: skip


def run_cli(tree: Path, work: Path) -> dict:
    from tests.cli.test_cli_segment import make_dataset

    ds = work / "ds"
    if not ds.exists():
        make_dataset(ds)
    cache = work / f"cache_cli_{tree.name}_{time.time_ns()}"
    env = {**os.environ, "PYTHONPATH": str(tree.resolve()), "JAXCR_CACHE_DIR": str(cache),
           "JAX_PLATFORMS": "cpu"}  # fmt: skip
    env.pop("JAXCR_COMPILE_CACHE", None)
    rows = []
    for name, extra in (("default", []), ("prior-weight 5", ["--prior-weight", "5"])):
        out = work / f"seg_{time.time_ns()}"
        before = _entries(cache) if cache.exists() else set()
        load = os.getloadavg()[0]
        r0, t0 = resource.getrusage(resource.RUSAGE_CHILDREN), time.perf_counter()
        p = subprocess.run(
            [sys.executable, "-m", "jaxcr", "segment", str(ds), "-o", str(out), *SEGMENT, *extra],
            env=env,
            capture_output=True,
            text=True,
            cwd=tree,
        )  # fmt: skip  (cwd: `python -m` puts it first on sys.path)
        wall = time.perf_counter() - t0
        r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
        if p.returncode not in (0, 1):
            raise SystemExit(f"segment failed in {tree}: {p.stderr[-600:]}")
        summ = json.loads((out / "summary.json").read_text())
        new = _entries(cache) - before
        rows.append({"run": name, "compile_s": round(float(summ.get("compile_s", float("nan"))), 2),
                     "new_entries": len(new),
                     "new_exported": sorted(e.split("/")[1].rsplit("-", 1)[0] for e in new
                                            if e.startswith("exported/")),
                     "wall_s": round(wall, 2),
                     "cpu_s": round(r1.ru_utime - r0.ru_utime + r1.ru_stime - r0.ru_stime, 2),
                     "load": round(load, 2), "ok": summ.get("ok")})  # fmt: skip
    return {"rows": rows}


def _child(tree: Path, part: str, work: Path) -> dict:
    env = {**os.environ, "PYTHONPATH": str(tree.resolve()), "JAX_PLATFORMS": "cpu"}
    env["JAXCR_COMPILE_CACHE"] = "0"
    for k in ("JAX_COMPILATION_CACHE_DIR", "XLA_FLAGS"):
        env.pop(k, None)
    args = [sys.executable, str(Path(__file__).resolve()), "--child", part]
    if part == "stored":
        env.pop("JAXCR_COMPILE_CACHE")
        args += ["--cache", str(work / f"cache_stored_{time.time_ns()}")]
    load = os.getloadavg()[0]
    p = subprocess.run(args, env=env, capture_output=True, text=True, cwd=tree)
    if p.returncode != 0:
        raise SystemExit(f"{part} failed in {tree}: {p.stderr[-1500:]}")
    out = json.loads(p.stdout.strip().splitlines()[-1])
    out["load"] = round(load, 2)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tree", action="append", metavar="NAME=PATH")
    ap.add_argument("--parts", nargs="+", default=["frame", "stored", "cli"])
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--out", default=OUT)
    ap.add_argument("--child", default=None)
    ap.add_argument("--cache", default=None)
    a = ap.parse_args(argv)
    if a.child:
        sys.path.insert(0, os.getcwd())
        out = child_frame() if a.child == "frame" else child_stored(a.cache)
        print(json.dumps(out))
        return 0
    trees = [(t.split("=", 1)[0], Path(t.split("=", 1)[1]).resolve()) for t in a.tree]
    work = Path(tempfile.mkdtemp(prefix="static34_"))
    results = {"uptime": subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip(),
               "runs": []}  # fmt: skip
    for rep in range(a.repeat):
        for part in a.parts:
            for name, tree in trees:  # interleaved: part by part, tree by tree
                sys.path.insert(0, str(tree))
                r = run_cli(tree, work) if part == "cli" else _child(tree, part, work)
                sys.path.pop(0)
                r.update(tree=name, part=part, rep=rep)
                results["runs"].append(r)
                print(json.dumps(r), flush=True)
    results["uptime_end"] = subprocess.run(
        ["uptime"], capture_output=True, text=True
    ).stdout.strip()
    Path(a.out + ".json").parent.mkdir(parents=True, exist_ok=True)
    Path(a.out + ".json").write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
