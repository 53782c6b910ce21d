"""Calibration: from a neutral take and a target rig to everything a solver needs (the Profile).

* Neutral: the actor's rest markers, a robust estimate over a neutral take or the first frames of
  a stream after head motion is removed (Curio et al. 2006 §2.1, §2.3; Seol et al. 2012 §3.1).
* Frame: the neutral is expressed in the rig's frame (one rigid fit of the actor's neutral onto
  the rig's marker sites), so stabilised markers and the published head pose are relative to the
  character's head, whatever the capture volume's axes.
* Proportions: an RBF warp from the rig's marker sites to the actor's markers (Seol §3.2, see
  livecap.calibration.warp), applied to every sculpt's sites to give the marker-space basis B and a warped
  marker-site rig (with in-betweens and correctives) in the actor's proportions.
"""

from __future__ import annotations

import hashlib
import json
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from livecap.calibration.animation_prior import AnimationPrior
from livecap.calibration.stabilise import MAD_TO_SIGMA, HeadStabiliser
from livecap.calibration.warp import ProportionWarp, WarpError, warp_rig
from livecap.core.markers import MarkerLayout
from livecap.core.rig import Corrective, InBetween, Rig
from livecap.core.take import Take
from solvers.rigid import kabsch, similarity

WARPS = ("rbf", "similarity", "rigid")


class CalibrationError(ValueError):
    pass


@dataclass
class Profile:
    """Everything calibration produced; saved to one ``.npz`` so a session starts instantly.

    ``warp`` (the fitted proportion warp) and ``marker_rig`` (the rig at the marker sites warped
    into the actor's proportions, with in-betweens and correctives, for nonlinear solvers:
    ``marker_rig.evaluate(w) - marker_rig.neutral`` is the model of a target) are optional:
    profiles written before they existed load with None. ``prior``: a Gaussian prior on the weights
    learned from real animation (``livecap calibrate --prior``; Lewis et al. 2014 §7.8-7.9), which
    makes the default mode the dense ``kalman`` fit (livecap.modes.registry.resolve_mode).
    """

    labels: list[str]
    names: list[str]
    source_neutral: np.ndarray  # n x 3, actor rest markers in the stabilised (head = rig) frame, mm
    stable: np.ndarray  # n bool
    basis: np.ndarray  # 3n x m, actor-space marker displacement per unit weight
    lower: np.ndarray
    upper: np.ndarray
    target_sites: np.ndarray  # n x 3 rig marker sites at rest (rig frame)
    settings: dict = field(default_factory=dict)
    warp: ProportionWarp | None = None
    marker_rig: Rig | None = None
    prior: AnimationPrior | None = None

    @property
    def n_markers(self) -> int:
        return len(self.labels)

    def stabiliser(self, robust: bool | None = None) -> HeadStabiliser:
        """The head stabiliser against this actor's neutral (robust unless the settings say not)."""
        robust = self.settings.get("robust_stabilise", True) if robust is None else robust
        return HeadStabiliser(self.source_neutral, self.stable, robust=robust,
                              floor_mm=float(self.settings.get("stabilise_floor_mm", 1.0)))

    def save(self, path: str | Path) -> None:
        extra: dict[str, np.ndarray] = {}
        if self.warp is not None:
            extra.update(self.warp.to_arrays("warp_"))
        if self.marker_rig is not None:
            extra.update(_rig_arrays(self.marker_rig, "mr_"))
        if self.prior is not None:
            extra.update(self.prior.to_arrays("prior_"))
        np.savez_compressed(
            path, labels=np.array(self.labels), names=np.array(self.names),
            source_neutral=self.source_neutral, stable=self.stable, basis=self.basis,
            lower=self.lower, upper=self.upper, target_sites=self.target_sites,
            settings=np.array(json.dumps(self.settings)), **extra,
        )

    @classmethod
    def load(cls, path: str | Path) -> Profile:
        try:
            z = np.load(path, allow_pickle=False)
            names = [str(s) for s in z["names"]]
            warp = ProportionWarp.from_arrays(z, "warp_") if "warp_centres" in z else None
            mrig = _rig_from_arrays(z, "mr_", names) if "mr_neutral" in z else None
            prior = AnimationPrior.from_arrays(z, "prior_") if "prior_mean" in z else None
            profile = cls([str(s) for s in z["labels"]], names, z["source_neutral"],
                          z["stable"], z["basis"], z["lower"], z["upper"], z["target_sites"],
                          json.loads(str(z["settings"])), warp, mrig, prior)
        except (OSError, KeyError, ValueError, TypeError, EOFError, zipfile.BadZipFile) as exc:
            raise CalibrationError(f"{path}: not a livecap profile ({exc})") from None
        profile.check(str(path))
        return profile

    def check(self, where: str = "profile") -> None:
        """Refuse a profile a session could only solve badly with: shapes that do not match,
        NaN/inf in the basis or neutral (every weight would be NaN and nothing published)."""
        n, m = len(self.labels), len(self.names)
        if n == 0 or m == 0:
            raise CalibrationError(f"{where}: profile has {n} markers and {m} shapes")
        if len(set(self.labels)) != n:
            raise CalibrationError(f"{where}: profile has duplicate marker labels")
        if np.shape(self.basis) != (3 * n, m) or np.shape(self.source_neutral) != (n, 3):
            raise CalibrationError(f"{where}: profile basis {np.shape(self.basis)} / neutral "
                                   f"{np.shape(self.source_neutral)} do not fit {n} markers and {m} shapes")
        for name in ("basis", "source_neutral", "target_sites", "lower", "upper"):
            if not np.isfinite(np.asarray(getattr(self, name), dtype=float)).all():
                raise CalibrationError(f"{where}: profile {name} holds NaN or infinite values")
        if int(np.count_nonzero(self.stable)) < 3:
            raise CalibrationError(f"{where}: profile has fewer than 3 stable markers (head motion cannot be removed)")
        if self.prior is not None:
            try:
                self.prior.check(self.names)
            except ValueError as exc:
                raise CalibrationError(f"{where}: {exc}") from None


