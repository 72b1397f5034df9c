"""Issue 17's contract audit (items 1-8), run as a new user would: the ``jaxcr`` CLI of this
checkout in subprocesses, in a scratch folder, over adversarial cases grouped by the issue's
items. Not part of the pytest suite (it takes minutes of CPU: compiles, Ctrl-C and resumes).

    python experiments/contract_audit.py [--only 1,3] [--scratch DIR] [--report FILE.md]

Each case records the command, what the contract expects, the exit code, the number of stderr
lines and whether it held. Items:

1. Ctrl-C (SIGINT a delay after OUT's lock appears) of every long command: exit 130 with the
   line ``jaxcr CMD: interrupted``, no SIGSEGV (139), the lock released, and the rerun
   (``--resume`` where the command has it) finishes with the outputs of an uninterrupted run
   (byte-identical images/arrays where the command promises it: seeded generators, segment,
   stereo).
2. OUT protection: foreign files, another command's OUT, a live lock (refusal names pid, host,
   start), a stale lock (taken over), leftovers ``.tmp`` of a kill -9 (cleaned by the rerun),
   two concurrent runs (exactly one wins, no duplicate records).
3. Limits: huge sizes, counts, levels, 1e308 joint values, NaN obstacles, ``--max-rms nan``,
   LEFT == RIGHT in calibrate: exit 2 with one line, nothing written.
4. evaluate: non-finite centreline, malformed ``files``, incomplete run: exit 1 with the count.
5. manifold train/query with one corrupt image: that frame failed, exit 1.
6. Stray output: no native/Python warnings, bad usage one line + "see ... --help",
   ``--preview`` into a read-only folder refused first, a full disk names the file (a tiny
   tmpfs when this process may mount one, else RLIMIT_FSIZE).
7. No writes outside OUT: the working directory, TMPDIR and the checkout's git folder are
   unchanged by every command.
8. ``np.load`` with ``allow_pickle=False`` everywhere (static, per call) and pickled inputs
   refused with one line.

Every run is also checked for the generic contract: no traceback, no crash signal, no stray
warning lines, one stderr line on exit 2. The report (Markdown) has one row per case.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import re
import resource
import shlex
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

STRAY = re.compile(
    r"Warning:|libpng|libjpeg|JPEG data|Premature end|Corrupt JPEG|^[WEI]\d{4} |absl|"
    r"Exception ignored|Segmentation fault|core dumped",
    re.M,
)
#: outputs compared byte for byte between an interrupted-and-rerun run and a clean one
COMPARED = {".png", ".npy", ".ply", ".csv", ".npz"}
#: files that hold times, dates, paths or pids, not results
VOLATILE = {
    "run.json",
    "summary.json",
    "report.md",
    "report.json",
    "DONE",
    ".jaxcr-out.json",
    "summary.md",
    "timings.csv",
    "table2.md",
    "results.jsonl",
    "frames.jsonl",
    "estimates.jsonl",
    "estimates.csv",
    "dataset.json",
    "stereo.json",
    "poses.csv",
}


class Audit:
    def __init__(self, scratch: Path):
        self.S = scratch
        self.rows: list[dict] = []
        self.fx: dict[str, Path] = {}
        self.tmp = scratch / "tmpdir"
        self.tmp.mkdir(parents=True, exist_ok=True)
        self.n = 0
        self.cpu0 = self._cpu()

    @staticmethod
    def _cpu() -> float:
        r = resource.getrusage(resource.RUSAGE_CHILDREN)
        return r.ru_utime + r.ru_stime

    # ----------------------------------------------------------------------------- running
    def env(self) -> dict:
        env = dict(os.environ)
        env["PYTHONPATH"] = str(REPO) + (
            os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else ""
        )
        env["TMPDIR"] = str(self.tmp)
        env.pop("PYTHONWARNINGS", None)
        return env

    def cmd(self, argv) -> list[str]:
        return [sys.executable, "-m", "jaxcr", *map(str, argv)]

    def popen(self, argv, cwd=None, preexec=None):
        return subprocess.Popen(
            self.cmd(argv),
            cwd=cwd or self.S,
            env=self.env(),
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            preexec_fn=preexec,
        )

    def run(self, argv, cwd=None, timeout=1800, preexec=None):
        p = self.popen(argv, cwd, preexec)
        try:
            out, err = p.communicate(timeout=timeout)
        except subprocess.TimeoutExpired:
            p.kill()
            out, err = p.communicate()
            err += "\n[audit: timeout]"
        return p.returncode, out, err

    def show(self, argv) -> str:
        return " ".join(shlex.quote(str(a)) for a in argv).replace(str(self.S), "$S")

    # ----------------------------------------------------------------------------- judging
    def record(self, item, case, argv, expected, rc, err, problems, note=""):
        lines = [ln for ln in err.strip().splitlines() if ln.strip()]
        held = not problems
        self.rows.append(
            dict(
                item=item,
                case=case,
                command=self.show(argv),
                expected=expected,
                rc=rc,
                err_lines=len(lines),
                held=held,
                note="; ".join(problems) if problems else note,
            )
        )
        self.n += 1
        mark = "held" if held else "BROKEN"
        print(
            f"[{self.n:3d}] item {item} {case}: exit {rc}, {len(lines)} stderr line(s): {mark}"
            + ("" if held else f" -- {'; '.join(problems)[:300]}"),
            flush=True,
        )
        return held

    @staticmethod
    def generic(rc, err, expect, one_line=True, must=()):
        probs = []
        if rc is None or rc < 0 or rc in (134, 137, 139):
            probs.append(f"crashed (exit {rc})")
        elif rc not in expect:
            probs.append(f"exit {rc}, expected {'/'.join(map(str, expect))}")
        if "Traceback" in err:
            probs.append("traceback")
        m = STRAY.search(err)
        if m:
            probs.append(f"stray stderr: {err[max(0, m.start() - 40) : m.end() + 40]!r}")
        lines = [ln for ln in err.strip().splitlines() if ln.strip()]
        if rc == 2 and one_line and len(lines) != 1:
            probs.append(f"{len(lines)} stderr lines on exit 2: {lines[:3]}")
        last = lines[-1] if lines else ""
        for s in must:
            if s.lower() not in err.lower():
                probs.append(f"stderr lacks {s!r} (last line: {last[:160]!r})")
        return probs

    def case(
        self,
        item,
        case,
        argv,
        expect=(2,),
        must=(),
        check=None,
        cwd=None,
        one_line=True,
        preexec=None,
        timeout=1800,
    ):
        rc, out, err = self.run(argv, cwd=cwd, preexec=preexec, timeout=timeout)
        probs = self.generic(rc, err, expect, one_line, must)
        if check is not None:
            try:
                extra = check(rc, out, err)
            except Exception as e:  # noqa: BLE001 - a check that cannot run is a broken case
                extra = [f"check failed: {type(e).__name__}: {e}"]
            probs += extra or []
        lines = err.strip().splitlines()
        return self.record(
            item,
            case,
            argv,
            "/".join(map(str, expect)),
            rc,
            err,
            probs,
            note=(lines[-1][:140] if lines else ""),
        )

    # ----------------------------------------------------------------------------- fixtures
    def fixture(self, name: str) -> Path:
        if name in self.fx:
            return self.fx[name]
        S = self.S / "fx"
        S.mkdir(exist_ok=True)
        p = S / name
        build = FIXTURES[name](self, p)
        if build is not None and not p.exists():
            rc, _, err = self.run(build)
            if rc not in (0, 1) or not p.exists():
                raise SystemExit(f"fixture {name} failed: exit {rc}: {err[-2000:]}")
        self.fx[name] = p
        return p

    def copy(self, name: str, dst: str) -> Path:
        d = self.S / "w" / dst
        if d.exists():
            shutil.rmtree(d)
        d.parent.mkdir(parents=True, exist_ok=True)
        src = self.fixture(name)
        if src.is_dir():
            shutil.copytree(src, d)
        else:
            shutil.copy2(src, d)
        return d

    def fresh(self, dst: str) -> Path:
        d = self.S / "w" / dst
        if d.exists():
            shutil.rmtree(d)
        d.parent.mkdir(parents=True, exist_ok=True)
        return d


def synth_argv(out, size: str, frames: int) -> list:
    """``jaxcr synth`` of the orthogonal preset into ``out``."""
    return ["synth", "--preset", "orthogonal", "--size", size, "--frames", str(frames), "-o", out]


def calibrate_argv(left, right) -> list:
    """``jaxcr calibrate`` of the audit's 6 x 5 chessboards (10 mm pitch), LEFT and RIGHT."""
    return ["calibrate", left, right, "--cols", "6", "--rows", "5", "--pitch", "0.01"]


