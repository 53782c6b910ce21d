"""The worker's cache and per-take statistics (issue 39 item 3): what a worker reads once per batch is read
once (a weights-CSV prior, the rig), read again when its file changes, and the statistics equal their
definitions."""

from __future__ import annotations

import os
import platform
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import transport.weights_csv
from livecap.batch.jobs import Job
from livecap.batch.spec import SolveSettings, SolveSpec
from livecap.batch.stats import frame_residual, missing_share
from livecap.batch.worker import SolverCache, solve_job
from livecap.cli import main
from livecap.core.take import Take
from livecap.offline.solve import SolvedTake
from transport.takefile import read_take, write_take

ROOT = Path(__file__).resolve().parents[1]
FRAMES = 60


@pytest.fixture(scope="module")
def lib(tmp_path_factory) -> dict:
    root = tmp_path_factory.mktemp("cache")
    for name in ("demo_rig.npz", "demo_rig.markers.json"):
        shutil.copy(ROOT / "recordings" / name, root / name)
    full = read_take(ROOT / "recordings" / "demo_take.c3d")
    takes = []
    for i in range(3):
        takes.append(root / f"take{i}.c3d")
        write_take(full.slice(300 * i, 300 * i + FRAMES), takes[-1])
    profile = root / "actor.npz"
    assert main(["calibrate", str(ROOT / "recordings" / "demo_neutral.c3d"), "--rig", str(root / "demo_rig.npz"),
                 "--out", str(profile)]) == 0
    return {"root": root, "rig": str(root / "demo_rig.npz"), "takes": takes, "profile": str(profile)}


def test_a_weights_csv_prior_is_read_once_per_worker_not_per_take(lib, tmp_path, monkeypatch):
    first = solve_job(Job(str(lib["takes"][0]), SolveSpec(lib["rig"], "robust", lib["profile"]), str(tmp_path)))
    assert first["status"] == "ok", first["error"]
    reads = []
    real = transport.weights_csv.read_weights_csv
    monkeypatch.setattr(transport.weights_csv, "read_weights_csv", lambda p: reads.append(p) or real(p))
    spec = SolveSpec(lib["rig"], "movement", lib["profile"], settings=SolveSettings(prior=first["output"]))
    cache = SolverCache()
    for take in lib["takes"]:
        row = solve_job(Job(str(take), spec, str(tmp_path / "k")), cache)
        assert row["status"] == "ok", row["error"]
    assert len(reads) == 1 and cache.built == 1
    os.utime(first["output"], ns=(os.stat(first["output"]).st_mtime_ns + 10**9,) * 2)
    assert solve_job(Job(str(lib["takes"][0]), spec, str(tmp_path / "k")), cache)["status"] == "ok"
    assert len(reads) == 2 and cache.built == 2  # a changed prior is read again


def test_the_rig_is_loaded_once_and_again_when_its_files_change(lib):
    cache = SolverCache()
    spec = SolveSpec(lib["rig"], "robust", lib["profile"])
    rig = cache.rig(spec)
    assert cache.rig(spec) is rig
    markers = lib["root"] / "demo_rig.markers.json"
    os.utime(markers, ns=(os.stat(markers).st_mtime_ns + 10**9,) * 2)
    assert cache.rig(spec) is not rig


@settings(max_examples=40, deadline=None)
@given(st.data())
def test_missing_share_is_the_selected_takes_missing_share(data):
    n, frames = data.draw(st.integers(1, 6)), data.draw(st.integers(0, 8))
    labels = [f"m{i}" for i in range(n)]
    valid = np.array(data.draw(st.lists(st.booleans(), min_size=n * frames, max_size=n * frames)), bool)
    take = Take(labels, np.zeros((frames, n, 3)), valid.reshape(frames, n), 120.0)
    wanted = data.draw(st.lists(st.sampled_from([*labels, "absent", "gone"]), min_size=1, max_size=8, unique=True))
    expected = float(1.0 - take.select(wanted).valid.mean()) if frames else 1.0
    assert missing_share(take, wanted) == expected


@settings(max_examples=40, deadline=None)
@given(st.integers(1, 5), st.integers(1, 4), st.integers(0, 6), st.integers(0, 2**32 - 1))
def test_frame_residual_is_the_rms_over_the_seen_markers(n, m, frames, seed):
    rng = np.random.default_rng(seed)
    targets, W = rng.normal(size=(frames, n, 3)), rng.normal(size=(frames, m))
    valid = rng.random((frames, n)) < 0.7

    class Profile:
        basis = rng.normal(size=(3 * n, m))

    solved = SolvedTake([f"s{i}" for i in range(m)], W, np.zeros((frames, 4)), np.zeros((frames, 3)), targets, valid,
                        120.0, 0, 0.0)
    got = frame_residual(solved, Profile)
    for t in range(frames):
        err = (targets[t] - (Profile.basis @ W[t]).reshape(n, 3))[valid[t]]
        want = np.sqrt((err**2).sum() / valid[t].sum()) if valid[t].any() else np.nan
        np.testing.assert_allclose(got[t], want, rtol=1e-12, atol=1e-12)


WARM_THEN_SOLVE = """
import sys
from livecap.batch.jobs import Job
from livecap.batch.runner import warm_kernels
from livecap.batch.spec import SolveSpec
from livecap.batch.worker import SolverCache, kernels, solve_job

def signatures():
    return {(obj.py_func.__qualname__, str(sig)) for obj in kernels() for sig in obj.signatures}

job = Job(sys.argv[1], SolveSpec(sys.argv[2], "robust", sys.argv[3]), sys.argv[4])
cache = SolverCache()
warm_kernels([job], cache)
before, modules = signatures(), set(sys.modules)
row = solve_job(job, cache)
assert row["status"] == "ok", row["error"]
print(sorted(signatures() - before), sorted(set(sys.modules) - modules))
"""


