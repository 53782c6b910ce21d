"""Open a take for review: rig, calibration, stabilised targets, weights (given or solved), truth."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from livecap.calibration.profile import Profile
from livecap.calibration.stabilise import to_quaternion
from livecap.modes.movement import build_movement
from livecap.modes.registry import build_solver
from livecap.offline.setup import check_labels, load_rig_layout, profile_from_take
from livecap.offline.solve import prepare_targets
from livecap.review.session import ReviewSession
from transport.takefile import read_take
from transport.weights_csv import read_weights_csv


def open_session(take_path: str, rig_path: str, markers: str | None = None, profile: str | None = None,
                 weights: str | None = None, truth: str | None = None, mode: str = "movement",
                 neutral_seconds: float = 1.0, pull: float = 1.0, robust_edits: bool = False) -> ReviewSession:
    """Everything the review page needs, solved once. Without ``weights`` the take is solved in ``mode``.

    Edits re-solve by Seol's movement matching (``livecap edit --take --plain``): milliseconds per edit.
    ``robust_edits`` uses the noise-robust solve's edit (smoothed markers, trend filter), ~0.5 s each."""
    rig, layout = load_rig_layout(rig_path, markers)
    take = read_take(take_path)
    check_labels(take, layout.labels, "take", rig_path)
    prof = Profile.load(profile) if profile else profile_from_take(rig, layout, take, neutral_seconds)
    sel, targets, R, t = prepare_targets(take, prof)
    if weights:
        names, W, _ = read_weights_csv(weights)
        missing = [n for n in prof.names if n not in names]
        if missing:
            raise ValueError(f"{weights}: no column for rig shapes {missing[:5]}")
        if len(W) != take.n_frames:
            raise ValueError(f"{weights}: {len(W)} rows but {take_path} has {take.n_frames} frames")
        W = W[:, [names.index(n) for n in prof.names]]
    else:
        solver = build_solver(mode, prof, {})
        if hasattr(solver, "solve"):
            W = solver.solve(targets, sel.valid)
        else:
            W = np.array([solver.step(targets[i], sel.valid[i]) for i in range(take.n_frames)])
    editor = build_movement(prof, {} if robust_edits else {"robust": False})
    gt = _truth(truth, take_path, prof.names, take.n_frames)
    return ReviewSession(rig, layout, prof, sel, np.array(W, dtype=np.float64), targets, sel.valid,
                         to_quaternion(R), t, editor, gt, pull)


def _truth(path: str | None, take_path: str, names: list[str], n_frames: int) -> np.ndarray | None:
    """Ground-truth weights in profile order: the given file, else ``<take>.truth.npz`` when present."""
    from livecap.demo import truth_path
    from livecap.demo.performance import GroundTruth

    p = Path(path) if path else truth_path(take_path)
    if not p.exists():
        if path:
            raise FileNotFoundError(f"{p}: no such ground truth file")
        return None
    try:
        gt = GroundTruth.load(p)
    except (KeyError, ValueError) as exc:
        raise ValueError(f"{p}: not a ground truth file ({exc})") from None
    missing = [n for n in names if n not in gt.names]
    if missing or len(gt.weights) != n_frames:
        raise ValueError(f"{p}: ground truth lacks shapes {missing[:4]} or has {len(gt.weights)} frames, "
                         f"not {n_frames}")
    return np.asarray(gt.weights)[:, [gt.names.index(n) for n in names]]


def weights_session(rig, layout, solved, pull: float = 1.0) -> ReviewSession:
    """A take of weights (a Live Link Face CSV put onto ``rig``, livecap.retarget.take): the rig's own marker
    sites driven by them stand for the markers, so edits re-solve against the curves as they came."""
    from livecap.calibration.profile import calibrate
    from livecap.core.take import Take

    sites = layout.marker_rig(rig)
    prof = calibrate(rig, layout, sites.neutral)
    W = np.asarray(solved.weights, dtype=np.float64)[:, [list(solved.names).index(n) for n in prof.names]]
    positions = sites.evaluate(W)
    valid = np.ones(positions.shape[:2], bool)
    take = Take(list(layout.labels), positions, valid, solved.rate, solved.first_frame)
    editor = build_movement(prof, {"robust": False})
    return ReviewSession(rig, layout, prof, take, W, positions - prof.source_neutral, valid, solved.head_rotation,
                         solved.head_translation, editor, None, pull)