SEG_FAST = ["--levels", "1", "--max-steps", "4", "--batch-size", "2", "--no-uncertainty", "--quiet"]

FIXTURES = {
    "syn": lambda a, p: [
        *synth_argv(p, "64x48", 4),
        "--quiet",
    ],
    "segout": lambda a, p: ["segment", a.fixture("syn"), "-o", p, *SEG_FAST],
    "ster": lambda a, p: ["stereo", "synth", "--size", "64x48", "--frames", "2", "-o", p],
    "ster12": lambda a, p: ["stereo", "synth", "--size", "128x96", "--frames", "12", "-o", p],
    "sterout": lambda a, p: ["stereo", a.fixture("ster"), "-o", p],
    "mot": lambda a, p: ["motion", "synth", "--size", "64x48", "--frames", "6", "-o", p],
    "motout": lambda a, p: ["motion", a.fixture("mot"), "-o", p],
    "mo": lambda a, p: ["model-object", "synth", "--size", "64x48", "-o", p],
    "moout": lambda a, p: ["model-object", a.fixture("mo"), "-o", p],
    "man": lambda a, p: ["manifold", "synth", "--size", "64x48", "--frames", "12", "-o", p],
    "man.npz": lambda a, p: [
        "manifold",
        "train",
        a.fixture("man"),
        "-o",
        p,
        "--bins",
        "24",
        "--step",
        "0.05",
    ],
    "mq": lambda a, p: ["manifold", "query", a.fixture("man.npz"), a.fixture("man"), "-o", p],
    "q.csv": lambda a, p: write_q(a.fixture("syn"), p),
    "fkout": lambda a, p: ["fk", a.fixture("syn"), a.fixture("q.csv"), "-o", p],
}


def write_q(syn: Path, p: Path):
    """200 joint vectors around the synthetic dataset's frames (a Python-made input)."""
    import numpy as np

    frames = json.loads((syn / "dataset.json").read_text())["frames"]
    q = np.array([f["q"] for f in frames], float)
    rows = q[np.arange(200) % len(q)] * (1 + 0.01 * np.linspace(-1, 1, 200)[:, None])
    p.write_text("\n".join(",".join(f"{v:.9g}" for v in r) for r in rows) + "\n")


def tree(d: Path, only_results=False) -> dict[str, str]:
    """Relative path -> sha1 of every file under ``d`` (or of the result files only)."""
    out = {}
    if not d.exists():
        return out
    for f in sorted(d.rglob("*")):
        if f.is_file():
            if only_results and (f.suffix not in COMPARED or f.name in VOLATILE):
                continue
            out[str(f.relative_to(d))] = hashlib.sha1(f.read_bytes()).hexdigest()
    return out


def watch_lock(lock: Path, procs) -> tuple[dict[int, float], dict[int, float]]:
    """Poll ``lock`` while ``procs`` run: {holder pid: first time seen}, {pid: exit time}."""
    holders: dict[int, float] = {}
    ended: dict[int, float] = {}
    t0 = time.monotonic()  # the outputs are small; a guard against a full pipe all the same
    while len(ended) < len(procs) and time.monotonic() - t0 < 600:
        now = time.monotonic()
        try:
            pid = json.loads(lock.read_text())["pid"]
            holders.setdefault(pid, now)
        except (OSError, ValueError, KeyError, TypeError):
            pass
        for p in procs:
            if p.pid not in ended and p.poll() is not None:
                ended[p.pid] = now
        time.sleep(0.01)
    return holders, ended


def sleeper():
    return subprocess.Popen([sys.executable, "-c", "import time; time.sleep(600)"])


def dead_pid() -> int:
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


def write_lock(out: Path, pid: int, command: str, started="2026-12-01T20:00:00+00:00"):
    out.mkdir(parents=True, exist_ok=True)
    pid_start = None
    try:
        pid_start = int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[19])
    except (OSError, IndexError, ValueError):
        pass
    (out / ".jaxcr.lock").write_text(
        json.dumps(
            {
                "format": "jaxcr.lock/1",
                "command": command,
                "pid": pid,
                "host": socket.gethostname(),
                "pid_start": pid_start,
                "started": started,
                "argv": ["jaxcr", command],
            }
        )
    )


# ================================================================================= the items
#: long-running commands: (label, argv for OUT, how to rerun, promised byte-identical)
def long_commands(a: Audit):
    return [
        (
            "synth",
            lambda o: [
                *synth_argv(o, "96x72", 24),
            ],
            [],
            True,
        ),
        (
            "stereo synth",
            lambda o: ["stereo", "synth", "--size", "96x72", "--frames", "12", "-o", o],
            [],
            True,
        ),
        ("stereo", lambda o: ["stereo", a.fixture("ster12"), "-o", o], [], True),
        (
            "motion synth",
            lambda o: ["motion", "synth", "--size", "96x72", "--frames", "16", "-o", o],
            [],
            True,
        ),
        ("motion", lambda o: ["motion", a.fixture("mot"), "-o", o], [], False),
        (
            "model-object synth",
            lambda o: ["model-object", "synth", "--size", "640x480", "-o", o],
            [],
            True,
        ),
        ("model-object", lambda o: ["model-object", a.fixture("mo"), "-o", o], [], False),
        (
            "segment",
            lambda o: ["segment", a.fixture("syn"), "-o", o, *SEG_FAST],
            ["--resume"],
            True,
        ),
        (
            "manifold synth",
            lambda o: ["manifold", "synth", "--size", "48x36", "--frames", "40", "-o", o],
            ["--overwrite"],
            True,
        ),
        (
            "manifold query",
            lambda o: ["manifold", "query", a.fixture("man.npz"), a.fixture("man"), "-o", o],
            [],
            False,
        ),
        ("fk", lambda o: ["fk", a.fixture("syn"), a.fixture("q.csv"), "-o", o], [], True),
    ]


def first_result(out: Path) -> bool:
    """A result file with content in OUT (an image, array or a per-item log line)."""
    if not out.exists():
        return False
    for f in out.rglob("*"):
        if (f.suffix in COMPARED or f.suffix == ".jsonl") and not f.name.endswith(".tmp"):
            try:
                if f.stat().st_size > 0:
                    return True
            except OSError:
                pass
    return False


