"""``livecap batch`` on a real 2-worker LocalCluster (processes), and through a ``dask scheduler`` and
``dask worker`` started as real processes: outputs equal ``livecap solve``'s bytes, bad takes are
reported and counted, finished takes are skipped on resume, a manifest mixes actors, profiles and modes."""

from __future__ import annotations

import json
import logging
import os
import re
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from livecap.batch.jobs import Job
from livecap.batch.plan import plan_jobs
from livecap.batch.runner import dask_client, exit_code, run_batch
from livecap.batch.spec import SolveSettings, SolveSpec
from livecap.batch.worker import PLUGIN_NAME, SolverCache, solve_job
from livecap.cli import main
from livecap.cli.batch import settings_from_flags
from transport.recorders import read_jsonl_recording
from transport.takefile import read_take, write_take
from transport.weights_csv import read_weights_csv

ROOT = Path(__file__).resolve().parents[1]
RIG = str(ROOT / "recordings" / "demo_rig.npz")
NEUTRAL = str(ROOT / "recordings" / "demo_neutral.c3d")
FRAMES = 120  # 1 s takes keep the batch tests short
USER_TRIM = os.environ.get("MALLOC_TRIM_THRESHOLD_")  # the shell's own, before a Nanny sets it in this process


@pytest.fixture(scope="module")
def library(tmp_path_factory) -> dict:
    """Three short takes, an unreadable one, one with wrong labels, and a calibrated profile."""
    root = tmp_path_factory.mktemp("library")
    takes = root / "takes"
    takes.mkdir()
    full = read_take(ROOT / "recordings" / "demo_take.c3d")
    for i in range(3):
        write_take(full.slice(400 * i + 100, 400 * i + 100 + FRAMES), takes / f"take{i}.c3d")
    (takes / "broken.c3d").write_bytes(b"this is not a C3D file")
    wrong = full.slice(0, FRAMES)
    write_take(type(wrong)([f"X{i}" for i in range(len(wrong.labels))], wrong.positions, wrong.valid, wrong.rate,
                           wrong.first_frame), takes / "wrong_labels.c3d")
    profile = root / "actor.npz"
    assert main(["calibrate", NEUTRAL, "--rig", RIG, "--out", str(profile)]) == 0
    return {"root": root, "takes": takes, "profile": str(profile)}


@pytest.fixture(scope="module")
def client():
    with dask_client(workers=2) as c:
        yield c


def _solve(take: Path, out: Path, *flags: str) -> bytes:
    assert main(["solve", str(take), "--rig", RIG, "--out", str(out), *flags]) == 0
    return out.read_bytes()


def test_local_cluster_equals_solve_and_reports_bad_takes(library, client, tmp_path):
    out = tmp_path / "out"
    jobs = plan_jobs([str(library["takes"])], [], rig=RIG, out_dir=str(out), mode="robust", fmt="csv",
                     profile=library["profile"])
    rows, meta = run_batch(jobs, out, client)
    status = {r["stem"]: r["status"] for r in rows}
    assert status == {"broken": "failed", "take0": "ok", "take1": "ok", "take2": "ok", "wrong_labels": "failed"}
    assert exit_code(rows) == 2 and meta["workers"] == 2
    errors = {r["stem"]: r["error"] for r in rows if r["status"] == "failed"}
    assert "broken.c3d" in errors["broken"] and "C3D" in errors["broken"] and "\n" not in errors["broken"]
    assert "wrong labels" in errors["wrong_labels"]
    for stem in ("take2",):  # bit for bit what livecap solve writes
        solo = _solve(library["takes"] / f"{stem}.c3d", tmp_path / f"{stem}.solo.csv", "--profile", library["profile"],
                      "--mode", "robust")
        assert (out / f"{stem}.csv").read_bytes() == solo
    # the prepared solver is built once per worker, not once per take
    built = client.run(lambda dask_worker: dask_worker.plugins[PLUGIN_NAME].built)
    assert 1 <= sum(built.values()) <= 2
    summary = json.loads((out / "summary.json").read_text())
    ok = [t for t in summary["takes"] if t["status"] == "ok"]
    assert summary["failed"] == 2 and len(ok) == 3
    for t in ok:
        assert t["frames"] == FRAMES and 0 < t["residual_p50_mm"] <= t["residual_p95_mm"] < 5
        assert 0 <= t["missing_share"] < 0.2 and len(t["weight_max"]) == len(t["names"]) == 43
    assert (out / "summary.csv").read_text().count("\n") == 6
    assert "data:image/png;base64," in (out / "summary.html").read_text()