def test_the_warm_up_loads_every_kernel_a_take_with_occlusions_needs(lib, tmp_path):
    """A worker's first take must load no numba kernel and import no module the forkserver's warm-up left out
    (each kernel ~14 ms from the on-disk cache, compiled by every worker on a cold one): the demo take hides
    markers, the warm-up's first frames do not; the CSV writer has a kernel of its own. A fresh process, so the
    kernels and modules other tests loaded do not hide the gap."""
    import subprocess
    import sys

    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), *filter(None, [os.environ.get("PYTHONPATH")])])}
    out = subprocess.run([sys.executable, "-c", WARM_THEN_SOLVE, str(ROOT / "recordings" / "demo_take.c3d"),
                          lib["rig"], lib["profile"], str(tmp_path)], capture_output=True, text=True, env=env,
                         timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip() == "[] []", out.stdout


def test_two_writers_of_one_take_s_record_both_succeed(lib, tmp_path, monkeypatch):
    """Dask may run one task twice at once: the second run finishing while the first is between writing its
    record and renaming it must not make the first fail (a fixed temporary name did: FileNotFoundError)."""
    import livecap.batch.worker as worker

    job = Job(str(lib["takes"][0]), SolveSpec(lib["rig"], "robust", lib["profile"]), str(tmp_path))
    real, nested = os.replace, []

    def replace(src, dst):
        if Path(dst) == Path(job.record) and not nested:
            nested.append(None)
            nested[0] = solve_job(job)  # the other run lands its record in between
        real(src, dst)

    monkeypatch.setattr(worker.os, "replace", replace)
    row = solve_job(job)
    assert nested[0]["status"] == "ok", nested[0]["error"]
    assert row["status"] == "ok", row["error"]
    assert Path(job.record).exists() and not list(Path(job.record).parent.glob("*.partial"))


def test_a_record_has_the_mode_a_plain_write_gives(tmp_path):
    """The record's temporary file is mkstemp's (0600); renamed, it keeps the user's umask like the outputs."""
    from livecap.batch.worker import _write_record

    (tmp_path / "plain").write_text("{}")
    _write_record(tmp_path / "take.json", {"status": "ok"})
    assert (tmp_path / "take.json").stat().st_mode & 0o777 == (tmp_path / "plain").stat().st_mode & 0o777



def test_a_job_failed_before_solving_leaves_no_old_record(tmp_path):
    """The runner reads a finished take's row from its record: a job that failed before solving (its actor did not
    calibrate) must not leave an earlier run's success there to be read as this run's row."""
    from livecap.batch.worker import _write_record

    job = Job(str(tmp_path / "take.c3d"), SolveSpec(str(tmp_path / "rig.npz"), "robust"), str(tmp_path),
              error="actor neutral.c3d: calibration failed")
    _write_record(job.record, {"status": "ok"})
    row = solve_job(job)
    assert row["status"] == "failed" and row["error"] == job.error
    assert not job.record.exists()

KEEP_HEAP_THEN_SOLVE = """
import sys
from livecap.batch.jobs import Job
from livecap.batch.spec import SolveSpec
from livecap.batch.worker import SolverCache, keep_heap, solve_job

if sys.argv[5] == "keep":
    assert keep_heap()
job, cache = Job(sys.argv[1], SolveSpec(sys.argv[2], "robust", sys.argv[3]), sys.argv[4]), SolverCache()
rows = [solve_job(job, cache) for _ in range(3)]
assert all(r["status"] == "ok" for r in rows), rows
print(rows[-1]["page_faults"])
"""


@pytest.mark.skipif(not sys.platform.startswith("linux") or platform.libc_ver()[0] != "glibc", reason="glibc's mallopt")
def test_a_worker_keeps_its_heap_between_takes(lib, tmp_path):
    """A worker (``SolverCache.setup`` calls ``keep_heap``) takes no page faults for the memory its previous take freed:
    without it glibc gave the heap back after each take and every 20 s take faulted ~3 k pages in again."""
    import subprocess

    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), *filter(None, [os.environ.get("PYTHONPATH")])])}
    faults = {}
    for how in ("keep", "default"):
        out = subprocess.run([sys.executable, "-c", KEEP_HEAP_THEN_SOLVE, str(ROOT / "recordings" / "demo_take.c3d"),
                              lib["rig"], lib["profile"], str(tmp_path / how), how], capture_output=True, text=True,
                             env=env, timeout=300)
        assert out.returncode == 0, out.stderr[-2000:]
        faults[how] = int(out.stdout.split()[-1])
    assert faults["keep"] * 4 < faults["default"], faults


def test_kernels_are_looked_for_again_only_after_an_import():
    """``solve_job`` counts the kernels compiled during a take, twice a take: the modules are walked again only when
    one was imported (or dropped) since, which still finds a kernel module imported mid-take."""
    import types

    from numba import njit

    from livecap.batch.worker import kernels

    first = kernels()
    assert kernels() is first
    mod = types.ModuleType("solvers._kernel_probe")
    mod.probe = njit(lambda x: x + 1)
    sys.modules[mod.__name__] = mod
    try:
        assert mod.probe in kernels() and mod.probe not in first
    finally:
        del sys.modules[mod.__name__]
    assert mod.probe not in kernels()
