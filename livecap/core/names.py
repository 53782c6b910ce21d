"""One name matcher for every place that maps shape names between rigs and wire formats.

Rigs name the same blendshape differently: ARKit's ``eyeBlinkLeft``, ICT FaceKit's ``eyeBlink_L``,
a PascalCase ``EyeBlinkLeft``, a studio's ``eye_blink.L``. Names match when they agree up to case,
separators and the spelling of a side suffix (``_L``/``_R``/``.l``/``Left``/``Right``). A side-less
target that the source has only per side (ARKit ``browInnerUp`` from ICT ``browInnerUp_L``/``_R``)
takes the mean of the sides; a target with a side suffix of its own (``browInnerUp_L``) whose source is
side-less takes the side-less one. Several source names with one key are averaged.
An exact name always wins. Used by ``livecap map`` (livecap.offline.mapping), the Live Link / VMC /
recorder ARKit mapping (transport.arkit) and anything else that pairs names.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

_SIDE = re.compile(r"(?:[_.\-\s](l|r|left|right)|(?<=[a-z0-9])(Left|Right))$", re.IGNORECASE)


def split_side(name: str) -> tuple[str, str, bool]:
    """``(stem key, side, separated)``: lower case, separators dropped, side "left", "right" or "";
    ``separated`` when the side was a suffix of its own (``_L``), not a word's end (``jawLeft``)."""
    m = _SIDE.search(name)
    side = ""
    if m:
        side = "left" if (m.group(1) or m.group(2)).lower().startswith("l") else "right"
        name = name[:m.start()]
    return re.sub(r"[^a-z0-9]", "", name.lower()), side, bool(m and m.group(1))


def name_key(name: str) -> str:
    """Normalised name: ``eyeBlink_L``, ``EyeBlinkLeft`` and ``eyeBlinkLeft`` all give ``eyeblinkleft``."""
    stem, side, _ = split_side(name)
    return stem + side


@dataclass(frozen=True)
class NameMatch:
    """For each target name the source indices it is the mean of (empty: no source)."""

    source: tuple[str, ...]
    target: tuple[str, ...]
    sources: tuple[tuple[int, ...], ...]

    @property
    def unmatched(self) -> list[str]:
        """Target names no source name matches."""
        return [t for t, s in zip(self.target, self.sources, strict=True) if not s]

    @property
    def unused(self) -> list[str]:
        """Source names no target takes."""
        used = {i for s in self.sources for i in s}
        return [n for i, n in enumerate(self.source) if i not in used]

    def matrix(self) -> np.ndarray:
        """``len(target) x len(source)`` averaging matrix: ``target = M @ source``."""
        M = np.zeros((len(self.target), len(self.source)))
        for t, cols in enumerate(self.sources):
            for j in cols:
                M[t, j] = 1.0 / len(cols)
        return M


def match_names(source: Sequence[str], target: Sequence[str]) -> NameMatch:
    """Pair every target name with the source names it corresponds to (see the module doc)."""
    source, target = tuple(source), tuple(target)
    exact = {n: i for i, n in enumerate(source)}
    by_key: dict[str, list[int]] = {}
    for i, n in enumerate(source):
        by_key.setdefault(name_key(n), []).append(i)
    out = []
    for t in target:
        if t in exact:
            out.append((exact[t],))
            continue
        stem, side, separated = split_side(t)
        cols = by_key.get(stem + side, [])
        if not cols and not side:
            cols = by_key.get(stem + "left", []) + by_key.get(stem + "right", [])
        if not cols and separated:
            cols = by_key.get(stem, [])
        out.append(tuple(cols))
    return NameMatch(source, target, tuple(out))
