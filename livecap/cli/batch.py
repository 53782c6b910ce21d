"""``livecap batch``: solve a take library on Dask (a LocalCluster, or the user's scheduler)."""

from __future__ import annotations

import argparse
import shlex
import time
from collections.abc import Sequence
from dataclasses import fields

from livecap.batch.spec import SolveSettings, marker_weights
from livecap.modes.registry import DEFAULT_MODE, MODE_HELP, MODES_AND_AUTO

# ``livecap solve`` flags that are a job's own (batch flags or manifest columns), not solver settings
JOB_FLAGS = {"--rig": "--rig / rig", "--markers": "--markers / markers", "--profile": "--profile / profile",
             "--mode": "--mode / mode", "--neutral-seconds": "--neutral-seconds", "--out": "--out",
             "--unlabelled": "no batch form: label the takes first with 'livecap label'",
             "--map": "no batch form yet: retarget Live Link Face takes one by one with 'livecap solve'",
             "--transfer": "no batch form yet: retarget Live Link Face takes one by one with 'livecap solve'",
             "--help": "livecap solve --help", "-h": "livecap solve --help"}


# rich redraws its bar 10 times a second by default, in this process beside the LocalCluster's scheduler, on the
# cores the workers solve on: ~1.3 ms CPU a redraw in a terminal (docs/batch.md "the wall beyond CPU")
PROGRESS_REFRESH_PER_S = 2


def register(sub) -> None:
    p = sub.add_parser("batch", help="solve many takes on Dask (local worker processes or a cluster)",
                       description="Solve a library of takes, one output per take equal to what 'livecap solve' "
                                   "writes, on a distributed.LocalCluster or an existing Dask scheduler; "
                                   "resumable; DIR/summary.{json,csv,html} report every take (docs/batch.md).")
    p.add_argument("takes", nargs="*", help="take files, folders or globs (quote globs with ** for recursion)")
    p.add_argument("--manifest", action="append", default=[], metavar="FILE",
                   help="CSV or TOML manifest: take, actor, profile, calibrate_from, mode, options, rig, markers "
                        "(repeatable; mixes actors, profiles and modes in one batch)")
    p.add_argument("--rig", help="rig (OBJ folder or .npz); a manifest row may name its own")
    p.add_argument("--markers", help="markers.json (default: the rig's)")
    cal = p.add_mutually_exclusive_group()
    cal.add_argument("--profile", help="calibrated profile (.npz) for every take")
    cal.add_argument("--calibrate-from", metavar="NEUTRAL",
                     help="neutral take: calibrate once (as 'livecap calibrate' does) and use it for every take")
    p.add_argument("--neutral-seconds", type=float, default=1.0,
                   help="without a profile: each take calibrates on its first seconds, as 'livecap solve' does")
    p.add_argument("--out", required=True, help="output folder: DIR/<take stem>.<format>, DIR/summary.*")
    p.add_argument("--mode", default=DEFAULT_MODE, choices=sorted(MODES_AND_AUTO), help=MODE_HELP)
    p.add_argument("--format", default="csv", choices=["csv", "jsonl", "glb"], help="output format (default csv)")
    p.add_argument("--solve-options", default="", metavar="FLAGS",
                   help="further 'livecap solve' flags for every take, quoted: --solve-options '--ridge 0.01'")
    p.add_argument("--workers", type=int, help="LocalCluster worker processes (default: the cores)")
    p.add_argument("--scheduler", metavar="ADDR", help="connect to this Dask scheduler (tcp://HOST:8786) instead")
    p.add_argument("--force", action="store_true", help="solve every take again, even those up to date")
    p.set_defaults(func=run)


class _Raising(argparse.ArgumentParser):
    def error(self, message: str):
        raise ValueError(f"solve options: {message}")


def _solve_parser() -> argparse.ArgumentParser:
    from livecap.cli import solve

    sub = _Raising(prog="livecap").add_subparsers(parser_class=_Raising)
    solve.register(sub)
    parser = sub.choices["solve"]
    parser.allow_abbrev = False  # a job's flag is spelt in full: no '--neutral' standing for another flag
    return parser


