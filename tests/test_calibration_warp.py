"""The RBF proportion warp (Seol 2012 §3.2): exact at its centres, exact on affine maps."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from livecap.calibration.warp import ProportionWarp, WarpError, warp_rig


def _centres(seed, n):
    rng = np.random.default_rng(seed)
    return rng.normal(0, 1, (n, 3)) * rng.uniform(20, 100, 3) + rng.normal(0, 200, 3)


@settings(max_examples=50, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(5, 80))
def test_rbf_warp_interpolates_its_centres(seed, n):
    c = _centres(seed, n)
    y = c + np.random.default_rng(seed + 1).normal(0, 5, c.shape)  # an arbitrary non-affine target
    warp = ProportionWarp.fit(c, y)
    np.testing.assert_allclose(warp(c), y, atol=1e-9 * np.abs(y).max())


@settings(max_examples=50, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(5, 80))
def test_rbf_warp_reproduces_an_arbitrary_affine_map(seed, n):
    rng = np.random.default_rng(seed)
    c = _centres(seed, n)
    A = rng.normal(0, 1, (3, 3)) + 2 * np.eye(3)
    b = rng.normal(0, 100, 3)
    warp = ProportionWarp.fit(c, c @ A.T + b)
    x = rng.normal(0, 150, (200, 3)) + c.mean(0)  # anywhere, not just at the centres
    scale = np.abs(x @ A.T + b).max()
    np.testing.assert_allclose(warp(x), x @ A.T + b, atol=1e-9 * scale)
    assert np.abs(warp.weights).max() < 1e-9 * scale
    np.testing.assert_allclose(warp.linear, A, atol=1e-9 * np.abs(A).max())


def test_from_affine_is_that_map():
    rng = np.random.default_rng(0)
    c = _centres(1, 10)
    A, b = rng.normal(0, 1, (3, 3)), rng.normal(0, 10, 3)
    w = ProportionWarp.from_affine(A, b, c)
    x = rng.normal(0, 100, (20, 3))
    np.testing.assert_allclose(w(x), x @ A.T + b, atol=1e-9)


def test_coplanar_or_too_few_centres_are_refused():
    c = _centres(2, 10)
    c[:, 2] = 0.0
    with pytest.raises(WarpError, match="non-coplanar"):
        ProportionWarp.fit(c, c)
    with pytest.raises(WarpError):
        ProportionWarp.fit(c[:3], c[:3])


def test_warp_arrays_round_trip():
    c = _centres(3, 12)
    w = ProportionWarp.fit(c, c * 1.1 + np.sin(c / 30))
    w2 = ProportionWarp.from_arrays(w.to_arrays("x_"), "x_")
    x = c + 3.0
    np.testing.assert_array_equal(w(x), w2(x))


def test_warped_rig_gives_the_warped_sculpt_at_every_sculpt(demo):
    """b*_ij = d(b_ij) for shapes, in-betweens and combination shapes alike (Seol §3.2)."""
    rig, layout = demo
    sites = layout.marker_rig(rig)
    assert sites.inbetweens and sites.correctives

    def d(p):  # a smooth non-affine warp
        return np.stack([1.05 * p[..., 0] + 4e-4 * p[..., 0] * p[..., 1], 0.95 * p[..., 1] + 3e-4 * p[..., 0] ** 2,
                         p[..., 2] + 2e-4 * p[..., 1] ** 2], -1)

    out = warp_rig(sites, d)
    for name, face in sites.whole_face().items():
        w = np.zeros(rig.n_shapes)
        if "+" in name:
            w[[rig.index(s) for s in name.split("+")]] = 1.0
        elif "@" in name:
            base, wt = name.split("@")
            w[rig.index(base)] = float(wt)
        else:
            w[rig.index(name)] = 1.0
        np.testing.assert_allclose(out.evaluate(w), d(face), atol=1e-9, err_msg=name)
    np.testing.assert_allclose(out.neutral, d(sites.neutral), atol=1e-12)
