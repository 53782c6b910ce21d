"""The client side of a batch: skip what is done, send the rest to Dask, follow it, summarise."""

from __future__ import annotations

import logging
import multiprocessing
import os
import pickle
import queue
import shutil
import tempfile
import time
import weakref
from collections import Counter
from collections.abc import Callable, Sequence
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path

from livecap.batch.jobs import RECORDS, Job
from livecap.batch.summary import LiveSummary, write_summary
from livecap.batch.worker import SolverCache, load_record, read_record, solve_job
from livecap.core.take import Take

log = logging.getLogger(__name__)
MAX_EXIT_CODE = 100  # exit code = failed takes, capped below the shell's signal codes

# Dask's defaults suit workers holding data; a worker solving one take after another pays for them per take
# (profiled and measured in docs/batch.md "Throughput"). The statistical profiler samples the solving
# thread every 10 ms; the 20 ms event-loop tick and the 100 ms memory monitor wake the event loop, which
# then waits for the solving thread's GIL; MALLOC_TRIM_THRESHOLD_ (glibc returns freed memory at once)
# turns every large numpy temporary into fresh zeroed pages. BLAS threads stay at one, as Dask sets them.
LOCAL_CLUSTER_CONFIG = {
    "distributed.worker.profile.enabled": False,
    "distributed.admin.tick.interval": "1s",
    "distributed.worker.memory.monitor-interval": "1s",
    "distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None,  # None: not set (Dask's convention)
}


# Worker processes forked from one forkserver that has imported distributed and livecap's worker side, set up
# numba and loaded the batch's kernels once (livecap/batch/forkserver.py): Dask's default, spawn, starts a fresh
# interpreter per worker that imports and loads them again (docs/batch.md "Start-up, fixed costs and scale").
FORKSERVER_PRELOAD = ["distributed", "livecap.batch.forkserver"]
WARM_ENV = "LIVECAP_BATCH_WARM"  # a pickle of the jobs whose kernels the forkserver loads
# "spawn" is Dask's default (benchmarks.batch compares the two); Windows has no forkserver
START_METHOD = "forkserver" if "forkserver" in multiprocessing.get_all_start_methods() else "spawn"
WARM_FRAMES = 120  # frames of a take solved per spec and format to load (or, on a cold cache, compile) its kernels
WARM_TRIES = 3  # takes of a spec and format tried before its kernels are left to the workers (they may all be bad)
_forkserver: dict = {}  # the forkserver outlives a cluster: it is started, and loads kernels, once a process
_THREADS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()  # client -> its workers' threads (_threads)


def default_workers() -> int:
    return max(1, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1))


def _few_per_spec(jobs: Sequence[Job]) -> list[Job]:
    """What warm_kernels may try: WARM_TRIES takes of each spec and format (the forkserver gets them pickled)."""
    count: Counter = Counter()
    return [j for j in jobs if not j.error and (count.update([(j.spec, j.fmt)]) or count[j.spec, j.fmt] <= WARM_TRIES)]


def warm_kernels(jobs: Sequence[Job], cache: SolverCache | None = None) -> float:
    """Solve the first frames of one take per spec and output format in this process, and write their output (to a
    temporary folder) as a worker would, which loads the numba kernels and modules a take needs, compiling the
    kernels into the on-disk cache (numba's ``cache=True``, shared by every process of this user and install) only
    if they are not there yet; the rigs, profiles and solvers it prepares stay in ``cache``. Seconds taken."""
    from livecap.batch.worker import solve_and_write
    from transport.takefile import read_take

    start = time.perf_counter()
    cache, done, tries = SolverCache() if cache is None else cache, set(), Counter()
    with tempfile.TemporaryDirectory(prefix="livecap-warm-") as out:
        for job in jobs:
            key = (job.spec, job.fmt)
            if job.error or key in done or tries[key] >= WARM_TRIES:
                continue
            tries[key] += 1
            try:
                solve_and_write(replace(job, out_dir=out), _warm_take(read_take(job.take)), cache)
                done.add(key)
            except Exception as exc:  # the take's own solve will report it; another take of the spec may warm
                log.debug("warm-up on %s: %s", job.take, exc)
    return time.perf_counter() - start


