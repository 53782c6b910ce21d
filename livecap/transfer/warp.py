"""Smooth non-rigid pre-alignment: the generic bent onto the new face by a warp with no small-scale detail.

Xiang et al. 2008 §3.1 assume the two faces "roughly globally aligned" before Algorithm 1, and
§4 show that deforming the generic first (then detecting again) improves the landmarks: the
patches of Algorithm 1 are only ``r_d = 6 %`` of the eye width wide, so they can only correct
offsets of that order. A similarity leaves offsets of 10-30 % of the eye width wherever the two
faces' proportions differ (a wider jaw, a longer nose), and the deformable model of §3.2 does
not remove them: its closest-point term is much stiffer than its stretching term at the scale
of a face, so each vertex snaps onto the target along the normal and slides nowhere.

This step is the bending part of Xiang's strain energy (§3.2, Eq. 2: the change of the second
fundamental form, linearised as the thin-plate energy ``∫|Δd|²``) with the closest-point potential
only, weighted so that the balance is set by a length: per iteration

    (ℓ⁴ K M⁻¹ K + M C) d = M C (p′ − x)

on the mesh scaled to unit eye width (K the cotangent stiffness, M the Voronoi mass; both terms
are surface integrals, so the result does not depend on the resolution or the units). A
displacement field varying over less than ``ℓ`` costs more than it gains, so the generic follows
the new face's proportions (affine and smooth changes are free: ``Δ`` of an affine field vanishes)
and slides tangentially with them, while the features stay where the warp carries them. ``ℓ``
is annealed from coarse to fine (eight iterations at 2 eye widths, then 1 and 0.7), in the spirit
of the paper's annealing schedule; one closest-point iteration per entry of ``lengths``.
Closest points are the normal-compatible ones not on the target's open boundary (§3.1's test);
all of them are kept (trimming the farthest 10 % drops exactly the regions whose proportions
differ most: on the known-answer case of benchmarks/transfer.py it cut the share of landmarks
within 8 % of the eye width from 100 % to 62 %).

Limits: the warp only moves points along the surface where the surface's shape says how (a
whole head, a nose, lips). On a smooth face patch with few features a non-affine change of
proportions is only partly recovered (the procedural demo face warped by a strong shear:
18 % within 8 %, see docs/transfer.md).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import igl
import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import splu

from livecap.transfer.deformable import closest_targets
from livecap.transfer.surface import Surface

# ℓ in eye widths per iteration, coarse to fine (measured on ICT -> warped, decimated ICT: docs/transfer.md)
DEFAULT_LENGTHS: tuple[float, ...] = (2.0,) * 8 + (1.0, 0.7)


@dataclass
class WarpResult:
    vertices: np.ndarray  # V x 3 (mm): the generic bent onto the new face
    rms: list[float] = field(default_factory=list)  # per iteration: RMS distance of the kept pairs (mm)


def smooth_warp(vertices: np.ndarray, triangles: np.ndarray, target: Surface, eye_width: float,
                lengths: Sequence[float] = DEFAULT_LENGTHS, max_angle: float = 60.0, trim: float = 1.0,
                progress: Callable[[int, int], None] | None = None) -> WarpResult:
    """Bend (``vertices``, ``triangles``) onto ``target``: one closest-point iteration per smoothing
    length in ``lengths`` (units of ``eye_width``, mm). ``trim`` < 1 keeps only that share of the
    nearest pairs per iteration."""
    F = np.asarray(triangles, dtype=np.int64)
    x = np.asarray(vertices, dtype=np.float64).copy()
    w = float(eye_width)
    if not w > 0:
        raise ValueError("eye width must be positive")
    out = WarpResult(x)
    for done, ell in enumerate(lengths, start=1):
        xs = x / w
        K = -igl.cotmatrix(xs, F)
        mass = igl.massmatrix(xs, F, igl.MASSMATRIX_TYPE_VORONOI).diagonal()
        mass = np.where(mass > 1e-12, mass, max(float(mass.mean()), 1e-12))
        p, ok, dist = closest_targets(x, F, target, max_angle)
        if ok.sum() > 10 and trim < 1:
            ok &= dist <= np.quantile(dist[ok], trim)
        c = mass * ok
        A = ell ** 4 * (K @ sp.diags(1.0 / mass) @ K) + sp.diags(c)
        A = (A + sp.identity(len(x)) * (1e-9 * max(float(A.diagonal().mean()), 1e-12))).tocsc()
        d = splu(A).solve(np.ascontiguousarray(c[:, None] * (p / w - xs)))
        x = x + d * w
        out.rms.append(float(np.sqrt(np.mean(dist[ok] ** 2))) if ok.any() else float("nan"))
        if progress is not None:
            progress(done, len(lengths))
    out.vertices = x
    return out
