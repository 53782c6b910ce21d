"""Session files: a ``livecap run`` set-up kept in TOML, so a stage session is one command.

Every key is a ``livecap run`` option (``zmq-out`` or ``zmq_out``), at the top level or inside
any table (tables only group: ``[source]``, ``[sinks]``, ``[record]``...), except ``[options]``,
whose keys are the solver mode's options. Options given on the command line win over the file.
Paths in the file are relative to the file's folder. Example::

    mode = "lsq"
    profile = "actor.npz"
    actor = "anna"

    [source]
    zmq-in = "tcp://127.0.0.1:5555"

    [sinks]
    zmq-out = "tcp://127.0.0.1:5556"
    vmc = "127.0.0.1:39539"
    record-csv = "takes/anna_001.csv"

    [options]
    ridge = 0.01
"""

from __future__ import annotations

import tomllib
from pathlib import Path

PATH_KEYS = {"profile", "rig", "markers", "replay", "record_csv", "record_jsonl", "record_markers", "arkit_map",
             "curve_secret", "curve_clients", "curve_server", "stats_file", "vrm_map"}


class SessionError(ValueError):
    """A session file that cannot be used; the message names the file and the key."""


def load_session(path: str | Path, known: set[str]) -> tuple[dict, dict]:
    """``(settings, solver options)`` from a TOML session file; ``known`` are the option names
    (argparse dests) a key may name."""
    p = Path(path)
    try:
        data = tomllib.loads(p.read_text())
    except (OSError, UnicodeDecodeError) as exc:
        raise SessionError(f"{p}: cannot read session file ({exc})") from None
    except tomllib.TOMLDecodeError as exc:
        raise SessionError(f"{p}: not valid TOML ({exc})") from None
    settings: dict = {}
    options: dict = {}

    def take(key: str, value, table: str) -> None:
        dest = key.replace("-", "_")
        if dest not in known:
            where = f"[{table}] " if table else ""
            raise SessionError(f"{p}: unknown setting {where}{key!r}")
        if dest in settings:
            raise SessionError(f"{p}: {key!r} is set twice")
        if dest in PATH_KEYS and isinstance(value, str) and "://" not in value:
            value = str((p.parent / value).resolve()) if not Path(value).is_absolute() else value
        settings[dest] = value

    for key, value in data.items():
        if key == "options":
            if not isinstance(value, dict):
                raise SessionError(f"{p}: [options] must be a table of solver options")
            options.update(value)
        elif isinstance(value, dict):
            for k, v in value.items():
                if isinstance(v, dict):
                    raise SessionError(f"{p}: [{key}.{k}] nests too deep (tables only group options)")
                take(k, v, key)
        else:
            take(key, value, "")
    return settings, options