def item1(a: Audit):
    for label, mk, rerun_extra, promised in long_commands(a):
        ref = a.fresh(f"i1/{label.replace(' ', '_')}_ref")
        rc, _, err = a.run(mk(ref))
        if rc not in (0, 1):
            a.record(
                1,
                f"{label}: reference run",
                mk(ref),
                "0/1",
                rc,
                err,
                [f"reference run exit {rc}: {err.strip().splitlines()[-1:]}"],
            )
            continue
        for when in ("0.5 s after the lock", "0.2 s after the first result file"):
            delay = 0.5 if "lock" in when else 0.2
            out = a.fresh(f"i1/{label.replace(' ', '_')}_{when.split()[4]}")
            argv = mk(out)
            p = a.popen(argv)
            t0 = time.monotonic()
            lock = out / ".jaxcr.lock"
            lock_seen = False
            while p.poll() is None and time.monotonic() - t0 < 900:
                lock_seen = lock_seen or lock.exists()
                if "lock" in when and lock_seen:
                    break
                if "result" in when and first_result(out):
                    break
                time.sleep(0.02)
            time.sleep(delay)
            # the lock is released when the work is done, before the interpreter's (slow,
            # under load) teardown: a signal then finds a complete run, and exit 0 is the truth
            finished_first = p.poll() is not None or (lock_seen and not lock.exists())
            if not finished_first:
                p.send_signal(signal.SIGINT)
                t_sig = time.monotonic()
            try:
                _, err = p.communicate(timeout=60)
            except subprocess.TimeoutExpired:
                p.kill()
                _, err = p.communicate()
                err += "\n[audit: no exit 60 s after SIGINT]"
            rc = p.returncode
            case = f"{label}: SIGINT {when}"
            if not finished_first and rc == 0 and time.monotonic() - t_sig < 0.5:
                # the work was done and the process on its way out as the signal came: a
                # complete run that says so is the truth, not a swallowed Ctrl-C
                finished_first = "interrupted" not in err
            if finished_first:
                a.rows.append(
                    dict(
                        item=1,
                        case=case,
                        command=a.show(argv),
                        expected="130",
                        rc=rc,
                        err_lines=len(err.strip().splitlines()),
                        held=None,
                        note="finished before the signal: not counted",
                    )
                )
                print(f"[---] item 1 {case}: finished first, not counted", flush=True)
                continue
            probs = a.generic(rc, err, (130,), one_line=False)
            last = (err.strip().splitlines() or [""])[-1]
            if rc == 130 and not (
                last.startswith(f"jaxcr {label.split()[0]}") and last.endswith(": interrupted")
            ):
                probs.append(f"last line {last!r}")
            if rc == 130 and time.monotonic() - t_sig > 30:
                probs.append("took > 30 s to stop")
            if lock.exists():
                probs.append("lock left behind")
            a.record(1, case, argv, "130", rc, err, probs)
            # the rerun finishes and gives the clean run's results
            argv2 = [*argv, *rerun_extra]
            rc2, _, err2 = a.run(argv2)
            probs = a.generic(rc2, err2, (0, 1), one_line=False)
            note = ""
            if rc2 in (0, 1):
                diff = {}
                A, B = tree(ref, True), tree(out, True)
                for k in set(A) | set(B):
                    if A.get(k) != B.get(k):
                        diff[k] = (k in A, k in B)
                if diff and promised:
                    probs.append(
                        f"{len(diff)} result file(s) differ from a clean run, e.g. "
                        f"{sorted(diff)[:3]}"
                    )
                note = (
                    f"{len(diff)} differ (not promised)"
                    if diff and not promised
                    else f"{len(A)} result files identical"
                )
            left = [str(f.relative_to(out)) for f in out.rglob("*.tmp")]
            if left:
                probs.append(f"temporary files left: {left[:3]}")
            if (out / ".jaxcr.lock").exists():
                probs.append("lock left behind after the rerun")
            a.record(
                1,
                f"{label}: rerun after SIGINT {when}"
                + (" (byte-identical promised)" if promised else ""),
                argv2,
                "0/1 + same",
                rc2,
                err2,
                probs,
                note=note if rc2 in (0, 1) else "",
            )


def writers(a: Audit):
    """Every command that writes an OUT folder: (label, argv for OUT, cheap?)."""
    return [
        (
            "synth",
            lambda o: [
                *synth_argv(o, "64x48", 2),
                "--quiet",
            ],
            True,
        ),
        (
            "stereo synth",
            lambda o: ["stereo", "synth", "--size", "64x48", "--frames", "2", "-o", o],
            True,
        ),
        ("stereo", lambda o: ["stereo", a.fixture("ster"), "-o", o], True),
        (
            "motion synth",
            lambda o: ["motion", "synth", "--size", "64x48", "--frames", "6", "-o", o],
            True,
        ),
        ("motion", lambda o: ["motion", a.fixture("mot"), "-o", o], True),
        (
            "model-object synth",
            lambda o: ["model-object", "synth", "--size", "32x24", "-o", o],
            True,
        ),
        ("model-object", lambda o: ["model-object", a.fixture("mo"), "-o", o], False),
        ("segment", lambda o: ["segment", a.fixture("syn"), "-o", o, *SEG_FAST], True),
        (
            "manifold synth",
            lambda o: ["manifold", "synth", "--size", "32x24", "--frames", "4", "-o", o],
            True,
        ),
        (
            "manifold query",
            lambda o: ["manifold", "query", a.fixture("man.npz"), a.fixture("man"), "-o", o],
            True,
        ),
        ("fk", lambda o: ["fk", a.fixture("syn"), a.fixture("q.csv"), "-o", o], True),
        ("demo", lambda o: ["demo", "-o", o, "--frames", "1", "--size", "64x48"], False),
        ("evaluate -o", lambda o: ["evaluate", a.fixture("segout"), "-o", o, "--no-plot"], True),
    ]


def unchanged(d: Path, before: dict):
    def check(rc, out, err):
        after = tree(d)
        after.pop(".jaxcr.lock", None)
        b = dict(before)
        b.pop(".jaxcr.lock", None)
        if after != b:
            ch = sorted(k for k in set(after) | set(b) if after.get(k) != b.get(k))
            return [f"OUT changed: {ch[:4]}"]
        return []

    return check


