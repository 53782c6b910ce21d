"""livecap.calibration.stabilise.to_quaternion (numpy, used every live frame) agrees with scipy's Rotation."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from livecap.calibration.stabilise import to_quaternion


@given(st.integers(0, 2**32 - 1), st.sampled_from([0.0, 1e-3, np.pi - 1e-6, np.pi]))
@settings(max_examples=60, deadline=None)
def test_matches_scipy_sign_included(seed, angle):
    rng = np.random.default_rng(seed)
    rots = Rotation.random(20, random_state=seed)
    axis = rng.normal(size=3)
    special = Rotation.from_rotvec(angle * axis / np.linalg.norm(axis))  # identity, tiny, half turns
    R = np.concatenate([rots.as_matrix(), special.as_matrix()[None]])
    q = to_quaternion(R)
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(q, Rotation.from_matrix(R).as_quat(), atol=1e-9)
    np.testing.assert_allclose(Rotation.from_quat(q).as_matrix(), R, atol=1e-9)
    np.testing.assert_allclose([to_quaternion(r) for r in R], q, atol=1e-12)  # one matrix at a time (live path)
    assert to_quaternion(R.reshape(3, 7, 3, 3)).shape == (3, 7, 4)
