"""``livecap rig``: rig tools. ``livecap rig import`` reads a glTF / GLB / VRM / USD rig (docs/rigs.md);
``livecap rig transfer`` builds a rig for a new face from its neutral mesh.

Xiang et al. 2008 (landmarks, deformable model, deformation transfer); see docs/transfer.md.
No PNG contact sheet is written: livecap has no offscreen rig renderer to call yet.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from livecap.cli.common import command_group, markers_path, progress_bar
from livecap.core.markers import MarkerLayout
from livecap.core.objfile import read_obj
from livecap.core.rig import Rig
from livecap.core.units import MM_PER_UNIT, to_mm
from transport.rig_files import RIG_FILES_HELP, is_imported
from transport.rig_files import load_rig as load_rig_file


def register(sub) -> None:
    rsub = command_group(sub, "rig", "rig tools (import a glTF/VRM/USD rig, transfer a rig to a new face)")
    i = rsub.add_parser(
        "import", help="read a glTF/GLB, VRM 0.x/1.0 or USD rig (blend shapes) as a livecap rig",
        description="Read the face mesh and its morph targets (glTF, VRM) or UsdSkel blend shapes (USD) of a "
                    "file into livecap's rig (.npz, or an OBJ folder when --out has no .npz suffix), in "
                    "millimetres with the file's units and node transforms applied (docs/rigs.md).")
    i.add_argument("file", help="rig file: .glb, .gltf, .vrm, .usd, .usda, .usdc or .usdz")
    i.add_argument("--out", required=True, help="livecap rig: .npz, or a folder for OBJ files")
    i.add_argument("--mesh", help="the mesh (glTF mesh or node name, USD prim name or path) when the file "
                   "holds several with blend shapes (default: the VRM's expression mesh, else one named face/head)")
    i.add_argument("--names", choices=["targets", "expressions"], default="targets",
                   help="shape names: the file's morph-target names (default), or for a VRM the expression "
                   "(preset / Perfect Sync clip) that drives each target alone, the names VMC receivers apply")
    i.add_argument("--markers", help="markers.json binding marker labels to this mesh's vertices: checked "
                   "against the rig and written beside it (<out>.markers.json, or OUT/markers.json)")
    i.set_defaults(func=run_import)
    a = rsub.add_parser(
        "animate", help="write solved weights back into the user's glTF/GLB/VRM file as an animation",
        description="Copy a glTF/GLB/VRM file (meshes, materials, skins, VRM extension) and add one animation "
                    "of its face mesh's morph-target weights from a weights CSV solved on that same file's rig "
                    "(livecap solve --rig FILE). The output is a GLB container (.glb or .vrm).")
    a.add_argument("file", help="the rig file the weights were solved for: .glb, .gltf or .vrm")
    a.add_argument("--weights", required=True, help="weights CSV (frame,time,<shape>...) from livecap solve, or "
                   "the .glb of livecap solve --out take.glb, whose head rotation then turns a VRM's head bone")
    a.add_argument("--out", required=True, help="output .glb or .vrm (the file with the animation), or .vrma (a VRM "
                   "animation of its expressions alone, what VRM runtimes play)")
    a.add_argument("--mesh", help="the mesh, as given to livecap rig import / chosen by default")
    a.set_defaults(func=run_animate)
    t = rsub.add_parser(
        "transfer", help="build a full rig + markers for a new face from its neutral OBJ",
        description="Transfer every shape (in-betweens and correctives too) and the marker sites of a generic "
                    "rig onto a new face's neutral mesh (Xiang et al. 2008; Sumner & Popovic 2004). The output "
                    "keeps the new face's topology and frame.")
    t.add_argument("--generic", required=True, help=f"generic rig: {RIG_FILES_HELP}")
    t.add_argument("--generic-markers", help="its markers.json (default: in the folder / <rig>.markers.json)")
    t.add_argument("--target", required=True, help="the new face's neutral mesh (.obj), or a glTF/VRM/USD rig "
                   "file whose face mesh's neutral it is (then OUT/markers.json binds that file's vertices)")
    t.add_argument("--target-units", default="mm", choices=sorted(MM_PER_UNIT), help="units of the OBJ (default mm)")
    t.add_argument("--out", required=True, help="output rig folder (neutral.obj, one OBJ per shape, markers.json)")
    t.add_argument("--radius-fraction", default="0.06",
                   help="landmark patch radius in eye widths (paper: 0.06); a comma list runs coarse to fine")
    t.add_argument("--prealign", default="similarity", choices=["similarity", "rigid", "none"],
                   help="global alignment of the generic onto the new face (default similarity)")
    t.add_argument("--warp", default=None, metavar="LENGTHS",
                   help="smooth-warp pre-alignment: smoothing length per iteration in eye widths, comma list "
                        "coarse to fine (default 2 x8, 1, 0.7), or 'none' for Xiang's similarity only")
    t.add_argument("--refine", action="store_true",
                   help="detect landmarks again on the deformed model and deform again (Xiang 4)")
    t.add_argument("--landmarks", action="store_true", help="print every detected landmark")
    t.add_argument("--sheet", help="contact sheet PNG of the new rig (default: OUT/contact_sheet.png; 'none' to skip)")
    t.add_argument("--check-against", metavar="MARKERS_JSON",
                   help="markers.json of the new face (its vertex indices): print per-landmark distances to it")
    t.set_defaults(func=run_transfer)


def run_import(args: argparse.Namespace) -> int:
    from transport.rig_files import describe, import_rig, named_by_expressions

    imported = import_rig(args.file, args.mesh)
    if args.names == "expressions":
        if not imported.expressions:
            raise ValueError(f"{args.file}: --names expressions: the file has no VRM expressions for mesh "
                             f"{imported.mesh!r}")
        imported = named_by_expressions(imported)
    layout = MarkerLayout.load(args.markers, imported.rig) if args.markers else None  # before writing anything
    out = Path(args.out)
    if out.suffix.lower() == ".npz":
        imported.rig.save(out)
    else:
        imported.rig.save_obj_folder(out)
    print(f"{out}: {describe(imported)}")
    if imported.expressions:
        npz = out.suffix.lower() == ".npz"
        epath = out.with_name(out.stem + ".expressions.json") if npz else out / "expressions.json"
        epath.write_text(json.dumps({"format": imported.format, "mesh": imported.mesh,
                                     "expressions": imported.expressions}, indent=1))
        print(f"  expression table (expression -> {{shape: weight}}) {epath}")
    if layout is not None:
        layout.save(markers_path(out))
        print(f"  {layout.n_markers} markers {markers_path(out)}")
    return 0


def run_animate(args: argparse.Namespace) -> int:
    from transport.rig_files import GLTF_SUFFIXES, import_rig
    from transport.rig_gltf_anim import animate_gltf, read_solved_glb
    from transport.weights_csv import read_weights_csv

    if Path(args.file).suffix.lower() not in GLTF_SUFFIXES:
        raise ValueError(f"{args.file}: animations are written back into glTF, GLB and VRM files only")
    suffix = Path(args.out).suffix.lower()
    if suffix not in (".glb", ".vrm", ".vrma"):
        raise ValueError(f"--out {args.out}: the output is a GLB container (.glb or .vrm) or a VRM animation (.vrma)")
    imported = import_rig(args.file, args.mesh)
    rotation = None
    if Path(args.weights).suffix.lower() == ".glb":
        names, times, weights, rotation = read_solved_glb(args.weights)
        rotation = rotation if imported.format.startswith("VRM") else None
    else:
        names, weights, times = read_weights_csv(args.weights)
    if suffix == ".vrma":
        from transport.vrma import write_vrma

        if not imported.format.startswith("VRM"):
            raise ValueError(f"{args.file}: a VRM animation (.vrma) is made for a VRM file's expressions")
        n = write_vrma(args.out, args.file, imported, names, times, weights, rotation)
        print(f"{args.out}: VRM animation of {n} expressions of {args.file} ({len(times)} frames"
              f"{', and the head bone' if rotation is not None else ''})")
        return 0
    n = animate_gltf(args.file, args.out, imported, names, times, weights, Path(args.out).stem, rotation)
    print(f"{args.out}: {args.file} with an animation of mesh {imported.mesh!r} ({len(times)} frames, "
          f"{len(names)} of its {n} morph targets{', and the head bone' if rotation is not None else ''})")
    return 0


def _radii(text: str) -> float | tuple[float, ...]:
    try:
        vals = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise ValueError(f"--radius-fraction: not a number list: {text!r}") from None
    if not vals or min(vals) <= 0:
        raise ValueError("--radius-fraction must be positive")
    return vals[0] if len(vals) == 1 else vals


def _warp(text: str | None) -> tuple[float, ...]:
    if text is None:
        from livecap.transfer import TransferOptions

        return TransferOptions().warp
    if text.strip().lower() == "none":
        return ()
    try:
        vals = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise ValueError(f"--warp: not a number list: {text!r}") from None
    if min(vals) <= 0:
        raise ValueError("--warp lengths must be positive")
    return vals


def _write_sheet(rig: Rig, path) -> None:
    """Render the neutral and the most pronounced shapes; a machine without OpenGL only loses the sheet."""
    if str(path) == "none":
        return
    import cv2

    from viewer.errors import ViewerUnavailable

    try:
        from viewer.contact_sheet import contact_sheet

        cv2.imwrite(str(path), contact_sheet(rig))
        print(f"contact sheet {path}")
    except ViewerUnavailable as exc:
        print(f"no contact sheet: {exc}")


def run_transfer(args: argparse.Namespace) -> int:
    # the transfer's modules (scipy.sparse.linalg, csgraph) load only for this command, not for every livecap one
    from livecap.transfer import TransferOptions, transfer, transfer_steps
    from livecap.transfer.labels import landmark_distances
    from livecap.transfer.landmarks import eye_width

    generic = load_rig_file(args.generic)
    mpath = Path(args.generic_markers) if args.generic_markers else markers_path(args.generic)
    if not mpath.exists():
        raise ValueError(f"{mpath}: no markers.json for generic rig {args.generic} (give --generic-markers)")
    layout = MarkerLayout.load(mpath, generic)
    target = Path(args.target)
    if is_imported(target):  # a glTF / VRM / USD file: its face mesh's neutral, already in mm
        neutral = load_rig_file(target)
        verts, tris = neutral.neutral, neutral.triangles
    else:
        verts, tris = read_obj(target / "neutral.obj" if target.is_dir() else target)
        verts = to_mm(verts, args.target_units)
    options = TransferOptions(prealign=args.prealign, radius_fraction=_radii(args.radius_fraction),
                              refine_landmarks=args.refine, warp=_warp(args.warp))
    with progress_bar("transferring rig", transfer_steps(generic, layout, options)) as update:
        res = transfer(generic, layout, verts, tris, options, progress=update)
    out = Path(args.out)
    res.rig.save_obj_folder(out)
    res.layout.save(out / "markers.json")
    _write_sheet(res.rig, out / "contact_sheet.png" if args.sheet is None else args.sheet)
    a = res.alignment
    print(f"{out}: {res.rig.n_vertices} vertices, {res.rig.n_shapes} shapes, {len(res.rig.inbetweens)} in-betweens, "
          f"{len(res.rig.correctives)} correctives, {res.layout.n_markers} markers ({int(res.layout.stable.sum())} "
          f"stable)")
    print(f"  aligned generic -> target: scale {a.scale:.4f}, {np.degrees(np.arccos(np.clip((np.trace(a.rotation) - 1) / 2, -1, 1))):.1f} deg, "  # noqa: E501
          f"eye width {res.eye_width:.1f} mm ({res.eye_width_source}); deformed generic to target "
          f"RMS {res.deformed.rms[-1]:.3f} mm, {res.deformed.matched[-1] * 100:.0f} % matched")
    print("  seconds: " + ", ".join(f"{k} {v:.2f}" for k, v in res.seconds.items()))
    lm = res.landmarks
    if args.landmarks:
        print(f"  {'label':14s} {'x':>8s} {'y':>8s} {'z':>8s}  moved mm  ICP rms  normal ok")
        for lab, p, mv, e, ok in zip(layout.labels, lm.points, lm.moved, lm.error, lm.compatible, strict=True):
            print(f"  {lab:14s} {p[0]:8.2f} {p[1]:8.2f} {p[2]:8.2f}  {mv:8.2f}  {e:7.3f}  {'yes' if ok else 'NO'}")
    if args.check_against:
        ref = MarkerLayout.load(args.check_against)  # vertex bindings on the target mesh
        if ref.vertices.max() >= len(verts):
            raise ValueError(f"{args.check_against}: markers bound past the target's {len(verts)} vertices")
        ref_pts = ref.sampling_matrix(len(verts)) @ verts
        w_ref, how = eye_width(ref, verts)
        w = w_ref if how.startswith("eye corners") else res.eye_width
        rows = landmark_distances(layout.labels, lm.points, ref.labels, ref_pts)
        if not rows:
            raise ValueError(f"{args.check_against}: no marker label matches the generic's landmarks")
        pct = np.array([d / w * 100 for _, _, d in rows])
        print(f"  landmarks vs {args.check_against} (unit: eye width {w:.1f} mm):")
        for (a_lab, b_lab, d), p in zip(rows, pct, strict=True):
            print(f"    {a_lab:12s} -> {b_lab:12s} {d:7.2f} mm {p:6.1f} %")
        print(f"  {int((pct < 8).sum())}/{len(rows)} within 8 % of the eye width, median {np.median(pct):.1f} %")
    return 0
