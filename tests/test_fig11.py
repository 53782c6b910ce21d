"""Seol et al. 2012 Fig. 11 scenario: retargeting onto a different, reduced rig (livecap.demo.retarget),
the alpha rule of §7, the prior's form, the finding, and ``livecap fig11``.

The finding (movement + prior with the constraints active costs less extra velocity error than
Range PF and Prior PF) is asserted on a short noise-free scenario; docs/movement.md has the
measurements on the 20 s default scenario, the demo take and other targets.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from livecap.cli import main
from livecap.cli.fig11 import BOUNDED, SOFT, TOL, compare, extra, fit_alpha
from livecap.demo.face import demo_rig
from livecap.demo.performance import PerformanceSettings
from livecap.demo.retarget import reduced_rig, retarget_scenario
from livecap.offline.metrics import position_error, range_excess
from solvers.movement import MovementMatching
from solvers.per_frame import prior_pf
from solvers.prior import PCAPrior

SHORT = PerformanceSettings(seconds=6.0, noise_mm=0.0, occlusion=0.0, stable_dropout=0.0, seed=1)


@pytest.fixture(scope="module")
def short():
    return retarget_scenario(settings=SHORT)


def test_reduced_rig_keeps_a_seeded_subset_with_its_inbetweens_and_correctives(demo):
    rig, _ = demo
    a, b = reduced_rig(rig, 20, 4), reduced_rig(rig, 20, 4)
    assert a.names == b.names and len(set(a.names)) == 20 and set(a.names) <= set(rig.names)
    assert reduced_rig(rig, 20, 5).names != a.names
    for k, name in enumerate(a.names):
        assert np.array_equal(a.deltas[k], rig.deltas[rig.index(name)])
    w = np.random.default_rng(0).random(20)
    full = np.zeros(rig.n_shapes)
    full[[rig.index(n) for n in a.names]] = w
    kept = {tuple(rig.names[s] for s in c.shapes) for c in rig.correctives} & {
        tuple(a.names[s] for s in c.shapes) for c in a.correctives}
    dropped = [c for c in rig.correctives if tuple(rig.names[s] for s in c.shapes) not in kept]
    expect = rig.evaluate(full) - sum((np.prod(full[list(c.shapes)]) * c.delta for c in dropped), 0.0)
    assert np.allclose(a.evaluate(w), expect)
    with pytest.raises(ValueError):
        reduced_rig(rig, 0, 1)
    with pytest.raises(ValueError):
        reduced_rig(rig, rig.n_shapes + 1, 1)


def test_scenario_is_another_face_that_cannot_follow_so_constraints_are_active(short):
    target = demo_rig(3)[0]
    names = short.info["target_names"]
    assert len(names) == 33 and set(names) <= set(target.names)
    assert short.basis.shape == (3 * short.info["markers"], 33)
    r = compare(short.basis, short.targets, short.valid, -0.5, 1.5)
    W0 = r["weights"]["No Const"]
    # Seol §7: unconstrained, the target contorts with extreme weights, and still misses the source
    assert range_excess(W0, -0.5, 1.5) > 1.0
    assert position_error(short.basis, W0, short.targets, short.valid) > 0.2  # noise-free source, mm
    for name in ("Range PF", "Prior PF", SOFT, BOUNDED):
        assert range_excess(r["weights"][name], -0.5, 1.5) <= TOL
        assert extra(r)[name] > 0  # No Const is the velocity optimum among these
    assert range_excess(r["weights"][BOUNDED], -0.5, 1.5) == 0  # hard limits
    assert r["admm"].converged


def test_fig11_finding_movement_with_constraints_active_adds_the_least_velocity_error(short):
    """Seol §7 Fig. 11: with the range a constraint of the spacetime solve (and a small prior,
    alpha 0.01), movement matching adds less velocity error over No Const than per-frame
    clipping (Range PF) and the per-frame prior (Prior PF). Measured, so it can fail."""
    r = compare(short.basis, short.targets, short.valid, -0.5, 1.5, soft=False)
    e = extra(r)
    assert e[BOUNDED] < e["Range PF"] and e[BOUNDED] < e["Prior PF"]
    # and Seol's Fig. 3 reason: it is many small velocity errors instead of a few large ones
    base = r["velocity"]["No Const"]
    d_b, d_r = r["velocity"][BOUNDED] - base, r["velocity"]["Range PF"] - base
    assert np.percentile(d_b, 99) < np.percentile(d_r, 99)


def test_fitted_alpha_is_the_smallest_reaching_the_range(short):
    prior = PCAPrior.from_shapes(short.basis)
    for solve in (lambda a: prior_pf(short.basis, short.targets, short.valid, prior, a),
                  lambda a: MovementMatching(short.basis, alpha=a, prior=prior).solve(short.targets, short.valid)):
        a, W = fit_alpha(solve, -0.5, 1.5)
        assert range_excess(W, -0.5, 1.5) <= TOL
        assert range_excess(solve(a / 1.05), -0.5, 1.5) > TOL


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10_000), m=st.integers(2, 12))
def test_shapes_prior_is_an_isotropic_ridge_in_weight_space(seed, m):
    """Why Prior PF behaves like ridge regression: for any full-rank basis the shapes prior's
    precision has eigenvalue m+1 (m-1 times) and (m+1)^2 along the all-ones direction."""
    B = np.random.default_rng(seed).normal(size=(3 * (m + 3), m)) * np.random.default_rng(seed + 1).uniform(
        0.1, 10, m)
    lam = np.linalg.eigvalsh(PCAPrior.from_shapes(B, threshold=1e-12).precision)
    expect = np.array([m + 1.0] * (m - 1) + [(m + 1.0) ** 2])
    assert np.allclose(lam, expect, rtol=1e-6)


def test_cli_runs_the_scenario_and_writes_table_csv_png(tmp_path, capsys):
    out = tmp_path / "f"
    assert main(["fig11", "--seconds", "6", "--noise-mm", "0", "--occlusion", "0", "--target-shapes", "18",
                 "--out-dir", str(out)]) == 0
    text = (out / "fig11.md").read_text()
    assert "reduced to 18 of 43 shapes" in text and f"| {BOUNDED} |" in text and f"| {SOFT} |" in text
    rows = np.loadtxt(out / "fig11.csv", delimiter=",", skiprows=1)
    assert rows.shape == (720, 6)
    assert (out / "fig11.png").stat().st_size > 10_000
    assert "Range PF" in capsys.readouterr().out


def test_cli_still_takes_a_users_take_and_rig(tmp_path):
    from livecap.demo import DEMO_RIG, DEMO_TAKE, generate

    generate(tmp_path, 0, PerformanceSettings(seconds=3.0, occlusion=0.0, stable_dropout=0.0, seed=1))
    out = tmp_path / "f"
    assert main(["fig11", "--take", str(tmp_path / DEMO_TAKE), "--rig", str(tmp_path / DEMO_RIG),
                 "--alpha-pf", "1", "--alpha-mm", "0.1", "--out-dir", str(out)]) == 0
    assert np.loadtxt(out / "fig11.csv", delimiter=",", skiprows=1).shape == (360, 6)
    assert main(["fig11", "--take", str(tmp_path / "missing.c3d"), "--rig", str(tmp_path / DEMO_RIG),
                 "--out-dir", str(out)]) == 1
