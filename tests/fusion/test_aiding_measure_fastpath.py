"""heading.measure, dvl.measure and learned_velocity.measure build z, H, R, h in one pass
(one attitude matrix, no np.cross); they must give exactly — bit for bit — what predict() and jacobian() give
(heading: to the last bits, its trigonometry is libm's). Both estimator paths measure with the same functions,
so replay output does not depend on which path the estimator takes."""
import math

import numpy as np
import pytest

from adaptnav.fusion.aiding import dvl, heading, learned_velocity
from adaptnav.fusion.aiding.common import dcm
from adaptnav.fusion.frames import euler_to_quat
from adaptnav.fusion.motion_model import MotionParams
from adaptnav.fusion.samples import DvlSample, HeadingSample
from adaptnav.fusion.state import N_ERR, initial_nominal

OMEGA = np.array([0.013, -0.021, 0.1037])
LEVER = np.array([0.51, 0.12, 0.33])
R_DB = dvl.rotation_db((0.01, 0.02, math.pi / 4))


def _states(n=50):
    rng = np.random.default_rng(7)
    for _ in range(n):
        roll, pitch, yaw = rng.uniform(-0.4, 0.4), rng.uniform(-1.2, 1.2), rng.uniform(-math.pi, math.pi)
        yield initial_nominal(rng.normal(size=3) * 100, rng.normal(size=3), euler_to_quat(roll, pitch, yaw))


@pytest.mark.parametrize("i", range(3))
def test_heading_measure_is_predict_and_jacobian_to_the_last_bits(i):
    """heading.measure's trigonometry is libm's (math.*), predict's and jacobian's numpy's:
    atan2, asin and tan differ in the last bit for some inputs, nothing more."""
    for x in _states(500):
        x[6:10] *= 1.0 + 1e-3 * i  # a slightly unnormalised quaternion too
        m = heading.measure(HeadingSample(0.0, 2.4), x, 0.01)
        np.testing.assert_allclose(m.H, heading.jacobian(x), rtol=1e-14, atol=1e-15)
        assert m.H.shape == (1, N_ERR) and np.array_equal(m.H[0, 6:9] != 0.0, heading.jacobian(x)[0, 6:9] != 0.0)
        assert np.count_nonzero(m.H) == np.count_nonzero(heading.jacobian(x))
        np.testing.assert_allclose(m.h, heading.predict(x), rtol=1e-15, atol=1e-15)
        assert np.array_equal(m.z, [2.4]) and np.array_equal(m.R, [[0.01**2]]) and m.angular.tolist() == [True]


def test_dvl_measure_is_predict_and_jacobian_exactly():
    for x in _states():
        m = dvl.measure(DvlSample(0.0, (1.0, 0.0, 0.1)), x, OMEGA, LEVER, R_DB, 0.02)
        assert np.array_equal(m.H, dvl.jacobian(x, LEVER, R_DB))
        assert np.array_equal(m.h, dvl.predict(x, OMEGA, LEVER, R_DB))
        assert np.array_equal(m.R, np.eye(3) * 0.02**2) and not m.angular.any()


@pytest.mark.parametrize("h_w", [0.0, 0.08, -0.05])
def test_learned_velocity_measure_is_predict_and_jacobian_exactly(h_w):
    """One rotation and water-relative velocity for h and H, or the caller's rotation (the
    estimator has it for the yaw rate): the numbers of predict() and jacobian()."""
    params = MotionParams(heave_per_surge=h_w)
    for k, x in enumerate(_states()):
        x[16:18] = (0.2, -0.1)
        x[18] = 1.0 + 0.01 * k
        m = learned_velocity.measure(x, 1.4, 0.05, params, 0.05)
        model = float(m.z[0])  # k_V u (1 − κ w²)
        assert np.array_equal(m.H, learned_velocity.jacobian(x, model, 0.0, h_w))
        assert np.array_equal(m.h, learned_velocity.predict(x, model, 0.0, h_w))
        given = learned_velocity.measure(x, 1.4, 0.05, params, 0.05, R_nb=dcm(x))
        for a, b in zip(m, given):
            assert a.tobytes() == b.tobytes()
