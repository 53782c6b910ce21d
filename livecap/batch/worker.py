"""What runs on a Dask worker: a per-worker cache of rigs, profiles and prepared solvers (a worker
plugin), and the solve of one take, written by the worker to the output folder."""

from __future__ import annotations

import json
import logging
import os
import tempfile
import threading
import time
from pathlib import Path

from distributed.diagnostics.plugin import WorkerPlugin

from livecap.batch.jobs import Job
from livecap.batch.outputs import write_output
from livecap.batch.spec import PRIOR_WORDS, SolveSpec
from livecap.batch.stats import take_stats
from livecap.core.take import Take
from livecap.modes.registry import build_solver
from livecap.offline.setup import check_labels, load_rig_layout, markers_path, profile_from_take
from livecap.offline.solve import solve_take
from transport.takefile import read_take

PLUGIN_NAME = "livecap-batch-cache"
MAX_ERROR_CHARS = 300
# glibc gives a freed heap top back to the kernel once it passes the trim threshold, so a worker faulted in again,
# every take, the ~13 MB that reading a C3D take allocates in small pieces (3.2 k page faults, ~6 % of a 20 s
# take's CPU; docs/batch.md "the first take"). Fixed thresholds keep the freed heap for the next take; arrays of
# 32 MB and more (glibc's own ceiling for its moving mmap threshold) are still mapped and unmapped on their own.
HEAP_TRIM_BYTES = 1 << 29
HEAP_MMAP_BYTES = 1 << 25
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3  # glibc's mallopt parameters (malloc.h)
# glibc gives the worker's solving thread a malloc arena of its own, empty until its first take grows it page by
# page (9.7 k minor faults, +20-30 ms CPU on a 20 s take: docs/batch.md "one task per worker"); faulted in on that
# thread at worker start instead, in pieces under HEAP_MMAP_BYTES so that they come from the arena and stay in it.
PRETOUCH_BYTES = 1 << 26
PRETOUCH_PIECE = 1 << 23
_UMASK = os.umask(0o022)
os.umask(_UMASK)


class SolverCache(WorkerPlugin):
    """Rigs, profiles and prepared solvers, built once per worker (per thread for solvers, which hold
    state) and reused across takes; a solver is ``reset()`` before each take, which gives the same
    numbers as a fresh one (tested against ``livecap solve``)."""

    name = PLUGIN_NAME

    def __init__(self) -> None:
        self.parser = None
        self.rigs: dict = {}
        self.profiles: dict = {}
        self.solvers: dict = {}
        self.spare: dict = {}  # solvers prepared before the fork, not yet claimed by a thread
        self.built = 0
        self._lock = threading.Lock()

    def setup(self, worker=None):
        """Start from what the forkserver prepared before forking this worker (``PRELOADED``; empty in a
        spawned worker or on a user's cluster): its first take then loads and builds nothing (keys hold the
        files' mtimes, so nothing stale is adopted); the worker's solving thread gets its heap (``pretouch_heap``),
        awaited by the plugin's registration."""
        keep_heap()
        self.rigs = dict(PRELOADED.rigs)
        self.profiles = dict(PRELOADED.profiles)
        self.solvers.clear()
        self.spare = {key[:-1]: solver for key, solver in PRELOADED.solvers.items()}
        executor = getattr(worker, "executors", {}).get("default")
        if executor is not None:  # on the thread that will solve, before registration completes
            import asyncio

            return asyncio.wrap_future(executor.submit(pretouch_heap))
        return None

    def __getstate__(self) -> dict:  # travels to the workers empty
        return {}

    def __setstate__(self, state: dict) -> None:
        self.__init__()

    def rig(self, spec: SolveSpec):
        key = (spec.rig, spec.markers, _stamp([Path(spec.rig), *_rig_files(spec)]))
        with self._lock:
            if key not in self.rigs:
                self.rigs[key] = load_rig_layout(spec.rig, spec.markers)
            return self.rigs[key]

    def profile(self, path: str, noise_mm: float | None = None):
        from livecap.calibration.profile import Profile
        from livecap.modes.robust import override_noise

        key = (path, os.stat(path).st_mtime_ns, noise_mm)
        with self._lock:
            if key not in self.profiles:
                profile = Profile.load(path)
                if noise_mm is not None:
                    override_noise(profile, noise_mm)
                self.profiles[key] = profile
            return key, self.profiles[key]

    def solver(self, spec: SolveSpec, profile_key, profile):
        """The spec's solver, built (its options read: a weights-CSV prior is parsed then) only on a miss."""
        files = [Path(p) for p in (spec.settings.keys, spec.settings.prior) if p and p not in PRIOR_WORDS]
        key = (profile_key, spec.mode, spec.settings, _stamp(files), threading.get_ident())
        solver = self.solvers.get(key)
        if solver is None and (solver := self.spare.pop(key[:-1], None)) is not None:
            self.solvers[key] = solver
        if solver is None or not hasattr(solver, "reset"):
            solver = build_solver(spec.mode, profile, spec.settings.options())
            self.built += 1
            self.solvers[key] = solver
        else:
            solver.reset()
        return solver