def rig_fingerprint(rig: Rig) -> str:
    """A short id of a rig's shape names and neutral mesh (to 0.01 mm): a profile stores the id
    of the rig it was calibrated against, so ``livecap run --rig`` can refuse another rig's profile."""
    return _fingerprint(rig.names, rig.neutral)


def _fingerprint(names, neutral: np.ndarray, single: bool = False) -> str:
    """``single``: of the neutral as a rig's .npz stores it (float32), so a rig calibrated in memory and then
    saved is still recognised."""
    v = np.asarray(neutral, dtype=np.float32 if single else np.float64).astype(np.float64)
    h = hashlib.sha1("\n".join(names).encode())
    h.update(np.round(v, 2).astype("<f8").tobytes())
    return h.hexdigest()[:16]


def check_rig_path(profile: Profile, rig_path: str | Path, profile_path: str | Path
                   ) -> tuple[np.ndarray, np.ndarray]:
    """The rig at ``rig_path`` must be the one ``profile`` was calibrated against (its fingerprint), read
    cheaply: the shape names from the folder listing or the .npz, the neutral alone (not every shape's OBJ).
    Returns the neutral (mm) and triangles it read."""
    from livecap.core.objfile import read_obj
    from livecap.core.rig import _folder_metadata
    from livecap.core.units import to_mm

    stored = profile.settings.get("rig_fingerprint")
    path = Path(rig_path)
    if path.is_dir():
        names = {p.stem for p in path.glob("*.obj") if p.stem != "neutral" and not {"@", "+"} & set(p.stem)}
        neutral, triangles = read_obj(path / "neutral.obj")
        neutral = neutral * to_mm(1.0, _folder_metadata(path).get("units", "mm"))
    else:
        try:
            with np.load(path, allow_pickle=False) as z:
                names, neutral, triangles = {str(n) for n in z["names"]}, z["neutral"], z["triangles"]
        except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as exc:
            raise CalibrationError(f"{rig_path}: not a livecap rig file ({exc})") from None
    if names != set(profile.names):
        raise CalibrationError(f"{profile_path}: calibrated for a rig with {len(profile.names)} shapes, but --rig "
                               f"{rig_path} has {len(names)} ({sorted(names ^ set(profile.names))[:3]} differ)")
    if stored is not None:
        mine = _fingerprint(profile.names, neutral)
        single = profile.settings.get("rig_fingerprint_f32")
        if mine != stored and (single is None or _fingerprint(profile.names, neutral, True) != single):
            raise CalibrationError(f"{profile_path}: calibrated against rig {stored}, but --rig {rig_path} is "
                                   f"{mine} (another neutral mesh): recalibrate, or give its rig")
    return neutral, triangles


