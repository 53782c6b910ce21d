"""Accuracy on takes driven by real performances, measured against what is possible (issue 15).

The reference is the *oracle*: per-frame bounded least squares with the actor's true marker basis
and the true head pose, which only the generator knows. A mode's weight RMSE and vertex p95 are
reported as ratios to the oracle's on the same take, beside jitter as a multiple of the truth's and
blink peak retention (how much of each real blink's peak the solve keeps).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from scipy.optimize import lsq_linear
from scipy.signal import find_peaks
from scipy.spatial.transform import Rotation

from livecap.calibration.animation_prior import AnimationPrior
from livecap.calibration.profile import Profile, calibrate, estimate_neutral
from livecap.core.markers import MarkerLayout
from livecap.core.rig import Rig
from livecap.demo.curves_take import CurveTake
from livecap.modes.registry import build_solver, resolve_mode
from livecap.modes.robust import tune_profile
from livecap.offline.metrics import jitter, weight_rmse
from livecap.offline.solve import DEFAULT_MAX_GAP_SECONDS, DEFAULT_POSE_SMOOTHING_SECONDS, prepare_targets, solve_take
from livecap.offline.streamed import stream_take


def oracle_weights(ct: CurveTake, lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """Per-frame bounded least squares with the true actor basis and the true head pose."""
    take = ct.take
    R = Rotation.from_quat(ct.head_rotation).as_matrix()
    local = np.einsum("tji,tnj->tni", R, take.positions - ct.head_translation[:, None, :]) - ct.actor_neutral
    B = ct.actor_basis.reshape(len(ct.names), -1).T  # 3n x m
    W = np.zeros((take.n_frames, len(ct.names)))
    for i in range(take.n_frames):
        rows = np.repeat(take.valid[i], 3)
        W[i] = lsq_linear(B[rows], local[i].reshape(-1)[rows], bounds=(lower, upper), method="bvls").x
    return W


def vertex_p95(rig: Rig, weights: np.ndarray, truth: np.ndarray, stride: int = 3) -> float:
    """95th percentile over (frame, vertex) of the distance between the rig posed by both (mm)."""
    d = []
    for i in range(0, len(weights), 64 * stride):
        sl = slice(i, i + 64 * stride, stride)
        d.append(np.linalg.norm(rig.evaluate(weights[sl]) - rig.evaluate(truth[sl]), axis=2).ravel())
    return float(np.percentile(np.concatenate(d), 95))


def blink_retention(blinks: list[int], weights: np.ndarray, truth: np.ndarray, rate: float) -> float:
    """Median over real blinks (truth peaks above 0.5 on the ``blinks`` shapes) of the solved peak / the true peak."""
    ratios = []
    for k in blinks:
        peaks, _ = find_peaks(truth[:, k], height=0.5, distance=max(1, int(0.2 * rate)))
        for p in peaks:
            ratios.append(weights[max(0, p - 2):p + 3, k].max() / truth[p, k])
    return float(np.median(ratios)) if ratios else float("nan")


def plain_profile(rig: Rig, layout: MarkerLayout, ct: CurveTake, warp: str = "rbf") -> Profile:
    """What plain ``livecap calibrate NEUTRAL`` stores (robust stabiliser, default gap and pose settings, and the
    noise level and ridges tuned on the neutral take, which every CLI calibration stores)."""
    sel = ct.neutral.select(layout.labels)
    neutral = estimate_neutral(sel, layout.stable, None)
    settings = {"max_gap_seconds": DEFAULT_MAX_GAP_SECONDS, "robust_stabilise": True,
                "pose_smoothing_seconds": DEFAULT_POSE_SMOOTHING_SECONDS}
    profile = calibrate(rig, layout, neutral, settings, warp=warp)
    neutral_take, targets, _, _ = prepare_targets(ct.neutral, profile)
    tune_profile(profile, targets, neutral_take.valid, ct.neutral.rate)
    return profile


ACTIVE = 0.05  # a shape is active in a frame above this weight (issue 41: "keeps 14 of 27 active shapes")


@dataclass
class Row:
    mode: str
    rmse: float
    p95_mm: float
    jitter_x: float
    blink: float
    ms_per_frame: float
    active_true: float = float("nan")  # shapes active in the truth, mean over frames
    active_kept: float = float("nan")  # of those, active in the solve too
    bias: dict[str, float] | None = None  # per shape: mean solved - true weight
    phantom: float = float("nan")   # mean weight where the truth rests (< 0.01): activity never asked for
    rmse_curves: float = float("nan")  # model-mismatch takes: weight RMSE against the driving curves (the old truth)


def score(label: str, rig: Rig, ct: CurveTake, W: np.ndarray, seconds: float) -> Row:
    truth = ct.weights
    on = truth > ACTIVE
    return Row(label, weight_rmse(W, truth), vertex_p95(rig, W, truth),
               jitter(W) / max(jitter(truth), 1e-12), blink_retention(ct.blinks, W, truth, ct.take.rate),
               seconds * 1e3 / max(len(W), 1), float(on.sum(1).mean()), float((on & (W > ACTIVE)).sum(1).mean()),
               dict(zip(rig.names, (W - truth).mean(0).tolist(), strict=True)),
               float(np.asarray(W)[truth < 0.01].mean()) if (truth < 0.01).any() else float("nan"),
               weight_rmse(W, ct.curves) if hasattr(ct, "curves") else float("nan"))


def streamed(solver, targets: np.ndarray, valid: np.ndarray, step_us: np.ndarray | None = None) -> np.ndarray:
    """``solver.step`` over every frame, aligned by the mode's latency (its first outputs belong to no frame; the last
    frames repeat the last output). ``step_us``: filled with each step's wall microseconds when given."""
    if step_us is None:
        W = np.stack([solver.step(targets[i], valid[i]) for i in range(len(targets))])
    else:
        clock, out = time.perf_counter_ns, []
        for i in range(len(targets)):
            t0 = clock()
            out.append(solver.step(targets[i], valid[i]))
            step_us[i] = (clock() - t0) / 1e3
        W = np.stack(out)
    lag = int(getattr(solver, "latency_frames", 0))
    return np.concatenate([W[lag:], np.repeat(W[-1:], lag, 0)]) if lag else W