def item2(a: Audit):
    host = socket.gethostname()
    W = writers(a)
    for label, mk, cheap in W:
        key = label.replace(" ", "_")
        # foreign files
        out = a.fresh(f"i2/{key}_foreign")
        (out / "images" / "main").mkdir(parents=True)
        (out / "images" / "main" / "000.png").write_bytes(b"user's own picture")
        (out / "notes.txt").write_text("my notes\n")
        a.case(
            2,
            f"{label}: OUT holds a user's files",
            mk(out),
            must=(),
            check=unchanged(out, tree(out)),
        )
        # another command's OUT
        other = "sterout" if label == "segment" else "segout"
        out = a.copy(other, f"i2/{key}_other")
        a.case(
            2,
            f"{label}: OUT is another command's ({other})",
            mk(out),
            check=unchanged(out, tree(out)),
        )
        # a live lock
        out = a.fresh(f"i2/{key}_locked")
        s = sleeper()
        try:
            write_lock(out, s.pid, "segment")
            a.case(
                2,
                f"{label}: OUT locked by a live process",
                mk(out),
                must=(str(s.pid), host, "started"),
                check=unchanged(out, tree(out)),
            )
        finally:
            s.kill()
            s.wait()
        if not cheap:
            continue
        # a stale lock: taken over, the run completes, the lock is gone
        out = a.fresh(f"i2/{key}_stale")
        write_lock(out, dead_pid(), label.split()[0])

        def gone(rc, o, e, out=out):
            return ["lock left behind"] if (out / ".jaxcr.lock").exists() else []

        a.case(
            2,
            f"{label}: stale lock (dead pid) is taken over",
            mk(out),
            expect=(0, 1),
            must=("stale",),
            check=gone,
            one_line=False,
        )
        # leftovers of a kill -9 in an earlier run of the same command: cleaned by the rerun
        ow = (
            ["--resume"]
            if label == "segment"
            else (["--overwrite"] if label == "manifold synth" else [])
        )
        tmps = [out / ".000000.png.ab12cd.tmp", out / "sub" / "frame.json.tmp"]
        if out.exists():
            (out / "sub").mkdir(exist_ok=True)
            for t in tmps:
                t.write_bytes(b"partial")

            def cleaned(rc, o, e, tmps=tmps):
                return [f"left: {t.name}" for t in tmps if t.exists()]

            a.case(
                2,
                f"{label}: rerun cleans kill -9 leftovers (.tmp)",
                [*mk(out), *ow],
                expect=(0, 1),
                check=cleaned,
                one_line=False,
            )
    # two concurrent runs: exactly one wins, the other is refused naming the holder
    for label, mk, _ in [
        w
        for w in W
        if w[0] in ("synth", "stereo synth", "segment", "fk", "motion synth", "manifold query")
    ]:
        out = a.fresh(f"i2/{label.replace(' ', '_')}_race")
        argv = mk(out)
        p1, p2 = a.popen(argv), a.popen(argv)
        holders, ended = watch_lock(out / ".jaxcr.lock", (p1, p2))
        r = [p.communicate() + (p.returncode,) for p in (p1, p2)]
        rcs = sorted(x[2] for x in r)
        if rcs in ([0, 0], [0, 1], [1, 1]) and len(holders) == 2:
            # both ran: sequential when the first holder had ended before the second took
            # the lock (the second is then a rerun), not a race
            (first, _), (second, t2) = sorted(holders.items(), key=lambda kv: kv[1])
            if ended.get(first, 1e18) <= t2:
                a.rows.append(
                    dict(
                        item=2,
                        case=f"{label}: two concurrent runs into one OUT",
                        command=a.show(argv),
                        expected="one 0/1, one 2",
                        rc="/".join(map(str, rcs)),
                        err_lines=0,
                        held=None,
                        note="the runs did not overlap: not counted",
                    )
                )
                print(f"[---] item 2 {label}: the runs did not overlap, not counted", flush=True)
                continue
        errs = [x[1] for x in r]
        probs = []
        if rcs not in ([0, 2], [1, 2]):
            probs.append(f"exit codes {rcs}")
        loser = errs[[x[2] for x in r].index(2)] if 2 in rcs else ""
        if 2 in rcs and not all(s in loser for s in ("pid", host, "started")):
            probs.append(f"refusal does not name pid/host/start: {loser.strip()[:200]!r}")
        for f in ("results.jsonl", "frames.jsonl", "estimates.jsonl"):
            if (out / f).exists():
                ids = [
                    json.dumps(
                        {
                            k: v
                            for k, v in json.loads(x).items()
                            if k in ("frame", "id", "row", "index")
                        }
                    )
                    for x in (out / f).read_text().splitlines()
                    if x.strip()
                ]
                if len(ids) != len(set(ids)):
                    probs.append(f"{len(ids) - len(set(ids))} duplicate records in {f}")
        a.record(
            2,
            f"{label}: two concurrent runs into one OUT",
            argv,
            "one 0/1, one 2",
            "/".join(map(str, rcs)),
            loser,
            probs,
        )
    # --overwrite / --resume of a finished run while another process holds the lock
    for label, extra in (
        ("segment", "--overwrite"),
        ("segment", "--resume"),
        ("manifold synth", "--overwrite"),
    ):
        src = "segout" if label == "segment" else "man"
        out = a.copy(src, f"i2/{label.replace(' ', '_')}_locked_{extra[2:]}")
        mk = dict((w[0], w[1]) for w in W)[label]
        s = sleeper()
        try:
            write_lock(out, s.pid, label.split()[0])
            a.case(
                2,
                f"{label} {extra} of a finished run while it is locked",
                [*mk(out), extra],
                must=(str(s.pid), "started"),
                check=unchanged(out, tree(out)),
            )
        finally:
            s.kill()
            s.wait()
    # a lock from another host is never taken over
    out = a.fresh("i2/otherhost")
    out.mkdir(parents=True, exist_ok=True)
    (out / ".jaxcr.lock").write_text(
        json.dumps(
            {
                "format": "jaxcr.lock/1",
                "command": "synth",
                "pid": 1,
                "host": "node-elsewhere",
                "pid_start": None,
                "started": "2026-12-01T20:00:00+00:00",
                "argv": ["jaxcr"],
            }
        )
    )
    a.case(
        2,
        "synth: lock from another host is refused (names the file to delete)",
        writers(a)[0][1](out),
        must=("node-elsewhere", ".jaxcr.lock"),
    )
    # synth into a folder that is a dataset of the user's (no dataset.json, images)
    out = a.fresh("i2/synth_userimgs")
    (out / "images" / "main").mkdir(parents=True)
    (out / "images" / "main" / "000000.png").write_bytes(b"mine")
    a.case(
        2,
        "synth never overwrites a user's images/main/000000.png",
        writers(a)[0][1](out),
        check=unchanged(out, tree(out)),
    )
    # OUT is the input dataset itself
    for label, argv in (
        ("segment", ["segment", a.fixture("syn"), "-o", a.fixture("syn"), *SEG_FAST]),
        ("stereo", ["stereo", a.fixture("ster"), "-o", a.fixture("ster")]),
        ("motion", ["motion", a.fixture("mot"), "-o", a.fixture("mot")]),
        ("fk", ["fk", a.fixture("syn"), a.fixture("q.csv"), "-o", a.fixture("syn")]),
        ("model-object", ["model-object", a.fixture("mo"), "-o", a.fixture("mo")]),
        (
            "manifold query",
            ["manifold", "query", a.fixture("man.npz"), a.fixture("man"), "-o", a.fixture("man")],
        ),
    ):
        d = Path(argv[argv.index("-o") + 1])
        a.case(2, f"{label}: OUT is the input dataset", argv, check=unchanged(d, tree(d)))


