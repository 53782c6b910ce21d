"""Mapping weights between two parameterisations (Lewis et al. 2014 §5.3).

* Parallel parameterisation: source and target rigs share shape semantics, so weights are copied
  by name; a per-channel gain, offset and clamp lets an animator tune the cross-mapping
  (target = clamp(gain * source + offset)). Config (JSON or TOML):

      [defaults]                # optional, for every channel
      clamp = [0.0, 1.0]
      [channels.jawOpen]        # target channel
      source = "JawOpen"        # default: the same name
      gain = 1.2
      offset = 0.0
      clamp = [0.0, 1.0]

  Target channels not listed are copied from the source channel of the same name as
  ``livecap.core.names`` matches them (case, separators, ``_L``/``Left``; a side-less target from
  the mean of a source's two sides); target channels with no source stay at their offset (0) and
  are reported.
* Linear expression cloning: from p >= n corresponding pose pairs, the least-squares matrix E
  with v ~ E w (Lewis §5.3: E = V W' (W W')^-1; Lewis write the map in the other direction,
  W = E V, but the construction is the same).
"""

from __future__ import annotations

import json
import tomllib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from livecap.core.names import match_names


class MappingError(ValueError):
    pass


@dataclass
class ChannelMap:
    """target = clip(gain * (M @ source) + offset, lo, hi); a row of M is the mean of the target's
    matched source channels, all zero when it has none."""

    source_names: list[str]
    target_names: list[str]
    matrix: np.ndarray
    gain: np.ndarray
    offset: np.ndarray
    lo: np.ndarray
    hi: np.ndarray

    @property
    def unmapped(self) -> list[str]:
        return [n for n, row in zip(self.target_names, self.matrix, strict=True) if not row.any()]

    @property
    def unused(self) -> list[str]:
        """Source channels no target channel reads."""
        return [n for n, col in zip(self.source_names, self.matrix.T, strict=True) if not col.any()]

    def apply(self, weights: np.ndarray) -> np.ndarray:
        """Source weights (m_s,) or (T, m_s) -> target weights (m_t,) or (T, m_t)."""
        w = np.asarray(weights, dtype=np.float64)
        return np.clip(self.gain * (w @ self.matrix.T) + self.offset, self.lo, self.hi)


def by_name(source_names: list[str], target_names: list[str], config: dict | None = None) -> ChannelMap:
    """A name map, tuned by a config dict (see the module doc)."""
    cfg = config or {}
    unknown_keys = set(cfg) - {"defaults", "channels"}
    if unknown_keys:
        raise MappingError(f"unknown mapping sections: {sorted(unknown_keys)} (use 'defaults' and 'channels')")
    defaults = cfg.get("defaults", {})
    channels = cfg.get("channels", {})
    unknown = [t for t in channels if t not in target_names]
    if unknown:
        raise MappingError(f"mapping names target channels the target lacks: {unknown[:5]}")
    src_index = {n: i for i, n in enumerate(source_names)}
    k = len(target_names)
    M = match_names(source_names, target_names).matrix()
    gain, offset = np.ones(k), np.zeros(k)
    lo, hi = np.full(k, -np.inf), np.full(k, np.inf)
    for t, name in enumerate(target_names):
        ch = {**defaults, **channels.get(name, {})}
        if "source" in ch:
            src = ch["source"]
            if src not in src_index:
                if name in channels and "source" in channels[name]:
                    raise MappingError(f"channel {name!r}: source {src!r} is not a source channel")
            else:
                M[t] = 0.0
                M[t, src_index[src]] = 1.0
        try:
            gain[t] = float(ch.get("gain", 1.0))
            offset[t] = float(ch.get("offset", 0.0))
            if "clamp" in ch:
                lo[t], hi[t] = (float(x) for x in ch["clamp"])
        except (TypeError, ValueError) as exc:
            raise MappingError(f"channel {name!r}: bad gain/offset/clamp ({exc})") from None
        if lo[t] > hi[t]:
            raise MappingError(f"channel {name!r}: clamp lower bound above upper")
    return ChannelMap(list(source_names), list(target_names), M, gain, offset, lo, hi)


def load_config(path: str | Path) -> dict:
    """A mapping config from .toml or .json."""
    path = Path(path)
    try:
        if path.suffix.lower() == ".toml":
            return tomllib.loads(path.read_text())
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError, tomllib.TOMLDecodeError) as exc:
        raise MappingError(f"{path}: cannot read mapping config ({exc})") from None


def cloning_matrix(source_poses: np.ndarray, target_poses: np.ndarray, ridge: float = 0.0) -> np.ndarray:
    """E (m_t x m_s) minimising sum_k |E w_k - v_k|^2 (+ ridge |E|^2), Lewis §5.3's linear cloning.

    ``source_poses`` p x m_s and ``target_poses`` p x m_t, row k a corresponding pair. Lewis ask for
    p >= m_s pairs; fewer need ``ridge`` > 0.
    """
    Wm = np.asarray(source_poses, dtype=np.float64)
    Vm = np.asarray(target_poses, dtype=np.float64)
    if Wm.ndim != 2 or Vm.ndim != 2 or len(Wm) != len(Vm):
        raise MappingError(f"need p source and p target poses, got {Wm.shape} and {Vm.shape}")
    if ridge <= 0 and len(Wm) < Wm.shape[1]:
        raise MappingError(f"{len(Wm)} pose pairs for {Wm.shape[1]} source shapes: need at least as many (or ridge)")
    G = Wm.T @ Wm + ridge * np.eye(Wm.shape[1])
    try:
        return np.linalg.solve(G, Wm.T @ Vm).T
    except np.linalg.LinAlgError:
        raise MappingError("source poses are linearly dependent: add poses or a ridge") from None