def _warm_take(take: Take) -> Take:
    """The take's first frames with one marker hidden from half way on: a visibility pattern new to the solver
    loads the kernels of a take's occluded frames (qp_kernels.pattern_workspace in weight space, pattern_hessian
    in marker space; ~14 ms from numba's cache), which a fully visible warm-up left to each worker's first take."""
    warm = take.slice(0, min(take.n_frames, WARM_FRAMES))
    valid = warm.valid.copy()
    valid[warm.n_frames // 2:, -1] = False
    return Take(warm.labels, warm.positions, valid, warm.rate, warm.first_frame)


def _start_cluster(workers: int | None, warm: Sequence[Job]):
    import dask
    from distributed import LocalCluster
    from distributed.utils import get_mp_context

    config = {**LOCAL_CLUSTER_CONFIG, "distributed.worker.multiprocessing-method": START_METHOD}
    forked = START_METHOD == "forkserver"
    if not forked or _forkserver:  # workers that start bare, or a forkserver that loaded other kernels
        warm_kernels(warm)  # ... find them in the cache, compiled once
    with tempfile.TemporaryDirectory(prefix="livecap-batch-") as tmp, dask.config.set(config):
        if forked and not _forkserver:
            get_mp_context().set_forkserver_preload(FORKSERVER_PRELOAD)  # Dask's own list is set by the first call
            path = Path(tmp) / "warm.pickle"
            path.write_bytes(pickle.dumps(_few_per_spec(warm)))
            os.environ[WARM_ENV] = str(path)  # the forkserver, started by the first worker, inherits it
        try:
            return LocalCluster(n_workers=workers or default_workers(), threads_per_worker=1, processes=True,
                                dashboard_address=None, silence_logs=logging.ERROR)
        finally:
            if os.environ.pop(WARM_ENV, None):
                _forkserver["started"] = True


@contextmanager
def dask_client(workers: int | None = None, scheduler: str | None = None, warm: Sequence[Job] = ()):
    """A client of the user's scheduler, or of a LocalCluster of worker processes (one thread each)
    that is closed on exit; the solver cache is registered as a worker plugin either way. The kernels of
    ``warm``'s specs are loaded once before any task runs: in the forkserver every local worker is forked
    from, or here, on the client, so that a user's workers that share this cache find them compiled."""
    from distributed import Client

    logging.getLogger("distributed").setLevel(logging.ERROR)  # its INFO lines would bury the progress bar
    if scheduler:
        warm_kernels(warm)
        client, cluster = Client(scheduler, timeout="30s"), None
    else:
        cluster = _start_cluster(workers, warm)
        client = Client(cluster)
    try:
        client.register_plugin(SolverCache(), name=SolverCache.name)
        _threads(client)
        yield client
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


def _size(job: Job) -> int:
    try:
        return os.stat(job.take).st_size
    except OSError:
        return 0


def _written_row(job: Job) -> dict | None:
    """A solved take's row as its worker wrote it (the record, complete before the task ends), read here instead
    of fetched from the worker: no gather round trip (client, scheduler, worker and back) per take; None if there
    is no record (a failed take), and the row is then fetched."""
    try:
        return read_record(job)
    except (OSError, ValueError):
        return None


def _failed(job: Job, error: str) -> dict:
    return {"take": job.take, "stem": job.stem, "actor": job.actor, "mode": job.spec.mode, "status": "failed",
            "error": error, "output": str(job.output)}


def run_batch(jobs: list[Job], out_dir: str | Path, client, force: bool = False,
              on_done: Callable[[dict], None] | None = None) -> tuple[list[dict], dict]:
    """Solve every job not already up to date on ``client``'s workers, largest take first, one task per worker
    thread that pulls takes until none is left (``worker.solve_queue``); each row goes to DIR/summary.csv as it
    comes in. Takes a dead worker had claimed and not finished are solved again, one task each, as Dask retries
    them. Rows in job order, and meta."""
    Path(out_dir).mkdir(parents=True, exist_ok=True)
    rows: dict[int, dict] = {}
    pending = []
    live = LiveSummary(out_dir)

    def add(i: int, row: dict) -> None:
        rows[i] = row
        live.add(row)
        if on_done:
            on_done(row)

    try:
        for i, job in enumerate(jobs):
            if not force and not job.error and job.up_to_date():
                try:
                    add(i, load_record(job))
                    continue
                except (OSError, ValueError):
                    pass  # an unreadable record: solve again
            pending.append(i)
        start, run_id = time.perf_counter(), time.time_ns()
        sizes = {i: _size(jobs[i]) for i in pending}
        order = sorted(pending, key=lambda i: -sizes[i])
        left = _pull(jobs, order, Path(out_dir), client, run_id, add) if order else []
        if left:
            log.warning("%d take(s) left unsolved by a lost worker: solved again", len(left))
            _each(jobs, left, client, run_id, add)
    finally:
        live.close()
    wall = time.perf_counter() - start
    ordered = [rows[i] for i in range(len(jobs))]
    meta = {"n_takes": len(jobs), "solved": len(pending), "skipped": len(jobs) - len(pending),
            "failed": sum(r["status"] == "failed" for r in ordered), "wall_seconds": wall,
            "workers": len(client.scheduler_info().get("workers", {})), "scheduler": client.scheduler.address}
    write_summary(ordered, out_dir, meta)
    return ordered, meta


def _threads(client) -> int:
    """The worker threads of ``client``'s cluster, read when ``dask_client`` made it: ``scheduler_info`` is a round
    trip to the scheduler (on the workers' cores), which the batch's first take waited for."""
    if client not in _THREADS:
        _THREADS[client] = sum(w.get("nthreads", 1) for w in client.scheduler_info().get("workers", {}).values()) or 1
    return _THREADS[client]


def _pull(jobs: list[Job], order: list[int], out_dir: Path, client, run_id: int,
          add: Callable[[int, dict], None]) -> list[int]:
    """``order``'s jobs solved by one ``solve_queue`` task per worker thread (fewer tasks than takes: the
    scheduler's hand-over, its per-task messages and the worker's task state machine once per worker, not per
    take); each take's row added as its worker reports it. The takes no worker reported (a worker died holding
    one), in ``order``."""
    from livecap.batch.worker import solve_queue

    topic, claims = f"livecap-batch-{run_id}", out_dir / RECORDS / f"claims-{run_id}"
    claims.mkdir(parents=True)
    inbox: queue.SimpleQueue = queue.SimpleQueue()
    queued = [jobs[i] for i in order]

    def take_in(item: list) -> None:
        k, row = item
        if order[k] not in rows_seen and (row := row or _written_row(queued[k])):  # no record: the task's result
            rows_seen.add(order[k])
            add(order[k], row)

    rows_seen: set[int] = set()
    client.subscribe_topic(topic, lambda event: inbox.put(("take", event[1])))  # sent before the tasks
    try:
        n = min(_threads(client), len(order))
        # one map, one message to the scheduler: every worker gets its task at once
        tasks = client.map(solve_queue, range(n), jobs=queued, claims=str(claims), topic=topic, pure=False,
                           key=[f"{topic}-queue-{k}" for k in range(n)])
        for task in tasks:
            task.add_done_callback(lambda fut: inbox.put(("task", fut)))
        running = set(tasks)
        while running:
            kind, item = inbox.get()
            if kind == "take":
                take_in(item)
                continue
            running.discard(item)
            try:
                for done in item.result():  # what the events brought, unless one was lost: one fetch per worker
                    take_in(done)
            except Exception as exc:  # the task was lost with its workers (Dask's retries spent): rows it sent stand
                log.warning("batch worker task lost: %s", exc)
    finally:
        client.unsubscribe_topic(topic)
        shutil.rmtree(claims, ignore_errors=True)
    return [i for i in order if i not in rows_seen]


def _each(jobs: list[Job], order: list[int], client, run_id: int, add: Callable[[int, dict], None]) -> None:
    """``order``'s jobs as one task each, which Dask retries on another worker if theirs dies (and reports lost
    after ``distributed.scheduler.allowed-failures`` deaths: a take that kills its worker fails alone)."""
    from distributed import as_completed

    from livecap.batch.worker import one_line

    futures = dict(zip(client.map(solve_job, [jobs[i] for i in order], pure=False,
                                  key=[f"livecap-batch-{run_id}-{i}-{jobs[i].stem}" for i in order]), order,
                       strict=True))
    for fut in as_completed(list(futures)):
        i = futures[fut]
        try:
            row = _written_row(jobs[i]) if fut.status == "finished" else None
            row = row or fut.result()
        except Exception as exc:  # the worker died or the task could not run: the take failed
            row = _failed(jobs[i], f"worker: {one_line(exc)}")
        add(i, row)


def exit_code(rows: list[dict]) -> int:
    return min(sum(r["status"] == "failed" for r in rows), MAX_EXIT_CODE)
