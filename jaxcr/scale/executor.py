"""Run a command's frames in chunks, locally or on a Ray cluster: ``--executor local|ray``.

Every batch command has the same shape: a list of frame ids, a *worker* that turns a chunk of
ids into one record per frame (writing the frames' files into OUT atomically as it goes), and
one results log (``results.jsonl``) that only the driver appends to. This module runs that
shape; the commands only say how to build their worker (:class:`WorkerSpec`).

- ``local`` (default): one worker in this process, chunk after chunk; each chunk's records
  are appended as it completes (the behaviour of every command before Ray).
- ``ray``: one Ray actor per worker (``--workers``, default: the cluster's CPUs), each building
  its worker once, so the compiled functions live across chunks (compile once per worker;
  the actors also share JAX's persistent compilation cache when it is on). The driver hands
  out chunks of ``--chunk`` frames, at most two in flight per actor, and appends the records
  **in frame order** as chunks complete, so ``results.jsonl`` has the lines of a local run in
  the same order. A worker that dies (killed, out of memory, node lost) is restarted by Ray
  and its chunks re-run (``max_restarts``/``max_task_retries`` = :data:`RAY_RETRIES`); a frame
  whose chunk still cannot finish is recorded as failed (``"worker lost: ..."``), as a local
  bad frame is, and the run goes on (exit 1; ``--retry-failed`` re-runs it).

Exactly once: the driver appends one record per frame (it keeps the set of frames it wrote),
and records are appended only after the worker returned, i.e. after the frame's files exist;
a re-run chunk rewrites the same files by atomic rename (identical content, never a partial
file), and its duplicate records are dropped. A Ray run's OUT therefore equals a local run's:
the same files and records, apart from timings (``time_s``, ``compile_s``) and the summary's
``executor`` entry (workers, hosts).

Bad input is found by the driver before any task is sent (one line, exit 2, as locally); an
:class:`~jaxcr.errors.InputError` raised inside a worker is re-raised by the driver as itself.
"""

from __future__ import annotations

import argparse
import os
import socket
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Protocol

from jaxcr.errors import InputError

EXECUTORS = ("local", "ray")
#: restarts of a dead Ray actor and retries of its chunks before they are recorded failed
RAY_RETRIES = 3
#: chunks in flight per Ray actor (one running, one queued: no idle gap between chunks)
IN_FLIGHT = 2
WORKER_LOST = "worker lost"


class FrameWorker(Protocol):
    """What a command's worker provides: ``process(frame_ids) -> records`` (one dict per
    frame, with the frame id under the command's key, files already written), and the
    accumulated ``compile_s`` / ``run_s`` of its process."""

    compile_s: float
    run_s: float

    def process(self, frame_ids: list[str]) -> list[dict]: ...

    def failed_record(self, frame_id: str, reason: str) -> dict: ...


@dataclass(frozen=True)
class WorkerSpec:
    """A picklable recipe for a worker: ``factory(*args, **kwargs)`` (a module-level function,
    so Ray can send it to another machine; the arguments are paths and options, not
    arrays)."""

    factory: Callable[..., FrameWorker]
    args: tuple = ()
    kwargs: dict = field(default_factory=dict)

    def build(self) -> FrameWorker:
        return self.factory(*self.args, **self.kwargs)


@dataclass(frozen=True)
class ExecutorConfig:
    """``kind``: ``"local"`` or ``"ray"``; ``address``: Ray cluster (None: start a local
    instance; ``"auto"`` or ``"ray://host:port"``: join one); ``chunk``: frames per task (None:
    the command's default); ``workers``: Ray actors (None: one per CPU of the cluster)."""

    kind: str = "local"
    address: str | None = None
    chunk: int | None = None
    workers: int | None = None


def add_executor_arguments(parser: argparse.ArgumentParser, chunk_default: str) -> None:
    """``--executor``, ``--address``, ``--chunk``, ``--workers`` on a command's parser."""
    g = parser.add_argument_group("scale-out (docs/scale-out.md)")
    g.add_argument("--executor", choices=EXECUTORS, default="local",
                   help="run the frames in this process (local, default) or as tasks on a Ray "
                   "cluster (ray; needs pip install 'jaxcr[ray]')")  # fmt: skip
    g.add_argument("--address", default=None, metavar="ADDR",
                   help="with --executor ray: the cluster to join, 'auto' (the one started "
                   "with 'ray start --head' on this node) or ray://HOST:PORT (default: start a "
                   "local Ray instance for this run)")  # fmt: skip
    g.add_argument("--chunk", type=int, default=None, metavar="N",
                   help=f"frames per task (default: {chunk_default})")  # fmt: skip
    g.add_argument("--workers", type=int, default=None, metavar="W",
                   help="with --executor ray: worker actors (default: one per CPU of the "
                   "cluster)")  # fmt: skip


