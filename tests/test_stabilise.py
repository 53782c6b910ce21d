import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from livecap.stabilise import HeadStabiliser, kabsch


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(3, 30))
def test_kabsch_recovers_rigid_motion(seed, k):
    rng = np.random.default_rng(seed)
    src = rng.normal(0, 50, (k, 3))
    R = Rotation.random(random_state=seed).as_matrix()
    t = rng.normal(0, 500, 3)
    R_est, t_est = kabsch(src, src @ R.T + t)
    np.testing.assert_allclose(R_est, R, atol=1e-9)
    np.testing.assert_allclose(t_est, t, atol=1e-7)
    assert np.linalg.det(R_est) > 0


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**32 - 1))
def test_kabsch_never_reflects(seed):
    rng = np.random.default_rng(seed)
    src = rng.normal(0, 1, (6, 3))
    dst = src * np.array([-1, 1, 1])  # a mirror image: the best rotation, not a reflection
    R, _ = kabsch(src, dst)
    assert np.linalg.det(R) > 0.999999


def test_batched_stabilise_matches_per_frame():
    rng = np.random.default_rng(0)
    ref = rng.normal(0, 50, (10, 3))
    stable = np.zeros(10, bool)
    stable[:4] = True
    Rs = Rotation.random(5, random_state=1).as_matrix()
    ts = rng.normal(0, 100, (5, 3))
    pos = np.einsum("tij,nj->tni", Rs, ref) + ts[:, None]
    valid = np.ones((5, 10), bool)
    valid[2, 0] = False
    local, R, t = HeadStabiliser(ref, stable).stabilise(pos, valid)
    np.testing.assert_allclose(R, Rs, atol=1e-9)
    np.testing.assert_allclose(local[valid], np.broadcast_to(ref, local.shape)[valid], atol=1e-9)
    for i in range(5):
        li, Ri, _ = HeadStabiliser(ref, stable).stabilise(pos[i], valid[i])
        np.testing.assert_allclose(li, local[i], atol=1e-9)