def item3(a: Audit):
    syn, ster, mot, mo, man = (a.fixture(k) for k in ("syn", "ster", "mot", "mo", "man"))
    o = lambda k: a.S / "w" / "i3" / k  # noqa: E731 - never created when refused

    def nothing(out):
        def check(rc, _o, _e):
            return [f"{out.name} was written"] if out.exists() and any(out.iterdir()) else []

        return check

    cases = []
    for size in ("100000x100000", "8192x8192", "8x8", "0x0", "-64x48", "64", "abcxdef", "1e9x1e9"):
        for label, argv in (
            ("synth", ["synth", "--preset", "orthogonal", "--frames", "1"]),
            ("stereo synth", ["stereo", "synth", "--frames", "1"]),
            ("motion synth", ["motion", "synth", "--frames", "6"]),
            ("model-object synth", ["model-object", "synth"]),
            ("manifold synth", ["manifold", "synth", "--frames", "1"]),
            ("demo", ["demo", "--frames", "1"]),
        ):
            if size in ("8192x8192",) and label in ("model-object synth",):
                continue
            cases.append((f"{label} --size {size}", [*argv, "--size", size]))
    cases += [
        ("bench segment --size 100000x100000", ["bench", "segment", "--size", "100000x100000"]),
        ("synth --cameras 100000", ["synth", "--preset", "orthogonal", "--cameras", "100000"]),
        ("synth --cameras 0", ["synth", "--preset", "orthogonal", "--cameras", "0"]),
        ("synth --frames 10000000", ["synth", "--preset", "orthogonal", "--frames", "10000000"]),
        ("synth --frames 0", ["synth", "--preset", "orthogonal", "--frames", "0"]),
        ("synth --frames -3", ["synth", "--preset", "orthogonal", "--frames", "-3"]),
        ("synth --model-error nan", ["synth", "--preset", "orthogonal", "--model-error", "nan"]),
        ("synth --model-error -1", ["synth", "--preset", "orthogonal", "--model-error", "-1"]),
        ("stereo synth --frames 10000000", ["stereo", "synth", "--frames", "10000000"]),
        ("motion synth --frames 3", ["motion", "synth", "--frames", "3"]),
        ("motion synth --frames 10000000", ["motion", "synth", "--frames", "10000000"]),
        ("manifold synth --frames 10000000", ["manifold", "synth", "--frames", "10000000"]),
        ("segment --levels 30", ["segment", syn, *SEG_FAST, "--levels", "30"]),
        ("segment --levels 0", ["segment", syn, "--levels", "0"]),
        ("segment --levels 4 at 64x48", ["segment", syn, "--levels", "4"]),
        ("segment --batch-size 1000000000", ["segment", syn, "--batch-size", "1000000000"]),
        ("segment --batch-size 0", ["segment", syn, "--batch-size", "0"]),
        ("segment --max-steps 1000000", ["segment", syn, "--max-steps", "1000000"]),
        ("segment --max-steps 0", ["segment", syn, "--max-steps", "0"]),
        ("segment --basis 1000000", ["segment", syn, "--basis", "1000000"]),
        ("segment --prior-weight nan", ["segment", syn, "--prior-weight", "nan"]),
        ("segment --prior-weight -1", ["segment", syn, "--prior-weight", "-1"]),
        ("segment --g-cam-rel inf", ["segment", syn, "--g-cam-rel", "inf"]),
        ("segment --limit -1", ["segment", syn, "--limit", "-1"]),
        ("segment --seed -1", ["segment", syn, "--seed", "-1"]),
        ("segment --seed 2**40", ["segment", syn, "--seed", str(2**40)]),
        ("segment --shard 3/2", ["segment", syn, "--shard", "3/2"]),
        ("segment --shard 0/0", ["segment", syn, "--shard", "0/0"]),
        ("stereo --segments 0", ["stereo", ster, "--segments", "0"]),
        ("stereo --segments 1000", ["stereo", ster, "--segments", "1000"]),
        ("stereo --tolerance 0.9 0.1", ["stereo", ster, "--tolerance", "0.9", "0.1"]),
        ("stereo --tolerance nan 1", ["stereo", ster, "--tolerance", "nan", "1"]),
        ("stereo synth --seed 2**40", ["stereo", "synth", "--seed", str(2**40)]),
        ("motion --lambda nan", ["motion", mot, "--lambda", "nan"]),
        ("motion --lambda 0", ["motion", mot, "--lambda", "0"]),
        ("motion --prior-frames inf", ["motion", mot, "--prior-frames", "inf"]),
        ("motion --superpixel-step 100000", ["motion", mot, "--superpixel-step", "100000"]),
        ("motion --flow-step 100000", ["motion", mot, "--flow-step", "100000"]),
        ("motion --threshold nan", ["motion", mot, "--threshold", "nan"]),
        ("model-object --seed -5", ["model-object", mo, "--seed", "-5"]),
        ("fk --points 100000", ["fk", syn, a.fixture("q.csv"), "--points", "100000"]),
        ("fk --points 1", ["fk", syn, a.fixture("q.csv"), "--points", "1"]),
        ("bench fk --batch 1000000000", ["bench", "fk", "--batch", "1000000000"]),
        ("bench fk --repeats 1000000000", ["bench", "fk", "--repeats", "1000000000"]),
        ("manifold train --step 0", ["manifold", "train", man, "--step", "0"]),
        ("manifold train --step nan", ["manifold", "train", man, "--step", "nan"]),
        ("manifold train --step 1e-9", ["manifold", "train", man, "--step", "1e-9"]),
        ("manifold train --bins 100000000", ["manifold", "train", man, "--bins", "100000000"]),
        ("manifold train --variance 2", ["manifold", "train", man, "--variance", "2"]),
        ("manifold train --clusters 0", ["manifold", "train", man, "--clusters", "0"]),
        ("manifold train --smoothing nan", ["manifold", "train", man, "--smoothing", "nan"]),
        (
            "manifold train --neighbours 1000000000",
            [
                "manifold",
                "train",
                man,
                "--step",
                "0.05",
                "--bins",
                "24",
                "--neighbours",
                "1000000000",
            ],
        ),
        ("manifold train --marker-rgb 2,0,0", ["manifold", "train", man, "--marker-rgb", "2,0,0"]),
    ]
    for k, (name, argv) in enumerate(cases):
        out = o(f"c{k}")
        if argv[0] == "manifold" and argv[1] == "train":
            out = o(f"c{k}.npz")
        elif argv[0] == "bench":
            out = o(f"c{k}.md")
        a.case(
            3,
            name,
            [*argv, "-o", out],
            check=nothing(out)
            if out.suffix == ""
            else (lambda rc, _o, _e, out=out: [f"{out.name} written"] if out.exists() else []),
        )

    # motion: a joint value of 1e308 (inf in float32) and NaN
    for bad, tag in ((1e308, "1e308"), (float("nan"), "NaN"), (1e4, "1e4 rad")):
        d = a.copy("mot", f"i3/mot_{tag}")
        m = json.loads((d / "motion.json").read_text())
        fr = m["frames"][2]
        fr["x"][0] = bad
        (d / "motion.json").write_text(json.dumps(m))
        a.case(
            3,
            f"motion: joint value {tag} in motion.json",
            ["motion", d, "-o", o(f"m{tag}")],
            must=("motion.json",),
            check=nothing(o(f"m{tag}")),
        )
    # model-object: NaN / inf / huge obstacles
    import numpy as np

    for tag, fill in (("all-NaN", np.nan), ("inf", np.inf), ("1e308", 1e308)):
        d = a.copy("mo", f"i3/mo_{tag}")
        obs = np.load(d / "obstacles.npy", allow_pickle=False)
        obs = np.full_like(obs, fill) if tag == "all-NaN" else obs.copy()
        if tag != "all-NaN":
            obs.flat[0] = fill
        np.save(d / "obstacles.npy", obs)
        a.case(
            3,
            f"model-object: {tag} obstacles",
            ["model-object", d, "-o", o(f"mo{tag}")],
            must=("obstacles.npy",),
            check=nothing(o(f"mo{tag}")),
        )
    d = a.copy("mo", "i3/mo_bigcam")
    sc = json.loads((d / "scene.json").read_text())
    if "camera" in sc and isinstance(sc["camera"], dict):
        sc["camera"]["width"] = sc["camera"]["height"] = 100000
        (d / "scene.json").write_text(json.dumps(sc))
        a.case(
            3,
            "model-object: scene.json camera 100000x100000",
            ["model-object", d, "-o", o("mobig")],
            must=("scene.json",),
            check=nothing(o("mobig")),
        )
    # calibrate
    cal = a.S / "w" / "i3" / "calib"
    make_chessboards(cal)
    for name, argv, must in (
        (
            "calibrate LEFT == RIGHT",
            ["calibrate", cal / "L", cal / "L", "--cols", "6", "--rows", "5", "--pitch", "0.01"],
            (),
        ),
        (
            "calibrate LEFT == RIGHT (other spelling)",
            [
                *calibrate_argv(cal / "L", str(cal / "L") + "/"),
            ],
            (),
        ),
        (
            "calibrate LEFT == RIGHT (symlink)",
            [
                *calibrate_argv(cal / "L", cal / "Llink"),
            ],
            (),
        ),
        (
            "calibrate --max-rms nan",
            [
                *calibrate_argv(cal / "L", cal / "R"),
                "--max-rms",
                "nan",
            ],
            ("max-rms",),
        ),
        (
            "calibrate --max-rms -1",
            [
                *calibrate_argv(cal / "L", cal / "R"),
                "--max-rms",
                "-1",
            ],
            ("max-rms",),
        ),
        (
            "calibrate --max-std nan",
            [
                *calibrate_argv(cal / "L", cal / "R"),
                "--max-std",
                "nan",
            ],
            ("max-std",),
        ),
        (
            "calibrate --pitch nan",
            ["calibrate", cal / "L", cal / "R", "--cols", "6", "--rows", "5", "--pitch", "nan"],
            ("pitch",),
        ),
        (
            "calibrate --pitch 0",
            ["calibrate", cal / "L", cal / "R", "--cols", "6", "--rows", "5", "--pitch", "0"],
            ("pitch",),
        ),
        (
            "calibrate --cols 100000",
            [
                "calibrate",
                cal / "L",
                cal / "R",
                "--cols",
                "100000",
                "--rows",
                "5",
                "--pitch",
                "0.01",
            ],
            ("cols",),
        ),
        (
            "calibrate --cols 1",
            ["calibrate", cal / "L", cal / "R", "--cols", "1", "--rows", "5", "--pitch", "0.01"],
            ("cols",),
        ),
    ):
        out = o(f"{abs(hash(name)) % 10**6}.yaml")
        a.case(
            3,
            name,
            [*argv, "-o", out],
            must=must,
            check=lambda rc, _o, _e, out=out: ["calibration written"] if out.exists() else [],
        )


def make_chessboards(root: Path):
    import cv2
    import numpy as np

    for side in ("L", "R"):
        (root / side).mkdir(parents=True, exist_ok=True)
        for k in range(2):
            img = np.full((240, 320), 255, np.uint8)
            sq = 24
            for r in range(6):
                for c in range(7):
                    if (r + c) % 2 == 0:
                        y, x = 40 + r * sq + 3 * k, 60 + c * sq + (4 if side == "R" else 0)
                        img[y : y + sq, x : x + sq] = 0
            cv2.imwrite(str(root / side / f"{k:03d}.png"), img)
    link = root / "Llink"
    if not link.exists():
        link.symlink_to(root / "L")


