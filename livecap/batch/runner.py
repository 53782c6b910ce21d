"""The client side of a batch: skip what is done, send the rest to Dask, follow it, summarise."""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Callable
from contextlib import contextmanager
from pathlib import Path

from livecap.batch.jobs import Job
from livecap.batch.summary import write_summary
from livecap.batch.worker import SolverCache, load_record, solve_job

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


def default_workers() -> int:
    return max(1, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1))


@contextmanager
def dask_client(workers: int | None = None, scheduler: str | None = None):
    """A client of the user's scheduler, or of a LocalCluster of worker processes (one thread each)
    that is closed on exit; the solver cache is registered as a worker plugin either way."""
    from distributed import Client, LocalCluster

    logging.getLogger("distributed").setLevel(logging.ERROR)  # its INFO lines would bury the progress bar
    if scheduler:
        client = Client(scheduler, timeout="30s")
        cluster = None
    else:
        import dask

        with dask.config.set(LOCAL_CLUSTER_CONFIG):
            cluster = LocalCluster(n_workers=workers or default_workers(), threads_per_worker=1, processes=True,
                                   dashboard_address=None, silence_logs=logging.ERROR)
        client = Client(cluster)
    try:
        client.register_plugin(SolverCache(), name=SolverCache.name)
        yield client
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


def run_batch(jobs: list[Job], out_dir: str | Path, client, force: bool = False,
              on_done: Callable[[dict], None] | None = None) -> tuple[list[dict], dict]:
    """Solve every job not already up to date on ``client``'s workers; rows in job order, and meta."""
    from distributed import as_completed

    Path(out_dir).mkdir(parents=True, exist_ok=True)
    rows: dict[int, dict] = {}
    pending = []
    for i, job in enumerate(jobs):
        if not force and not job.error and job.up_to_date():
            try:
                rows[i] = load_record(job)
                if on_done:
                    on_done(rows[i])
                continue
            except (OSError, ValueError):
                pass  # an unreadable record: solve again
        pending.append(i)
    start = time.perf_counter()
    run_id = time.time_ns()
    futures = {client.submit(solve_job, jobs[i], pure=False, key=f"livecap-batch-{run_id}-{i}-{jobs[i].stem}"): i
               for i in pending}
    for fut in as_completed(list(futures)):
        i = futures[fut]
        try:
            row = fut.result()
        except Exception as exc:  # the worker died or the task could not run: the take failed
            from livecap.batch.worker import one_line

            row = {"take": jobs[i].take, "stem": jobs[i].stem, "actor": jobs[i].actor, "mode": jobs[i].spec.mode,
                   "status": "failed", "error": f"worker: {one_line(exc)}", "output": str(jobs[i].output)}
        rows[i] = row
        if on_done:
            on_done(row)
    wall = time.perf_counter() - start
    ordered = [rows[i] for i in range(len(jobs))]
    meta = {"n_takes": len(jobs), "solved": len(pending), "skipped": len(jobs) - len(pending),
            "failed": sum(r["status"] == "failed" for r in ordered), "wall_seconds": wall,
            "workers": len(client.scheduler_info().get("workers", {})), "scheduler": client.scheduler.address}
    write_summary(ordered, out_dir, meta)
    return ordered, meta


def exit_code(rows: list[dict]) -> int:
    return min(sum(r["status"] == "failed" for r in rows), MAX_EXIT_CODE)