def test_solved_rows_are_read_from_their_records_not_fetched_per_take(library, client, tmp_path, monkeypatch):
    """A solved take's row comes from the record its worker wrote, as its worker reports it done (an event), not
    through a gather per take (client, scheduler, worker and back: docs/batch.md "the wall beyond CPU"); the only
    results fetched are the workers' tasks', one each, however many takes."""
    from distributed import Future

    fetched, result = [], Future.result

    def counted(self, *args, **kwargs):
        fetched.append(self.key)
        return result(self, *args, **kwargs)

    monkeypatch.setattr(Future, "result", counted)
    out = tmp_path / "out"
    jobs = plan_jobs([str(library["takes"])], [], rig=RIG, out_dir=str(out), mode="robust", fmt="csv",
                     profile=library["profile"])
    rows, _ = run_batch(jobs, out, client)
    assert {r["stem"]: r["status"] for r in rows} == {"broken": "failed", "take0": "ok", "take1": "ok", "take2": "ok",
                                                      "wrong_labels": "failed"}
    assert len(fetched) <= 2 and all("-queue-" in key for key in fetched), fetched
    for r in rows:
        if r["status"] == "ok":
            assert r == json.loads((out / ".batch" / f"{r['stem']}.json").read_text())
            assert r["frames"] == FRAMES and r["cpu_seconds"] > 0
    assert [p.name for p in (out / ".batch").iterdir() if not p.suffix == ".json"] == []  # no claims left behind


def test_a_batch_is_one_message_and_one_task_per_worker(library, client, tmp_path):
    """Every task of a batch goes to the scheduler in one graph (a submit per take is a message each, which the
    client sends at most every 10 ms: docs/batch.md "Batch: the last percent"), and there is one task per worker
    thread, not per take: the scheduler hands a worker its work once (docs/batch.md "one task per worker")."""
    from distributed.diagnostics.plugin import SchedulerPlugin

    class Graphs(SchedulerPlugin):
        name = "count-graphs"

        def __init__(self) -> None:
            self.graphs: list[set] = []

        def update_graph(self, scheduler, *, keys, **kwargs) -> None:
            self.graphs.append({k for k in keys if str(k).startswith("livecap-batch-")})

    plugin = Graphs()
    client.cluster.scheduler.add_plugin(plugin)  # the LocalCluster's scheduler runs in this process
    try:
        out = tmp_path / "out"
        jobs = plan_jobs([str(library["takes"])], [], rig=RIG, out_dir=str(out), mode="robust", fmt="csv",
                         profile=library["profile"])
        rows, _ = run_batch(jobs, out, client)
    finally:
        client.cluster.scheduler.remove_plugin(name=Graphs.name)
    batch = [g for g in plugin.graphs if g]
    assert len(jobs) == 5 and len(batch) == 1 and len(batch[0]) == 2, plugin.graphs
    assert [r["status"] for r in rows].count("ok") == 3
    assert len({r["worker"] for r in rows}) == 2  # both workers pulled takes


