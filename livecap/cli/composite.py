"""``livecap composite``: combine emotional and verbal key models into the full set (Pyun et al. 2003 §2)."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from livecap.core.objfile import read_obj, write_obj
from solvers.compositing import ImportanceSettings, composite_all


def register(sub) -> None:
    p = sub.add_parser("composite", help="combine emotional x verbal key models (OBJ) into every combination",
                       description="Pyun et al. 2003 key-model compositing: per-vertex importance decides where "
                       "speech (visemes) wins over emotion; writes <emotion>_<viseme>.obj for every pair.")
    p.add_argument("--base", help="neutral mesh (OBJ) the key models displace")
    p.add_argument("--emotional", nargs="+", default=[], help="emotional key models (OBJ; name = file stem)")
    p.add_argument("--verbal", nargs="+", default=[], help="verbal key models / visemes (OBJ)")
    p.add_argument("--demo", action="store_true", help="pose emotional and verbal key models on --rig "
                   "(default: the bundled demo rig) instead of reading OBJs")
    p.add_argument("--rig", help="rig for --demo (default: the bundled demo rig)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--lp", type=float, help="verbal propagation radius Lp (mesh units; default 4%% of its size)")
    p.add_argument("--le", type=float, help="emotional propagation radius Le (default as Lp)")
    p.add_argument("--s1", type=float, default=0.5, help="propagation threshold S1 (default 0.5)")
    p.add_argument("--s2", type=float, default=0.5, help="Eq. 13 switch S2 (default 0.5)")
    p.set_defaults(func=run)


def _read(paths: list[str], base: np.ndarray, tris: np.ndarray) -> dict[str, np.ndarray]:
    out = {}
    for p in map(Path, paths):
        v, f = read_obj(p)
        if v.shape != base.shape or (len(f) and not np.array_equal(f, tris)):
            raise ValueError(f"{p}: topology differs from the base mesh")
        out[p.stem] = v
    return out


def run(args: argparse.Namespace) -> int:
    if args.demo:
        from livecap.demo import DEMO_RIG
        from livecap.demo.keymodels import key_models
        from transport.rig_files import load_rig

        rig = load_rig(args.rig or Path(__file__).resolve().parents[2] / "recordings" / DEMO_RIG)
        base, tris = rig.neutral, rig.triangles
        emotional, verbal = key_models(rig)
    else:
        if not (args.base and args.emotional and args.verbal):
            raise ValueError("give --base, --emotional and --verbal OBJs (or --demo)")
        base, tris = read_obj(args.base)
        emotional, verbal = _read(args.emotional, base, tris), _read(args.verbal, base, tris)
    size = float(np.linalg.norm(np.ptp(base, axis=0)))
    lp = args.lp if args.lp is not None else 0.04 * size
    s = ImportanceSettings(s1=args.s1, s2=args.s2, lp=lp, le=args.le if args.le is not None else lp)
    combined, alpha = composite_all(base, emotional, verbal, s)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    write_obj(out / "neutral.obj", base, tris, "livecap composite: base")
    for name, mesh in {**emotional, **verbal, **combined}.items():
        write_obj(out / f"{name}.obj", mesh, tris)
    np.save(out / "importance.npy", alpha)
    print(f"{out}: {len(emotional)} emotional x {len(verbal)} verbal -> {len(combined)} combined key models "
          f"(+ {len(emotional) + len(verbal)} pure, neutral.obj, importance.npy)")
    print(f"importance: {np.mean(alpha >= 0.5) * 100:.1f}% of vertices follow speech (alpha >= 0.5); "
          f"Lp {s.lp:.3g}, Le {s.le:.3g}, S1 {s.s1:g}, S2 {s.s2:g}")
    return 0
