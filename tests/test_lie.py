"""SO(3) helpers against scipy's Rotation (an independent implementation)."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pipeline.lie import exp_so3, log_so3


@pytest.mark.parametrize("scale", [0.0, 1e-9, 1e-4, 1.0, np.pi - 1e-6])
def test_exp_so3_single_and_batched_match_scipy(scale):
    rng = np.random.default_rng(7)
    w = rng.normal(size=(20, 3))
    w = scale * w / np.linalg.norm(w, axis=1, keepdims=True)
    ref = Rotation.from_rotvec(w).as_matrix()
    np.testing.assert_allclose(exp_so3(w), ref, atol=1e-14)
    for k in range(len(w)):  # the scalar fast path for a single vector
        np.testing.assert_allclose(exp_so3(w[k]), ref[k], atol=1e-14)
    if 0 < scale < np.pi - 1e-3:
        np.testing.assert_allclose(log_so3(exp_so3(w)), w, atol=1e-9)