def check_layout_labels(profile: Profile, markers_path: str | Path, profile_path: str | Path,
                        mesh: tuple[np.ndarray, np.ndarray] | None = None) -> None:
    """``--markers`` beside ``--profile`` must name the markers the profile was calibrated with, and, given the
    rig's (neutral, triangles), bind them to the same sites."""
    from livecap.core.markers import LayoutError

    try:
        labels = [str(m.get("label")) for m in json.loads(Path(markers_path).read_text())["markers"]]
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as exc:
        raise LayoutError(f"{markers_path}: cannot read marker layout ({exc})") from None
    if labels != list(profile.labels):
        diff = sorted(set(labels) ^ set(profile.labels))
        raise CalibrationError(f"{profile_path}: calibrated with {len(profile.labels)} markers, but --markers "
                               f"{markers_path} binds {len(labels)}" + (f" ({diff[:4]} differ)" if diff else
                                                                        " in another order") + ": recalibrate")
    if mesh is None:
        return
    from types import SimpleNamespace

    from livecap.core.markers import MarkerLayout

    neutral, triangles = mesh
    layout = MarkerLayout.load(markers_path, SimpleNamespace(triangles=triangles, n_vertices=len(neutral)))
    moved = np.where(np.linalg.norm(layout.sampling_matrix(len(neutral)) @ neutral - profile.target_sites,
                                    axis=1) > 0.01)[0]
    if len(moved):
        raise CalibrationError(f"{profile_path}: --markers {markers_path} binds {len(moved)} markers to other sites "
                               f"than the profile was calibrated with ({[profile.labels[i] for i in moved[:4]]}): "
                               "recalibrate with these markers")


def _rig_arrays(rig: Rig, p: str) -> dict[str, np.ndarray]:
    n = rig.n_vertices
    return {
        f"{p}neutral": rig.neutral, f"{p}deltas": rig.deltas,
        f"{p}ib_shape": np.array([i.shape for i in rig.inbetweens], dtype=np.int32),
        f"{p}ib_knots": np.array([(i.left, i.weight, i.right) for i in rig.inbetweens]).reshape(-1, 3),
        f"{p}ib_residual": np.array([i.residual for i in rig.inbetweens]).reshape(-1, n, 3),
        f"{p}co_shapes": np.array([c.shapes + (-1,) * (3 - len(c.shapes)) for c in rig.correctives],
                                  dtype=np.int32).reshape(-1, 3),
        f"{p}co_delta": np.array([c.delta for c in rig.correctives]).reshape(-1, n, 3),
    }


def _rig_from_arrays(z, p: str, names: list[str]) -> Rig:
    ibs = [InBetween(int(s), float(k[1]), float(k[0]), float(k[2]), r)
           for s, k, r in zip(z[f"{p}ib_shape"], z[f"{p}ib_knots"], z[f"{p}ib_residual"], strict=True)]
    cos = [Corrective(tuple(int(i) for i in s if i >= 0), d)
           for s, d in zip(z[f"{p}co_shapes"], z[f"{p}co_delta"], strict=True)]
    return Rig(z[f"{p}neutral"], np.zeros((0, 3), np.int64), names, z[f"{p}deltas"], z["lower"], z["upper"],
               ibs, cos)


