"""Calibration (Seol 2012 §3.1-3.2, Curio 2006 §2.1): neutral, proportion warp, profile, what it buys."""

from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from livecap.calibration.profile import (
    CalibrationError,
    NeutralCapture,
    Profile,
    calibrate,
    estimate_neutral,
    neutral_from_frames,
)
from livecap.calibration.stabilise import head_pose_error, kabsch
from livecap.calibration.warp import warp_rig
from livecap.demo.performance import PerformanceSettings, actor_warp, perform

NEUTRAL = PerformanceSettings(seconds=2.0, rate=60, neutral_start=2.0, neutral_end=0.0, beyond_limits=False,
                              stable_dropout=0.0, occlusion=0.0, seed=101)


def _aligned_error(est, truth):
    R, t = kabsch(est, truth)
    return np.linalg.norm(est @ R.T + t - truth, axis=1)


def test_neutral_is_robust_to_a_blink_a_dropout_and_a_jump(demo):
    rig, layout = demo
    perf = perform(rig, layout, replace(NEUTRAL, noise_mm=0.3))
    pos, val = perf.take.positions.copy(), perf.take.valid.copy()
    eye = [i for i, lab in enumerate(layout.labels) if "LID" in lab.upper() or "EYE" in lab.upper()] or [20, 21]
    pos[30:60, eye] += [0.0, -8.0, 1.0]  # a quarter of the span: a long blink (head frame ~ world here)
    val[0:50, 3] = False  # a dropout, including the first frame
    pos[70:75, 10] += 40.0  # a glitch
    neutral = neutral_from_frames(pos, val, layout.stable)
    assert _aligned_error(neutral, perf.actor_neutral).max() < 0.3


def test_neutral_names_markers_never_seen(demo):
    rig, layout = demo
    take = perform(rig, layout, NEUTRAL).take
    take.valid[:, 5] = False
    with pytest.raises(CalibrationError, match=layout.labels[5]):
        estimate_neutral(take, layout.stable)


def test_neutral_capture_from_a_stream_waits_for_every_marker(demo):
    rig, layout = demo
    take = perform(rig, layout, NEUTRAL).take
    cap = NeutralCapture(layout.stable, frames=30, labels=layout.labels)
    done_at = None
    for i, f in enumerate(take.frames()):
        v = f.valid.copy()
        if i < 40:
            v[7] = False  # marker 7 only appears after 40 frames
        if cap.add(f.positions, v):
            done_at = i
            break
    assert done_at is not None and 40 <= done_at < 60
    assert _aligned_error(cap.neutral(), take.positions[0]).max() < 2.0  # the rest face, up to noise


def _true_basis(rig, layout, profile, actor_neutral, seed=7):
    """The generator's actor basis (its warp applied to every sculpt), in the profile's frame."""
    w = actor_warp(np.random.default_rng(seed))
    A, a = kabsch(actor_neutral, profile.source_neutral)
    true = warp_rig(layout.marker_rig(rig), lambda p: w(p) @ A.T + a)
    return true.deltas.reshape(rig.n_shapes, -1).T


@pytest.mark.parametrize("fixture", ["demo", "ict"])
def test_rbf_basis_is_much_closer_to_the_actors_than_a_similarity(fixture, request):
    rig, layout = request.getfixturevalue(fixture)
    perf = perform(rig, layout, NEUTRAL)
    neutral = estimate_neutral(perf.take, layout.stable)
    err = {}
    for kind in ("rbf", "similarity", "rigid"):
        prof = calibrate(rig, layout, neutral, warp=kind)
        true = _true_basis(rig, layout, prof, perf.actor_neutral)
        err[kind] = np.linalg.norm(prof.basis - true) / np.linalg.norm(true)
    assert err["rbf"] < 0.5 * err["similarity"] and err["rbf"] < 0.5 * err["rigid"], err
    assert err["rbf"] < 0.05, err


def test_calibrate_puts_the_neutral_in_the_rig_frame_and_fits_it_exactly(demo):
    rig, layout = demo
    neutral = perform(rig, layout, NEUTRAL).take.positions[0]  # capture-volume frame, head turned
    prof = calibrate(rig, layout, neutral)
    assert prof.settings["warp"] == "rbf"
    sites = layout.marker_rig(rig).neutral
    R, _ = kabsch(prof.source_neutral, sites)
    assert Rotation.from_matrix(R).magnitude() < 1e-9  # no rotation left between neutral and rig
    np.testing.assert_allclose(_aligned_error(prof.source_neutral, neutral), 0, atol=1e-9)  # rigidly moved only
    np.testing.assert_allclose(prof.marker_rig.neutral, prof.source_neutral, atol=1e-9)
    np.testing.assert_allclose(prof.basis, prof.marker_rig.deltas.reshape(rig.n_shapes, -1).T)


