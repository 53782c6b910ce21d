"""Observability of a rig through a marker layout: singular structure, noise floor, pairs, CLI."""

from __future__ import annotations

import numpy as np

from livecap.cli import main
from solvers.observability import noise_floor, observability, tying_prior


def test_duplicate_and_invisible_shapes_are_reported():
    rng = np.random.default_rng(0)
    B = rng.normal(size=(30, 5))
    B[:, 3] = B[:, 1] * 1.02 + rng.normal(0, 0.01, 30)  # nearly indistinguishable from shape 1
    B[:, 4] = 0.0  # no marker sees it
    rep = observability(B, list("abcde"), noise_mm=0.5)
    assert rep.pairs[0][:2] == (1, 3) and rep.pairs[0][2] > 0.99
    assert np.isinf(rep.noise_sd[4]) and rep.marker_count[4] == 0
    assert rep.condition > 1e6
    assert any(abs(rep.directions[4, k]) > 0.99 for k in rep.unobservable())
    text = "\n".join(rep.lines())
    assert "b ~ d" in text and "e" in text
    # each shape's own part (issue 35): the near-duplicates have little, the unseen shape none
    assert rep.own_sd[1] > 10 * rep.own_sd[0] and rep.own_sd[3] > 10 * rep.own_sd[0] and np.isinf(rep.own_sd[4])
    assert "own sd" in text


def test_noise_floor_matches_monte_carlo():
    rng = np.random.default_rng(1)
    B = rng.normal(size=(24, 4)) @ np.diag([5, 2, 1, 0.3])
    sd = noise_floor(B, 0.5, ridge=0.2)
    noise = rng.normal(0, 0.5, (20000, 24))
    est = np.linalg.solve(B.T @ B + 0.2 * np.eye(4), B.T @ noise.T).T
    np.testing.assert_allclose(sd, est.std(0), rtol=0.05)
    assert (noise_floor(B, 0.5, ridge=5.0) < noise_floor(B, 0.5)).all()


def test_tying_prior_penalises_differences_only():
    rng = np.random.default_rng(2)
    B = rng.normal(size=(30, 3))
    B[:, 2] = B[:, 0] + rng.normal(0, 0.02, 30)
    P = tying_prior(observability(B, ["x", "y", "z"]), 4.0)
    assert np.allclose(P, P.T) and np.linalg.eigvalsh(P).min() > -1e-12
    assert abs(np.array([1.0, 0.3, 1.0]) @ P @ np.array([1.0, 0.3, 1.0])) < 1e-12
    assert np.array([1.0, 0.0, -1.0]) @ P @ np.array([1.0, 0.0, -1.0]) > 10


def test_demo_rig_report(demo):
    rig, layout = demo
    rep = observability(layout.basis(rig), rig.names, 0.5)
    jaw, press = rig.names.index("jawOpen"), rig.names.index("mouthPressLeft")
    assert rep.displacement[jaw] > 20 and rep.noise_sd[jaw] < rep.noise_sd[press]
    assert np.all(np.diff(rep.singular_values) <= 0)


def test_ict_rig_report(ict):
    rig, layout = ict
    rep = observability(layout.basis(rig), rig.names, 0.5)
    assert len(rep.names) == 53 and np.isfinite(rep.condition)
    assert rep.noise_sd[rig.names.index("jawOpen")] < np.median(rep.noise_sd)


def test_info_observability_cli(tmp_path, demo, capsys):
    rig, layout = demo
    rig.save(tmp_path / "r.npz")
    layout.save(tmp_path / "r.markers.json")
    assert main(["info", str(tmp_path / "r.npz"), "--observability", "--noise-mm", "0.3"]) == 0
    out = capsys.readouterr().out
    assert "observability: 43 shapes" in out and "marker noise 0.3 mm" in out and "jawOpen" in out
    (tmp_path / "bare.npz").write_bytes((tmp_path / "r.npz").read_bytes())
    assert main(["info", str(tmp_path / "bare.npz"), "--observability"]) == 1
    assert "markers.json" in capsys.readouterr().err
