"""``livecap batch`` throughput: takes per second on a LocalCluster of 1 and 2 worker processes, and
the per-take overhead of the batch path against a warm in-process loop doing what ``livecap solve``
does (read the take, build the solver, solve, write the CSV), on copies of the bundled 20 s demo take
(2400 frames, 60 markers, 43 shapes) with a profile calibrated from the demo neutral take.

    python -m benchmarks.batch [--quick] [--json FILE]

Each cluster is started and warmed (every worker solves a 1 s take: imports, rig and profile loaded,
solver prepared) before the timed batch; that fixed cost is reported beside it. The baseline loop runs
in its own process with one BLAS thread, as Dask's worker processes do (OMP/MKL/OPENBLAS_NUM_THREADS=1).
The machine is shared: the load average is recorded beside every figure.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from benchmarks.timing import suite_main

ROOT = Path(__file__).resolve().parents[1]
RIG = ROOT / "recordings" / "demo_rig.npz"
MODE = "robust"
ONE_THREAD = {"OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"}


def _load() -> float:
    with open("/proc/loadavg") as fh:
        return float(fh.read().split()[0])


def loop(profile: str, out: str, warm: str, takes: list[str]) -> dict:
    """Wall and CPU seconds of the plain in-process loop over ``takes`` (after one untimed warm-up solve)."""
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

    one(warm)
    start, cpu = time.perf_counter(), time.process_time()
    for t in takes:
        one(t)
    return {"wall": time.perf_counter() - start, "cpu": time.process_time() - cpu}


def _loop_in_process(profile: str, out: Path, warm: Path, takes: list[Path]) -> dict:
    out.mkdir(parents=True, exist_ok=True)
    code = ("import json, sys; from benchmarks.batch import loop; "
            "print(json.dumps(loop(sys.argv[1], sys.argv[2], sys.argv[3], sys.argv[4:])))")
    done = subprocess.run([sys.executable, "-c", code, profile, str(out), str(warm), *map(str, takes)],
                          capture_output=True, text=True, env={**os.environ, **ONE_THREAD, "PYTHONPATH": str(ROOT)},
                          cwd=ROOT, check=True)
    return json.loads(done.stdout.strip().splitlines()[-1])


def _batch(workers: int, profile: str, out: Path, warm: Path, takes: list[Path]) -> dict:
    from livecap.batch.jobs import Job
    from livecap.batch.runner import dask_client, run_batch

    def jobs(paths, where):
        return [Job(str(p), str(RIG), str(where), MODE, "csv", profile=profile) for p in paths]

    t0 = time.perf_counter()
    load0 = _load()
    with dask_client(workers=workers) as client:
        started = time.perf_counter() - t0
        warm_jobs = []
        for i in range(workers):  # one warm-up take per worker (same file under another name)
            copy = warm.with_name(f"{warm.stem}_w{i}{warm.suffix}")
            shutil.copy(warm, copy)
            warm_jobs.append(copy)
        run_batch(jobs(warm_jobs, out / "warm"), out / "warm", client, force=True)
        warmed = time.perf_counter() - t0 - started
        t1 = time.perf_counter()
        rows, _ = run_batch(jobs(takes, out / "timed"), out / "timed", client, force=True)
        wall = time.perf_counter() - t1
    failed = [r["error"] for r in rows if r["status"] != "ok"]
    if failed:
        raise RuntimeError(f"batch failed: {failed[0]}")
    return {"workers": workers, "takes": len(takes), "wall_s": wall, "takes_per_s": len(takes) / wall,
            "per_take_s": wall / len(takes) * workers, "cluster_start_s": started, "warm_up_s": warmed,
            "worker_seconds_per_take": sum(r["seconds"] for r in rows) / len(rows),
            "cpu_per_take_s": sum(r["cpu_seconds"] for r in rows) / len(rows),
            "load_start": load0, "load_end": _load()}


def run(quick: bool = False) -> dict:
    from livecap.cli import main as livecap
    from transport.takefile import read_take, write_take

    n = 2 if quick else 4
    work = Path(tempfile.mkdtemp(prefix="livecap-batch-bench-"))
    try:
        profile = str(work / "actor.npz")
        with open(os.devnull, "w") as null:
            stdout, sys.stdout = sys.stdout, null
            try:
                livecap(["calibrate", str(ROOT / "recordings" / "demo_neutral.c3d"), "--rig", str(RIG),
                         "--out", profile])
            finally:
                sys.stdout = stdout
        demo = ROOT / "recordings" / "demo_take.c3d"
        takes = []
        for i in range(n):
            takes.append(work / "takes" / f"take{i:03d}.c3d")
            takes[-1].parent.mkdir(exist_ok=True)
            shutil.copy(demo, takes[-1])
        warm = work / "warm.c3d"
        write_take(read_take(demo).slice(0, 120), warm)
        frames = read_take(demo).n_frames
        duration = frames / 120.0

        load0 = _load()
        timed = _loop_in_process(profile, work / "loop", warm, takes)
        loop_s = timed["wall"]
        base = {"takes": n, "wall_s": loop_s, "per_take_s": loop_s / n, "takes_per_s": n / loop_s,
                "cpu_per_take_s": timed["cpu"] / n, "load_start": load0, "load_end": _load()}
        one = _batch(1, profile, work / "one", warm, takes)
        two = _batch(2, profile, work / "two", warm, takes)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    overhead = one["per_take_s"] / base["per_take_s"] - 1.0
    cpu_overhead = one["cpu_per_take_s"] / base["cpu_per_take_s"] - 1.0
    speedup = two["takes_per_s"] / one["takes_per_s"]
    print(f"{n} takes of {duration:.0f} s ({frames} frames, mode {MODE}), profile calibrated once")
    print(f"{'':>28} {'takes/s':>8} {'s/take':>7} {'CPU s/take':>10} {'vs loop':>8} {'start+warm s':>13} "
          f"{'load':>11}")
    print(f"{'in-process loop (baseline)':>28} {base['takes_per_s']:>8.3f} {base['per_take_s']:>7.2f} "
          f"{base['cpu_per_take_s']:>10.2f} {'1.00':>8} {'-':>13} {base['load_start']:>5.1f}-{base['load_end']:<5.1f}")
    for r in (one, two):
        print(f"{'batch, ' + str(r['workers']) + ' worker(s)':>28} {r['takes_per_s']:>8.3f} "
              f"{r['wall_s'] / r['takes']:>7.2f} {r['cpu_per_take_s']:>10.2f} "
              f"{r['takes_per_s'] / base['takes_per_s']:>8.2f} "
              f"{r['cluster_start_s'] + r['warm_up_s']:>13.1f} {r['load_start']:>5.1f}-{r['load_end']:<5.1f}")
    print(f"per-take overhead of the batch path (1 worker) over the warm loop: wall {overhead:+.1%}, "
          f"CPU {cpu_overhead:+.1%} (goal <= 10%)")
    print(f"2 workers / 1 worker takes/s: {speedup:.2f}x (goal >= 1.7x)")
    return {"takes": n, "take_seconds": duration, "take_frames": frames, "mode": MODE, "loop": base,
            "batch": [one, two], "overhead_1_worker": overhead,
            "cpu_overhead_1_worker": cpu_overhead, "speedup_2_workers": speedup}


if __name__ == "__main__":
    sys.exit(suite_main(run, __doc__))
