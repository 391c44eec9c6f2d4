"""The earth model of a navigation-grade mechanisation away from the origin: the plumb line
turns with the position (and the alignment levels on it), so a FOG at rest far from the
origin — sensing its local gravity and the earth rate, as :mod:`adaptnav.sim.navgrade`
makes it — stays put; without the turning plumb line it oscillates away (Schuler)."""
import math
from dataclasses import replace

import numpy as np
import pytest

from adaptnav.fusion import strapdown as sd
from adaptnav.fusion.config import FilterConfig, ImuConfig
from adaptnav.fusion.eskf import Estimator
from adaptnav.fusion.frames import GRAVITY_M_S2, GeoOrigin, euler_to_quat
from adaptnav.fusion.motion_model import MotionParams, RpmSpeedTable
from adaptnav.fusion.samples import HeadingSample, ImuBatch, UsblSample
from adaptnav.fusion.state import ACC_G_OVER_R
from adaptnav.sim.navgrade import rotating_earth_imu

ORIGIN = GeoOrigin(math.radians(59.4), math.radians(10.5), 0.0)


def _at_rest(pos_n_m, duration_s, rate_hz=100.0):
    """A perfect IMU at rest, level on its local plumb line, heading 0.3 rad, at ``pos_n_m``."""
    n = int(duration_s * rate_hz)
    pos = np.tile(np.asarray(pos_n_m, float), (n + 1, 1))
    q = np.tile(euler_to_quat(0.0, 0.0, 0.3), (n + 1, 1))
    flat_f = np.tile([0.0, 0.0, -GRAVITY_M_S2], (n, 1))
    f, w = rotating_earth_imu(pos, np.zeros((n + 1, 3)), q, ORIGIN, flat_f, np.zeros((n, 3)))
    return ImuBatch(np.arange(1, n + 1) / rate_hz, f, w)


def _run(pos_n_m, earth_gradient=True):
    est = Estimator(replace(FilterConfig(), imu=ImuConfig(grade="navigation")), MotionParams(), RpmSpeedTable(),
                    ORIGIN)
    lat, lon, _ = ORIGIN.to_geodetic(np.asarray(pos_n_m, float))
    est.process(HeadingSample(0.0, 0.3))
    est.process(UsblSample(0.0, float(lat), float(lon), float("nan"), 0.3))
    imu = _at_rest(pos_n_m, 600.0)
    if not earth_gradient:
        set_earth = sd.set_earth

        def no_gradient(acc, lat_rad):
            set_earth(acc, lat_rad)
            acc[ACC_G_OVER_R] = 0.0

        sd.set_earth = no_gradient
    try:
        for a in range(0, len(imu), 2000):
            est.process(ImuBatch(imu.t_s[a:a + 2000], imu.specific_force_b_m_s2[a:a + 2000],
                                 imu.omega_b_rad_s[a:a + 2000]))
    finally:
        if not earth_gradient:
            sd.set_earth = set_earth
    return est.nav_state()


@pytest.mark.parametrize("pos", [(2000.0, 1000.0, 20.0), (-1500.0, -3000.0, 5.0)])
def test_a_fog_at_rest_far_from_the_origin_stays_put_for_ten_minutes(pos):
    s = _run(pos)
    assert np.linalg.norm(s.pos_n_m[:2] - np.asarray(pos[:2])) < 1.0
    assert np.linalg.norm(s.vel_n_m_s[:2]) < 0.01


def test_without_the_turning_plumb_line_it_drifts_away():
    s = _run((2000.0, 1000.0, 20.0), earth_gradient=False)
    assert np.linalg.norm(s.pos_n_m[:2] - np.array([2000.0, 1000.0])) > 5.0  # 6.5 m (with it: < 1 m)
