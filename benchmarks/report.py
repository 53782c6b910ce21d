"""Markdown tables (and the issue-8 goals with ratios) from a results JSON written by ``python -m benchmarks``.

    python -m benchmarks.report [benchmarks/results/latest.json]

docs/performance.md pastes this output, so every figure there comes straight from the JSON.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results" / "latest.json"
NAN = float("nan")


def _f(x, digits: int = 3) -> str:
    if x is None or (isinstance(x, float) and x != x):
        return "-"
    if isinstance(x, float):
        return f"{x:.{digits}g}" if abs(x) < 10 ** digits else f"{x:.0f}"
    return str(x)


def _load(x) -> str:
    return f"{x:.2f}" if isinstance(x, float) else str(x)


def _table(header: list[str], rows: list[list]) -> str:
    out = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    out += ["| " + " | ".join(_f(c) if not isinstance(c, str) else c for c in r) + " |" for r in rows]
    return "\n".join(out)


def _row(rows: list[dict], mode: str, size: str) -> dict:
    return next((r for r in rows if r["mode"] == mode and r["size"] == size), {})


def solve_latency(s: dict) -> str:
    rows = s["rows"]
    sizes = list(dict.fromkeys(r["size"] for r in rows))
    modes = list(dict.fromkeys(r["mode"] for r in rows))
    header = ["mode"] + [f"{z} p50 / p99 µs (×pinv p99)" for z in sizes]
    body = []
    for m in modes:
        cells = [m]
        for z in sizes:
            r = _row(rows, m, z)
            if "p99_us" in r:
                note = f" [{r['note']}]" if r.get("note") else ""
                cells.append(f"{_f(r['median_us'])} / {_f(r['p99_us'])} (×{_f(r['ratio_p99'], 2)}){note}")
            else:
                cells.append(f"not timed: {r.get('skipped', '-')}")
        body.append(cells)
    return _table(header, body)


def movement(s: dict) -> str:
    rows = [[r["frames"], r["ours_s"] * 1e3, r["ours_solve_only_s"] * 1e3, r.get("reference_s", NAN),
             r["seol_matlab_s"], r["seol_matlab_s"] / r["ours_s"], r.get("max_abs_diff", NAN)] for r in s["offline"]]
    t = _table(["frames (54×50)", "ours ms (incl. set-up)", "solve only ms", "literal sparse Eq. 5 s",
                "Seol Table I s (Matlab)", "speed-up vs Seol", "max abs(ours − literal)"], rows)
    e = s["edit"]
    t += ("\n\nSpacetime edit re-solve, 1000-frame take at 54×50: 12-frame range "
          f"{e['range12_s'] * 1e3:.3f} ms; whole take as the range {e['whole_s'] * 1e3:.2f} ms "
          f"(solving the take from scratch: {e['full_resolve_s'] * 1e3:.2f} ms).")
    st = s["streaming_72x150"]
    t += "\n\n" + _table(["streaming movement 72×150", "p50 µs", "p99 µs", "thread CPU p99 µs"],
                         [[k, v["p50_us"], v["p99_us"], v["cpu_p99_us"]] for k, v in st.items()])
    return t


def qp_libraries(s: dict) -> str:
    out = []
    for size, block in s["sizes"].items():
        rows = [[name, r.get("p50_us", NAN), r.get("p99_us", NAN), r.get("max_err", NAN)]
                for name, r in block["libraries"].items()]
        out.append(f"{size} ({block['active_bound_fraction'] * 100:.0f}% of weights on a bound):\n\n"
                   + _table(["library", "p50 µs", "p99 µs", "max abs(w − BVLS)"], rows))
    return "\n\n".join(out)


def rbf_blend(s: dict) -> str:
    rows = [[z, r["keys"], r["prepare_ms"], r["all seen"]["p50_us"], r["all seen"]["p99_us"],
             r["one missing"]["p99_us"]] for z, r in s["sizes"].items()]
    return _table(["size", "keys", "prepare ms", "p50 µs", "p99 µs", "p99 µs, 1 marker missing"], rows)


def live_latency(s: dict) -> str:
    b = s["bare_zmq"]
    rows = [["bare ZeroMQ relay", f"{b['received']}/{b['sent']}", "-", b["p50_ms"], b["p99_ms"], 1.0, "-", "-"]]
    for m, r in s["modes"].items():
        rows.append([m, f"{r['received']}/{r['sent']}", r.get("stale", 0), r.get("p50_ms", NAN), r.get("p99_ms", NAN),
                     r.get("p99_ms", NAN) / b["p99_ms"], r["solve_p99_ms"], f"{r['driver_cpu_pct']:.0f}%"])
    return (f"{s['rate_hz']:g} Hz for {s['seconds']} s per mode ({s['machine']}); {s['data']}.\n\n"
            + _table(["path", "received/sent", "stale", "p50 ms", "p99 ms", "p99 / bare", "solve p99 ms",
                      "driver CPU"], rows))


def concurrency(s: dict) -> str:
    names = {"1": "1 process (threads)", "2": "2 processes (threads)", "per-actor": "process per actor"}
    rows = []
    for r in s["results"]:
        ok = [t for t in r["trials"] if t["sustained"] and t["actors"] == r["sustained_actors"]]
        bad = [t for t in r["trials"] if not t["sustained"]]
        fail = (f"N={bad[-1]['actors']}: p99 {bad[-1]['p99_ms']:.1f} ms, received min "
                f"{bad[-1]['received_min']}/{bad[-1]['sent_per_actor']}") if bad else "-"
        rows.append([r["mode"], names.get(r["layout"], r["layout"]), r["sustained_actors"],
                     ok[-1]["p99_ms"] if ok else NAN, f"{ok[-1]['driver_cpu_pct']:.0f}%" if ok else "-", fail])
    return (f"{s['seconds_per_trial']:g} s per trial; sustained = {s['criterion']}; load average "
            f"{_load(s['load_start'])} → {_load(s['load_end'])}.\n\n"
            + _table(["mode", "layout", "actors sustained", "p99 ms there", "driver CPU there (of 200%)",
                      "first failing N"], rows))


def viewer_fps(s: dict) -> str:
    rows = [[r["deformation"], r["msaa"], r["deform_fps"], r["frame_fps"], r["annotated_fps"], r["frame_cpu_ms"]]
            for r in s["rows"]]
    return (f"{s['rig']}, {s['vertices']} vertices, {s['size']}, {s.get('renderer', '')}.\n\n"
            + _table(["deformation", "MSAA", "deform/s", "frames/s", "annotated frames/s", "CPU ms/frame"], rows))


def weight_smoothing(s: dict) -> str:
    rows = [[r["smoother"], r["seconds"], r["time_ratio"], r["iterations"], r["jitter_ratio"], r["rmse"], r["blink"]]
            for r in s["rows"]]
    scale = ", ".join(f"{r['frames']} frames {r['ms_per_frame']:.2f} ms/frame" for r in s["scaling"])
    return (f"Demo take, {s['frames']} frames x {s['shapes']} shapes, best of {s['repeats']}.\n\n"
            + _table(["smoother", "s per take", "x quartic", "ADMM it", "jitter x truth", "RMSE", "blinks"], rows)
            + f"\n\nTrend filter (10 sd) on longer takes: {scale}.")


def goals(report: dict) -> str:
    """Each goal of issue 8 next to the measured figure and their ratio (measured / goal)."""
    su = report["suites"]
    rows = []

    def add(goal: str, target: float, measured: float, unit: str, higher_better: bool = False):
        ok = measured >= target if higher_better else measured <= target
        rows.append([goal, f"{_f(target)} {unit}", f"{_f(measured)} {unit}",
                     _f(measured / target, 2) if target else "-", "met" if ok else "missed"])

    sl = su.get("solve_latency", {}).get("rows", [])
    for mode, target in (("movement-stream", 50.0), ("qp", 200.0), ("rbf", 50.0)):
        r = _row(sl, mode, "72x150")
        if "p99_us" in r:
            add(f"72×150 {mode} p99", target, r["p99_us"], "µs")
    for mode in ("movement-stream", "qp", "rbf", "robust", "lsq"):
        r = _row(sl, mode, "72x1000")
        if "p99_us" in r:
            add(f"72×1000 {mode} p99", 2000.0, r["p99_us"], "µs")
    mv = su.get("movement", {}).get("offline", [])
    r1000 = next((r for r in mv if r["frames"] == 1000), None)
    if r1000:
        add("offline 1000 frames: speed-up vs Seol's 31.65 s", 500.0, 31.65 / r1000["ours_s"], "×", True)
    ll = su.get("live_latency", {})
    for m, r in ll.get("modes", {}).items():
        if "p99_ms" in r:
            add(f"end-to-end p99 / bare ZeroMQ p99, {m}", 3.0, r["p99_ms"] / ll["bare_zmq"]["p99_ms"], "×")
    for r in su.get("concurrency", {}).get("results", []):
        add(f"actors at 120 Hz, {r['mode']}, layout {r['layout']}", 8.0, float(r["sustained_actors"]), "actors",
            True)
    return _table(["goal (issue 8)", "target", "measured", "measured / target", ""], rows)


SECTIONS = [("solve_latency", "Per-frame solve latency", solve_latency), ("movement", "Movement matching", movement),
            ("qp_libraries", "QP libraries", qp_libraries), ("rbf_blend", "RBF key blending", rbf_blend),
            ("live_latency", "End-to-end live latency", live_latency), ("concurrency", "Concurrency", concurrency),
            ("viewer_fps", "Offscreen preview", viewer_fps),
            ("weight_smoothing", "Offline weight smoothing (l1 trend filter)", weight_smoothing)]


def render(report: dict) -> str:
    m = report["machine"]
    out = [f"Machine: {m['cpu']}, {m['cores']} cores, {m['platform']}; Python {m['python']}, numpy {m['numpy']}, "
           f"scipy {m['scipy']}; {m['date']}. Command: `{report.get('command', 'python -m benchmarks')}`"
           f"{' (quick)' if report.get('quick') else ''}. Load average at start {report.get('load_start', '?')}, "
           f"at end {report.get('load_end', '?')}.", "", "### Goals", "", goals(report)]
    for key, title, fn in SECTIONS:
        s = report["suites"].get(key)
        if s is None:
            continue
        run_kind = {True: " (quick run)", False: " (full run)"}.get(s.get("quick", report.get("quick")), "")
        out += ["", f"### {title}{run_kind}", ""]
        if "error" in s:
            out.append(f"failed: {s['error']}")
            continue
        out.append(fn(s))
        start = s.get("load_avg_start", s.get("load_start", "?"))
        end = s.get("load_avg_end", s.get("load_end", "?"))
        out.append(f"\n(peak RSS {s.get('peak_rss_mb', NAN):.0f} MB, {s.get('wall_s', NAN):.0f} s, load average "
                   f"{_load(start)} → {_load(end)})")
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    path = Path(argv[0]) if argv else RESULTS
    print(render(json.loads(path.read_text())))
    return 0


if __name__ == "__main__":
    sys.exit(main())