def named_in_stderr_or_per_frame(d: Path, what: str):
    """A check: ``what`` is named on stderr (a one-line refusal) or in a reason of
    ``per_frame.csv`` (a failed frame, as the README's batch contract has it)."""

    def check(rc, _o, err):
        pf = d / "per_frame.csv"
        if what in err or (pf.exists() and what in pf.read_text()):
            return []
        return [f"{what} named neither on stderr nor in per_frame.csv"]

    return check


def item4(a: Audit):
    import numpy as np

    run = a.fixture("segout")
    recs = [json.loads(x) for x in (run / "results.jsonl").read_text().splitlines() if x]
    ok = [
        r
        for r in recs
        if r.get("ok") and isinstance(r.get("files"), dict) and r["files"].get("centreline")
    ]
    if not ok:
        a.record(
            4,
            "fixture has an ok frame",
            ["segment"],
            "ok frame",
            None,
            "",
            ["the segment fixture has no ok frame"],
        )
        return
    fid = ok[0]["frame"]
    n = len(recs)

    def evaluate(case, d, must, expect=(1,)):
        def check(rc, _o, _e):
            import csv

            probs = []
            pf = d / "per_frame.csv"
            if not pf.exists():
                return ["no per_frame.csv"]
            rows = {r["frame"]: r for r in csv.DictReader(open(pf))}
            if fid in rows and rows[fid]["ok"] != "False" and case != "incomplete":
                probs.append(f"frame {fid} counted ok")
            return probs

        a.case(
            4,
            case,
            ["evaluate", d, "--no-plot"],
            expect=expect,
            must=must,
            check=check,
            one_line=False,
        )

    for tag, arr in (
        ("all-NaN", np.full((24, 3), np.nan)),
        ("one inf", None),
        ("empty (0, 3)", np.zeros((0, 3))),
        ("wrong shape (5,)", np.zeros(5)),
        ("object array (pickle)", np.array([{"a": 1}], dtype=object)),
    ):
        d = a.copy("segout", f"i4/{tag.split()[0]}_{len(tag)}")
        p = d / ok[0]["files"]["centreline"]
        if arr is None:
            arr = np.load(p, allow_pickle=False).copy()
            arr[-1, 0] = np.inf
        np.save(p, arr, allow_pickle=True)
        evaluate(f"evaluate: {tag} output centreline", d, (f"of {n} frame(s) failed",))
    for k, files in enumerate(
        (
            "masks/main/000001.png",
            ["masks"],
            {"masks": "x.png"},
            {"masks": {"main": 7}},
            {"centreline": ["c.npy"]},
            {"masks": {"main": "../../../../etc/passwd"}},
            None,
            5,
            {"centreline": "/etc/passwd"},
            {"masks": {"main": None}},
        )
    ):
        d = a.copy("segout", f"i4/files{k}")
        lines = (d / "results.jsonl").read_text().splitlines()
        for i, x in enumerate(lines):
            r = json.loads(x)
            if r.get("frame") == fid:
                r["files"] = files
                lines[i] = json.dumps(r)
        (d / "results.jsonl").write_text("\n".join(lines) + "\n")
        evaluate(
            f"evaluate: malformed files {json.dumps(files)[:40]}", d, (f"of {n} frame(s) failed",)
        )
    # malformed lines
    for k, bad in enumerate(("{not json", "[]", '{"frame": 3}', '"x"')):
        d = a.copy("segout", f"i4/line{k}")
        with open(d / "results.jsonl", "a") as f:
            f.write(bad + "\n")
        a.case(
            4,
            f"evaluate: results.jsonl line {bad!r}",
            ["evaluate", d, "--no-plot"],
            expect=(1, 2),
            one_line=False,
            check=named_in_stderr_or_per_frame(d, "results.jsonl"),
        )
    # incomplete run
    d = a.copy("segout", "i4/incomplete")
    lines = (d / "results.jsonl").read_text().splitlines()
    (d / "results.jsonl").write_text("\n".join(lines[:1]) + "\n")
    (d / "DONE").unlink(missing_ok=True)
    evaluate("incomplete", d, (f"{n - 1} of {n} frame(s) missing",))
    d = a.copy("segout", "i4/incomplete_done")
    (d / "results.jsonl").write_text("\n".join(lines[:1]) + "\n")
    evaluate("incomplete", d, (f"{n - 1} of {n} frame(s) missing",))
    d = a.copy("segout", "i4/empty_results")
    (d / "results.jsonl").write_text("")
    (d / "DONE").unlink(missing_ok=True)
    a.case(
        4,
        "evaluate: run with no record at all (exit 2: nothing to evaluate, or 1 with the count)",
        ["evaluate", d, "--no-plot"],
        expect=(1, 2),
        one_line=False,
        check=lambda rc, _o, e: (
            []
            if (rc == 2 and "results.jsonl" in e) or f"{n} of {n}" in e
            else ["neither the count nor the empty results.jsonl named"]
        ),
    )
    d = a.copy("segout", "i4/norun")
    (d / "run.json").write_text("{trunc")
    a.case(4, "evaluate: truncated run.json", ["evaluate", d, "--no-plot"], must=("run.json",))
    d = a.copy("segout", "i4/missingmask")
    for f in (d / "masks").rglob(f"{fid}.png"):
        f.unlink()
    evaluate("evaluate: an ok frame's mask deleted", d, (f"of {n} frame(s) failed",))


def item5(a: Audit):
    import numpy as np

    model = a.fixture("man.npz")
    for how in ("truncated", "zero bytes", "garbage", "a directory"):
        d = a.copy("man", f"i5/{how.replace(' ', '_')}")
        imgs = sorted((d / "images").rglob("*.png"))
        victim = [p for p in imgs if p.name == "000003.png"][0]
        if how == "truncated":
            victim.write_bytes(victim.read_bytes()[:60])
        elif how == "zero bytes":
            victim.write_bytes(b"")
        elif how == "garbage":
            victim.write_bytes(os.urandom(500))
        else:
            victim.unlink()
            victim.mkdir()
        out = a.S / "w" / "i5" / f"m_{how.replace(' ', '_')}.npz"

        def trained(rc, _o, _e, out=out):
            if not out.exists():
                return ["no model written"]
            with np.load(out, allow_pickle=False) as z:
                meta = json.loads(str(z["meta"]))
            bad = {
                **dict.fromkeys(meta.get("frames_failed") or []),
                **(meta.get("frames_bad") or {}),
                **(meta.get("frames_unreadable") or {}),
            }
            return [] if "000003" in bad else [f"000003 not listed as failed: {bad}"]

        a.case(
            5,
            f"manifold train, one image {how}",
            ["manifold", "train", d, "-o", out, "--bins", "24", "--step", "0.05"],
            expect=(1,),
            must=("000003",),
            check=trained,
            one_line=False,
        )
        q = a.S / "w" / "i5" / f"q_{how.replace(' ', '_')}"

        def queried(rc, _o, _e, q=q):
            p = q / "estimates.jsonl"
            if not p.exists():
                return ["no estimates.jsonl"]
            rows = {r["id"]: r for r in map(json.loads, p.read_text().splitlines())}
            probs = []
            if rows.get("000003", {}).get("ok") is not False:
                probs.append("000003 not failed")
            if sum(bool(r.get("ok")) for r in rows.values()) < len(rows) - 1:
                probs.append("other frames failed too")
            return probs

        a.case(
            5,
            f"manifold query, one image {how}",
            ["manifold", "query", model, d, "-o", q],
            expect=(1,),
            must=("1 frame(s) failed",),
            check=queried,
            one_line=False,
        )