def test_a_killed_worker_s_unfinished_takes_are_still_solved(library, tmp_path, caplog):
    """A worker process killed (SIGKILL) in the middle of the batch, holding a take it had claimed: every take is
    still solved and reported once, the rows already in stand, and the lost take is solved again elsewhere."""
    import signal

    full = read_take(ROOT / "recordings" / "demo_take.c3d")
    takes = tmp_path / "takes"
    takes.mkdir()
    for i in range(8):
        write_take(full.slice(100 * i, 100 * i + 1200), takes / f"t{i}.c3d")
    out = tmp_path / "out"
    jobs = plan_jobs([str(takes)], [], rig=RIG, out_dir=str(out), mode="robust", fmt="csv", profile=library["profile"])
    seen, killed = [], []
    caplog.set_level(logging.WARNING, logger="livecap.batch.runner")
    with dask_client(workers=2) as c:
        pids = set(c.run(os.getpid).values())

        def done(row: dict) -> None:
            seen.append(row["stem"])
            if not killed:  # the other worker is in the middle of a take it claimed
                killed.append((pids - {row["worker"]}).pop())
                os.kill(killed[0], signal.SIGKILL)

        rows, meta = run_batch(jobs, out, c, on_done=done)
    assert [r["status"] for r in rows] == ["ok"] * 8 and meta["failed"] == 0
    assert sorted(seen) == sorted(j.stem for j in jobs)  # each take reported once
    assert all((out / f"t{i}.csv").is_file() for i in range(8))
    # the take it held solved again (and one it had finished if it died before its report went out)
    assert re.search(r"\b[12] take\(s\) left unsolved by a lost worker", caplog.text), caplog.text


def _worker_settings(dask_worker) -> dict:
    return {"trim": os.environ.get("MALLOC_TRIM_THRESHOLD_"), "blas": os.environ.get("OPENBLAS_NUM_THREADS"),
            "tick": dask_worker.periodic_callbacks["tick"].callback_time,
            "memory": dask_worker.periodic_callbacks["memory_monitor"].callback_time,
            "profile": "profile" in dask_worker.periodic_callbacks}


def _fresh_pages(n_bytes: int) -> int:
    """Minor page faults of allocating and touching ``n_bytes`` of heap, in 8 MB pieces, on this thread."""
    from livecap.batch.worker import _faults

    faults = _faults()
    pieces = [bytearray(8 << 20) for _ in range(n_bytes >> 23)]
    del pieces
    return _faults() - faults


def test_a_worker_s_solving_thread_has_its_heap_before_its_first_take(client):
    """The thread that runs a worker's tasks finds a take's working set (48 MB here) in its malloc arena already,
    faulted in when the worker started: a worker's first take faulted in ~10 k fresh pages (docs/batch.md "one task
    per worker"). 12.3 k of 12.3 k pages fresh without; 0-2 k with (the takes before may have split the free space)."""
    workers = list(client.scheduler_info()["workers"])
    pages = client.gather([client.submit(_fresh_pages, 48 << 20, workers=[w], pure=False) for w in workers])
    assert len(pages) == 2 and max(pages) < (48 << 20) // 4096 // 2, pages


def test_local_cluster_workers_get_the_batch_settings(client):
    """The settings that cut the worker's per-take overhead (docs/batch.md) reach the worker processes."""
    for got in client.run(_worker_settings).values():
        assert got == {"trim": USER_TRIM, "blas": "1", "tick": 1000, "memory": 1000, "profile": False}


