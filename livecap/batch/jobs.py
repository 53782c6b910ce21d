"""What a batch is made of: one job per take, from paths, folders, globs or a manifest."""

from __future__ import annotations

import csv
import glob
import json
import shlex
import tomllib
from dataclasses import dataclass
from pathlib import Path

from livecap.batch.spec import SolveSpec

TAKE_SUFFIXES = (".c3d", ".trc", ".csv")
MANIFEST_COLUMNS = ("take", "actor", "profile", "calibrate_from", "mode", "options", "rig", "markers")
RECORDS = ".batch"  # per-take records (the summary row of each solved take) inside the output folder


@dataclass(frozen=True)
class Job:
    """One take to solve and where its output goes; travels to a worker as paths and the typed spec (the
    worker reads and writes the files)."""

    take: str
    spec: SolveSpec
    out_dir: str
    fmt: str = "csv"
    actor: str = ""
    error: str = ""  # set when the job failed before solving (e.g. its actor's neutral take did not calibrate)

    @property
    def stem(self) -> str:
        return Path(self.take).stem

    @property
    def output(self) -> Path:
        return Path(self.out_dir) / f"{self.stem}.{self.fmt}"

    @property
    def record(self) -> Path:
        return Path(self.out_dir) / RECORDS / f"{self.stem}.json"

    def inputs(self) -> list[Path]:
        """Files whose change makes the output stale."""
        return [Path(self.take), *self.spec.inputs()]

    def up_to_date(self) -> bool:
        """The output and its record exist, are newer than every input that exists, and the record was solved
        with this spec (other settings or mode: solved again)."""
        if not (self.output.is_file() and self.record.is_file()):
            return False
        made = min(self.output.stat().st_mtime_ns, self.record.stat().st_mtime_ns)
        if not all(made > p.stat().st_mtime_ns for p in self.inputs() if p.exists()):
            return False
        try:
            return json.loads(self.record.read_text()).get("spec") == repr(self.spec)
        except (OSError, ValueError):
            return False


def expand_takes(items: list[str]) -> list[Path]:
    """Files as given, folders as the take files inside them, globs (``**`` too) as what they match."""
    out: list[Path] = []
    for item in items:
        if glob.has_magic(item):
            hits = sorted(Path(p) for p in glob.glob(item, recursive=True))
            out += [p for p in hits if p.is_file() and p.suffix.lower() in TAKE_SUFFIXES]
        elif Path(item).is_dir():
            out += sorted(p for p in Path(item).iterdir() if p.is_file() and p.suffix.lower() in TAKE_SUFFIXES)
        else:
            out.append(Path(item))
    return out


def _options(value, where: str) -> tuple[str, ...]:
    """Manifest options: a string of ``livecap solve`` flags, a list of them, or a TOML table."""
    if value is None or value == "":
        return ()
    if isinstance(value, str):
        return tuple(shlex.split(value))
    if isinstance(value, list):
        return tuple(str(v) for v in value)
    if isinstance(value, dict):
        flags: list[str] = []
        for k, v in value.items():
            flag = "--" + str(k).replace("_", "-")
            if v is True:
                flags.append(flag)
            elif v is not False:
                flags += [flag, str(v)]
        return tuple(flags)
    raise ValueError(f"{where}: options must be a string, a list or a table, not {type(value).__name__}")


def read_manifest(path: str | Path) -> list[dict]:
    """Rows of a manifest (CSV with a header, or TOML with ``[[take]]`` tables): take, actor, profile,
    calibrate_from, mode, options, rig, markers. Relative paths are relative to the manifest's folder;
    a row's take may be a glob or a folder."""
    path = Path(path)
    if not path.is_file():
        raise OSError(f"{path}: no such manifest")
    if path.suffix.lower() == ".toml":
        try:
            data = tomllib.loads(path.read_text())
        except tomllib.TOMLDecodeError as exc:
            raise ValueError(f"{path}: not a TOML manifest ({exc})") from None
        rows = data.get("take")
        if not isinstance(rows, list):
            raise ValueError(f"{path}: a TOML manifest needs [[take]] tables")
        defaults = data.get("defaults", {})
        rows = [{**defaults, **r} for r in rows]
    else:
        with open(path, newline="") as fh:
            rows = [{k.strip(): (v or "").strip() for k, v in r.items() if k} for r in csv.DictReader(fh)]
        if rows and "take" not in rows[0]:
            raise ValueError(f"{path}: a CSV manifest needs a header with a 'take' column")
    base = path.parent
    out = []
    for i, row in enumerate(rows, start=1):
        where = f"{path} row {i}"
        unknown = sorted(set(row) - set(MANIFEST_COLUMNS))
        if unknown:
            raise ValueError(f"{where}: unknown column(s) {unknown} (known: {', '.join(MANIFEST_COLUMNS)})")
        if not row.get("take"):
            raise ValueError(f"{where}: no take")
        clean = {k: v for k, v in row.items() if v not in ("", None) and k != "options"}
        for key in ("take", "profile", "calibrate_from", "rig", "markers"):
            if key in clean:
                clean[key] = str(base / clean[key]) if not Path(clean[key]).is_absolute() else clean[key]
        clean["options"] = _options(row.get("options"), where)
        out.append(clean)
    return out

