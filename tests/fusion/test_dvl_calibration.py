"""What the filter treats as known but is not, carried in the published covariance (consider
covariance): the DVL's scale and misalignment on its track since the last fix, and the water
density the depth is converted with."""
import math
from dataclasses import replace

import numpy as np
import pytest

from adaptnav.fusion.aiding.dvl import DvlCalibration
from adaptnav.fusion.config import FilterConfig
from adaptnav.fusion.eskf import Estimator
from adaptnav.fusion.frames import GRAVITY_M_S2
from adaptnav.fusion.motion_model import MotionParams, RpmSpeedTable
from adaptnav.fusion.samples import DepthSample, HeadingSample, ImuBatch

from .mission import ATM_PA, ORIGIN, RHO


def _track(cal, t0, vel_ne, seconds):
    for k in range(seconds + 1):  # (a sample at t0 already fed is skipped as re-fused history)
        cal.on_dvl(t0 + k, np.array([vel_ne[0], vel_ne[1], 0.0]))
    return t0 + seconds


def test_a_leg_of_dvl_track_carries_its_scale_and_misalignment_sigma():
    # GIVEN a DVL whose scale is known to 0.5 % and misalignment to 0.01 rad, after a fix
    cal = DvlCalibration(0.005, 0.01)
    cal.on_fix(0.0, (0.0, 0.0), 1.0)
    assert np.all(cal.position_cov_ne() == 0.0)
    # WHEN it tracks 300 m north
    t = _track(cal, 0.0, (1.5, 0.0), 200)
    # THEN the position is unsure by 0.5 % along the track and 0.01 rad across it
    np.testing.assert_allclose(cal.position_cov_ne(), np.diag([(0.005 * 300) ** 2, (0.01 * 300) ** 2]), rtol=1e-9)
    # AND back south on the reciprocal leg the same errors cancel (the lawnmower's sawtooth):
    # what is left is the 1.5 m of net track the instant turn leaves
    _track(cal, t, (-1.5, 0.0), 200)
    assert np.max(cal.position_cov_ne()) <= (0.01 * 1.5) ** 2 + 1e-12


def test_the_published_depth_sigma_carries_the_water_density_uncertainty():
    # GIVEN two filters at 20 m, one told the density is known, one that it is 1025 ± 10 kg/m³
    def at_20_m(sigma_rho):
        base = FilterConfig()
        est = Estimator(replace(base, depth=replace(base.depth, density_sigma_kg_m3=sigma_rho)), MotionParams(),
                        RpmSpeedTable(), ORIGIN)
        t = np.arange(1, 101) / 100.0
        est.process(ImuBatch(t, np.tile([0.0, 0.0, -GRAVITY_M_S2], (100, 1)), np.zeros((100, 3))))
        est.process(HeadingSample(1.0, 0.5))
        for k in range(20):
            est.process(DepthSample(1.0 + 0.1 * k, ATM_PA + RHO * GRAVITY_M_S2 * 20.0))
        return est.nav_state()

    known, unsure = at_20_m(0.0), at_20_m(10.0)
    # THEN the down variance grows by the depth scale it implies, (20 m × 10/1025)², and the
    # position itself is the same (the density is not estimated, only considered)
    assert unsure.cov[2, 2] - known.cov[2, 2] == pytest.approx((20.0 * 10.0 / 1025.0) ** 2, rel=0.01)
    assert unsure.pos_n_m[2] == pytest.approx(known.pos_n_m[2], abs=1e-12)
    assert math.sqrt(known.cov[2, 2]) < 0.05 < math.sqrt(unsure.cov[2, 2])


def test_an_unmeasured_lever_arm_enters_the_dvl_covariance_as_omega_cross_its_error():
    """lever_arm_doubt against the velocity errors ω × δl of drawn lever-arm errors, seen in
    the head's frame (R_db): zero without rotation, the sway of a turn when turning."""
    from adaptnav.fusion.aiding.dvl import lever_arm_doubt, rotation_db

    rng = np.random.default_rng(3)
    R_db = rotation_db((0.02, -0.01, 0.3))
    omega = np.array([0.01, -0.02, 0.1])  # rad/s: a turn with some roll and pitch rate
    dl = 0.5 * rng.standard_normal((200_000, 3))
    dv_d = np.cross(omega, dl) @ R_db.T
    empirical = np.cov(dv_d.T)
    C = lever_arm_doubt(omega, 0.5, R_db)
    assert np.allclose(C, empirical, atol=0.01 * np.max(np.abs(C)))
    assert np.allclose(lever_arm_doubt(np.zeros(3), 0.5, R_db), 0.0)


def test_the_report_says_whether_the_dvl_was_calibrated_or_ran_on_its_prior():
    # GIVEN a DVL track that no second fix has closed yet
    cal = DvlCalibration(0.005, 0.01)
    cal.on_fix(0.0, (0.0, 0.0), 1.0)
    t = _track(cal, 0.0, (1.5, 0.0), 200)
    # THEN the report says the scale and misalignment are still the prior's
    first = cal.report()
    assert first["status"] == "prior" and first["pairs_used"] == 0
    assert first["scale_sigma"] == pytest.approx(0.005)
    # WHEN a fix closes the 300 m track 2 m east of where the DVL put it (a 0.38° misalignment)
    cal.on_fix(t, (300.0, 2.0), 0.5)
    # THEN it is calibrated: one pair, the misalignment moved toward the fix, its σ shrank
    after = cal.report()
    assert after["status"] == "estimated" and after["pairs_used"] == 1
    assert after["misalignment_sigma_deg"] < first["misalignment_sigma_deg"]
    assert abs(after["misalignment_deg"]) > 0.1
