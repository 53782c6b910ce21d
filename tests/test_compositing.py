"""Key-model compositing (Pyun et al. 2003 §2 and appendix)."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from solvers.compositing import ImportanceSettings, composite, composite_all, importance, propagate


@settings(max_examples=50, deadline=None)
@given(seed=st.integers(0, 10_000))
def test_verbal_displacement_kept_where_alpha_at_least_half(seed):
    rng = np.random.default_rng(seed)
    V = 200
    base = rng.normal(0, 10, (V, 3))
    E, P = base + rng.normal(0, 2, (V, 3)), base + rng.normal(0, 2, (V, 3))
    alpha = rng.uniform(0, 1, V)
    C = composite(base, E, P, alpha)
    dC, dP, dE = C - base, P - base, E - base
    verbal = alpha >= 0.5
    # the component of dC along dP is exactly dP: speech is preserved
    along = np.einsum("ij,ij->i", dC, dP) / np.einsum("ij,ij->i", dP, dP)
    np.testing.assert_allclose(along[verbal], 1.0, atol=1e-9)
    # and the rest is (1 - alpha) x the emotional part perpendicular to dP
    perp = dE - (np.einsum("ij,ij->i", dE, dP) / np.einsum("ij,ij->i", dP, dP))[:, None] * dP
    np.testing.assert_allclose((dC - dP)[verbal], ((1 - alpha[:, None]) * perp)[verbal], atol=1e-9)
    # where alpha < 0.5 the roles swap: emotion kept along dE
    along_e = np.einsum("ij,ij->i", dC, dE) / np.einsum("ij,ij->i", dE, dE)
    np.testing.assert_allclose(along_e[~verbal], 1.0, atol=1e-9)


def test_zero_displacements_do_not_divide_by_zero():
    base = np.zeros((3, 3))
    E = np.array([[1.0, 0, 0], [0, 0, 0], [0, 0, 0]])
    P = np.array([[0.0, 0, 0], [0, 1.0, 0], [0, 0, 0]])
    C = composite(base, E, P, np.array([0.9, 0.1, 0.5]))
    np.testing.assert_allclose(C, [[0.1, 0, 0], [0, 0.1, 0], [0, 0, 0]])


def test_importance_follows_the_appendix():
    # a line of vertices: the mouth end moves in speech, the eye end in emotion
    base = np.stack([np.arange(10.0), np.zeros(10), np.zeros(10)], 1)
    verbal = base.copy()
    verbal[0, 1] = 4.0
    verbal[1, 1] = 1.0
    emotional = base.copy()
    emotional[9, 1] = 3.0
    s = ImportanceSettings(s1=0.5, s2=0.5, lp=1.5, le=1.5)
    alpha = importance(base, emotional[None], verbal[None], s)
    # p1 = [1, .25, 0...]; propagated within 1.5 -> p2 = [1, 1, 0...]; e2 = [0..., 1, 1]
    np.testing.assert_allclose(alpha, [1, 1, 0, 0, 0, 0, 0, 0, 0, 0])
    assert np.all((alpha >= 0) & (alpha <= 1))


def test_propagation_only_from_values_above_s1():
    base = np.stack([np.arange(4.0), np.zeros(4), np.zeros(4)], 1)
    np.testing.assert_allclose(propagate(base, np.array([0.4, 0.0, 0.9, 0.1]), 1.01, 0.5), [0.4, 0.9, 0.9, 0.9])


def test_combined_set_on_demo_rig_keeps_visemes_at_the_mouth(demo, tmp_path):
    from livecap.cli import main
    from livecap.core.objfile import read_obj
    from livecap.demo.keymodels import key_models

    rig, _ = demo
    emotional, verbal = key_models(rig)
    combined, alpha = composite_all(rig.neutral, emotional, verbal)
    assert len(combined) == len(emotional) * len(verbal)
    dP = verbal["AA"] - rig.neutral
    dC = combined["happy_AA"] - rig.neutral
    moving = np.linalg.norm(dP, axis=1) > 0.5
    keep = moving & (alpha >= 0.5)
    assert keep.sum() > 20
    along = np.einsum("ij,ij->i", dC[keep], dP[keep]) / np.einsum("ij,ij->i", dP[keep], dP[keep])
    np.testing.assert_allclose(along, 1.0, atol=1e-9)
    assert main(["composite", "--demo", "--out", str(tmp_path)]) == 0
    v, _ = read_obj(tmp_path / "happy_AA.obj")
    assert v.shape == rig.neutral.shape and (tmp_path / "importance.npy").exists()