def test_resume_skips_finished_takes_and_force_redoes_them(library, client, tmp_path):
    out = tmp_path / "out"
    takes = tmp_path / "takes"
    shutil.copytree(library["takes"], takes)
    for name in ("broken.c3d", "wrong_labels.c3d", "take0.c3d"):
        (takes / name).unlink()

    def batch(force: bool = False, settings: SolveSettings | None = None) -> dict:
        jobs = plan_jobs([str(takes / "*.c3d")], [], rig=RIG, out_dir=str(out), mode="qp", fmt="csv",
                         profile=library["profile"], settings=settings)
        rows, _ = run_batch(jobs, out, client, force=force)
        return {r["stem"]: r["status"] for r in rows}

    assert batch() == {"take1": "ok", "take2": "ok"}
    first = (out / "take1.csv").read_bytes()
    assert batch() == {"take1": "skipped", "take2": "skipped"}
    assert (out / "summary.csv").read_text().count(",skipped,") == 2  # skipped takes keep their figures
    assert batch(settings=SolveSettings(ridge=0.5)) == {"take1": "ok", "take2": "ok"}  # other settings: solved again
    assert (out / "take1.csv").read_bytes() != first
    assert batch(settings=SolveSettings(ridge=0.5)) == {"take1": "skipped", "take2": "skipped"}
    assert batch() == {"take1": "ok", "take2": "ok"}
    later = time.time() + 5
    os.utime(takes / "take1.c3d", (later, later))  # an input newer than its output
    assert batch() == {"take1": "ok", "take2": "skipped"}
    assert (out / "take1.csv").read_bytes() == first
    assert batch(force=True) == {"take1": "ok", "take2": "ok"}
    assert len(json.loads((out / "summary.json").read_text())["takes"]) == 2


def test_manifest_mixes_actors_profiles_and_modes(library, client, tmp_path):
    takes = library["takes"]
    manifest = tmp_path / "day1.toml"
    manifest.write_text(f"""
[defaults]
rig = "{RIG}"

[[take]]
take = "{takes / 'take0.c3d'}"
actor = "anna"
profile = "{library['profile']}"
mode = "robust"

[[take]]
take = "{takes / 'take1.c3d'}"
actor = "ben"
calibrate_from = "{NEUTRAL}"
mode = "qp"
options = {{ ridge = 0.01 }}
""")
    out = tmp_path / "out"
    jobs = plan_jobs([], [str(manifest)], rig=None, out_dir=str(out), mode="robust", fmt="csv",
                     parse_flags=settings_from_flags)
    rows, _ = run_batch(jobs, out, client)
    assert [(r["actor"], r["mode"], r["status"]) for r in rows] == [("anna", "robust", "ok"), ("ben", "qp", "ok")]
    ben = _solve(takes / "take1.c3d", tmp_path / "ben.csv", "--profile", jobs[1].spec.profile, "--mode", "qp",
                 "--ridge", "0.01")
    assert (out / "take1.csv").read_bytes() == ben
    other = _solve(takes / "take1.c3d", tmp_path / "ben_robust.csv", "--profile", jobs[1].spec.profile)
    assert other != ben  # the manifest's mode and options did reach the solve


def test_manifest_errors_name_the_file(tmp_path):
    bad = tmp_path / "m.csv"
    bad.write_text("take,actress\nx.c3d,anna\n")
    with pytest.raises(ValueError, match=r"m\.csv row 1: unknown column\(s\) \['actress'\]"):
        plan_jobs([], [str(bad)], rig=RIG, out_dir=str(tmp_path), mode="qp", fmt="csv")
    bad.write_text("take,options\nx.c3d,--no-such-flag\n")
    with pytest.raises(ValueError, match=r"x\.c3d: solve options: unrecognized arguments: --no-such-flag"):
        plan_jobs([], [str(bad)], rig=RIG, out_dir=str(tmp_path), mode="qp", fmt="csv", parse_flags=settings_from_flags)