def executor_config(args) -> ExecutorConfig:
    """The :class:`ExecutorConfig` of parsed arguments; bad combinations are
    :class:`InputError` (exit 2) before any work."""
    from jaxcr.limits import check_count

    kind = getattr(args, "executor", "local") or "local"
    chunk = getattr(args, "chunk", None)
    workers = getattr(args, "workers", None)
    address = getattr(args, "address", None)
    if chunk is not None:
        check_count(chunk, "chunk", 1, 1_000_000)
    if workers is not None:
        check_count(workers, "workers", 1, 100_000)
    if kind == "local" and (address is not None or workers is not None):
        flag = "--address" if address is not None else "--workers"
        raise InputError(f"{flag} needs --executor ray", field=flag[2:])
    if kind == "ray":
        try:
            import ray  # noqa: F401
        except ImportError:
            raise InputError("--executor ray needs Ray: pip install 'jaxcr[ray]'",
                             field="executor") from None  # fmt: skip
    return ExecutorConfig(kind, address, chunk, workers)


def chunks_of(ids: list[str], size: int) -> list[list[str]]:
    return [ids[i : i + size] for i in range(0, len(ids), size)]


@dataclass
class RunStats:
    """What :func:`run_frames` did: the records it appended (in order), the workers' compile
    and run seconds, and the executor's description for ``summary.json``."""

    records: list[dict] = field(default_factory=list)
    compile_s: float = 0.0
    run_s: float = 0.0
    executor: dict = field(default_factory=dict)


def run_frames(
    spec: WorkerSpec,
    frame_ids: list[str],
    log,
    config: ExecutorConfig,
    *,
    chunk: int,
    key: str = "frame",
    local_worker: FrameWorker | None = None,
    on_record: Callable[[dict], None] | None = None,
    on_chunk: Callable[[int], None] | None = None,
) -> RunStats:
    """Process ``frame_ids`` in chunks of ``config.chunk or chunk`` frames and append each
    frame's record to ``log`` (an open :class:`jaxcr.io.results.ResultsLog`) exactly once.

    Args:
        spec: how to build a worker (in this process for ``local``, in each actor for ``ray``).
        local_worker: an already-built worker (e.g. the one the command built to validate its
            inputs): it runs the chunks for ``local``, and writes the failed records of
            chunks lost with their Ray worker.
        on_record: called with each appended record (a progress bar).
        on_chunk: called with the number of records appended, after each chunk's (a progress
            bar counting in chunks).
    """
    size = config.chunk or chunk
    parts = chunks_of(list(frame_ids), max(1, size))
    stats = RunStats()
    written: set[str] = set()

    def emit(recs: Iterable[dict]) -> None:
        # a generator (segment, stereo) yields each frame as its files are written: appended
        # one by one at once; a list (a whole chunk, e.g. fk's rows) is appended in one write
        batch = [] if isinstance(recs, list) else None
        n = 0
        for rec in recs:
            fid = str(rec[key])
            if fid in written:  # a re-run chunk's duplicate: never written twice
                continue
            written.add(fid)
            if batch is None:
                log.append(rec)
            else:
                batch.append(rec)
            stats.records.append(rec)
            n += 1
            if on_record is not None and batch is None:
                on_record(rec)
        if batch:
            log.append_many(batch)
            if on_record is not None:
                for rec in batch:
                    on_record(rec)
        if on_chunk is not None and n:
            on_chunk(n)

    if config.kind == "local":
        worker = local_worker or spec.build()
        c0, r0 = worker.compile_s, worker.run_s
        for part in parts:
            emit(worker.process(part))
        stats.compile_s, stats.run_s = worker.compile_s - c0, worker.run_s - r0
        stats.executor = {"kind": "local", "tasks": len(parts), "chunk": size,
                          "hosts": [socket.gethostname()]}  # fmt: skip
        return stats
    if config.kind == "ray":
        failed = local_worker.failed_record if local_worker is not None else (
            lambda fid, reason: {key: fid, "ok": False, "reason": reason})  # fmt: skip
        return _run_ray(spec, parts, config, emit, stats, failed)
    raise InputError(f"unknown executor {config.kind!r}", field="executor")


# --------------------------------------------------------------------------- Ray


def _actor_class():
    import ray

    @ray.remote(max_restarts=RAY_RETRIES, max_task_retries=RAY_RETRIES)
    class FrameActor:
        """One per worker process: builds the command's worker once (its jitted functions stay
        compiled across chunks) and processes chunks."""

        def __init__(self, spec: WorkerSpec):
            os.environ.setdefault("JAX_PLATFORMS", "cpu")
            from jaxcr.io.compile_cache import enable_compile_cache

            enable_compile_cache()  # the driver's JAXCR_* settings reach the workers' env
            self.worker = spec.build()

        def process(self, ids: list[str]) -> dict:
            c0, r0, t0 = self.worker.compile_s, self.worker.run_s, time.perf_counter()
            recs = list(self.worker.process(ids))
            return {
                "records": recs,
                "compile_s": self.worker.compile_s - c0,
                "run_s": self.worker.run_s - r0,
                "wall_s": time.perf_counter() - t0,
                "host": socket.gethostname(),
                "pid": os.getpid(),
            }

        def pid(self) -> int:
            return os.getpid()

    return FrameActor


