"""``livecap batch`` throughput: takes per second on a LocalCluster of 1 and 2 worker processes, and
the per-take overhead of the batch path against a warm in-process loop doing what ``livecap solve``
does (read the take, build the solver, solve, write the CSV), on copies of the bundled 20 s demo take
(2400 frames, 60 markers, 43 shapes) with a profile calibrated from the demo neutral take.

    python -m benchmarks.batch [--quick] [--json FILE] [--settings livecap,dask] [--placement cluster,sessions]
                               [--takes demo|real] [--scale 8,16,32,64] [--methods 16]
                               [--order uneven] [--refit FILE]

``--takes real``: instead of demo copies, 12 different 20 s takes on the ICT-FaceKit rig driven by the real
Live Link Face performances of ../shared/realdata/performance (`livecap generate --curves`, one actor, 20 s
segments of the files long enough for one), the profile calibrated from that actor's neutral take.

Each cluster is started and warmed (every worker solves a 1 s take: imports, rig and profile loaded,
solver prepared) before the timed batch; that fixed cost is reported beside it. Takes/s count the
solving (first task sent to last result in); the batch's summary (summary.json/csv/html/png, written
once per batch by the client) is timed and reported beside it. The baseline loop runs in its own
process with one BLAS thread, as Dask's worker processes do (OMP/MKL/OPENBLAS_NUM_THREADS=1), and
alternates with the batch's per-take function (``solve_job``: also the statistics and the record) in
that process, so the batch path's own work and the cost of running it in a Dask worker are told apart.
``--settings dask`` also runs the LocalCluster with Dask's defaults (livecap's settings, A/B).
The machine is shared: the load average is recorded beside every figure; CPU is process CPU time.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from contextlib import contextmanager
from itertools import pairwise
from pathlib import Path

import numpy as np

from benchmarks.timing import suite_main

ROOT = Path(__file__).resolve().parents[1]
RIG = Path(os.environ.get("LIVECAP_BENCH_RIG", ROOT / "recordings" / "demo_rig.npz"))  # the loop's process reads it
MODE = "robust"
ONE_THREAD = {"OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"}


def _load() -> float:
    with open("/proc/loadavg") as fh:
        return float(fh.read().split()[0])


def loop(profile: str, out: str, warm: str, takes: list[str], start_at: float | None = None) -> dict:
    """Wall and CPU seconds of the plain in-process loop over ``takes`` (after one untimed warm-up solve),
    and of the batch's per-take function on the same takes, alternating take by take. With ``start_at``
    (a ``time.time()``), only the loop, started then, and the time it ended: loops in parallel processes."""
    from livecap.batch.jobs import Job
    from livecap.batch.spec import SolveSpec
    from livecap.batch.worker import SolverCache, solve_job
    from livecap.calibration.profile import Profile
    from livecap.cli.common import load_rig
    from livecap.modes.registry import build_solver
    from livecap.offline.solve import solve_take
    from transport.takefile import read_take
    from transport.weights_csv import write_weights_csv

    class Args:
        rig, markers = str(RIG), None

    load_rig(Args)
    prof = Profile.load(profile)

    def one(path: str) -> None:
        solved = solve_take(read_take(path), prof, build_solver(MODE, prof, {}))
        write_weights_csv(Path(out) / (Path(path).stem + ".csv"), solved.names, solved.weights, solved.rate,
                          solved.first_frame)

    cache = SolverCache()

    def job(path: str) -> None:
        row = solve_job(Job(path, SolveSpec(str(RIG), MODE, profile), str(Path(out) / "job")), cache)
        if row["status"] != "ok":
            raise RuntimeError(row["error"])

    times = {"loop": [0.0, 0.0], "job": [0.0, 0.0]}
    for fn in (one, job):
        fn(warm)
    if start_at is not None:
        time.sleep(max(0.0, start_at - time.time()))
        began, cpu = time.time(), time.process_time()
        for t in takes:
            one(t)
        return {"ended": time.time(), "cpu": time.process_time() - cpu, "late": began - start_at}
    for t in takes:
        for name, fn in (("loop", one), ("job", job)):
            start, cpu = time.perf_counter(), time.process_time()
            fn(t)
            times[name][0] += time.perf_counter() - start
            times[name][1] += time.process_time() - cpu
    return {"wall": times["loop"][0], "cpu": times["loop"][1], "job_wall": times["job"][0], "job_cpu": times["job"][1]}


def child_env(extra: dict | None = None) -> dict:
    """This environment for a child process that must import what this one imports, however it is installed:
    the folders livecap and these benchmarks came from (unless the interpreter finds them anyway, as an installed
    package's site-packages) before whatever PYTHONPATH already holds."""
    import site

    import livecap

    own = {str(Path(p).resolve()) for p in [*site.getsitepackages(), site.getusersitepackages()]}
    paths = [str(p) for p in (Path(livecap.__file__).resolve().parents[1], ROOT) if str(p) not in own]
    paths += [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]
    return {**os.environ, **(extra or {}), "PYTHONPATH": os.pathsep.join(dict.fromkeys(paths))}


def _in_child(call: str, *args: str) -> dict:
    """``benchmarks.batch.CALL(*args)`` in a fresh process with one BLAS thread, as a Dask worker has."""
    code = f"import json, sys; from benchmarks.batch import {call}; print(json.dumps({call}(*sys.argv[1:])))"
    done = subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True,
                          env=child_env(ONE_THREAD), cwd=ROOT)
    if done.returncode:
        raise RuntimeError(f"benchmarks.batch.{call} failed: {done.stderr.strip()[-2000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def _loop_in_process(profile: str, out: Path, warm: Path, takes: list[Path]) -> dict:
    out.mkdir(parents=True, exist_ok=True)
    return _in_child("loop_main", profile, str(out), str(warm), *map(str, takes))


def loop_main(profile: str, out: str, warm: str, *takes: str) -> dict:
    return loop(profile, out, warm, list(takes))


def parallel_loop_main(start_at: str, profile: str, out: str, warm: str, *takes: str) -> dict:
    return loop(profile, out, warm, list(takes), float(start_at))


def _parallel_loops(k: int, profile: str, out: Path, warm: Path, takes: list[Path]) -> dict:
    """``k`` warm in-process loops at once, each in its own process on every k-th take, all starting at one
    instant: the baseline with the batch's parallelism (two processes on a 2-core VM slow each other)."""
    from concurrent.futures import ThreadPoolExecutor

    out.mkdir(parents=True, exist_ok=True)
    start_at = time.time() + 10.0  # after every process has imported, loaded and warmed up
    with ThreadPoolExecutor(k) as pool:
        parts = list(pool.map(lambda i: _in_child("parallel_loop_main", repr(start_at), profile, str(out), str(warm),
                                                   *map(str, takes[i::k])), range(k)))
    return {"wall": max(p["ended"] for p in parts) - start_at, "cpu": sum(p["cpu"] for p in parts),
            "late_s": max(p["late"] for p in parts), "ended_s": sorted(p["ended"] - start_at for p in parts)}


def nested(dotted: dict) -> dict:
    """Dask settings as dotted keys, as the nested mapping a Dask YAML file holds."""
    out: dict = {}
    for key, value in dotted.items():
        *path, last = key.split(".")
        node = out
        for part in path:
            node = node.setdefault(part, {})
        node[last] = value
    return out


@contextmanager
def _session_workers(n: int):
    """A ``dask scheduler`` and ``n`` ``dask worker`` processes, each in its own session: the kernel's
    autogroup scheduling then gives every worker its own fair share, as separate machines would have."""
    from benchmarks.processes import free_port
    from livecap.batch.runner import LOCAL_CLUSTER_CONFIG

    dask = Path(sys.executable).with_name("dask")
    address = f"tcp://127.0.0.1:{free_port()}"
    config = Path(tempfile.mkdtemp(prefix="livecap-dask-config-")) / "livecap-batch.yaml"
    config.write_text(json.dumps(nested(LOCAL_CLUSTER_CONFIG)))  # JSON is YAML: the file docs/batch.md shows
    env = child_env({"DASK_CONFIG": str(config)})
    quiet = {"stdout": subprocess.DEVNULL, "stderr": subprocess.DEVNULL, "start_new_session": True, "env": env}
    procs = [subprocess.Popen([dask, "scheduler", "--host", "127.0.0.1", "--port", address.rsplit(":", 1)[1],
                               "--no-dashboard"], **quiet)]
    try:
        for _ in range(n):
            procs.append(subprocess.Popen([dask, "worker", address, "--nworkers", "1", "--nthreads", "1",
                                           "--no-dashboard"], **quiet))
        yield address
    finally:
        for proc in reversed(procs):
            proc.terminate()
        for proc in procs:
            proc.wait(timeout=60)
        shutil.rmtree(config.parent, ignore_errors=True)


@contextmanager
def _client(workers: int, placement: str, settings: str):
    from livecap.batch import runner

    if placement == "sessions":
        with _session_workers(workers) as address, runner.dask_client(scheduler=address) as client:
            client.wait_for_workers(workers, timeout=120)
            yield client
        return
    tuned, environ = runner.LOCAL_CLUSTER_CONFIG, dict(os.environ)
    if settings == "dask":  # the LocalCluster as before livecap's settings: Dask's defaults, profiler off
        runner.LOCAL_CLUSTER_CONFIG = {"distributed.worker.profile.enabled": False}
    try:
        with runner.dask_client(workers=workers) as client:
            yield client
    finally:
        runner.LOCAL_CLUSTER_CONFIG = tuned
        os.environ.clear()  # a Nanny sets its workers' variables (MALLOC_TRIM_THRESHOLD_) in this process too
        os.environ.update(environ)


def _batch(workers: int, profile: str, out: Path, warm: Path, takes: list[Path], placement: str = "cluster",
           settings: str = "livecap") -> dict:
    from livecap.batch.jobs import Job
    from livecap.batch.runner import run_batch
    from livecap.batch.spec import SolveSpec

    def jobs(paths, where):
        return [Job(str(p), SolveSpec(str(RIG), MODE, profile), str(where)) for p in paths]

    t0 = time.perf_counter()
    load0 = _load()
    with _client(workers, placement, settings) as client:
        started = time.perf_counter() - t0
        warm_jobs = []
        for i in range(workers):  # one warm-up take per worker (same file under another name)
            copy = warm.with_name(f"{warm.stem}_w{i}{warm.suffix}")
            shutil.copy(warm, copy)
            warm_jobs.append(copy)
        run_batch(jobs(warm_jobs, out / "warm"), out / "warm", client, force=True)
        warmed = time.perf_counter() - t0 - started
        t1, c1 = time.perf_counter(), time.process_time()
        rows, meta = run_batch(jobs(takes, out / "timed"), out / "timed", client, force=True)
        total, client_cpu = time.perf_counter() - t1, time.process_time() - c1
    failed = [r["error"] for r in rows if r["status"] != "ok"]
    if failed:
        raise RuntimeError(f"batch failed: {failed[0]}")
    wall = meta["wall_seconds"]  # solving: first task sent to last result in
    return {"workers": workers, "placement": placement, "settings": settings, "takes": len(takes), "wall_s": wall,
            "takes_per_s": len(takes) / wall, "summary_s": total - wall, "takes_per_s_with_summary": len(takes) / total,
            "per_take_s": wall / len(takes) * workers, "cluster_start_s": started, "warm_up_s": warmed,
            "worker_seconds_per_take": sum(r["seconds"] for r in rows) / len(rows),
            "cpu_per_take_s": sum(r["cpu_seconds"] for r in rows) / len(rows),
            "client_cpu_per_take_s": client_cpu / len(takes),  # this process: client and (LocalCluster) scheduler
            "load_start": load0, "load_end": _load()}


def start_once(method: str, profile: str, warm: str, workers: str = "2") -> dict:
    """One ``livecap batch`` start, in a fresh process as the command has: the cluster of ``method`` (spawn:
    Dask's default, the client warming the kernels first; forkserver: livecap's, the forkserver loading them),
    until every worker has solved a 1 s take (imports, rig, profile, kernels, solver loaded), then the close."""
    t0 = time.perf_counter()
    from livecap.batch import runner
    from livecap.batch.jobs import Job
    from livecap.batch.spec import SolveSpec
    from livecap.batch.worker import solve_job

    imported = time.perf_counter() - t0
    runner.START_METHOD = method
    n = int(workers)
    spec = SolveSpec(str(RIG), MODE, profile)
    out = Path(tempfile.mkdtemp(prefix="livecap-start-"))
    copies = []
    for i in range(n):
        copies.append(out / f"w{i}.c3d")
        shutil.copy(warm, copies[-1])
    jobs = [Job(str(p), spec, str(out)) for p in copies]
    t1 = time.perf_counter()
    with runner.dask_client(n, warm=jobs[:1]) as client:
        t2 = time.perf_counter()
        rows = client.gather([client.submit(solve_job, j, pure=False, workers=[w], allow_other_workers=False)
                              for j, w in zip(jobs, client.scheduler_info()["workers"], strict=True)])
        t3 = time.perf_counter()
    t4 = time.perf_counter()
    shutil.rmtree(out, ignore_errors=True)
    assert all(r["status"] == "ok" for r in rows), rows
    return {"method": method, "import_s": imported, "start_s": t2 - t1, "first_take_s": t3 - t2, "close_s": t4 - t3,
            "ready_s": t3 - t0, "total_s": t4 - t0, "first_take_cpu_s": max(r["cpu_seconds"] for r in rows),
            "kernels_compiled": sum(r["kernels_compiled"] for r in rows)}


def _end_to_end(workers: int, profile: str, out: Path, takes: list[Path]) -> dict:
    """What ``livecap batch`` does, phase by phase (a fresh cluster): start (the forkserver loading the
    kernels, the workers forked from it), solving (first task sent to last result in), summary, close."""
    from livecap.batch import runner
    from livecap.batch.jobs import Job
    from livecap.batch.spec import SolveSpec

    jobs = [Job(str(p), SolveSpec(str(RIG), MODE, profile), str(out)) for p in takes]
    load0 = _load()
    t0 = time.perf_counter()
    with runner.dask_client(workers, warm=jobs) as client:
        pids = client.run(os.getpid)
        count, ends = [0], {}

        def done(row: dict) -> None:  # the CPU of every process when the last result is in (the summary aside)
            count[0] += 1
            if count[0] == len(jobs):
                ends.update(cpu=_cpu_now(pids.values()), at=time.time())

        cpu0 = _cpu_now(pids.values())
        t1, c1, sent = time.perf_counter(), time.process_time(), time.time()
        rows, meta = runner.run_batch(jobs, out, client, force=True, on_done=done)
        t2, client_cpu = time.perf_counter(), time.process_time() - c1
    t3 = time.perf_counter()
    failed = [r["error"] for r in rows if r["status"] != "ok"]
    if failed:
        raise RuntimeError(f"batch failed: {failed[0]}")
    busy: dict = {}
    spans: dict = {}
    for r in rows:
        busy[r["worker"]] = busy.get(r["worker"], 0.0) + r["seconds"]
        spans.setdefault(r["worker"], []).append((r["started"], r["started"] + r["seconds"]))
    gaps = [b[0] - a[1] for s in spans.values() for a, b in pairwise(sorted(s))]
    firsts = {min((r for r in rows if r["worker"] == w), key=lambda r: r["started"])["take"] for w in spans}

    def mean(key: str, first: bool) -> float:  # over each worker's first take, or over the others
        values = [r.get(key, np.nan) for r in rows if (r["take"] in firsts) == first]
        return float(np.mean(values)) if values else float("nan")
    n, solve = len(takes), meta["wall_seconds"]
    return {"workers": workers, "takes": n, "start_s": t1 - t0, "solve_s": solve,
            "first_task_s": min(r["started"] for r in rows) - sent,  # run_batch called to the first take begun
            "idle_between_takes_s": float(np.mean(gaps)) if gaps else 0.0,  # a worker's, result out to next in
            "first_take_cpu_s": mean("cpu_seconds", True),
            "rest_cpu_per_take_s": mean("cpu_seconds", False),  # each worker's first aside
            "first_take_thread_cpu_s": mean("thread_cpu_seconds", True),
            "rest_thread_cpu_per_take_s": mean("thread_cpu_seconds", False),
            "first_take_page_faults": mean("page_faults", True),
            "rest_page_faults_per_take": mean("page_faults", False),
            "summary_s": t2 - t1 - solve, "close_s": t3 - t2, "total_s": t3 - t0, "per_take_s": solve * workers / n,
            "cpu_per_take_s": sum(r["cpu_seconds"] for r in rows) / n, "client_cpu_per_take_s": client_cpu / n,
            "kernels_compiled": sum(r["kernels_compiled"] for r in rows),
            "busy_max_over_mean": max(busy.values()) / (sum(busy.values()) / len(busy)),
            "busy_s": sorted(busy.values(), reverse=True) + [0.0] * (workers - len(busy)),
            **_wall_parts(spans, sent, ends["at"], solve, {k: ends["cpu"][k] - cpu0[k] for k in cpu0}),
            "load_start": load0, "load_end": _load()}


def _cpu_now(worker_pids) -> dict:
    """CPU seconds so far of this process's threads by role (the client, the LocalCluster's event loop running
    the scheduler and the nannies, Dask's other threads), of each worker process, and of the other children
    (the forkserver): where the wall beyond the workers' CPU may go."""
    import threading

    import psutil

    me = psutil.Process()
    names = {t.native_id: t.name for t in threading.enumerate()}
    out = {"client_main": 0.0, "cluster_loop": 0.0, "other_threads": 0.0}
    for t in me.threads():
        name = names.get(t.id, "")
        role = "client_main" if t.id == threading.main_thread().native_id else (
            "cluster_loop" if "IO loop" in name or "IOLoop" in name else "other_threads")
        out[role] += t.user_time + t.system_time
    workers = set(worker_pids)
    for i, pid in enumerate(sorted(workers)):
        c = psutil.Process(pid).cpu_times()
        out[f"worker{i}"] = c.user + c.system
    out["other_children"] = sum(sum(p.cpu_times()[:2]) for p in me.children(recursive=True) if p.pid not in workers)
    return out


def _wall_parts(spans: dict, sent: float, last_in: float, solve: float, cpu: dict) -> dict:
    """The solving wall split per worker: from the tasks sent to its first take begun, its takes' own seconds,
    its idle gaps between takes, and its idle tail (its last take ended to the last result in); with every
    process's CPU over the same span (``_cpu_now``)."""
    parts = []
    for worker_spans in spans.values():
        s = sorted(worker_spans)
        parts.append({"takes": len(s), "to_first_s": s[0][0] - sent, "busy_s": sum(b - a for a, b in s),
                      "gaps_s": sum(b[0] - a[1] for a, b in pairwise(s)), "tail_s": last_in - s[-1][1]})
    return {"per_worker": parts, "process_cpu_s": cpu, "last_result_s": last_in - sent, "solve_wall_s": solve}


def end_to_end_main(workers: str, profile: str, out: str, *takes: str) -> dict:
    return _end_to_end(int(workers), profile, Path(out), [Path(t) for t in takes])


def method_main(method: str, profile: str, out: str, *takes: str) -> dict:
    from livecap.batch import runner

    runner.START_METHOD = method
    return {"method": method, **_end_to_end(2, profile, Path(out), [Path(t) for t in takes])}


def order_main(order: str, profile: str, out: str, *takes: str) -> dict:
    from livecap.batch import runner

    if order == "listed":  # every take the same size: the sort keeps the listed order, Dask's first-in first-out
        runner._size = lambda job: 0
    return {"order": order, **_end_to_end(2, profile, Path(out), [Path(t) for t in takes])}


def _alternate(call: str, choices: tuple[str, ...], reps: int, profile: str, work: Path, takes: list[Path],
               line: Callable[[dict], str]) -> list[dict]:
    """``benchmarks.batch.CALL(choice, ...)`` end to end on ``takes``, a fresh process each, the choices
    alternating ``reps`` times (the machine is shared: neighbours' load falls on every choice alike)."""
    out = []
    for rep in range(reps):
        for choice in choices:
            r = {**_in_child(call, choice, profile, str(work / f"{call}-{choice}-{rep}"), *map(str, takes)), "rep": rep}
            out.append(r)
            print("  " + line(r))
    return out


def uneven(profile: str, work: Path, demo: Path, reps: int = 3) -> list[dict]:
    """A library of uneven takes, the long one listed last: 16 copies of the 20 s demo take, then one of 200 s
    (the demo take ten times over), at 2 workers, largest first (livecap's) against the listed order (Dask's
    first in, first out), alternating ``reps`` times. Listed, the long take starts when the short ones are
    done and runs alone; largest first, the other worker solves the short ones meanwhile."""
    from transport.takefile import read_take, write_take

    full = read_take(demo)
    long = type(full)(full.labels, np.concatenate([full.positions] * 10), np.concatenate([full.valid] * 10),
                      full.rate, full.first_frame)
    folder = work / "uneven"
    folder.mkdir(parents=True, exist_ok=True)
    takes = []
    for i in range(16):
        takes.append(folder / f"a{i:02d}.c3d")
        shutil.copy(demo, takes[-1])
    takes.append(folder / "z.c3d")
    write_take(long, takes[-1])
    return _alternate("order_main", ("listed", "largest"), reps, profile, work, takes, lambda r: (
        f"{r['order']:>8} first, rep {r['rep']}: solving {r['solve_s']:.2f} s, the two workers busy "
        f"{r['busy_s'][0]:.2f} / {r['busy_s'][1]:.2f} s, load {r['load_start']:.1f}-{r['load_end']:.1f}"))


def methods(n: int, profile: str, work: Path, demo: Path, reps: int = 3) -> list[dict]:
    """Per take, spawned (Dask's default) against forked workers: ``livecap batch`` end to end at 2 workers on
    ``n`` takes, a fresh process each, the two alternating ``reps`` times."""
    takes = []
    for i in range(n):
        takes.append(work / "methods" / f"take{i:03d}.c3d")
        takes[-1].parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(demo, takes[-1])
    return _alternate("method_main", ("spawn", "forkserver"), reps, profile, work, takes, lambda r: (
        f"{r['method']:>10} rep {r['rep']}: worker CPU {r['cpu_per_take_s']:.3f} s/take, solving "
        f"{r['solve_s']:.2f} s ({r['per_take_s']:.3f} s/take at 2 workers), start {r['start_s']:.2f} s, "
        f"close {r['close_s']:.2f} s, load {r['load_start']:.1f}-{r['load_end']:.1f}"))


def scale(ns: list[int], profile: str, work: Path, sources: list[Path], warm: Path, start_reps: int = 3) -> dict:
    """Issue 39.3's acceptance: per take, ``livecap batch`` at 2 workers (a fresh process, as the command is)
    against the warm in-process loop on the same takes (copies of ``sources`` in turn), run just before and
    just after it (the machine is shared: the mean of the two is the baseline), and against two such loops in
    parallel processes, run before the batch at every other take count and after it at the others; the fixed
    costs (start, first task, summary, close) beside, and their fit against the take count."""
    out: dict = {"start": [], "runs": []}
    for rep in range(start_reps):  # start-up A/B, alternating, each in a fresh process
        for method in ("spawn", "forkserver"):
            r = _in_child("start_once", method, profile, str(warm))
            r.update(rep=rep, load=_load())
            out["start"].append(r)
    for k, n in enumerate(ns):
        takes = []
        for i in range(n):
            takes.append(work / f"scale{n}" / f"take{i:03d}.c3d")
            takes[-1].parent.mkdir(parents=True, exist_ok=True)
            shutil.copy(sources[i % len(sources)], takes[-1])
        load0 = _load()
        before = _loop_in_process(profile, work / f"loop{n}", warm, takes)
        two = _parallel_loops(2, profile, work / f"loop2-{n}", warm, takes) if k % 2 else None
        e2e = _in_child("end_to_end_main", "2", profile, str(work / f"batch{n}"), *map(str, takes))
        two = two or _parallel_loops(2, profile, work / f"loop2-{n}", warm, takes)
        after = _loop_in_process(profile, work / f"loop{n}", warm, takes)
        base = {"takes": n, "per_take_s": (before["wall"] + after["wall"]) / (2 * n),
                "cpu_per_take_s": (before["cpu"] + after["cpu"]) / (2 * n),
                "per_take_before_after_s": [before["wall"] / n, after["wall"] / n],
                "cpu_per_take_before_after_s": [before["cpu"] / n, after["cpu"] / n],
                "job_cpu_per_take_s": (before["job_cpu"] + after["job_cpu"]) / (2 * n),
                "two_loops_per_take_s": two["wall"] * 2 / n, "two_loops_cpu_per_take_s": two["cpu"] / n,
                "two_loops_first": bool(k % 2), "load_start": load0, "load_end": _load()}
        e2e["overhead"] = e2e["per_take_s"] / base["per_take_s"] - 1.0
        e2e["cpu_overhead"] = e2e["cpu_per_take_s"] / base["cpu_per_take_s"] - 1.0
        e2e["overhead_vs_two_loops"] = e2e["per_take_s"] / base["two_loops_per_take_s"] - 1.0
        e2e["cpu_overhead_vs_two_loops"] = e2e["cpu_per_take_s"] / base["two_loops_cpu_per_take_s"] - 1.0
        e2e["speedup_end_to_end"] = base["per_take_s"] * n / e2e["total_s"]  # fixed costs included
        out["runs"].append({"loop": base, "batch": e2e})
        shutil.rmtree(takes[0].parent, ignore_errors=True)
    out["fits"] = fixed_cost_fits(out["runs"])
    return out


FIXED = ("start_s", "first_task_s", "summary_s", "close_s")


def fixed_cost_fits(runs: list[dict]) -> dict:
    """Each fixed cost of the batch (and their sum, and the solving) against the take count N: a least-squares
    line a + b N, and the exponent p of c ~ N^p (log-log fit): p <= 1 is growing no faster than the take count."""
    n = np.array([r["batch"]["takes"] for r in runs], float)
    costs = {key: np.array([r["batch"][key] for r in runs]) for key in (*FIXED, "solve_s")}
    costs["fixed_s"] = sum(costs[key] for key in FIXED)
    # CPU over all takes: the slope b is the CPU of one more take, the intercept a the batch's fixed CPU
    costs["worker_cpu_s"] = n * [r["batch"]["cpu_per_take_s"] for r in runs]
    costs["loop_cpu_s"] = n * [r["loop"]["cpu_per_take_s"] for r in runs]
    costs["two_loops_cpu_s"] = n * [r["loop"]["two_loops_cpu_per_take_s"] for r in runs]
    fits = {}
    for key, c in costs.items():
        b, a = np.polyfit(n, c, 1) if len(n) > 1 else (0.0, float(c[0]))
        p = np.polyfit(np.log(n), np.log(np.maximum(c, 1e-6)), 1)[0] if len(n) > 1 else float("nan")
        fits[key] = {"a_s": float(a), "b_s_per_take": float(b), "exponent": float(p)}
    fits["per_take_cpu_ratio"] = {"vs_loop": fits["worker_cpu_s"]["b_s_per_take"] / fits["loop_cpu_s"]["b_s_per_take"],
                                  "vs_two_loops": fits["worker_cpu_s"]["b_s_per_take"]
                                  / fits["two_loops_cpu_s"]["b_s_per_take"],
                                  "pooled_vs_loop": costs["worker_cpu_s"].sum() / costs["loop_cpu_s"].sum(),
                                  "pooled_vs_two_loops": costs["worker_cpu_s"].sum() / costs["two_loops_cpu_s"].sum()}
    return fits


def _print_scale(res: dict) -> None:
    print("start-up, 2 workers, each a fresh process (s): import / cluster up (spawn: kernels warmed on the client "
          "first; forkserver: loaded there) / every worker's first 1 s take / close")
    for r in res["start"]:
        print(f"  {r['method']:>10} rep {r['rep']}: import {r['import_s']:.2f}  start {r['start_s']:.2f}  first take "
              f"{r['first_take_s']:.2f} (CPU {r['first_take_cpu_s']:.2f})  close {r['close_s']:.2f}  total "
              f"{r['total_s']:.2f}  load {r['load']:.1f}")
    print(f"{'takes':>5} {'loop s/take':>11} {'batch s/take':>12} {'x2/loop':>8} {'loop CPU':>8} {'job CPU':>8} "
          f"{'worker CPU':>10} {'CPU ratio':>9} {'start s':>7} {'1st task s':>10} {'summary s':>9} {'close s':>7} "
          f"{'idle s':>6} {'total s':>7} {'e2e x':>6} {'load':>9}")
    for run in res["runs"]:
        b, e = run["loop"], run["batch"]
        print(f"{b['takes']:>5} {b['per_take_s']:>11.3f} {e['solve_s'] / e['takes']:>12.3f} {e['overhead'] + 1:>8.3f} "
              f"{b['cpu_per_take_s']:>8.3f} {b['job_cpu_per_take_s']:>8.3f} {e['cpu_per_take_s']:>10.3f} "
              f"{e['cpu_overhead'] + 1:>9.3f} {e['start_s']:>7.2f} {e['first_task_s']:>10.3f} {e['summary_s']:>9.2f} "
              f"{e['close_s']:>7.2f} {e['idle_between_takes_s']:>6.3f} {e['total_s']:>7.1f} "
              f"{e['speedup_end_to_end']:>6.2f} {b['load_start']:>4.1f}-{b['load_end']:<4.1f}")
    print("against two warm loops in parallel processes (the batch's parallelism, same takes):")
    for run in res["runs"]:
        b, e = run["loop"], run["batch"]
        print(f"{b['takes']:>5} takes: two loops {b['two_loops_per_take_s']:.3f} s/take "
              f"(CPU {b['two_loops_cpu_per_take_s']:.3f}, run {'before' if b['two_loops_first'] else 'after'} the "
              f"batch), batch {e['per_take_s']:.3f} (CPU {e['cpu_per_take_s']:.3f}): overhead wall "
              f"{e['overhead_vs_two_loops']:+.1%}, CPU {e['cpu_overhead_vs_two_loops']:+.1%} (goal <= 10%)")
    print("the solving wall per worker (s): tasks sent to its first take begun / its takes' own wall / "
          "idle between its takes / idle after its last take; CPU s per take of the livecap batch process")
    for run in res["runs"]:
        e = run["batch"]
        if "per_worker" not in e:
            continue
        workers = sorted(e["per_worker"], key=lambda p: -p["takes"])
        cpu = e["process_cpu_s"]
        own = sum(v for k, v in cpu.items() if k.startswith("worker"))
        print(f"{e['takes']:>5} takes, solving {e['solve_s']:.3f} s: " + "; ".join(
            f"{p['takes']} takes: {p['to_first_s']:.3f} / {p['busy_s']:.3f} / {p['gaps_s']:.3f} / {p['tail_s']:.3f}"
            for p in workers) + f"; workers' CPU {own:.2f} s; livecap batch process "
            f"{(cpu['client_main'] + cpu['cluster_loop'] + cpu['other_threads']) / e['takes'] * 1000:.1f} ms/take")
        two = run["loop"]["two_loops_per_take_s"] * e["takes"] / 2  # the two loops' wall: each loop's share of takes
        idle = sum(p["to_first_s"] + p["gaps_s"] + p["tail_s"] for p in workers) / len(workers)
        busy = sum(p["busy_s"] for p in workers) / len(workers)
        print(f"{'':>6}wall over two loops {e['overhead_vs_two_loops']:+.1%} = workers idle {idle / two:+.1%} "
              f"(first task, gaps, tail) + takes' own wall {busy / two - 1:+.1%} "
              f"(their CPU {e['cpu_overhead_vs_two_loops']:+.1%})")
    print("fixed costs against the take count N: c = a + b N, and c ~ N^p")
    fits = dict(res["fits"])
    ratio = fits.pop("per_take_cpu_ratio")
    for key, f in fits.items():
        print(f"  {key:>15}: a {f['a_s']:7.3f} s, b {f['b_s_per_take'] * 1000:8.2f} ms/take, p {f['exponent']:5.2f}")
    print(f"per-take CPU, worker over loop (goal <= 1.1): {ratio['vs_loop']:.3f} from the slopes, "
          f"{ratio['pooled_vs_loop']:.3f} pooled; over two loops {ratio['vs_two_loops']:.3f} / "
          f"{ratio['pooled_vs_two_loops']:.3f}")
    for run in res["runs"]:
        e = run["batch"]
        if "first_take_cpu_s" in e:
            print(f"{e['takes']:>5} takes: a worker's first take {e['first_take_cpu_s']:.3f} CPU s, the others "
                  f"{e['rest_cpu_per_take_s']:.3f}" + (
                      f"; solving thread {e['first_take_thread_cpu_s']:.3f} / {e['rest_thread_cpu_per_take_s']:.3f} s, "
                      f"page faults {e['first_take_page_faults']:.0f} / {e['rest_page_faults_per_take']:.0f}"
                      if "first_take_page_faults" in e else ""))


def _real_takes(work: Path, n: int) -> tuple[Path, list[Path]]:
    """``n`` 20 s ICT takes from the real performances (one actor) and that actor's neutral take."""
    from livecap.cli import main as livecap

    shared = Path(os.environ.get("LIVECAP_SHARED", ROOT.parent / "shared")) / "realdata"
    rig, curves = shared / "ict-face", sorted((shared / "performance").glob("*.csv"))
    if not rig.is_dir() or not curves:
        raise FileNotFoundError(f"--takes real needs {rig} and the CSVs of {shared / 'performance'}")
    takes, neutral = [], None
    for start in (0, 20, 40, 60):
        for csv in curves:
            if len(takes) == n:
                return neutral, takes
            out = work / "gen" / f"{csv.stem}-{start}"
            with open(os.devnull, "w") as null:
                stdout, sys.stdout = sys.stdout, null
                try:
                    livecap(["generate", "--rig", str(rig), "--curves", str(csv), "--start", str(start),
                             "--seconds", "20", "--rate", "120", "--out", str(out)])
                except SystemExit:
                    continue  # the file is shorter than this start
                finally:
                    sys.stdout = stdout
            take = out / f"{csv.stem}.c3d"
            from transport.takefile import read_take

            if take.exists() and read_take(take).n_frames == 2400:
                takes.append(take)
                neutral = neutral or out / f"{csv.stem}_neutral.c3d"
    raise FileNotFoundError(f"only {len(takes)} real-performance takes of 20 s could be made")


def run(quick: bool = False, placement: tuple[str, ...] = ("cluster",), settings: tuple[str, ...] = ("livecap",),
        takes: str = "demo", scale: tuple[str, ...] = ("",), methods: tuple[str, ...] = ("",),
        order: tuple[str, ...] = ("",), refit: tuple[str, ...] = ("",)) -> dict:
    """``placement``: "cluster" (livecap's LocalCluster) and/or "sessions" (dask scheduler and workers as
    separate processes, each in its own session); ``settings`` of the LocalCluster: "livecap" (what
    ``livecap batch`` starts) and/or "dask" (Dask's defaults, the profiler off: the code before them).
    ``scale`` (e.g. 12,24,48): instead, the start-up A/B and ``livecap batch`` end to end at 2 workers on that
    many demo takes, each against the warm loop on the same takes. ``methods`` (e.g. 16): instead, spawned
    against forked workers end to end on that many takes. ``order`` ("uneven"): instead, largest take first
    against the listed order on a library of uneven takes. ``refit`` (a ``--scale`` run's JSON file): instead,
    its tables and fits printed again."""
    if refit[0]:
        res = json.loads(Path(refit[0]).read_text())["scale"]
        res["fits"] = fixed_cost_fits(res["runs"])
        _print_scale(res)
        return {"scale": res}
    from livecap.cli import main as livecap
    from transport.takefile import read_take, write_take

    n = 2 if quick else 12  # enough takes that 2 workers reach steady state (4 short takes measured start-up)
    work = Path(tempfile.mkdtemp(prefix="livecap-batch-bench-"))
    try:
        global RIG
        if "real" in (takes if isinstance(takes, tuple) else (takes,)):
            RIG = Path(os.environ.get("LIVECAP_SHARED", ROOT.parent / "shared")) / "realdata" / "ict-face"
            os.environ["LIVECAP_BENCH_RIG"] = str(RIG)
            neutral, paths = _real_takes(work, n)
        else:
            neutral, demo = ROOT / "recordings" / "demo_neutral.c3d", ROOT / "recordings" / "demo_take.c3d"
            paths = []
            for i in range(n):
                paths.append(work / "takes" / f"take{i:03d}.c3d")
                paths[-1].parent.mkdir(exist_ok=True)
                shutil.copy(demo, paths[-1])
        profile = str(work / "actor.npz")
        with open(os.devnull, "w") as null:
            stdout, sys.stdout = sys.stdout, null
            try:
                livecap(["calibrate", str(neutral), "--rig", str(RIG), "--out", profile])
            finally:
                sys.stdout = stdout
        warm = work / "warm.c3d"
        write_take(read_take(paths[0]).slice(0, 120), warm)
        if order[0]:
            print("uneven takes (16 x 20 s listed first, 1 x 200 s last), 2 workers, each a fresh process:")
            return {"uneven": uneven(profile, work, paths[0], 1 if quick else 3)}
        if methods[0]:
            print("spawned (Dask's default) against forked (livecap's) workers, 2 workers, each a fresh process:")
            return {"methods": globals()["methods"](2 if quick else int(methods[0]), profile, work, paths[0], 1
                                                    if quick else 3)}
        ns = [int(x) for x in scale if x]
        if ns:
            res = globals()["scale"](ns if not quick else [2, 4], profile, work, paths, warm, 1 if quick else 3)
            _print_scale(res)
            return {"scale": res, "mode": MODE, "take_frames": read_take(paths[0]).n_frames}
        frames = read_take(paths[0]).n_frames
        duration = frames / 120.0
        takes = paths

        load0 = _load()
        timed = _loop_in_process(profile, work / "loop", warm, takes)
        loop_s = timed["wall"]
        base = {"takes": n, "wall_s": loop_s, "per_take_s": loop_s / n, "takes_per_s": n / loop_s,
                "cpu_per_take_s": timed["cpu"] / n, "job_per_take_s": timed["job_wall"] / n,
                "job_cpu_per_take_s": timed["job_cpu"] / n, "load_start": load0, "load_end": _load()}
        runs = [(where, how) for where in placement for how in (settings if where == "cluster" else ("livecap",))]
        results = [_batch(w, profile, work / f"{where}-{how}{w}", warm, takes, where, how) for where, how in runs
                   for w in (1, 2)]
    finally:
        shutil.rmtree(work, ignore_errors=True)
    one, two = results[0], results[1]
    overhead = one["per_take_s"] / base["per_take_s"] - 1.0
    cpu_overhead = one["cpu_per_take_s"] / base["cpu_per_take_s"] - 1.0
    speedup = two["takes_per_s"] / one["takes_per_s"]
    print(f"{n} takes of {duration:.0f} s ({frames} frames, mode {MODE}, rig {RIG.name}), profile calibrated once")
    print(f"{'':>34} {'takes/s':>8} {'s/take':>7} {'CPU s/take':>10} {'vs loop':>8} {'summary s':>9} "
          f"{'start+warm s':>13} {'load':>11}")
    print(f"{'in-process loop (baseline)':>34} {base['takes_per_s']:>8.3f} {base['per_take_s']:>7.2f} "
          f"{base['cpu_per_take_s']:>10.2f} {'1.00':>8} {'-':>9} {'-':>13} "
          f"{base['load_start']:>5.1f}-{base['load_end']:<5.1f}")
    print(f"{'in-process solve_job (same run)':>34} {1 / base['job_per_take_s']:>8.3f} {base['job_per_take_s']:>7.2f} "
          f"{base['job_cpu_per_take_s']:>10.2f} {base['per_take_s'] / base['job_per_take_s']:>8.2f}")
    for r in results:
        label = f"{r['placement']} ({r['settings']}), {r['workers']} worker(s)"
        print(f"{label:>34} {r['takes_per_s']:>8.3f} "
              f"{r['wall_s'] / r['takes']:>7.2f} {r['cpu_per_take_s']:>10.2f} "
              f"{r['takes_per_s'] / base['takes_per_s']:>8.2f} {r['summary_s']:>9.2f} "
              f"{r['cluster_start_s'] + r['warm_up_s']:>13.1f} {r['load_start']:>5.1f}-{r['load_end']:<5.1f}")
    for r in results:
        print(f"{r['placement']} ({r['settings']}), {r['workers']} worker(s): client/scheduler process CPU "
              f"{r['client_cpu_per_take_s']:.3f} s per take (summary included)")
    print(f"batch's per-take function in-process over the loop: wall "
          f"{base['job_per_take_s'] / base['per_take_s'] - 1:+.1%}, "
          f"CPU {base['job_cpu_per_take_s'] / base['cpu_per_take_s'] - 1:+.1%}")
    pairs = [(results[i], results[i + 1]) for i in range(0, len(results), 2)]
    speedups = {}
    for a, b in pairs:
        name = f"{a['placement']} ({a['settings']})"
        speedups[name] = b["takes_per_s"] / a["takes_per_s"]
        print(f"{name}: per-take overhead (1 worker) over the warm loop: "
              f"wall {a['per_take_s'] / base['per_take_s'] - 1:+.1%}, "
              f"worker CPU {a['cpu_per_take_s'] / base['cpu_per_take_s'] - 1:+.1%} (goal <= 10%); "
              f"2 workers / 1 worker takes/s: {speedups[name]:.2f}x solving, "
              f"{b['takes_per_s_with_summary'] / a['takes_per_s_with_summary']:.2f}x with the summary (goal >= 1.7x)")
    return {"takes": n, "take_seconds": duration, "take_frames": frames, "mode": MODE, "loop": base,
            "batch": results, "speedups": speedups, "overhead_1_worker": overhead,
            "cpu_overhead_1_worker": cpu_overhead, "speedup_2_workers": speedup}


if __name__ == "__main__":
    sys.exit(suite_main(run, __doc__, placement="cluster", settings="livecap", takes="demo", scale="", methods="",
                        order="", refit=""))
