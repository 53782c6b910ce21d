"""The default mode: kalman under an animation prior stored by `calibrate --prior` (issue 15), and without one
unless the tuning take shows sparse acting, then robust (issue 41.1)."""

from __future__ import annotations

import numpy as np
import pytest

from livecap.calibration.animation_prior import AnimationPrior
from livecap.calibration.profile import Profile
from livecap.cli import main
from tests.test_curves_take import short_csv  # noqa: F401 - fixture
from transport.weights_csv import read_weights_csv


def _calibrated_with_prior(tmp_path, short_csv, seconds: str):  # noqa: F811
    """A prior built from ``short_csv``, a take it drives on the demo rig, and a profile calibrated on the
    take's neutral with that prior stored: (prior, take, profile) paths."""
    prior = tmp_path / "p.npz"
    assert main(["prior", "build", str(short_csv), "--rig", "recordings/demo_rig.npz", "--out", str(prior)]) == 0
    assert main(["generate", "--curves", str(short_csv), "--seconds", seconds, "--out", str(tmp_path)]) == 0
    neutral = tmp_path / f"{short_csv.stem}_neutral.c3d"
    assert main(["calibrate", str(neutral), "--rig", "recordings/demo_rig.npz", "--out", str(tmp_path / "a.npz"),
                 "--prior", str(prior)]) == 0
    return prior, tmp_path / f"{short_csv.stem}.c3d", tmp_path / "a.npz"


def test_calibrate_prior_is_stored_and_makes_the_default_mode_kalman(tmp_path, short_csv, capsys):  # noqa: F811
    """`calibrate --prior` stores the animation prior in the profile; a solve with that profile and no
    --mode then runs kalman under it (equal to --mode kalman --prior), without it kalman under a ridge (the
    neutral take says nothing of the acting)."""
    rig = "recordings/demo_rig.npz"
    prior = tmp_path / "p.npz"
    assert main(["prior", "build", str(short_csv), "--rig", rig, "--out", str(prior)]) == 0
    assert main(["generate", "--curves", str(short_csv), "--seconds", "2", "--out", str(tmp_path)]) == 0
    take, neutral = tmp_path / f"{short_csv.stem}.c3d", tmp_path / f"{short_csv.stem}_neutral.c3d"
    assert main(["calibrate", str(neutral), "--rig", rig, "--out", str(tmp_path / "with.npz"),
                 "--prior", str(prior)]) == 0
    assert "default mode kalman" in capsys.readouterr().out
    assert main(["calibrate", str(neutral), "--rig", rig, "--out", str(tmp_path / "plain.npz")]) == 0
    stored = Profile.load(tmp_path / "with.npz").prior
    built = AnimationPrior.load(prior)
    assert stored is not None and stored.names == built.names and np.array_equal(stored.cov, built.cov)
    assert Profile.load(tmp_path / "plain.npz").prior is None

    def solve(profile: str, out: str, *extra: str) -> np.ndarray:
        assert main(["solve", str(take), "--rig", rig, "--profile", str(tmp_path / profile),
                     "--out", str(tmp_path / out), *extra]) == 0
        return read_weights_csv(tmp_path / out)[1]

    default_with = solve("with.npz", "a.csv")
    assert "solving (kalman)" in capsys.readouterr().err
    assert np.array_equal(default_with, solve("plain.npz", "k.csv", "--mode", "kalman", "--prior", str(prior)))
    assert np.array_equal(solve("plain.npz", "b.csv"), solve("plain.npz", "r.csv", "--mode", "kalman"))
    assert not np.array_equal(default_with, solve("with.npz", "r2.csv", "--mode", "robust"))


def test_a_prior_for_another_rig_is_refused_with_the_file_named(tmp_path, short_csv, capsys):  # noqa: F811
    prior = tmp_path / "p.npz"
    assert main(["prior", "build", str(short_csv), "--rig", "recordings/demo_rig.npz", "--out", str(prior)]) == 0
    p = AnimationPrior.load(prior)
    AnimationPrior(p.names[:-1], p.mean[:-1], p.cov[:-1, :-1], p.frames, p.sources).save(prior)
    assert main(["generate", "--curves", str(short_csv), "--seconds", "1", "--out", str(tmp_path)]) == 0
    capsys.readouterr()
    assert main(["calibrate", str(tmp_path / f"{short_csv.stem}_neutral.c3d"), "--rig", "recordings/demo_rig.npz",
                 "--out", str(tmp_path / "a.npz"), "--prior", str(prior)]) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "p.npz: animation prior was built for another rig" in err[0]
    assert not (tmp_path / "a.npz").exists()


