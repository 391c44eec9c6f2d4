"""DvlWaterVelocity.body / DvlBin.add (Python floats) against the array steps they
replaced: the same bits, for unrotated and rotated heads, bottom and water track, and the
non-finite velocities the unrotated shortcut must not take."""
import math

import numpy as np
import pytest

from adaptnav.calibration.dvl_teacher import DvlBin, DvlWaterVelocity


def _body_reference(wv, vel_d_m_s, water_track, yaw_rad, yaw_rate_rad_s, current_ne_m_s):
    """The array steps of DvlWaterVelocity.body when it returned an array."""
    v = wv.R_bd @ np.asarray(vel_d_m_s, dtype=float)
    lx, ly = wv.lever_b[0], wv.lever_b[1]
    v[0] += yaw_rate_rad_s * ly
    v[1] -= yaw_rate_rad_s * lx
    if not water_track:
        cn, ce = float(current_ne_m_s[0]), float(current_ne_m_s[1])
        c, s = math.cos(yaw_rad), math.sin(yaw_rad)
        v[0] -= c * cn + s * ce
        v[1] -= -s * cn + c * ce
    return v


MOUNTS = [((0.0, 0.0, 0.0), (0.0, 0.0, 0.0)), ((0.5, 0.0, 0.2), (0.0, 0.0, 0.0)),
          ((0.3, -0.1, 0.2), (0.01, -0.02, 0.7)), ((-0.2, 0.4, 0.0), (math.pi, 0.0, 0.0))]


@pytest.mark.parametrize("lever, rpy", MOUNTS)
def test_body_is_the_array_computation(lever, rpy):
    rng = np.random.default_rng(7)
    wv = DvlWaterVelocity(lever, rpy)
    want_bin, got_bin = np.zeros(3), DvlBin()
    for j in range(400):
        vel = tuple(rng.normal(0.0, 1.5, 3) * 10.0 ** rng.integers(-6, 2))
        if j % 17 == 0:
            vel = (0.0, -0.0, vel[2])
        args = (bool(j % 3 == 0), float(rng.uniform(-4, 4)), float(rng.normal(0, 0.1)),
                tuple(rng.normal(0, 0.2, 2)))
        want = _body_reference(wv, vel, *args)
        got = wv.body(vel, *args)
        assert all(type(v) is float for v in got)
        # every component equal (a zero's sign may differ only for an unrotated head)
        assert np.array_equal(np.array(got), want)
        want_bin += want
        got_bin.add(*got)
    assert got_bin.n == 400 and got_bin.sum_m_s.tobytes() == want_bin.tobytes()
    assert got_bin.mean(400).tobytes() == (want_bin / 400).tobytes() and got_bin.mean(401) is None


@pytest.mark.parametrize("vel", [(math.inf, 0.0, 0.0), (0.5, math.nan, 0.0), (0.0, 0.0, -math.inf)])
def test_body_of_a_non_finite_velocity_is_the_products(vel):
    """R_bd = I times a vector with an infinity has NaNs (0 × inf) where the vector has none:
    the unrotated shortcut is for finite velocities only."""
    wv = DvlWaterVelocity((0.5, 0.0, 0.2))
    want = _body_reference(wv, vel, False, 0.3, 0.01, (0.1, -0.05))
    got = np.array(wv.body(vel, False, 0.3, 0.01, (0.1, -0.05)))
    assert np.array_equal(got, want, equal_nan=True)


def test_bin_sums_as_numpy_does():
    b = DvlBin()
    b.add(0.1, 0.2, 0.3)
    b.add(1e-17, -0.2, 0.0)
    want = np.zeros(3)
    want += np.array([0.1, 0.2, 0.3])
    want += np.array([1e-17, -0.2, 0.0])
    assert b.n == 2 and b.sum_m_s.tobytes() == want.tobytes()
    assert DvlBin().sum_m_s.tobytes() == np.zeros(3).tobytes() and DvlBin().mean(1) is None
