"""Every rig file a user may have, read through one function: livecap's OBJ folder and .npz, glTF 2.0 /
GLB and VRM 0.x / 1.0 (morph targets, transport.rig_gltf) and USD (UsdSkel blend shapes, transport.rig_usd).

The CLI's rig loading, ``livecap rig import`` and the Python API call :func:`load_rig`; the format
readers load their libraries (pygltflib, pxr) only when a file of theirs is opened.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

from livecap.core.rig import Rig, RigError

GLTF_SUFFIXES = (".gltf", ".glb", ".vrm")
USD_SUFFIXES = (".usd", ".usda", ".usdc", ".usdz")
RIG_FILES_HELP = "OBJ folder, livecap .npz, glTF/GLB, VRM 0.x/1.0 or USD (UsdSkel blend shapes)"


@dataclass(frozen=True)
class ImportedRig:
    """A rig read from a third-party file, with what is needed to write animations back into that file.

    ``targets[k]`` is the file's morph-target (blend-shape) index of shape k; ``expressions`` is a VRM
    file's expression table restricted to the chosen mesh (expression -> {shape: weight in [0, 1]}).
    """

    rig: Rig
    format: str
    mesh: str
    meshes: tuple[str, ...]
    targets: tuple[int, ...]
    expressions: dict[str, dict[str, float]] = field(default_factory=dict)
    node: int | None = None


def is_imported(path: str | Path) -> bool:
    """True for the third-party formats :func:`import_rig` reads (not livecap's own folder / .npz)."""
    return Path(path).suffix.lower() in GLTF_SUFFIXES + USD_SUFFIXES


def import_rig(path: str | Path, mesh: str | None = None) -> ImportedRig:
    """Read a glTF/GLB/VRM or USD file's face mesh and its blend shapes as a rig in millimetres.

    ``mesh``: the mesh (or its node / prim) by name when the file holds several with blend shapes;
    by default the one named like a face or head (docs/rigs.md says how the choice is made).
    """
    p = Path(path)
    if not p.is_file():
        raise RigError(f"{p}: no such rig file")
    suffix = p.suffix.lower()
    if suffix in GLTF_SUFFIXES:
        from transport.rig_gltf import read_gltf_rig

        return read_gltf_rig(p, mesh)
    if suffix in USD_SUFFIXES:
        from transport.rig_usd import read_usd_rig

        return read_usd_rig(p, mesh)
    raise RigError(f"{p}: not a rig file this reader knows ({', '.join(GLTF_SUFFIXES + USD_SUFFIXES)})")


def load_rig(path: str | Path, mesh: str | None = None) -> Rig:
    """Any rig file or folder (:data:`RIG_FILES_HELP`) as a :class:`Rig` in millimetres."""
    if is_imported(path):
        return import_rig(path, mesh).rig
    if mesh is not None:
        raise RigError(f"{path}: a mesh name only applies to glTF, VRM and USD files")
    return Rig.load(path)


def choose_mesh(path: Path, candidates: list[str], mesh: str | None, preferred: str | None = None) -> int:
    """Index into ``candidates`` (names of the meshes with blend shapes): ``mesh`` by name when given,
    else ``preferred`` (a VRM's expression mesh), else the only one, else the one named face / head."""
    if not candidates:
        raise RigError(f"{path}: no mesh with morph targets (blend shapes) in this file: nothing to solve for")
    if mesh is not None:
        exact = [i for i, n in enumerate(candidates) if n == mesh]
        loose = [i for i, n in enumerate(candidates) if n.lower() == mesh.lower()]
        if exact or loose:
            return (exact or loose)[0]
        raise RigError(f"{path}: no mesh with blend shapes named {mesh!r} (meshes: {', '.join(candidates)})")
    if preferred is not None and preferred in candidates:
        return candidates.index(preferred)
    if len(candidates) == 1:
        return 0
    for word in ("face", "head"):
        named = [i for i, n in enumerate(candidates) if word in n.lower()]
        if named:
            return named[0]
    raise RigError(f"{path}: {len(candidates)} meshes with blend shapes and none named face or head "
                   f"({', '.join(candidates)}): choose one with --mesh")


def named_by_expressions(imported: ImportedRig) -> ImportedRig:
    """The rig with each shape that one expression drives alone (at full weight) renamed to that expression:
    VRM receivers (VSeeFace, VMC4U) apply clips by their names, so a solve on these names drives them as sent
    (``livecap run --vmc``). Among several such expressions, the one that names the shape (Perfect Sync
    ``JawOpen`` for ``jawOpen``) wins over a preset (``A``); other shapes keep their target names."""
    from livecap.core.names import name_key

    alone: dict[str, list[str]] = {}
    for expr, binds in imported.expressions.items():
        if len(binds) == 1 and abs(next(iter(binds.values())) - 1.0) < 1e-6:
            alone.setdefault(next(iter(binds)), []).append(expr)
    rig = imported.rig
    taken = set(rig.names)
    rename: dict[str, str] = {}
    for shape, exprs in alone.items():
        best = next((e for e in exprs if name_key(e) == name_key(shape)), exprs[0])
        if best not in taken:
            rename[shape] = best
            taken.add(best)
    names = [rename.get(n, n) for n in rig.names]
    new = Rig(rig.neutral, rig.triangles, names, rig.deltas, rig.lower, rig.upper, rig.inbetweens, rig.correctives)
    table = {e: {rename.get(s, s): w for s, w in b.items()} for e, b in imported.expressions.items()}
    return replace(imported, rig=new, expressions=table)


def describe(imported: ImportedRig) -> str:
    """What ``livecap rig import`` prints: format, the mesh chosen and the others, the expressions."""
    r = imported.rig
    lines = [f"{imported.format}: mesh {imported.mesh!r}, {r.n_vertices} vertices, {len(r.triangles)} triangles, "
             f"{r.n_shapes} shapes, {len(r.inbetweens)} in-betweens"]
    others = [m for m in imported.meshes if m != imported.mesh]
    if others:
        lines.append(f"  other meshes with blend shapes (choose with --mesh): {', '.join(others)}")
    if imported.expressions:
        shown = [f"{e}={'+'.join(b)}" for e, b in list(imported.expressions.items())[:6]]
        more = len(imported.expressions) - len(shown)
        lines.append(f"  {len(imported.expressions)} expressions: {', '.join(shown)}" + (f" (+{more})" if more else ""))
    return "\n".join(lines)