def test_glb_and_jsonl_outputs_and_a_reused_solver(library, tmp_path):
    """In process (no cluster): the .glb and the CSV are livecap solve's bytes though the CSV's solve is the
    last of four on one cached robust solver (reset between takes); the JSONL holds the CSV's weights."""
    take = library["takes"] / "take2.c3d"
    cache = SolverCache()
    for stem, fmt in (("take2", "glb"), ("take0", "csv"), ("take2", "jsonl"), ("take2", "csv")):
        spec = SolveSpec(RIG, "robust", library["profile"])
        job = Job(str(library["takes"] / f"{stem}.c3d"), spec, str(tmp_path), fmt)
        row = solve_job(job, cache)
        assert row["status"] == "ok", row["error"]
        assert 0 < row["thread_cpu_seconds"] <= row["cpu_seconds"] + 1e-3  # the solving thread's share
    assert cache.built == 1
    (tmp_path / "solo").mkdir()
    for fmt in ("glb", "csv"):
        solo = _solve(take, tmp_path / "solo" / f"take2.{fmt}", "--profile", library["profile"], "--mode", "robust")
        assert (tmp_path / f"take2.{fmt}").read_bytes() == solo
    names, frames = read_jsonl_recording(tmp_path / "take2.jsonl")
    csv_names, W, _ = read_weights_csv(tmp_path / "take2.csv")
    assert names == csv_names and len(frames) == FRAMES
    np.testing.assert_allclose([f["weights"] for f in frames], W, atol=5e-7)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_explicit_scheduler_with_dask_processes(library, tmp_path, capsys):
    """``dask scheduler`` and ``dask worker`` as real processes; ``livecap batch --scheduler`` connects to them."""
    dask = Path(sys.executable).with_name("dask")
    address = f"tcp://127.0.0.1:{_free_port()}"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    procs = [subprocess.Popen([dask, "scheduler", "--host", "127.0.0.1", "--port", address.rsplit(":", 1)[1],
                               "--no-dashboard"], env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)]
    try:
        procs.append(subprocess.Popen([dask, "worker", address, "--nworkers", "1", "--nthreads", "1",
                                       "--no-dashboard"], env=env, stdout=subprocess.DEVNULL,
                                      stderr=subprocess.DEVNULL))
        out = tmp_path / "out"
        code = main(["batch", str(library["takes"] / "take0.c3d"), str(library["takes"] / "broken.c3d"), "--rig", RIG,
                     "--profile", library["profile"], "--out", str(out), "--scheduler", address])
        printed = capsys.readouterr().out
        assert code == 1, printed[-2000:]
        assert "broken.c3d" in printed and "C3D header" in printed
        solo = _solve(library["takes"] / "take0.c3d", tmp_path / "solo.csv", "--profile", library["profile"])
        assert (out / "take0.csv").read_bytes() == solo
        summary = json.loads((out / "summary.json").read_text())
        assert summary["scheduler"] == address and summary["workers"] == 1
    finally:
        for p in reversed(procs):
            p.terminate()
        for p in procs:
            p.wait(timeout=30)


def test_csv_manifest_paths_and_options(tmp_path):
    (tmp_path / "day1").mkdir()
    for name in ("a.c3d", "b.c3d"):
        (tmp_path / "day1" / name).write_bytes(b"")
    (tmp_path / "m.csv").write_text("take,actor,profile,mode,options\n"
                                    "day1/*.c3d,anna,anna.npz,qp,--ridge 0.01 --temporal 2\n")
    from livecap.batch.jobs import read_manifest

    (row,) = read_manifest(tmp_path / "m.csv")
    assert row["take"] == str(tmp_path / "day1" / "*.c3d") and row["profile"] == str(tmp_path / "anna.npz")
    assert row["options"] == ("--ridge", "0.01", "--temporal", "2") and row["actor"] == "anna"
    jobs = plan_jobs([], [str(tmp_path / "m.csv")], rig=RIG, out_dir=str(tmp_path / "out"), mode="robust", fmt="csv",
                     parse_flags=settings_from_flags)
    assert [Path(j.take).name for j in jobs] == ["a.c3d", "b.c3d"] and {j.spec.mode for j in jobs} == {"qp"}
    assert jobs[0].spec.settings == SolveSettings(ridge=0.01, temporal=2.0)


def test_docs_dask_config_is_what_the_local_cluster_sets():
    """docs/batch.md's YAML for a user's `dask worker` carries the LocalCluster's settings, key for key."""
    import re

    import yaml

    from livecap.batch.runner import LOCAL_CLUSTER_CONFIG

    text = (ROOT / "docs" / "batch.md").read_text()
    block = re.search(r"```yaml\n# livecap-batch.yaml.*?\n(.*?)```", text, re.S)
    assert block, "docs/batch.md lacks the livecap-batch.yaml block"

    def flat(d: dict, prefix: str = "") -> dict:
        out = {}
        for k, v in d.items():
            out.update(flat(v, f"{prefix}{k}.") if isinstance(v, dict) else {f"{prefix}{k}": v})
        return out

    assert flat(yaml.safe_load(block.group(1))) == LOCAL_CLUSTER_CONFIG


