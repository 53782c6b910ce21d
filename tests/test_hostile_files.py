"""Mangled take files (issue 36, items 5-6): seeded byte flips, truncations and lying counts of
every vendor C3D (../shared) and of TRC / CSV takes, read in subprocesses under an address-space
limit of the interpreter's baseline plus twice what reading the valid files needs. Every file must
give a take or one error line; no traceback, no crash (segfault, ``bad_alloc``), no hang.
"""

from __future__ import annotations

import os
import random
import resource
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import VENDORS
from tests.hostile_files import mangle_c3d, mangle_text

ROOT = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "PYTHONPATH": str(ROOT), "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"}


def _read(files: list[Path], limit_kb: int | None = None, timeout: float = 120) -> tuple[dict[str, str], int, str]:
    """Read ``files`` in one reader process (tests/hostile_files.py): {name: its result line}, the
    process's VmPeak (kB), its stderr; asserts the process ended by itself."""
    def cap() -> None:
        if limit_kb:
            resource.setrlimit(resource.RLIMIT_AS, (limit_kb << 10, limit_kb << 10))

    r = subprocess.run([sys.executable, "-m", "tests.hostile_files", *map(str, files)], capture_output=True,
                       text=True, env=ENV, timeout=timeout, preexec_fn=cap)
    results, started, peak = {}, None, 0
    for line in r.stdout.splitlines():
        kind, _, rest = line.partition(" ")
        if kind == "start":
            started = rest
        elif kind in ("ok", "error", "multiline"):
            results[started] = line
            started = None
        elif kind == "peak":
            peak = int(rest)
    assert r.returncode == 0 and started is None, (
        f"reader died (exit {r.returncode}) on {started}:\n{r.stderr[-2000:]}")
    return results, peak, r.stderr


def _limit(valid: list[Path], need: int = 5) -> int:
    """Address-space cap: the reader's VmPeak on the valid files plus that much again above its
    baseline (baseline + 2x the valid need); at least ``need`` of them must read."""
    base = _read([])[1]
    results, peak, _ = _read(valid)
    assert sum(line.startswith("ok") for line in results.values()) >= need, results
    return peak + (peak - base)


def _check(results: dict[str, str], stderr: str, files: list[Path]) -> None:
    assert "Traceback" not in stderr, stderr[-3000:]
    assert sorted(results) == sorted(p.name for p in files)
    bad = [line for line in results.values() if line.startswith("multiline") or "bad_alloc" in line]
    assert not bad, bad
    for name, line in results.items():
        if line.startswith("error"):
            assert name in line.partition(": ")[2], line  # the message names the file


@pytest.fixture(scope="module")
def c3d_corpus(tmp_path_factory) -> tuple[list[Path], list[Path]]:
    if not VENDORS.is_dir():
        pytest.skip(f"vendor C3D files not found at {VENDORS}")
    out = tmp_path_factory.mktemp("mangled-c3d")
    files = sorted(VENDORS.glob("*.c3d"))
    corpus = [p for src in files for p in mangle_c3d(src, out, seed=0)]
    return files, corpus


def test_mangled_vendor_c3ds_never_crash_or_overallocate(c3d_corpus):
    """Before: 8 of 20 flips of FP_Type1 killed ``livecap info`` with a segfault, others allocated
    4.2 GB (``std::bad_alloc``) or hung in ezc3d."""
    valid, corpus = c3d_corpus
    limit = _limit(valid)
    results, peak, err = _read(corpus, limit)
    _check(results, err, corpus)
    assert peak <= limit
    errors = [line for line in results.values() if line.startswith("error")]
    assert len(errors) > len(corpus) / 2  # most mangled files are refused, with a reason
    assert any("truncated C3D" in e for e in errors) and any("parameter" in e for e in errors)


def test_the_issues_fp_type1_flips(c3d_corpus, tmp_path):
    """The issue's reproduction: 16 bytes of FP_Type1.c3d inverted (XOR 0xFF) in its first 2 KB, 20
    seeds. Before (under a 1 GiB cap): 8 segfaults and one ``std::bad_alloc``."""
    valid, _ = c3d_corpus
    src = (VENDORS / "FP_Type1.c3d").read_bytes()
    files = []
    for seed in range(20):
        b = bytearray(src)
        for i in np.random.default_rng(seed).choice(2048, 16, replace=False):
            b[i] ^= 0xFF
        files.append(tmp_path / f"fp1_{seed}.c3d")
        files[-1].write_bytes(bytes(b))
    results, _, err = _read(files, _limit(valid))
    _check(results, err, files)


