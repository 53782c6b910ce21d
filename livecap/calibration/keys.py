"""Key pairs: the actor's key expressions (marker frames) matched to target poses (rig weights).

Used by the example-based RBF mode (Pyun et al. 2003 §3: "source key-models" and their "target
key-models") and by the actor basis (Curio et al. 2006 §2.1/§2.3: "the peak frame with maximum
amplitude of the facial action was identified for each expression"). Keys come from a labelled
range-of-motion take or are given explicitly. A keys file (JSON):

    {"take": "demo_rom.c3d",                       # relative to the keys file
     "keys": [{"name": "jawOpen", "start": 120, "end": 239},      # a labelled range: peak frame
              {"name": "smile_wide", "frame": 800,                 # an explicit key frame ...
               "weights": {"mouthSmileLeft": 1.0, "mouthSmileRight": 1.0, "jawOpen": 0.3}}]}

Frame numbers are the take's own (C3D first frame included), ranges inclusive. Without
"weights", a key's target pose is its name's shape at full weight (parallel parameterisation,
Lewis et al. 2014 §5.3).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from livecap.calibration.profile import Profile
from livecap.calibration.targets import prepare_targets
from livecap.core.take import Take


class KeyFileError(ValueError):
    pass


@dataclass
class KeySpec:
    name: str
    start: int | None = None
    end: int | None = None
    frame: int | None = None
    weights: dict[str, float] | None = None

    def to_json(self) -> dict:
        return {k: v for k, v in self.__dict__.items() if v is not None}


@dataclass
class KeySet:
    """M key pairs in the profile's marker order and shape order."""

    names: list[str]  # key names
    frames: list[int]  # take frame number of each key
    source: np.ndarray  # M x n x 3 actor marker displacement from the neutral (stabilised), mm
    valid: np.ndarray  # M x n: marker seen at (or near) the key frame
    target: np.ndarray  # M x m rig weights
    shape_names: list[str]
    skipped: list[str] = field(default_factory=list)  # keys that name no rig shape and give no weights


def read_key_file(path: str | Path) -> tuple[Path | None, list[KeySpec]]:
    """(take path or None, key specs) from a keys JSON file."""
    path = Path(path)
    try:
        doc = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise KeyFileError(f"{path}: cannot read keys file ({exc})") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("keys"), list):
        raise KeyFileError(f"{path}: a keys file is {{'take': ..., 'keys': [...]}}")
    specs = []
    for i, k in enumerate(doc["keys"]):
        try:
            spec = KeySpec(str(k["name"]), _opt_int(k.get("start")), _opt_int(k.get("end")), _opt_int(k.get("frame")),
                           {str(a): float(b) for a, b in k["weights"].items()} if "weights" in k else None)
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            raise KeyFileError(f"{path}: key {i} is malformed ({exc})") from None
        if spec.frame is None and (spec.start is None or spec.end is None):
            raise KeyFileError(f"{path}: key {spec.name!r} needs 'frame' or both 'start' and 'end'")
        if spec.frame is None and spec.end < spec.start:
            raise KeyFileError(f"{path}: key {spec.name!r} ends before it starts")
        specs.append(spec)
    take = doc.get("take")
    return (path.parent / take if take else None), specs


def write_key_file(path: str | Path, specs: list[KeySpec], take: str | None = None) -> None:
    doc = {"take": take, "keys": [s.to_json() for s in specs]} if take else {"keys": [s.to_json() for s in specs]}
    Path(path).write_text(json.dumps(doc, indent=1))


def _opt_int(v) -> int | None:
    return None if v is None else int(v)


def peak_frame(targets: np.ndarray, valid: np.ndarray, start: int, end: int) -> int:
    """Index in [start, end] of the largest RMS marker displacement (Curio §2.1's peak frame).

    Only frames where at least half the markers are seen compete, so an occlusion cannot fake a
    peak; the RMS is over the markers seen.
    """
    seg, val = targets[start:end + 1], valid[start:end + 1]
    seen = val.sum(axis=1)
    amp = np.sum(np.where(val, np.sum(seg**2, axis=2), 0.0), axis=1) / np.maximum(seen, 1)
    amp = np.where(seen >= 0.5 * val.shape[1], amp, -1.0)
    return start + int(np.argmax(amp))


def fill_from_neighbours(targets: np.ndarray, valid: np.ndarray, index: int, start: int, end: int):
    """The frame at ``index`` with each missing marker taken from its nearest seen frame in range."""
    out, ok = targets[index].copy(), valid[index].copy()
    for j in np.where(~ok)[0]:
        seen = np.where(valid[start:end + 1, j])[0] + start
        if len(seen):
            near = seen[np.argmin(np.abs(seen - index))]
            out[j], ok[j] = targets[near, j], True
    return out, ok


def keys_from_take(take: Take, profile: Profile, specs: list[KeySpec]) -> KeySet:
    """Key pairs from a take of the same actor (stabilised against the profile's neutral)."""
    sel, targets, _, _ = prepare_targets(take, profile)
    names = list(profile.names)
    index = {n: i for i, n in enumerate(names)}
    out_names, frames, src, val, tgt, skipped = [], [], [], [], [], []
    last = sel.first_frame + sel.n_frames - 1
    for spec in specs:
        if spec.weights is None and spec.name not in index:
            skipped.append(spec.name)
            continue
        if spec.frame is not None:
            if not sel.first_frame <= spec.frame <= last:
                raise KeyFileError(f"key {spec.name!r}: frame {spec.frame} outside the take "
                                   f"({sel.first_frame}..{last})")
            k = spec.frame - sel.first_frame
            lo, hi = max(0, k - 5), min(sel.n_frames - 1, k + 5)
        else:
            lo, hi = spec.start - sel.first_frame, spec.end - sel.first_frame
            if lo < 0 or hi >= sel.n_frames:
                raise KeyFileError(f"key {spec.name!r}: range {spec.start}..{spec.end} outside the take "
                                   f"({sel.first_frame}..{last})")
            k = peak_frame(targets, sel.valid, lo, hi)
        d, ok = fill_from_neighbours(targets, sel.valid, k, lo, hi)
        w = np.zeros(len(names))
        if spec.weights is None:
            w[index[spec.name]] = min(1.0, float(profile.upper[index[spec.name]]))
        else:
            unknown = [n for n in spec.weights if n not in index]
            if unknown:
                raise KeyFileError(f"key {spec.name!r}: weights name shapes the rig lacks: {unknown[:5]}")
            for n, v in spec.weights.items():
                w[index[n]] = v
        out_names.append(spec.name)
        frames.append(sel.first_frame + k)
        src.append(d)
        val.append(ok)
        tgt.append(w)
    if not out_names:
        raise KeyFileError("no usable keys (none names a rig shape or gives weights)")
    return KeySet(out_names, frames, np.array(src), np.array(val), np.array(tgt), names, skipped)


def load_keys(path: str | Path, profile: Profile, take: Take | None = None) -> KeySet:
    """Keys from a keys file; its take is read unless one is given."""
    take_path, specs = read_key_file(path)
    if take is None:
        if take_path is None:
            raise KeyFileError(f"{path}: names no 'take' to take the key frames from")
        from transport.takefile import read_take

        take = read_take(take_path)
    return keys_from_take(take, profile, specs)
