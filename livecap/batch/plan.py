"""From the command line and manifests to jobs: defaults, per-actor profiles calibrated once."""

from __future__ import annotations

import hashlib
import logging
from collections.abc import Callable
from pathlib import Path

from livecap.batch.jobs import RECORDS, Job, expand_takes, read_manifest
from livecap.batch.spec import SolveSettings, SolveSpec
from livecap.batch.worker import one_line

log = logging.getLogger(__name__)


def calibrated_profile(neutral: str, rig: str, markers: str | None, out_dir: str | Path) -> str:
    """The profile ``livecap calibrate NEUTRAL --rig RIG`` writes, made once on the client and kept in
    the output folder (remade only when the neutral take or the rig is newer)."""
    from livecap.offline.setup import calibrate_neutral, load_rig_layout, tune_on_take
    from transport.takefile import read_take

    tag = hashlib.sha1(f"{Path(neutral).resolve()}|{Path(rig).resolve()}|{markers}".encode()).hexdigest()[:10]
    path = Path(out_dir) / RECORDS / "profiles" / f"{Path(neutral).stem}-{tag}.npz"
    sources = [Path(p) for p in (neutral, rig, markers) if p]
    if path.is_file() and all(path.stat().st_mtime_ns > p.stat().st_mtime_ns for p in sources if p.exists()):
        return str(path)
    rig_, layout = load_rig_layout(rig, markers)
    take = read_take(neutral)
    profile = calibrate_neutral(rig_, layout, take, take_path=neutral, rig_path=rig)
    tune_on_take(profile, take)
    path.parent.mkdir(parents=True, exist_ok=True)
    profile.save(path)
    log.info("calibrated %s from %s", path, neutral)
    return str(path)


def _no_flags(flags: tuple[str, ...]) -> SolveSettings:
    raise ValueError(f"solve options {' '.join(flags)!r}: flags need a parser (livecap batch gives its own); "
                     "give typed settings instead")


def plan_jobs(takes: list[str], manifests: list[str], *, rig: str | None, out_dir: str, mode: str, fmt: str,
              profile: str | None = None, calibrate_from: str | None = None, markers: str | None = None,
              neutral_seconds: float = 1.0, settings: SolveSettings | None = None,
              parse_flags: Callable[[tuple[str, ...]], SolveSettings] = _no_flags) -> list[Job]:
    """Jobs for the takes given on the command line (command-line settings) and for every manifest row
    (its own actor, profile or neutral take, mode, options, rig; the command line's where it says nothing).
    A row's options are ``livecap solve`` flags, turned into settings by ``parse_flags`` (the command's
    parser, given by livecap/cli/batch.py). Raises ValueError for a bad manifest or solve option, or two
    takes that would write one output."""
    rows = [{"take": str(p)} for p in expand_takes(takes)]
    for m in manifests:
        rows += read_manifest(m)
    if not rows:
        raise ValueError("no takes: give take files, folders or globs, or --manifest")
    profiles: dict[tuple, tuple[str | None, str]] = {}
    parsed: dict[tuple[str, ...], SolveSettings] = {}
    settings = settings or SolveSettings()
    jobs: list[Job] = []
    for row in rows:
        row_rig = row.get("rig", rig)
        if not row_rig:
            raise ValueError(f"{row['take']}: no rig (give --rig or a rig column)")
        row_markers = row.get("markers", markers)
        prof = row.get("profile")
        neutral = row.get("calibrate_from")
        if not prof and not neutral:
            prof, neutral = profile, calibrate_from
        error = ""
        if neutral and not prof:
            key = (neutral, row_rig, row_markers)
            if key not in profiles:
                try:
                    profiles[key] = calibrated_profile(neutral, row_rig, row_markers, out_dir), ""
                except Exception as exc:  # this actor's takes fail; the others go on
                    profiles[key] = None, f"calibration from {neutral} failed: {one_line(exc)}"
            prof, error = profiles[key]
        try:
            flags = tuple(row.get("options", ()))
            if flags and flags not in parsed:
                parsed[flags] = parse_flags(flags)
            spec = SolveSpec(row_rig, row.get("mode", mode), prof, row_markers, neutral_seconds,
                             parsed[flags] if flags else settings)
        except ValueError as exc:
            raise ValueError(f"{row['take']}: {exc}") from None
        for take in expand_takes([row["take"]]):
            jobs.append(Job(str(take), spec, out_dir, fmt, row.get("actor", ""), error))
    seen: dict[str, str] = {}
    for job in jobs:
        other = seen.setdefault(job.output.name, job.take)
        if other != job.take:
            raise ValueError(f"{job.take} and {other} would both write {job.output} (rename one)")
    return jobs