def ray_init(address: str | None, workers: int | None) -> None:
    """Connect to (``address``) or start (None) a Ray instance, once per process."""
    import ray

    if ray.is_initialized():
        return
    env = {k: v for k, v in os.environ.items()
           if k.startswith(("JAXCR_", "JAX_", "XLA_")) or k == "PYTHONPATH"}  # fmt: skip
    kw = {"runtime_env": {"env_vars": env}} if address is not None else {}
    if address is None:
        # a private local instance; the workers inherit this process's environment
        kw.update(num_cpus=workers or os.cpu_count(), include_dashboard=False)
    try:
        ray.init(address=address, log_to_driver=False, configure_logging=False, **kw)
    except (ConnectionError, ValueError, RuntimeError) as err:
        raise InputError(f"cannot reach the Ray cluster at {address!r}: {err}",
                         field="address") from None  # fmt: skip


def _cause(err: BaseException) -> BaseException:
    """The user-level exception inside a Ray task error (the original object, so an
    :class:`InputError` prints its one line, not Ray's traceback)."""
    cause = getattr(err, "cause", None)
    return cause if isinstance(cause, BaseException) else err


def _run_ray(spec, parts, config, emit, stats: RunStats, failed_record) -> RunStats:
    import ray
    from ray.exceptions import ActorDiedError, ActorUnavailableError, RayActorError, RayTaskError

    ray_init(config.address, config.workers)
    # one CPU per actor; more actors than the cluster's CPUs would wait forever (the others
    # never give theirs back), so --workers is capped at the cluster's CPUs
    cpus = max(1, int(ray.cluster_resources().get("CPU", 1)))
    n_workers = max(1, min(config.workers or cpus, cpus, len(parts)))
    Actor = _actor_class()
    t_start = time.perf_counter()
    actors = [Actor.options(num_cpus=1).remote(spec) for _ in range(n_workers)]
    queue = list(range(len(parts)))[::-1]  # pop() takes the next chunk in order
    inflight: dict = {}  # ObjectRef -> (chunk index, actor index)
    load = [0] * n_workers
    done: dict[int, list[dict]] = {}
    next_out = 0
    hosts: set[str] = set()
    pids: set[int] = set()
    task_wall: list[float] = []
    lost = 0

    def submit() -> None:
        for a in range(n_workers):
            while load[a] < IN_FLIGHT and queue:
                i = queue.pop()
                inflight[actors[a].process.remote(parts[i])] = (i, a)
                load[a] += 1

    submit()
    while inflight:
        ready, _ = ray.wait(list(inflight), num_returns=1)
        ref = ready[0]
        i, a = inflight.pop(ref)
        load[a] -= 1
        res, why = None, ""
        try:
            res = ray.get(ref)
        except RayTaskError as err:
            cause = _cause(err)
            if not isinstance(cause, (ActorDiedError, RayActorError)):
                for r in inflight:
                    ray.cancel(r, force=True)
                raise cause from None
            why = str(cause)
        except (ActorDiedError, ActorUnavailableError, RayActorError) as err:
            why = str(err)
        if res is None:
            # Ray's restarts and retries are used up: record the chunk failed, replace the actor
            lost += 1
            why = " ".join(why.split())[:200]
            reason = f"{WORKER_LOST} after {RAY_RETRIES} retries ({why})"
            done[i] = [failed_record(fid, reason) for fid in parts[i]]
            actors[a] = Actor.options(num_cpus=1).remote(spec)
        else:
            done[i] = res["records"]
            stats.compile_s += res["compile_s"]
            stats.run_s += res["run_s"]
            hosts.add(res["host"])
            pids.add(res["pid"])
            task_wall.append(res["wall_s"])
        while next_out in done:  # in frame order, as a local run writes them
            emit(done.pop(next_out))
            next_out += 1
        submit()
    for actor in actors:
        ray.kill(actor)
    stats.executor = {
        "kind": "ray",
        "address": config.address,
        "workers": n_workers,
        "tasks": len(parts),
        "chunk": len(parts[0]) if parts else 0,
        "hosts": sorted(hosts),
        # more worker processes than actors: some were restarted after dying
        "worker_processes": len(pids),
        "chunks_lost": lost,
        "wall_s": time.perf_counter() - t_start,
        # seconds the actors spent inside process() (the rest of wall x workers is start-up,
        # Ray's scheduling and transfer, and idle actors)
        "task_wall_s": sum(task_wall),
    }
    return stats