def test_profile_round_trip_keeps_warp_and_marker_rig(demo, tmp_path):
    rig, layout = demo
    prof = calibrate(rig, layout, perform(rig, layout, NEUTRAL).take.positions[0], {"note": "x"})
    prof.save(tmp_path / "p.npz")
    back = Profile.load(tmp_path / "p.npz")
    assert back.labels == prof.labels and back.names == prof.names and back.settings == prof.settings
    for f in ("source_neutral", "stable", "basis", "lower", "upper", "target_sites"):
        np.testing.assert_array_equal(getattr(back, f), getattr(prof, f))
    w = np.random.default_rng(0).uniform(0, 1, (3, rig.n_shapes))
    np.testing.assert_allclose(back.marker_rig.evaluate(w), prof.marker_rig.evaluate(w), atol=1e-12)
    x = prof.target_sites + 2.0
    np.testing.assert_allclose(back.warp(x), prof.warp(x))
    # a profile written before the warp fields existed still loads
    np.savez(tmp_path / "old.npz", labels=np.array(prof.labels), names=np.array(prof.names),
             source_neutral=prof.source_neutral, stable=prof.stable, basis=prof.basis, lower=prof.lower,
             upper=prof.upper, target_sites=prof.target_sites, settings=np.array("{}"))
    old = Profile.load(tmp_path / "old.npz")
    assert old.warp is None and old.marker_rig is None
    with pytest.raises(CalibrationError, match="bad.npz"):
        Profile.load(tmp_path / "bad.npz")


def test_calibrated_pipeline_beats_uncalibrated_on_a_generated_take(demo):
    from livecap.modes.registry import build_solver
    from livecap.offline.calibration_report import VARIANTS, compare

    rig, layout = demo
    s = PerformanceSettings(seconds=4.5, rate=40, seed=11)
    perf = perform(rig, layout, s)
    neutral = estimate_neutral(perform(rig, layout, replace(NEUTRAL, rate=40)).take, layout.stable)
    truth = type("T", (), {"weights": perf.weights, "names": perf.names, "head_rotation": perf.head_rotation,
                           "head_translation": perf.head_translation, "actor_neutral": perf.actor_neutral})
    chosen = [VARIANTS[0], next(v for v in VARIANTS if v.name.startswith("uncalibrated"))]
    cal, uncal = compare(perf.take, rig, layout, neutral, lambda p: build_solver("lsq", p), truth, chosen)
    assert cal.weight_rmse < 0.6 * uncal.weight_rmse
    assert np.mean(cal.frame_weight_error < uncal.frame_weight_error) > 0.9
    assert np.median(cal.frame_marker_error) < 0.2 * np.median(uncal.frame_marker_error)
    assert cal.model_error_mm < 0.2 * uncal.model_error_mm
    assert cal.rotation_deg.mean() < 0.6 and cal.translation_mm.mean() < 1.0


def test_calibration_on_the_ict_rig(ict):
    """The real ICT-FaceKit rig (cm on disk, 53 shapes): stabilise, warp and model a generated take."""
    from livecap.offline.calibration_report import model_error
    from livecap.offline.solve import prepare_targets

    rig, layout = ict
    rng = np.random.default_rng(0)  # 1 s neutral, then 15 s of random combinations of every shape
    W = np.zeros((480, rig.n_shapes))
    W[30:] = rng.uniform(0, 0.7, (450, rig.n_shapes)) * (rng.random((450, rig.n_shapes)) < 0.2)
    perf = perform(rig, layout, PerformanceSettings(rate=30, seed=4), weights=W)
    assert not perf.take.valid[:, layout.stable].all()  # a stable marker drops out
    neutral = estimate_neutral(perf.take, layout.stable, 30)
    prof = calibrate(rig, layout, neutral)
    assert np.isfinite(prof.basis).all() and prof.basis.shape == (3 * layout.n_markers, rig.n_shapes)
    take, targets, R, t = prepare_targets(perf.take, prof)
    assert np.isfinite(targets).all()
    rot, tr = head_pose_error(R, t, Rotation.from_quat(perf.head_rotation).as_matrix(), perf.head_translation,
                              prof.source_neutral, perf.actor_neutral)
    assert rot.mean() < 0.6 and tr.mean() < 1.0
    _, sys_rbf = model_error(prof, targets, take.valid, perf.weights)
    rigid = calibrate(rig, layout, neutral, warp="rigid")
    _, sys_rigid = model_error(rigid, targets, take.valid, perf.weights)
    assert sys_rbf < 0.8 * sys_rigid, (sys_rbf, sys_rigid)
