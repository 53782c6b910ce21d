"""What calibration buys: the same take solved with and without each calibration step.

Variants switch off one step at a time (Seol et al. 2012 §3.1 head motion, §3.2 proportion
matching; Curio et al. 2006 §2.1 gap filling), down to the uncalibrated pipeline. Against
ground truth each is scored per frame (weight error, marker fit) and by the model error at the
true weights, split into its systematic part (what the true weights predict, i.e. calibration
error; Gaussian marker noise does not survive the regression) and the rest.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from livecap.calibration.profile import Profile, calibrate
from livecap.calibration.stabilise import HeadStabiliser, head_pose_error
from livecap.core.markers import MarkerLayout
from livecap.core.rig import Rig
from livecap.core.take import Take
from livecap.offline.solve import SolvedTake, solve_take


class FixedPose:
    """Head motion NOT removed per frame: the first good frame's pose for the whole take
    (the 'stabilisation off' baseline: markers aligned once, as a take without tracking)."""

    def __init__(self, inner: HeadStabiliser) -> None:
        self.inner = inner

    def stabilise(self, positions: np.ndarray, valid: np.ndarray):
        R, t, ok = self.inner.pose_batch(positions, valid)
        first = int(np.argmax(ok))
        R = np.broadcast_to(R[first], R.shape).copy()
        t = np.broadcast_to(t[first], t.shape).copy()
        local = np.einsum("tji,tnj->tni", R, positions - t[:, None, :])
        return np.where(valid[..., None], local, 0.0), R, t


@dataclass
class Variant:
    name: str
    warp: str = "rbf"
    stabilise: str = "robust"  # robust | plain | off
    fill_gaps: bool = True
    smooth_pose: bool = True


VARIANTS = [
    Variant("calibrated (robust+smoothed pose, rbf, gaps)"),
    Variant("warp: similarity", warp="similarity"),
    Variant("warp off (rigid)", warp="rigid"),
    Variant("stabilise: plain Kabsch, no smoothing", stabilise="plain", smooth_pose=False),
    Variant("pose smoothing off", smooth_pose=False),
    Variant("stabilise off (first-frame pose)", stabilise="off"),
    Variant("no gap fill", fill_gaps=False),
    Variant("uncalibrated (all off)", warp="rigid", stabilise="off", fill_gaps=False, smooth_pose=False),
]


@dataclass
class VariantResult:
    variant: Variant
    profile: Profile
    solved: SolvedTake
    frame_weight_error: np.ndarray | None = None  # T, RMS over shapes
    frame_marker_error: np.ndarray = field(default_factory=lambda: np.zeros(0))  # T, RMS mm of the solve fit
    model_error_mm: float = float("nan")  # RMS marker error of the model at the true weights
    systematic_mm: float = float("nan")  # its part predicted by the true weights (calibration error)
    rotation_deg: np.ndarray | None = None
    translation_mm: np.ndarray | None = None
    relative_rotation_deg: np.ndarray | None = None

    @property
    def weight_rmse(self) -> float:
        return float(np.sqrt(np.mean(self.frame_weight_error ** 2))) if self.frame_weight_error is not None \
            else float("nan")


def _frame_rms(a: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    if mask is None:
        return np.sqrt(np.mean(a * a, axis=1))
    sq = np.where(mask, np.sum(a * a, axis=-1), 0.0)
    return np.sqrt(sq.sum(1) / np.maximum(mask.sum(1), 1))


def model_error(profile: Profile, targets: np.ndarray, valid: np.ndarray, weights: np.ndarray) -> tuple[float, float]:
    """RMS marker error (mm) of the profile's model at ``weights``, and its systematic part.

    The systematic part is what the weights predict about the error: each marker coordinate's
    error is regressed on [weights, 1] over the take, and the energy of the fit, less what noise
    alone would put there (p = m + 1 regressors times the residual variance, the unbiased
    correction), is the model's (calibration's) fault; the rest is marker noise and stabilisation
    jitter. It is estimated only when the take has at least 8 frames per shape (else NaN).
    """
    if profile.marker_rig is not None:
        model = profile.marker_rig.evaluate(weights) - profile.marker_rig.neutral
    else:
        model = (weights @ profile.basis.T).reshape(targets.shape)
    err = np.where(valid[..., None], targets - model, 0.0)
    count = max(int(valid.sum()), 1)
    total = float(np.sqrt(np.sum(err ** 2) / count))
    X = np.hstack([weights, np.ones((len(weights), 1))])
    p = X.shape[1]
    if len(X) < 8 * p:
        return total, float("nan")  # too few frames to tell the systematic part from noise
    sys_sq = 0.0
    for j in range(targets.shape[1]):
        rows = valid[:, j]
        if rows.sum() <= 2 * p:
            continue
        Xj, ej = X[rows], err[rows, j]
        coef, *_ = np.linalg.lstsq(Xj, ej, rcond=None)
        fit = Xj @ coef
        noise_var = np.sum((ej - fit) ** 2, axis=0) / (len(ej) - p)
        sys_sq += float(np.sum(fit ** 2) - p * noise_var.sum())
    return total, float(np.sqrt(max(sys_sq, 0.0) / count))


def compare(take: Take, rig: Rig, layout: MarkerLayout, neutral: np.ndarray,
            make_solver: Callable[[Profile], object], truth=None, variants: list[Variant] | None = None,
            progress: Callable[[str, int], Callable] | None = None) -> list[VariantResult]:
    """Solve ``take`` once per variant; score against ``truth`` (a demo GroundTruth) when given."""
    variants = variants or VARIANTS
    take = take.select(layout.labels)
    W_true = None
    if truth is not None:
        idx = [truth.names.index(n) for n in rig.names]
        W_true = truth.weights[:, idx]
        if len(W_true) != take.n_frames:
            raise ValueError(f"ground truth has {len(W_true)} frames, the take {take.n_frames}")
        R_true = Rotation.from_quat(truth.head_rotation).as_matrix()
    profiles: dict[str, Profile] = {}
    out = []
    for v in variants:
        if v.warp not in profiles:
            profiles[v.warp] = calibrate(rig, layout, neutral, warp=v.warp)
        prof = profiles[v.warp]
        stab = prof.stabiliser(robust=v.stabilise != "plain")
        if v.stabilise == "off":
            stab = FixedPose(stab)
        solver = make_solver(prof)
        kw = {"max_gap_seconds": None if v.fill_gaps else 0.0, "stabiliser": stab,
              "pose_smoothing_seconds": None if v.smooth_pose and v.stabilise != "off" else 0.0}
        if progress is not None:
            with progress(v.name, take.n_frames) as update:
                solved = solve_take(take, prof, solver, update, **kw)
        else:
            solved = solve_take(take, prof, solver, **kw)
        fit = (solved.weights @ prof.basis.T).reshape(solved.targets.shape)
        res = VariantResult(v, prof, solved, frame_marker_error=_frame_rms(fit - solved.targets, solved.valid))
        if W_true is not None:
            res.frame_weight_error = _frame_rms(solved.weights - W_true)
            res.model_error_mm, res.systematic_mm = model_error(prof, solved.targets, solved.valid, W_true)
            R = Rotation.from_quat(solved.head_rotation).as_matrix()
            res.rotation_deg, res.translation_mm = head_pose_error(
                R, solved.head_translation, R_true, truth.head_translation, prof.source_neutral, truth.actor_neutral)
            rel_est = R @ R[0].T
            rel_true = R_true @ R_true[0].T
            cos = (np.trace(np.einsum("tji,tjk->tik", rel_est, rel_true), axis1=1, axis2=2) - 1) / 2
            res.relative_rotation_deg = np.degrees(np.arccos(np.clip(cos, -1, 1)))
        out.append(res)
    return out


def marker_residual(result: VariantResult) -> tuple[np.ndarray, np.ndarray]:
    """Per marker: RMS and 95th percentile (mm) of the solve's fit residual over the frames it is seen.

    A marker the rig cannot follow (bound off its anatomy, on hair, a loose marker) stands out here
    long before it shows in the per-frame averages."""
    solved, prof = result.solved, result.profile
    fit = (solved.weights @ prof.basis.T).reshape(solved.targets.shape)
    err = np.linalg.norm(fit - solved.targets, axis=2)
    seen = solved.valid
    rms = np.sqrt(np.where(seen, err ** 2, 0.0).sum(0) / np.maximum(seen.sum(0), 1))
    p95 = np.array([np.percentile(err[seen[:, j], j], 95) if seen[:, j].any() else np.nan
                    for j in range(err.shape[1])])
    return rms, p95


def subsample(take: Take, stride: int) -> Take:
    """Every ``stride``-th frame (the report's quick mode; per-frame solvers only)."""
    if stride <= 1:
        return take
    return Take(take.labels, take.positions[::stride], take.valid[::stride], take.rate / stride, take.first_frame)
