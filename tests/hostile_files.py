"""The mangled-file corpus (issue 36, items 5-6) and a reader process to feed it to.

``mangle_c3d`` / ``mangle_text`` build, deterministically from a seed, byte-flipped,
truncated and count-lying copies of real files. ``python -m tests.hostile_files FILE...`` reads
each with livecap's own take reader and prints one line per file, ``start NAME`` before it and
``ok NAME`` / ``error NAME: MESSAGE`` after, then ``peak KB`` (VmPeak): a run that dies
(segfault, ``bad_alloc`` abort, address-space limit) leaves a ``start`` without its result.
``python -m tests.hostile_files --cli ARGS...`` runs ``livecap ARGS...`` and prints its VmPeak.
"""

from __future__ import annotations

import struct
import sys
from pathlib import Path

import numpy as np


def _flip(data: bytes, rng: np.random.Generator, n: int, span: int, alphabet: bytes = b"") -> bytes:
    """``n`` bytes of the first ``span`` changed: XORed with a random byte, or replaced by one of
    ``alphabet`` (text that still decodes and splits into cells)."""
    b = bytearray(data)
    for i in rng.choice(min(span, len(b)), min(n, len(b)), replace=False):
        b[i] = alphabet[rng.integers(len(alphabet))] if alphabet else b[i] ^ int(rng.integers(1, 256))
    return bytes(b)


def mangle_c3d(src: Path, out: Path, seed: int, flips: int = 8) -> list[Path]:
    """``flips`` byte-flipped copies (16 bytes in the first 2 KB as in the issue, or 16 KB), truncations at
    three places, and copies whose header lies about the point / analog / frame counts."""
    data = src.read_bytes()
    rng = np.random.default_rng([seed, len(data)])
    cases: dict[str, bytes] = {}
    for k in range(flips):  # odd ones anywhere in the header and parameter section (up to 16 KB)
        cases[f"flip{k}"] = _flip(data, rng, 16, 2048 if k % 2 == 0 else 16384)
    for frac in (0.1, 0.5, 0.97):
        cases[f"cut{int(frac * 100)}"] = data[: int(len(data) * frac)]
    for name, word, value in (("points", 2, 0xFFFF), ("analogs", 3, 0xFFFF), ("last", 5, 0xFFFE),
                              ("first", 4, 0), ("datastart", 16, 0xFFFF), ("scale", 12, 0)):
        b = bytearray(data)
        b[word:word + 2] = struct.pack("<H", value)
        cases[f"lie_{name}"] = bytes(b)
    b = bytearray(data)
    b[0] = 0xFF  # parameter block past the end
    cases["lie_parblock"] = bytes(b)
    return _write_cases(cases, src, out, seed, ".c3d")


def mangle_text(src: Path, out: Path, seed: int, flips: int = 4) -> list[Path]:
    """Byte-flipped, truncated (mid-row), count-lying copies of a TRC or CSV take, and one with a
    50 MB field."""
    data = src.read_bytes()
    rng = np.random.default_rng([seed, len(data)])
    cases = {f"flip{k}": _flip(data, rng, 16, len(data), b"" if k % 2 else b"0123456789.-eE\t\n ,#=")
             for k in range(flips)}
    for frac in (0.3, 0.77):
        cases[f"cut{int(frac * 100)}"] = data[: int(len(data) * frac)]
    text = data.decode()
    if src.suffix == ".trc":
        lines = text.split("\n")
        vals = lines[2].split("\t")
        for name, value in (("frames", "1000000000"), ("frames_nan", "nan"), ("markers", "100000")):
            v = list(vals)
            v[2 if name.startswith("frames") else 3] = value
            cases[f"lie_{name}"] = "\n".join([*lines[:2], "\t".join(v), *lines[3:]]).encode()
    lines = text.split("\n")
    lines[-3] += "7" * (50 << 20)  # a data row's last cell
    cases["hugefield"] = "\n".join(lines).encode()
    return _write_cases(cases, src, out, seed, src.suffix)


def _write_cases(cases: dict[str, bytes], src: Path, out: Path, seed: int, suffix: str) -> list[Path]:
    """Write each mangled copy as <stem>.s<seed>.<case><suffix> under `out`; return the paths."""
    paths = []
    for name, blob in cases.items():
        p = out / f"{src.stem}.s{seed}.{name}{suffix}"
        p.write_bytes(blob)
        paths.append(p)
    return paths


def _peak_kb() -> int:
    for line in open("/proc/self/status"):
        if line.startswith("VmPeak:"):
            return int(line.split()[1])
    return 0


def main(argv: list[str]) -> int:
    if argv[:1] == ["--cli"]:  # a livecap command, then its VmPeak on stdout
        from livecap.cli import main as livecap

        try:
            return livecap(argv[1:])
        finally:
            print(f"peak {_peak_kb()}", flush=True)
    from transport.errors import TakeFileError
    from transport.takefile import read_take

    print(f"base {_peak_kb()}", flush=True)
    for arg in argv:
        name = Path(arg).name
        print(f"start {name}", flush=True)
        try:
            take = read_take(arg)
            print(f"ok {name} {take.n_frames}x{take.n_markers}", flush=True)
        except TakeFileError as exc:
            msg = str(exc)
            print(f"error {name}: {msg}" if "\n" not in msg else f"multiline {name}: {msg!r}", flush=True)
    print(f"peak {_peak_kb()}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