def evaluate_curve_take(rig: Rig, layout: MarkerLayout, ct: CurveTake, modes: list[str],
                        options: dict[str, dict] | None = None, prior: AnimationPrior | None = None,
                        warp: str = "rbf") -> list[Row]:
    """The oracle and every mode in ``modes`` (plain profile from the neutral take, carrying ``prior`` as
    ``livecap calibrate --prior`` stores it, e.g. one trained on the other files) on one take; ``options``
    per mode (``auto`` takes the options of the mode it stands for and is labelled ``auto=<mode>``); ``warp``: the
    calibration's proportion match (``livecap calibrate --warp``).

    Two rows per mode that streams: ``<mode> stream``, the take fed frame by frame through the live pipeline
    as ``livecap run`` feeds it (causal head pose, no gap filling; livecap.offline.streamed), and
    ``<mode> offline``, what ``livecap solve`` gives (smoothed head pose, filled gaps, the mode's whole-take
    form when it has one). Modes with no ``step`` get the offline row only."""
    t0 = time.perf_counter()
    rows = []
    if hasattr(ct, "actor_basis"):  # a model-mismatch take (livecap.demo.mismatch_take) has no oracle
        rows.append(score("oracle", rig, ct, oracle_weights(ct, rig.lower, rig.upper), time.perf_counter() - t0))
    profile = plain_profile(rig, layout, ct, warp)
    profile.prior = prior
    for name in modes:
        resolved = resolve_mode(name, profile)
        mode = name if resolved == name else f"{name}={resolved}"
        opts = (options or {}).get(resolved, {})
        solver = build_solver(resolved, profile, opts)
        if hasattr(solver, "step"):
            st = stream_take(ct.take, profile, resolved, opts)
            rows.append(score(f"{mode} stream", rig, ct, st.weights, st.seconds))
        solved = solve_take(ct.take, profile, solver)
        rows.append(score(f"{mode} offline", rig, ct, solved.weights, solved.solve_seconds))
    return rows
