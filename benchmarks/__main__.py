"""Run the benchmark suite: ``python -m benchmarks [--quick] [--only NAME ...]``.

Each suite runs in its own process (so its peak memory is its own), prints its table, and the
figures are collected with the machine description into benchmarks/results/<date>.json and
benchmarks/results/latest.json.
"""

from __future__ import annotations

import argparse
import importlib
import json
import subprocess
import sys
import time
from pathlib import Path

from benchmarks.timing import machine, peak_rss_mb

# suite name -> module under benchmarks/ exposing run(quick) -> dict
SUITES = ["solve_latency", "movement", "qp_libraries", "rbf_blend", "live_latency", "live_driver", "concurrency",
          "viewer_fps", "transfer", "bounded", "weight_smoothing", "hostile", "review", "labelling",
          "offline", "batch"]
RESULTS = Path(__file__).resolve().parent / "results"


def _load() -> str:
    """The 1, 5 and 15 minute load averages (the machine is shared: timings depend on them)."""
    with open("/proc/loadavg") as fh:
        return " ".join(fh.read().split()[:3])


def run_one(name: str, quick: bool) -> dict:
    """Child-process entry: run one suite and print its JSON on the last line."""
    mod = importlib.import_module(f"benchmarks.{name}")
    out = mod.run(quick=quick)
    out["peak_rss_mb"] = peak_rss_mb()
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks", description=__doc__)
    p.add_argument("--quick", action="store_true", help="fewer repetitions (a smoke run)")
    p.add_argument("--only", nargs="*", help="suites to run (default: all available)")
    p.add_argument("--merge", action="store_true",
                   help="keep the other suites of results/latest.json (re-run some suites, e.g. in full)")
    p.add_argument("--child", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.child:
        result = run_one(args.child, args.quick)
        print("\nRESULT " + json.dumps(result, default=float))
        return 0
    names = args.only or [s for s in SUITES if (Path(__file__).parent / f"{s}.py").exists()]
    command = "python -m benchmarks " + " ".join(sys.argv[1:] if argv is None else argv)
    report = {"machine": machine(), "quick": args.quick, "command": command.strip(), "load_start": _load(),
              "suites": {}}
    print(f"{report['machine']['cpu']}, {report['machine']['cores']} cores; load average {report['load_start']}")
    for name in names:
        print(f"\n=== {name} === (load average {_load()})", flush=True)
        load = _load()
        cmd = [sys.executable, "-m", "benchmarks", "--child", name] + (["--quick"] if args.quick else [])
        t0 = time.monotonic()
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        result = None
        for line in proc.stdout:  # stream the suite's table as it is produced
            if line.startswith("RESULT "):
                result = json.loads(line[7:])
            else:
                print(line, end="", flush=True)
        err = proc.stderr.read()
        proc.wait()
        if proc.returncode or result is None:
            print(err[-2000:], file=sys.stderr)
            result = {"error": (err.strip().splitlines() or ["failed"])[-1]}
        result.update(load_avg_start=load, load_avg_end=_load(), wall_s=time.monotonic() - t0, quick=args.quick)
        report["suites"][name] = result
        if "peak_rss_mb" in result:
            print(f"[{name}] peak memory {result['peak_rss_mb']:.0f} MB, {result['wall_s']:.0f} s, "
                  f"load average {load} -> {result['load_avg_end']}")
    report["load_end"] = _load()
    if args.merge and (RESULTS / "latest.json").exists():
        old = json.loads((RESULTS / "latest.json").read_text())
        report["suites"] = {**old.get("suites", {}), **report["suites"]}
        report["merged_from"] = [*old.get("merged_from", []), {k: old.get(k) for k in ("command", "quick", "load_start",
                                                                                      "load_end")}]
        report["machine"]["first_date"] = old.get("machine", {}).get("first_date", old.get("machine", {}).get("date"))
    RESULTS.mkdir(exist_ok=True)
    stamp = report["machine"]["date"].replace(":", "").replace("-", "")[:15]
    for path in (RESULTS / f"{stamp}.json", RESULTS / "latest.json"):
        path.write_text(json.dumps(report, indent=1, default=float))
    print(f"\nwritten {RESULTS / 'latest.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