# ---------------------------------------------------------------------- neutral
def _robust_mean(local: np.ndarray, valid: np.ndarray, floor_mm: float) -> np.ndarray:
    """Per marker: mean of the samples within 3 sigma (sigma from the median distance to the
    per-marker median, never below ``floor_mm``) of the median; blinks and glitches drop out."""
    med = np.nanmedian(np.where(valid[..., None], local, np.nan), axis=0)
    dist = np.linalg.norm(local - med, axis=2)
    mad = np.nanmedian(np.where(valid, dist, np.nan), axis=0)
    keep = valid & (dist <= 3.0 * np.maximum(MAD_TO_SIGMA * mad, floor_mm))
    cnt = keep.sum(0)
    mean = (np.where(keep[..., None], local, 0.0).sum(0)) / np.maximum(cnt, 1)[:, None]
    return np.where((cnt > 0)[:, None], mean, med)


def neutral_from_frames(positions: np.ndarray, valid: np.ndarray, stable: np.ndarray,
                        labels: list[str] | None = None, floor_mm: float = 0.5) -> np.ndarray:
    """Actor rest markers (n, 3) from frames of a neutral face (T, n, 3) with head motion.

    Each frame is rigidly aligned (robustly, Seol §3.1) to a reference frame, the frame with the
    most stable then most markers visible, using only the markers visible in it; then the
    reference is replaced by the per-marker robust mean and the alignment repeated, so a blink, a
    dropout or a jump inside the span does not move the neutral. The result is in the frame of
    the reference frame (the capture volume's axes).
    """
    pos = np.asarray(positions, dtype=np.float64)
    val = np.asarray(valid, dtype=bool) & np.isfinite(pos).all(-1)
    stable = np.asarray(stable, dtype=bool)
    counts = val.sum(0)
    if (counts == 0).any():
        missing = [labels[i] if labels else str(i) for i in np.flatnonzero(counts == 0)]
        hint = " (none was seen: wrong take or marker labels?)" if len(missing) == len(counts) else ""
        raise CalibrationError(f"{len(missing)} of {len(counts)} markers never seen in the neutral span: "
                               f"{missing[:8]}{hint}")
    n = pos.shape[1]
    first = int(np.argmax(val[:, stable].sum(1) * (n + 1) + val.sum(1)))
    ref, ref_valid = np.where(val[first][:, None], pos[first], 0.0), val[first]
    for _ in range(3):
        R, t = HeadStabiliser(ref, stable).pose(pos, val & ref_valid)
        local = np.einsum("tji,tnj->tni", R, pos - t[:, None, :])
        ref, ref_valid = _robust_mean(local, val, floor_mm), np.ones(n, bool)
    return ref


def estimate_neutral(take: Take, stable: np.ndarray, frames: int | None = None) -> np.ndarray:
    """Actor rest markers from the first ``frames`` frames of ``take`` (all when None)."""
    span = take.slice(0, frames) if frames else take
    return neutral_from_frames(span.positions, span.valid, stable, span.labels)


class NeutralCapture:
    """Neutral capture from the first frames of a stream (Seol §3.1: the actor starts neutral).

    ``add`` frames until it returns True: after ``frames`` frames, once every marker has been
    seen at least ``min_seen`` times (a dropout extends the capture, up to ``4 * frames``).
    """

    def __init__(self, stable: np.ndarray, frames: int = 120, min_seen: int = 5,
                 labels: list[str] | None = None) -> None:
        self.stable = np.asarray(stable, dtype=bool)
        self.frames = int(frames)
        self.min_seen = int(min_seen)
        self.labels = labels
        n = len(self.stable)
        self._pos = np.zeros((4 * self.frames, n, 3))
        self._val = np.zeros((4 * self.frames, n), dtype=bool)
        self.count = 0

    @property
    def done(self) -> bool:
        if self.count >= len(self._pos):
            return True
        return self.count >= self.frames and bool((self._val[:self.count].sum(0) >= self.min_seen).all())

    def add(self, positions: np.ndarray, valid: np.ndarray) -> bool:
        if not self.done:
            p = np.asarray(positions, dtype=np.float64)
            v = np.asarray(valid, dtype=bool) & np.isfinite(p).all(-1)
            self._pos[self.count] = np.where(v[:, None], p, 0.0)
            self._val[self.count] = v
            self.count += 1
        return self.done

    def neutral(self) -> np.ndarray:
        if self.count == 0:
            raise CalibrationError("no frames captured for the neutral")
        return neutral_from_frames(self._pos[:self.count], self._val[:self.count], self.stable, self.labels)