def test_movement_takes_the_animation_prior_from_a_file_or_the_profile(tmp_path, short_csv):  # noqa: F811
    """An animation prior (mean, covariance) seen through the basis is the PCA prior of frames with those
    moments (Seol §5 from Lewis §7.8-7.9's Gaussian), and movement solves with it."""
    from livecap.modes.movement import build_prior
    from solvers.prior import PCAPrior

    rng = np.random.default_rng(0)
    B = rng.normal(size=(30, 6))
    W = rng.normal(size=(500, 6))
    frames = PCAPrior.from_animation(B, W)
    moments = PCAPrior.from_moments(B, W.mean(0), np.cov(W, rowvar=False, bias=True))
    assert np.allclose(frames.precision, moments.precision, atol=1e-9 * np.abs(frames.precision).max())
    assert np.allclose(frames.eigenvalues, moments.eigenvalues)

    prior, take, _ = _calibrated_with_prior(tmp_path, short_csv, "2")
    profile = Profile.load(tmp_path / "a.npz")
    from_file, from_profile = build_prior(profile, str(prior), 1e-6), build_prior(profile, "profile", 1e-6)
    assert np.array_equal(from_file.precision, from_profile.precision)
    assert not np.allclose(from_file.precision, build_prior(profile, "shapes", 1e-6).precision)
    assert main(["solve", str(take), "--rig", "recordings/demo_rig.npz", "--profile", str(tmp_path / "a.npz"),
                 "--mode", "movement", "--prior", "profile", "--out", str(tmp_path / "m.csv")]) == 0
    assert np.isfinite(read_weights_csv(tmp_path / "m.csv")[1]).all()


def test_prior_options_of_kalman_and_auto(tmp_path, short_csv):  # noqa: F811
    """'none' turns a stored prior off (auto is then kalman under a ridge, robust on sparse acting); 'profile'
    needs a stored prior;
    movement's priors ('shapes', weight curves) are refused by kalman with a message saying so."""
    from livecap.modes.marker_kalman import kalman_prior
    from livecap.modes.registry import resolve_mode

    prior, _, _ = _calibrated_with_prior(tmp_path, short_csv, "1")
    with_prior = Profile.load(tmp_path / "a.npz")
    plain = Profile(**{**vars(with_prior), "prior": None})
    assert resolve_mode("auto", with_prior) == "kalman"
    assert resolve_mode("auto", with_prior, {"prior": "none"}) == "kalman"
    sparse = Profile(**{**vars(plain), "settings": {**plain.settings,
                                                     "robust": {**plain.settings["robust"], "acting": "sparse"}}})
    assert resolve_mode("auto", sparse) == "robust" and resolve_mode("auto", plain) == "kalman"
    assert kalman_prior(with_prior, {"prior": "none"}) is None
    assert kalman_prior(with_prior, {"prior": "profile"}) is with_prior.prior
    assert resolve_mode("auto", plain, {"prior": str(prior)}) == "kalman"
    with pytest.raises(ValueError, match="profile carries no animation prior"):
        kalman_prior(plain, {"prior": "profile"})
    for movement_prior, what in (("shapes", "'shapes'"), ({"names": ["a"], "weights": [[0.0]]}, "weight curves")):
        with pytest.raises(ValueError, match=f"not {what} \\(that is a movement prior\\)"):
            kalman_prior(with_prior, {"prior": movement_prior})

    # the noise-robust movement wrapper (a tuned profile) streams through its marker filter's one frame of lag
    # (issues 35 / 41), the plain sliding window (``stream``) by its lookahead: the live pipeline pairs frames by it
    from livecap.live.pipeline import solver_latency
    from livecap.modes.movement import build_movement
    from livecap.modes.robust_movement import RobustMovement

    assert isinstance(build_movement(plain, {}), RobustMovement)
    assert solver_latency(build_movement(plain, {})) == 1
    assert solver_latency(build_movement(plain, {"stream": True, "lookahead": 4})) == 4
    assert solver_latency(build_movement(plain, {"stream": True})) == 0


def test_the_acting_decides_the_default_without_a_prior(tmp_path):
    """Issue 41.1: tuned on the demo take (scripted, sparse) the default is robust; tuned on its still neutral take
    (no evidence) it is the dense kalman fit; the prior is not what decides."""
    rig = "recordings/demo_rig.npz"
    out = {}
    for name, extra in (("still", []), ("acting", ["--tune", "recordings/demo_take.c3d"])):
        out[name] = tmp_path / f"{name}.npz"
        assert main(["calibrate", "recordings/demo_neutral.c3d", "--rig", rig, "--out", str(out[name]), *extra]) == 0
    from livecap.modes.registry import resolve_mode

    still, acting = Profile.load(out["still"]), Profile.load(out["acting"])
    assert still.settings["robust"]["acting"] is None and resolve_mode("auto", still) == "kalman"
    assert acting.settings["robust"]["acting"] == "sparse" and resolve_mode("auto", acting) == "robust"
    assert acting.settings["robust"]["active_fraction"] < 0.08


def test_without_a_prior_a_large_rig_keeps_the_sparse_fit():
    """kalman costs 94 / 343 ms p50 / p99 a frame at 72 markers x 1000 shapes (docs/modes.md): no default there."""
    from livecap.modes.registry import DENSE_MAX_SHAPES, resolve_mode

    m = DENSE_MAX_SHAPES + 1
    p = Profile(["a"], [f"s{i}" for i in range(m)], np.zeros((1, 3)), np.ones(1, bool), np.zeros((3, m)),
                np.zeros(m), np.ones(m), np.zeros((1, 3)), {"robust": {"noise_mm": 0.5, "acting": None}})
    assert resolve_mode("auto", p) == "robust"
    small = Profile(**{**vars(p), "names": p.names[:10], "basis": p.basis[:, :10]})
    assert resolve_mode("auto", small) == "kalman"