def _cli(args: list[str], limit_kb: int | None = None) -> tuple[subprocess.CompletedProcess, int]:
    def cap() -> None:
        if limit_kb:
            resource.setrlimit(resource.RLIMIT_AS, (limit_kb << 10, limit_kb << 10))

    r = subprocess.run([sys.executable, "-m", "tests.hostile_files", "--cli", *args], capture_output=True, text=True,
                       env=ENV, timeout=120, preexec_fn=cap)
    peak = [int(line.split()[1]) for line in r.stdout.splitlines() if line.startswith("peak ")]
    return r, peak[0] if peak else 0


def test_mangled_c3d_through_the_cli_is_one_line(c3d_corpus, tmp_path):
    """``livecap info`` and ``livecap solve`` on a seeded sample of the corpus, each capped at its own
    VmPeak on the largest valid vendor file plus twice what reading that file needs."""
    valid, corpus = c3d_corpus
    big = max(valid, key=lambda p: p.stat().st_size)
    need = _read([big])[1] - _read([])[1]
    rig = ROOT / "recordings" / "demo_rig.npz"
    commands = {"info": lambda p: ["info", str(p)],
                "solve": lambda p: ["solve", str(p), "--rig", str(rig), "--out", str(tmp_path / "w.csv")]}
    for name, cmd in commands.items():
        limit = _cli(cmd(big))[1] + 2 * need
        for path in random.Random(name).sample(corpus, 2):
            r, _ = _cli(cmd(path), limit)
            lines = [e for e in r.stderr.strip().splitlines() if not e.startswith(("WARNING ", "INFO "))]
            assert "Traceback" not in r.stderr and r.returncode in (0, 1), (path, r.returncode, r.stderr[-2000:])
            if r.returncode == 1:
                assert len(lines) == 1 and path.name in lines[0], (path, r.stderr)


@pytest.fixture(scope="module")
def text_corpus(tmp_path_factory) -> tuple[list[Path], list[Path]]:
    """A 240-frame, 20-marker piece of the demo take as TRC and CSV, and their mangled copies
    (three seeds: flips to bytes and to number-like characters, cuts mid-row, a NumFrames of 1e9,
    a 50 MB field)."""
    from livecap.core.take import Take
    from transport.takefile import read_take, write_take

    out = tmp_path_factory.mktemp("mangled-text")
    t = read_take(ROOT / "recordings" / "demo_take.c3d")
    t = Take(t.labels[:20], t.positions[:240, :20], t.valid[:240, :20], t.rate, t.first_frame)
    valid = [out / "take.trc", out / "take.csv"]
    for p in valid:
        write_take(t, p)
    return valid, [m for p in valid for seed in range(3) for m in mangle_text(p, out, seed)]


def test_mangled_trc_and_csv_are_refused_in_one_line(text_corpus):
    """Before: a truncated TRC and one claiming NumFrames=1e9 were read as shorter takes without a
    word, and a CSV with a 50 MB field raised ``_csv.Error`` (a traceback)."""
    valid, corpus = text_corpus
    results, peak, err = _read(corpus, _limit(valid, need=2))
    _check(results, err, corpus)
    line = {name.split(".", 2)[2]: text for name, text in results.items() if ".s0." in name}
    assert "NumFrames is 1000000000 but the file holds 240" in line["lie_frames.trc"]
    for case in ("cut30.trc", "cut77.trc", "cut30.csv", "cut77.csv"):
        assert line[case].startswith("error") and "truncated" in line[case], line[case]
    for case in ("hugefield.trc", "hugefield.csv"):
        assert line[case].startswith("error") and len(line[case]) < 300, line[case][:300]


def test_lying_trc_through_the_cli_is_one_line(text_corpus):
    valid, corpus = text_corpus
    for path in [p for p in corpus if ".s0.lie_frames." in p.name or ".s0.hugefield.csv" in p.name]:
        r, _ = _cli(["info", str(path)])
        lines = r.stderr.strip().splitlines()
        assert r.returncode == 1 and len(lines) == 1 and path.name in lines[0], r.stderr[-2000:]