# ---------------------------------------------------------------------- proportions
def fit_warp(kind: str, sites: np.ndarray, neutral: np.ndarray, smoothing: float = 0.0) -> ProportionWarp:
    """Rig marker sites -> actor neutral: ``rbf`` (Seol §3.2), ``similarity`` (uniform scale),
    or ``rigid`` (no proportion change at all: the uncalibrated baseline)."""
    if kind == "rbf":
        try:
            return ProportionWarp.fit(sites, neutral, smoothing)
        except WarpError as exc:
            raise CalibrationError(str(exc)) from None
    if kind == "similarity":
        s, R, t = similarity(sites, neutral)
        return ProportionWarp.from_affine(s * R, t, sites)
    if kind == "rigid":
        R, t = kabsch(sites, neutral)
        return ProportionWarp.from_affine(R, t, sites)
    raise CalibrationError(f"unknown warp {kind!r} (choose from {', '.join(WARPS)})")


def _check_fit(scale: float, fit_mm: float, neutral: np.ndarray, warp: str) -> None:
    """A proportion fit that explodes (a negative or huge scale, a residual larger than the face) is an
    error, not a profile: every solve with it would return nothing."""
    size = float(np.sqrt(np.mean(np.sum((neutral - neutral.mean(0)) ** 2, axis=1))))
    if not (np.isfinite(scale) and 0.2 < scale < 5.0 and np.isfinite(fit_mm) and fit_mm < 0.5 * size):
        raise CalibrationError(f"the {warp} proportion fit exploded (overall scale {scale:.4g}, fit at the markers "
                               f"{fit_mm:.3g} mm RMS on a face of {size:.0f} mm RMS radius): check the marker layout "
                               "against the take (labels, units, sites)")


def calibrate(rig: Rig, layout: MarkerLayout, neutral: np.ndarray, settings: dict | None = None,
              warp: str = "rbf", smoothing: float = 0.0) -> Profile:
    """Profile for ``rig`` seen through ``layout`` on an actor whose rest markers are ``neutral``.

    ``neutral`` may be in any frame (e.g. the capture volume's); it is moved rigidly into the rig's
    frame first. ``warp`` picks the proportion match (see :func:`fit_warp`).
    """
    neutral = np.asarray(neutral, dtype=np.float64)
    if neutral.shape != (layout.n_markers, 3) or not np.isfinite(neutral).all():
        raise CalibrationError(f"neutral must be {layout.n_markers} x 3 finite positions, got {neutral.shape}")
    same = layout.coincident()
    if same:
        raise CalibrationError(f"markers {' and '.join(same[0])} are bound to the same rig point: the proportion "
                               "warp cannot map one site to two markers (fix the marker layout)")
    sites_rig = layout.marker_rig(rig)
    sites = sites_rig.neutral
    Rc, tc = kabsch(neutral, sites)  # actor neutral -> rig frame, rigid only
    neutral_rig = neutral @ Rc.T + tc
    d = fit_warp(warp, sites, neutral_rig, smoothing)
    mrig = warp_rig(sites_rig, d)
    basis = mrig.deltas.reshape(rig.n_shapes, -1).T.copy()
    fit_mm = float(np.sqrt(np.mean(np.sum((mrig.neutral - neutral_rig) ** 2, axis=1))))
    _check_fit(d.mean_scale, fit_mm, neutral_rig, warp)
    info = {"warp": warp, "scale": d.mean_scale, "warp_fit_rms_mm": fit_mm, "frame": "rig", "smoothing": smoothing,
            "rig_fingerprint": rig_fingerprint(rig), "rig_fingerprint_f32": _fingerprint(rig.names, rig.neutral, True)}
    return Profile(list(layout.labels), list(rig.names), neutral_rig, layout.stable.copy(), basis,
                   rig.lower.copy(), rig.upper.copy(), sites, {**info, **(settings or {})}, d, mrig)
