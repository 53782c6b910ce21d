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


# The order of the Live Link Face UDP packet (PyLiveLinkFace's FaceBlendShape enum, 0..51).
ARKIT_NAMES = [
    "eyeBlinkLeft", "eyeLookDownLeft", "eyeLookInLeft", "eyeLookOutLeft", "eyeLookUpLeft", "eyeSquintLeft",
    "eyeWideLeft", "eyeBlinkRight", "eyeLookDownRight", "eyeLookInRight", "eyeLookOutRight", "eyeLookUpRight",
    "eyeSquintRight", "eyeWideRight", "jawForward", "jawLeft", "jawRight", "jawOpen", "mouthClose", "mouthFunnel",
    "mouthPucker", "mouthLeft", "mouthRight", "mouthSmileLeft", "mouthSmileRight", "mouthFrownLeft",
    "mouthFrownRight", "mouthDimpleLeft", "mouthDimpleRight", "mouthStretchLeft", "mouthStretchRight",
    "mouthRollLower", "mouthRollUpper", "mouthShrugLower", "mouthShrugUpper", "mouthPressLeft", "mouthPressRight",
    "mouthLowerDownLeft", "mouthLowerDownRight", "mouthUpperUpLeft", "mouthUpperUpRight", "browDownLeft",
    "browDownRight", "browInnerUp", "browOuterUpLeft", "browOuterUpRight", "cheekPuff", "cheekSquintLeft",
    "cheekSquintRight", "noseSneerLeft", "noseSneerRight", "tongueOut",
]


def is_arkit(names: Sequence[str]) -> bool:
    """True when every shape name is an ARKit name (any case): the rig speaks ARKit natively."""
    arkit = {n.lower() for n in ARKIT_NAMES}
    return len(names) > 0 and all(n.lower() in arkit for n in names)


def arkit_matrix(names: Sequence[str], mapping: dict | None = None, where: str = "mapping") -> np.ndarray:
    """52 x m matrix ``M`` with ``arkit = M @ weights`` for a rig with shape ``names``.

    ``mapping`` (ARKit name -> rig name or list of rig names, averaged) overrides the automatic
    match; an ARKit shape with no match stays 0.
    """
    names = list(names)
    M = match_names(names, ARKIT_NAMES).matrix()
    if mapping:
        where_name = {n: j for j, n in enumerate(names)}
        arkit_where = {a.lower(): i for i, a in enumerate(ARKIT_NAMES)}
        for a, src in mapping.items():
            i = arkit_where.get(str(a).lower())
            if i is None:
                raise ValueError(f"{where}: {a!r} is not an ARKit blendshape name")
            srcs = [src] if isinstance(src, str) else list(src)
            missing = [s for s in srcs if s not in where_name]
            if missing:
                raise ValueError(f"{where}: rig has no shape {missing[0]!r} (mapped to {a})")
            M[i] = 0.0
            for s in srcs:
                M[i, where_name[s]] = 1.0 / len(srcs)
    return M


def arkit_to_rig(names: list[str], mapping: dict | None = None) -> np.ndarray:
    """m x 52 matrix ``A`` with rig weights ``= A @ arkit``: the one place ARKit names meet the rig's.

    Names pair by the project's one matcher (livecap.core.names: a side-less ARKit shape such as
    ``browInnerUp`` drives both sided rig shapes); ``mapping`` (ARKit name -> rig shape(s), the
    file format of ``transport.arkit.load_mapping``) replaces the match of every rig shape it
    names, which then takes the mean of the ARKit shapes mapped onto it.
    """
    A = match_names(ARKIT_NAMES, names).matrix()
    if mapping:
        M = arkit_matrix(names, mapping) > 0  # validates the file's names
        keys = {str(x).lower() for x in mapping}
        mapped = [i for i, a in enumerate(ARKIT_NAMES) if a.lower() in keys]
        for j in np.where(M[mapped].any(0))[0]:
            cols = [i for i in mapped if M[i, j]]
            A[j] = 0.0
            A[j, cols] = 1.0 / len(cols)
    return A