def keep_heap() -> bool:
    """This process keeps its freed heap for the next take (glibc's ``mallopt``; elsewhere nothing): True if set."""
    import ctypes
    import platform
    import sys

    if not sys.platform.startswith("linux") or platform.libc_ver()[0] != "glibc":
        return False
    libc = ctypes.CDLL(None)
    return bool(libc.mallopt(_M_TRIM_THRESHOLD, HEAP_TRIM_BYTES) and libc.mallopt(_M_MMAP_THRESHOLD, HEAP_MMAP_BYTES))


def pretouch_heap() -> int:
    """The calling thread's malloc arena grown to a take's working set and freed again (kept: ``keep_heap``), so
    that its first take reuses those pages instead of faulting in fresh ones. Minor faults taken."""
    faults = _faults()
    pieces = [bytearray(PRETOUCH_PIECE) for _ in range(PRETOUCH_BYTES // PRETOUCH_PIECE)]  # zero-filled: touched
    del pieces
    return _faults() - faults


def _faults() -> int:
    """Minor page faults of the calling thread so far (Linux; 0 elsewhere)."""
    import resource

    who = getattr(resource, "RUSAGE_THREAD", None)
    return resource.getrusage(who).ru_minflt if who is not None else 0


def _stamp(paths: list[Path]) -> tuple:
    """The modification times of the files a cached object was read from: a changed file is read again."""
    return tuple(p.stat().st_mtime_ns if p.exists() else None for p in paths)


def _rig_files(spec: SolveSpec) -> list[Path]:
    rig = Path(spec.rig)
    files = sorted(p for p in rig.iterdir() if p.is_file()) if rig.is_dir() else []
    return [*files, Path(spec.markers) if spec.markers else markers_path(spec.rig)]


_LOCAL = SolverCache()  # in-process use (no Dask worker), e.g. the benchmark's loop
PRELOADED = SolverCache()  # filled in the forkserver (livecap/batch/forkserver.py) before workers are forked


def _cache() -> SolverCache:
    try:
        from distributed import get_worker

        return get_worker().plugins[PLUGIN_NAME]
    except (ValueError, KeyError):
        return _LOCAL


class _Warnings(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.lines: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        if record.thread == threading.get_ident():
            self.lines.append(record.getMessage())


def one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text if len(text) <= MAX_ERROR_CHARS else text[: MAX_ERROR_CHARS - 3] + "..."


def _check_labels(path: str, take_labels, profile_labels) -> list[str]:
    have = set(take_labels)
    lacking = [lab for lab in profile_labels if lab not in have]
    if len(lacking) * 2 > len(profile_labels):
        raise ValueError(f"{path}: wrong labels: lacks {len(lacking)} of the rig's {len(profile_labels)} markers "
                         f"(e.g. {', '.join(lacking[:4])})")
    return [f"labels absent from the take: {', '.join(lacking[:8])}"] if lacking else []


def solve_spec(spec: SolveSpec, take: Take, take_path: str, cache: SolverCache):
    """The take solved as ``livecap solve`` would with the spec's settings: (solved, profile, rig)."""
    rig, layout = cache.rig(spec)
    settings = spec.settings
    if spec.profile:
        profile_key, profile = cache.profile(spec.profile, settings.noise_mm)
        solver = cache.solver(spec, profile_key, profile)
    else:
        check_labels(take, layout.labels, take_path, spec.rig)
        profile = profile_from_take(rig, layout, take, spec.neutral_seconds, settings.noise_mm)
        solver = build_solver(spec.mode, profile, settings.options())
    return solve_take(take, profile, solver), profile, rig


def solve_and_write(job: Job, take: Take, cache: SolverCache) -> tuple[list[str], dict]:
    """The take solved, its statistics and its output written: the whole of a take's work, which the forkserver's
    warm-up (runner.warm_kernels) also does on a short take so that a worker's first take loads nothing new (the
    CSV writer's kernel, ``transport.fixed_point``, was left to it). The label notes and the statistics."""
    notes = _check_labels(job.take, take.labels, cache.rig(job.spec)[1].labels)
    solved, profile, rig = solve_spec(job.spec, take, job.take, cache)
    stats = take_stats(take, solved, profile)
    write_output(job, solved, stats.pop("frame_residual_mm"), rig)
    return notes, stats


KERNEL_PACKAGES = ("solvers", "transport")  # where livecap's numba kernels live (livecap/ only imports them)


_FOUND: dict = {"modules": -1, "kernels": []}  # kernels() as of the last module count


def kernels() -> list:
    """The numba kernels this process has imported from livecap's packages (solvers/, and the CSV writer's in
    transport/). Looked for again only when a module was imported since: walking every module's names took
    0.4 ms, twice a take (``solve_job`` counts the kernels compiled during it)."""
    import sys

    from numba.core.registry import CPUDispatcher

    if len(sys.modules) != _FOUND["modules"]:
        found = {id(obj): obj for name, mod in list(sys.modules.items()) if name.split(".")[0] in KERNEL_PACKAGES
                 for obj in vars(mod).values() if isinstance(obj, CPUDispatcher)}  # one each, wherever imported
        _FOUND.update(modules=len(sys.modules), kernels=list(found.values()))
    return _FOUND["kernels"]


def compiled_kernels() -> int:
    """Numba kernels this process has compiled so far (cache misses): 0 in a worker whose kernels all came from
    the on-disk cache the client warmed (runner.warm_kernels)."""
    return sum(sum(obj.stats.cache_misses.values()) for obj in kernels())


def solve_job(job: Job, cache: SolverCache | None = None) -> dict:
    """Solve one take exactly as ``livecap solve`` would and write its output and record; never raises:
    a failure comes back as a row with ``status`` "failed" and a one-line ``error``."""
    cache = cache or _cache()
    start, cpu, compiled, built = time.perf_counter(), time.process_time(), compiled_kernels(), cache.built
    thread_cpu, faults = time.thread_time(), _faults()
    row: dict = {"take": job.take, "stem": job.stem, "actor": job.actor, "mode": job.spec.mode,
                 "profile": job.spec.profile or "", "output": str(job.output), "status": "failed", "error": "",
                 "worker": os.getpid(), "started": time.time(), "spec": repr(job.spec)}
    if job.error:
        row["error"] = job.error
        row["seconds"] = 0.0
        job.record.unlink(missing_ok=True)  # the runner reads a finished take's record: no old success for this
        return row
    handler = _Warnings()
    logging.getLogger().addHandler(handler)
    try:
        notes, stats = solve_and_write(job, read_take(job.take), cache)
        row["warnings"] = notes + stats.pop("flags") + handler.lines
        row.update(stats)
        row["status"] = "ok"
    except Exception as exc:  # a bad take must not stop the batch: it comes back as a failed row
        row["error"] = one_line(exc)
    finally:
        logging.getLogger().removeHandler(handler)
    row["seconds"] = time.perf_counter() - start
    row["cpu_seconds"] = time.process_time() - cpu  # the worker process's CPU: load on a shared machine aside
    row["thread_cpu_seconds"] = time.thread_time() - thread_cpu  # the solving thread's alone (no event loop)
    row["page_faults"] = _faults() - faults  # the solving thread's minor faults: memory given back and taken again
    row["kernels_compiled"] = compiled_kernels() - compiled
    row["solvers_built"] = cache.built - built
    if row["status"] == "ok":
        _write_record(job.record, row)
    else:
        job.record.unlink(missing_ok=True)  # an old success must not stand in for this failure
    return row


def solve_queue(slot: int, jobs: list[Job], claims: str, topic: str) -> list[list]:
    """One worker thread's share of a batch, in one Dask task for many takes (the scheduler hands over once per
    worker, not once per take: docs/batch.md "one task per worker"): claim the next unclaimed job of ``jobs`` (the
    client's order, largest first, so uneven takes end the batch evenly), solve it (``solve_job``), tell the client
    (an event on ``topic``), until every job is claimed. ``slot`` tells this worker's task from the others'.
    A claim is a file created exclusively in ``claims``, a folder on the file system the outputs and records
    already share: exactly one worker gets each take, in 0.02 ms (a ``distributed.Queue`` get, a round trip to
    the scheduler, took 0.6 ms). An event carries a failed take's row, a solved take's index only (the client reads
    its record); the task returns [index, row] for every take solved here, what the events may have missed."""
    cache, report = _cache(), _reporter(topic)
    done = []
    for i, job in enumerate(jobs):
        if not _claim(Path(claims) / str(i)):
            continue
        row = solve_job(job, cache)
        report([i, None if row["status"] == "ok" else json.loads(json.dumps(row, default=str))])
        done.append([i, row])
    return done


def _claim(path: Path) -> bool:
    try:
        os.close(os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644))
        return True
    except FileExistsError:
        return False


def _reporter(topic: str):
    """Sends an event to the batch's client on ``topic`` (through the scheduler, no reply awaited); outside a Dask
    worker, nothing."""
    try:
        from distributed import get_worker

        worker = get_worker()
    except ValueError:
        return lambda item: None
    return lambda item: worker.log_event(topic, item)


def read_record(job: Job) -> dict:
    """The row a solve of ``job`` wrote (``_write_record``)."""
    return json.loads(Path(job.record).read_text())


def load_record(job: Job) -> dict:
    """An up-to-date take's row from its record, as skipped in this run."""
    return {**read_record(job), "status": "skipped"}


def _write_record(record: Path, row: dict) -> None:
    """The record replaced atomically through a temporary file of this call's own: Dask may run one task twice
    at once (a worker presumed lost, its task resubmitted), and two writers of one fixed temporary name would make
    the slower one's rename fail and report the take failed."""
    record.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=record.name + ".", suffix=".partial", dir=record.parent)
    try:
        os.fchmod(fd, 0o666 & ~_UMASK)  # mkstemp's 0600 would survive the rename: the mode a plain write gives
        with os.fdopen(fd, "w") as f:
            f.write(json.dumps(row))
        os.replace(tmp, record)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