def settings_from_flags(flags: Sequence[str]) -> SolveSettings:
    """``livecap solve`` flags as the typed settings a batch job carries, parsed by the solve command's own
    parser on the client (workers never see flags); ValueError "solve options: ..." naming the flag."""
    for token in flags:
        name = token.partition("=")[0]
        if name in JOB_FLAGS:
            raise ValueError(f"solve options: {name} is not a solver setting (use {JOB_FLAGS[name]})")
    args = _solve_parser().parse_args(["take", "--rig", "rig", "--out", "out", *flags])
    given = {f.name: getattr(args, f.name) for f in fields(SolveSettings) if f.name != "marker_weights"}
    return SolveSettings(**given, marker_weights=marker_weights(args.marker_weight))


def _progress(total: int):
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    prog = Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
                    TextColumn("{task.fields[fps]:>8.0f} frames/s"), TextColumn("{task.fields[failed]} failed"),
                    TimeRemainingColumn(), refresh_per_second=PROGRESS_REFRESH_PER_S)
    task = prog.add_task("takes", total=total, fps=0.0, failed=0)
    state = {"frames": 0, "failed": 0, "start": time.perf_counter()}

    def done(row: dict) -> None:
        if row["status"] == "ok":
            state["frames"] += row.get("frames", 0)
        state["failed"] += row["status"] == "failed"
        fps = state["frames"] / max(time.perf_counter() - state["start"], 1e-9)
        prog.update(task, advance=1, fps=fps, failed=state["failed"])
        if row["status"] == "failed":
            prog.console.print(f"[red]failed[/red] {row['take']}: {row['error']}", highlight=False)

    return prog, done


def _table(rows: list[dict], meta: dict):
    from rich.table import Table

    t = Table(title=f"livecap batch: {meta['n_takes']} takes, {meta['solved']} solved, {meta['skipped']} skipped "
                    f"(up to date), {meta['failed']} failed, {meta['wall_seconds']:.1f} s on {meta['workers']} workers")
    for col in ("take", "status", "frames", "s", "p50 mm", "p95 mm", "missing", "@upper"):
        t.add_column(col, justify="left" if col in ("take", "status") else "right", no_wrap=True,
                     min_width=len(col))
    for r in rows:
        ok = r["status"] != "failed"
        cells = [str(r.get("frames", "")), f"{r.get('seconds', 0):.1f}", f"{r['residual_p50_mm']:.3f}",
                 f"{r['residual_p95_mm']:.3f}", f"{r['missing_share']:.1%}", f"{r['at_upper_share']:.1%}"] if ok \
            else [""] * 6
        t.add_row(r["stem"], r["status"], *cells, style=None if ok else "red")
    return t


def run(args: argparse.Namespace) -> int:
    from livecap.batch.plan import plan_jobs
    from livecap.batch.runner import dask_client, exit_code, run_batch

    jobs = plan_jobs(args.takes, args.manifest, rig=args.rig, out_dir=args.out, mode=args.mode, fmt=args.format,
                     profile=args.profile, calibrate_from=args.calibrate_from, markers=args.markers,
                     neutral_seconds=args.neutral_seconds,
                     settings=settings_from_flags(shlex.split(args.solve_options)), parse_flags=settings_from_flags)
    prog, done = _progress(len(jobs))
    todo = jobs if args.force else [j for j in jobs if not j.up_to_date()]
    with dask_client(args.workers, args.scheduler, warm=todo) as client, prog:
        rows, meta = run_batch(jobs, args.out, client, force=args.force, on_done=done)
    prog.console.print(_table(rows, meta))
    for r in rows:
        note = r.get("error") or "; ".join(r.get("warnings", []))
        if note:
            prog.console.print(f"{r['stem']}: {note}", highlight=False, soft_wrap=True)
    print(f"summary: {args.out}/summary.html, summary.csv, summary.json")
    return exit_code(rows)