def item6(a: Audit):
    syn = a.fixture("syn")
    usage = [
        ("synth", ["synth", "--bogus"]),
        ("synth", ["synth", "--preset", "nope", "-o", "x"]),
        ("segment", ["segment"]),
        ("segment", ["segment", syn, "-o", "x", "--levels", "two"]),
        ("evaluate", ["evaluate"]),
        ("stereo", ["stereo"]),
        ("stereo", ["stereo", "x", "--segments"]),
        ("motion", ["motion", "x"]),
        ("motion", ["motion", "x", "-o", "y", "--model", "z"]),
        ("model-object", ["model-object"]),
        ("manifold", ["manifold"]),
        ("manifold", ["manifold", "train"]),
        ("manifold", ["manifold", "query", "m"]),
        ("manifold", ["manifold", "nope"]),
        ("calibrate", ["calibrate", "a"]),
        ("fk", ["fk"]),
        ("fit", ["fit", "r.json"]),
        ("validate", ["validate"]),
        ("bench", ["bench", "nope"]),
        ("demo", ["demo", "--frames", "x"]),
        ("warmup", ["warmup"]),
        ("jaxcr", ["nope"]),
        ("jaxcr", []),
        ("jaxcr", ["--bogus"]),
        ("stereo synth", ["stereo", "synth", "-o", "x", "--size", "big"]),
    ]
    for _label, argv in usage:
        # argparse's errors point at --help; a value checked after parsing (a bad WxH) is bad
        # input instead: one line naming the flag
        a.case(
            6,
            f"bad usage: jaxcr {' '.join(map(str, argv))[:50]}",
            argv,
            must=("size",) if "big" in argv else ("--help",),
            cwd=a.fresh(f"i6/u{abs(hash(tuple(map(str, argv)))) % 10**6}").parent,
        )
    # a truncated PNG in a dataset: the frame fails, no libpng noise
    d = a.copy("syn", "i6/truncpng")
    img = sorted((d / "images").rglob("*.png"))[1]
    img.write_bytes(img.read_bytes()[:100])
    a.case(
        6,
        "segment: one truncated PNG, no libpng lines",
        ["segment", d, "-o", a.S / "w" / "i6" / "truncout", *SEG_FAST],
        expect=(1,),
        one_line=False,
    )
    a.case(
        6, "validate: truncated PNG, no libpng lines", ["validate", d], expect=(2,), one_line=False
    )
    # a damaged JPEG in a motion dataset
    d = a.copy("mot", "i6/jpeg")
    frames = sorted((d / "frames").iterdir())
    import cv2

    im = cv2.imread(str(frames[2]))
    ok, buf = cv2.imencode(".jpg", im)
    b = bytearray(buf.tobytes())
    b[len(b) // 2 : len(b) // 2 + 40] = b"\x00" * 40
    jp = frames[2].with_suffix(".jpg")
    frames[2].unlink()
    jp.write_bytes(bytes(b[: len(b) * 3 // 4]))
    # the frames come from the folder (source.images), sorted by name: motion.json is unchanged
    a.case(
        6,
        "motion: a damaged JPEG frame, no libjpeg lines",
        ["motion", d, "-o", a.S / "w" / "i6" / "jpegout"],
        expect=(0, 1, 2),
        one_line=True,
    )
    # --preview into a read-only folder: refused before the dataset is written
    ro = mount_tmpfs(a.S / "w" / "i6" / "ro", "64k", ro=True)
    out = a.S / "w" / "i6" / "preview_out"
    a.case(
        6,
        "synth --preview into a read-only folder is refused first",
        [
            *synth_argv(out, "64x48", 2),
            "--preview",
            ro if ro else "/proc/1/preview",
        ],
        must=("preview",),
        check=lambda rc, _o, _e: ["dataset written"] if (out / "dataset.json").exists() else [],
    )
    a.case(
        6,
        "synth --preview into a missing folder under /proc",
        [
            *synth_argv(a.S / "w" / "i6" / "preview_out2", "64x48", 2),
            "--preview",
            "/proc/nope/x",
        ],
    )
    # read-only OUT
    make_chessboards(a.S / "w" / "i3" / "calib")  # also when item 3 did not run
    if ro:
        for label, argv in (
            (
                "synth",
                [
                    *synth_argv(ro / "x", "64x48", 1),
                ],
            ),
            ("segment", ["segment", syn, "-o", ro / "x", *SEG_FAST]),
            ("fk", ["fk", syn, a.fixture("q.csv"), "-o", ro / "x"]),
            (
                "stereo synth",
                ["stereo", "synth", "--size", "64x48", "--frames", "1", "-o", ro / "x"],
            ),
            ("manifold train", ["manifold", "train", a.fixture("man"), "-o", ro / "m.npz"]),
            (
                "calibrate",
                [
                    *calibrate_argv(
                        a.S / "w" / "i3" / "calib" / "L", a.S / "w" / "i3" / "calib" / "R"
                    ),
                    "-o",
                    ro / "c.yaml",
                ],
            ),
        ):
            a.case(6, f"{label}: read-only OUT, one line", argv, must=(str(ro),))
    # a full disk names the file
    for label, argv_of, size in (
        (
            "synth",
            lambda o: [
                *synth_argv(o, "64x48", 4),
                "--quiet",
            ],
            "48k",
        ),
        (
            "stereo synth",
            lambda o: ["stereo", "synth", "--size", "64x48", "--frames", "4", "-o", o],
            "32k",
        ),
        ("segment", lambda o: ["segment", syn, "-o", o, *SEG_FAST], "12k"),
        ("fk", lambda o: ["fk", syn, a.fixture("q.csv"), "-o", o], "4k"),
        (
            "manifold query",
            lambda o: ["manifold", "query", a.fixture("man.npz"), a.fixture("man"), "-o", o],
            "4k",
        ),
        (
            "motion synth",
            lambda o: ["motion", "synth", "--size", "64x48", "--frames", "6", "-o", o],
            "24k",
        ),
    ):
        mnt = mount_tmpfs(a.S / "w" / "i6" / f"full_{label.replace(' ', '_')}", size)
        pre = None
        if mnt is None:
            mnt = a.fresh(f"i6/fsize_{label.replace(' ', '_')}")

            def pre():
                signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
                resource.setrlimit(resource.RLIMIT_FSIZE, (4096, 4096))

        out = mnt / "out"
        a.case(
            6,
            f"{label}: full disk names the file",
            argv_of(out),
            expect=(2,),
            must=(str(mnt),),
            preexec=pre,
        )
    a.unmount_all = True


_MOUNTS: list[Path] = []


def mount_tmpfs(d: Path, size: str, ro=False) -> Path | None:
    d.mkdir(parents=True, exist_ok=True)
    opts = f"size={size}" + (",ro" if ro else "")
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", opts, "tmpfs", str(d)], capture_output=True)
    if r.returncode != 0:
        return None
    _MOUNTS.append(d)
    return d


def git_dir() -> Path | None:
    g = REPO / ".git"
    if g.is_file():
        txt = g.read_text().strip()
        if txt.startswith("gitdir:"):
            return Path(txt.split(":", 1)[1].strip())
    return g if g.is_dir() else None


def git_state() -> dict:
    g = git_dir()
    if g is None:
        return {}
    st = {}
    for f in g.iterdir():
        if f.is_file():
            s = f.stat()
            st[f.name] = (s.st_mtime_ns, s.st_size)
    return st


def item7(a: Audit):
    cmds = [w for w in writers(a)] + [
        ("validate", lambda o: ["validate", a.fixture("syn"), "-o", o / "v.json"], True),
        (
            "manifold train",
            lambda o: [
                "manifold",
                "train",
                a.fixture("man"),
                "-o",
                o / "m.npz",
                "--bins",
                "24",
                "--step",
                "0.05",
            ],
            True,
        ),
        ("evaluate", lambda o: ["evaluate", a.copy("segout", "i7/evalrun"), "--no-plot"], True),
        (
            "bench fk",
            lambda o: ["bench", "fk", "--repeats", "2", "--batch", "4", "-o", o / "b.md"],
            True,
        ),
    ]
    for label, mk, _ in cmds:
        cwd = a.fresh(f"i7/cwd_{label.replace(' ', '_')}")
        cwd.mkdir()
        out = a.fresh(f"i7/out_{label.replace(' ', '_')}")
        if label in ("validate", "manifold train", "bench fk"):
            out.mkdir()
        for f in a.tmp.iterdir():
            shutil.rmtree(f) if f.is_dir() else f.unlink()
        g0 = git_state()

        def check(rc, _o, _e, cwd=cwd, g0=g0):
            probs = []
            if any(cwd.iterdir()):
                probs.append(f"wrote into the working directory: {os.listdir(cwd)[:3]}")
            left = os.listdir(a.tmp)
            if left:
                probs.append(f"left in TMPDIR: {left[:3]}")
            g1 = git_state()
            if g1 != g0:
                ch = sorted(k for k in set(g0) | set(g1) if g0.get(k) != g1.get(k))
                probs.append(f"checkout's git folder changed: {ch}")
            return probs

        a.case(
            7,
            f"{label}: nothing written outside OUT (cwd, TMPDIR, .git)",
            mk(out),
            expect=(0, 1),
            check=check,
            cwd=cwd,
            one_line=False,
        )


def item8(a: Audit):
    import numpy as np

    pkg = REPO / "jaxcr"
    for f in sorted(pkg.rglob("*.py")):
        src = f.read_text()
        for m in re.finditer(r"\bnp\.load\(", src):
            depth, i = 1, m.end()
            while depth and i < len(src):
                depth += {"(": 1, ")": -1}.get(src[i], 0)
                i += 1
            call = src[m.start() : i]
            line = src.count("\n", 0, m.start()) + 1
            rel = f.relative_to(REPO)
            probs = (
                []
                if re.search(r"allow_pickle\s*=\s*False", call)
                else [f"no allow_pickle=False: {call[:80]!r}"]
            )
            a.record(
                8,
                f"{rel}:{line} np.load",
                [f"grep np.load {rel}:{line}"],
                "allow_pickle=False",
                "-",
                "",
                probs,
                note=call[:60],
            )
    # pickled inputs are refused with one line
    pick = np.array([{"a": 1}, None], dtype=object)
    d = a.copy("mo", "i8/mo")
    np.save(d / "obstacles.npy", pick, allow_pickle=True)
    a.case(
        8,
        "model-object: pickled obstacles.npy",
        ["model-object", d, "-o", a.S / "w" / "i8" / "moout"],
        must=("obstacles.npy",),
    )
    bb = a.S / "w" / "i8" / "bb.npy"
    np.save(bb, pick, allow_pickle=True)
    a.case(
        8,
        "fit: pickled --backbone .npy",
        ["fit", a.fixture("syn"), "--backbone", bb, "-o", a.S / "w" / "i8" / "fitout"],
        must=("bb.npy",),
    )
    m = a.S / "w" / "i8" / "model.npz"
    np.savez(m, meta=np.array([{"x": 1}], dtype=object))
    a.case(
        8,
        "manifold query: pickled model .npz",
        ["manifold", "query", m, a.fixture("man"), "-o", a.S / "w" / "i8" / "mq"],
        must=("model.npz",),
    )
    d = a.copy("syn", "i8/syn")
    truth = sorted((d / "truth").rglob("*.npy"))
    if truth:
        np.save(truth[0], pick, allow_pickle=True)
        a.case(
            8,
            "validate: pickled truth .npy (listed on stdout)",
            ["validate", d],
            one_line=False,
            check=lambda rc, o, e, n=truth[0].name: (
                []
                if n in o and "allow_pickle" in o or "memory-mapped" in o
                else [f"stdout does not name {n}"]
            ),
        )


ITEMS = {1: item1, 2: item2, 3: item3, 4: item4, 5: item5, 6: item6, 7: item7, 8: item8}


def write_report(a: Audit, path: Path, argv: list[str], cpu: float, wall: float):
    counted = [r for r in a.rows if r["held"] is not None]
    held = sum(r["held"] for r in counted)
    lines = [
        "# Issue 17 contract audit (items 1-8)",
        "",
        f"Command: `{' '.join(argv)}` at commit {commit()}, host {socket.gethostname()}, "
        f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}.",
        f"Children CPU {cpu:.0f} s, wall {wall:.0f} s, load average at the end "
        f"{os.getloadavg()[0]:.1f}.",
        "",
        f"**Tried {len(counted)}, held {held}, broken {len(counted) - held}** "
        f"({len(a.rows) - len(counted)} not counted: the command finished before the signal).",
        "",
        "| item | tried | held | broken |",
        "|---|---|---|---|",
    ]
    for it in sorted({r["item"] for r in a.rows}):
        rs = [r for r in counted if r["item"] == it]
        h = sum(r["held"] for r in rs)
        lines.append(f"| {it} | {len(rs)} | {h} | {len(rs) - h} |")
    lines += [
        "",
        "| # | item | case | expected | exit | stderr lines | held | note / command |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for k, r in enumerate(a.rows, 1):
        h = {True: "yes", False: "**no**", None: "n/a"}[r["held"]]
        note = str(r["note"]).replace("|", "\\|").replace("\n", " ")[:200]
        cmd = r["command"].replace("|", "\\|")[:200]
        lines.append(
            f"| {k} | {r['item']} | {r['case'].replace('|', '/')} | {r['expected']} | "
            f"{r['rc']} | {r['err_lines']} | {h} | {note} <br>`{cmd}` |"
        )
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines) + "\n")


def commit() -> str:
    g = git_dir()
    try:
        head = (g / "HEAD").read_text().strip()
        if head.startswith("ref:"):
            ref = head.split(None, 1)[1]
            for base in (
                g,
                Path((g / "commondir").read_text().strip()) if (g / "commondir").exists() else g,
            ):
                base = base if base.is_absolute() else g / base
                if (base / ref).exists():
                    return (base / ref).read_text().strip()[:10]
            return ref
        return head[:10]
    except (OSError, TypeError):
        return "unknown"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--only", default="1,2,3,4,5,6,7,8", help="items, e.g. 3,4")
    ap.add_argument("--scratch", type=Path, default=None, help="scratch folder (default: temp)")
    ap.add_argument(
        "--report", type=Path, default=REPO / "experiments" / "results" / "issue17_audit.md"
    )
    ap.add_argument("--json", type=Path, default=None, help="also write the rows as JSON")
    ap.add_argument(
        "--merge",
        type=Path,
        nargs="+",
        default=None,
        help="write one report from the --json files of runs of parts (no case is run)",
    )
    args = ap.parse_args(argv)
    if args.merge:
        a = Audit(Path(tempfile.mkdtemp(prefix="jaxcr-audit-")))
        cpu = wall = 0.0
        for f in args.merge:
            part = json.loads(f.read_text())
            a.rows += part["rows"]
            cpu += part["cpu_s"]
            wall += part["wall_s"]
        a.rows.sort(key=lambda r: r["item"])
        write_report(
            a,
            args.report,
            [
                "python",
                "experiments/contract_audit.py",
                *(argv if argv is not None else sys.argv[1:]),
            ],
            cpu,
            wall,
        )
        shutil.rmtree(a.S, ignore_errors=True)
        return 0
    scratch = args.scratch or Path(tempfile.mkdtemp(prefix="jaxcr-audit-"))
    scratch.mkdir(parents=True, exist_ok=True)
    a = Audit(scratch.resolve())
    t0 = time.monotonic()
    g0 = git_state()
    try:
        for it in (int(x) for x in args.only.split(",")):
            print(f"== item {it}", flush=True)
            ITEMS[it](a)
    finally:
        for d in reversed(_MOUNTS):
            subprocess.run(["umount", str(d)], capture_output=True)
    if git_state() != g0:
        a.record(
            7,
            "whole audit: checkout's git folder unchanged",
            ["(all)"],
            "unchanged",
            "-",
            "",
            ["git folder changed during the audit"],
        )
    cpu = a._cpu() - a.cpu0
    write_report(
        a,
        args.report,
        ["python", "experiments/contract_audit.py", *(argv if argv is not None else sys.argv[1:])],
        cpu,
        time.monotonic() - t0,
    )
    if args.json:
        args.json.write_text(
            json.dumps({"rows": a.rows, "cpu_s": cpu, "wall_s": time.monotonic() - t0}, default=str)
        )
    counted = [r for r in a.rows if r["held"] is not None]
    print(
        f"tried {len(counted)}, held {sum(r['held'] for r in counted)}, broken "
        f"{sum(not r['held'] for r in counted)}; CPU {cpu:.0f} s; report {args.report}"
    )
    return 0 if all(r["held"] for r in counted) else 1


if __name__ == "__main__":
    sys.exit(main())