def test_noise_and_settings_reach_the_worker_as_livecap_solve_gives_them(library, tmp_path):
    """A job's typed settings (``--noise-mm`` included, which replaces the profile's calibrated noise) give
    ``livecap solve``'s bytes with the same flags, with and without a saved profile."""
    take = library["takes"] / "take1.c3d"
    flags = ["--noise-mm", "2.5", "--trend", "3"]
    for prof in (library["profile"], None):
        spec = SolveSpec(RIG, "robust", prof, settings=settings_from_flags(flags))
        out = tmp_path / ("with" if prof else "without")
        row = solve_job(Job(str(take), spec, str(out)), SolverCache())
        assert row["status"] == "ok", row["error"]
        solo = _solve(take, tmp_path / "solo.csv", "--mode", "robust", *flags, *(["--profile", prof] if prof else []))
        assert (out / "take1.csv").read_bytes() == solo
        plain = _solve(take, tmp_path / "plain.csv", "--mode", "robust", *(["--profile", prof] if prof else []))
        assert plain != solo  # the flags change the solve


def test_largest_takes_first_and_the_summary_grows_as_takes_finish(library, client, tmp_path):
    """Uneven takes: the two long ones start before any short one though listed last (one per worker, the rest
    queued by size), and summary.csv holds a row for every take finished so far while the batch runs."""
    full = read_take(ROOT / "recordings" / "demo_take.c3d")
    takes = tmp_path / "takes"
    takes.mkdir()
    for name, n in (("a0", 60), ("a1", 60), ("z0", 360), ("z1", 360)):
        write_take(full.slice(100, 100 + n), takes / f"{name}.c3d")
    out = tmp_path / "out"
    jobs = plan_jobs([str(takes)], [], rig=RIG, out_dir=str(out), mode="robust", fmt="csv", profile=library["profile"])
    assert [j.stem for j in jobs] == ["a0", "a1", "z0", "z1"]
    lines = []
    rows, _ = run_batch(jobs, out, client, on_done=lambda row: lines.append(
        (out / "summary.csv").read_text().count("\n") - 1))
    assert lines == [1, 2, 3, 4]
    started = {r["stem"]: r["started"] for r in rows}
    assert max(started["z0"], started["z1"]) < min(started["a0"], started["a1"]), started
    assert {r["worker"] for r in rows if r["stem"].startswith("z")} == {r["worker"] for r in rows}  # both busy


def test_kernels_are_compiled_once_and_loaded_by_every_worker(library, tmp_path):
    """``livecap batch`` on a cold numba cache (its own NUMBA_CACHE_DIR): the mode's kernels are compiled once,
    into the cache, by the forkserver the workers are forked from; no worker compiles one (each row counts its
    worker's compilations during the take), nor builds a solver (the forkserver's, adopted by every worker)."""
    cache = tmp_path / "numba"
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache)}
    out = tmp_path / "out"
    takes = [str(library["takes"] / f"take{i}.c3d") for i in range(3)]
    done = subprocess.run([sys.executable, "-m", "livecap", "batch", *takes, "--rig", RIG, "--profile",
                           library["profile"], "--mode", "lsq", "--workers", "2", "--out", str(out)],
                          env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
    rows = json.loads((out / "summary.json").read_text())["takes"]
    assert [r["status"] for r in rows] == ["ok"] * 3
    assert [r["kernels_compiled"] for r in rows] == [0, 0, 0]
    assert [r["solvers_built"] for r in rows] == [0, 0, 0]
    assert list(cache.rglob("*.nbi")), "the kernels were not cached where the workers look"
