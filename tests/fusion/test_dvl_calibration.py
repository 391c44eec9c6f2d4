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


def _lawnmower_dvl(cal, misalignment_rad, current_ne, rng, headings_deg=(0.0, 180.0), legs=8, leg_s=230.0,
                   speed_m_s=1.5, turn_rate_rad_s=0.1, scale=0.003, along_sigma_m_s=0.005):
    """Feed ``cal.on_straight`` a lawnmower's bottom track at 5 Hz: straight legs (heading into
    the cross current so that the ground track is the leg's), turns between them. The head
    reports ``(1 + s) R_z(ψ)ᵀ`` of the body's ground velocity, beam noise 1 cm/s; the
    "filter's" along-heading current is the truth plus a bias of ``along_sigma_m_s``."""
    c = np.asarray(current_ne, dtype=float)
    t = 0.0
    along_bias = along_sigma_m_s * rng.standard_normal()
    heading = math.radians(headings_deg[0])
    for leg in range(legs):
        course = math.radians(headings_deg[leg % len(headings_deg)])
        # crab into the current: the across-course component of u (cos h, sin h) cancels c's
        across = -math.sin(course) * c[0] + math.cos(course) * c[1]
        target = course - math.asin(across / speed_m_s)
        while abs(math.remainder(target - heading, 2 * math.pi)) > 1e-3:  # the turn
            step = math.copysign(min(turn_rate_rad_s * 0.2, abs(math.remainder(target - heading, 2 * math.pi))),
                                 math.remainder(target - heading, 2 * math.pi))
            heading += step
            t += 0.2
            _ping(cal, t, heading, speed_m_s, c, misalignment_rad, scale, rng, along_bias)
        for _ in range(int(leg_s / 0.2)):
            t += 0.2
            _ping(cal, t, heading, speed_m_s, c, misalignment_rad, scale, rng, along_bias)
    return cal


def _ping(cal, t, heading, speed, c, psi, scale, rng, along_bias):
    ch, sh = math.cos(heading), math.sin(heading)
    rotation_z = np.array([[math.cos(psi), -math.sin(psi), 0.0], [math.sin(psi), math.cos(psi), 0.0], [0.0, 0.0, 1.0]])
    ground = speed * np.array([ch, sh]) + c
    body = np.array([ch * ground[0] + sh * ground[1], -sh * ground[0] + ch * ground[1], 0.0])
    meas = (1.0 + scale) * rotation_z.T @ body + 0.01 * rng.standard_normal(3)
    cal.on_straight(t, meas[0], meas[1], heading, ch * c[0] + sh * c[1] + along_bias)


@pytest.mark.parametrize("psi_deg,current_ne", [(0.4, (0.07, 0.07)), (-0.3, (0.0, -0.15)), (0.0, (0.1, 0.05))])
def test_reciprocal_straight_legs_give_the_misalignment_without_any_fix(psi_deg, current_ne):
    from adaptnav.fusion.aiding.dvl import StraightLegs

    # GIVEN a torpedo AUV's DVL on a lawnmower in a cross current, no fix at all
    cal = _lawnmower_dvl(DvlCalibration(0.005, 0.01, straight_legs=StraightLegs()), math.radians(psi_deg),
                         current_ne, np.random.default_rng(int(10 * psi_deg) + 7))
    rep = cal.report()
    # THEN the reciprocal legs separate the head's misalignment from the current: within
    # 3 σ of the truth, and σ far below the 0.57° prior
    assert rep["status"] == "estimated" and rep["pairs_used"] == 0 and rep["straight_segments_used"] >= 20
    assert rep["misalignment_sigma_deg"] < 0.1
    assert abs(rep["misalignment_deg"] - psi_deg) < 3.0 * rep["misalignment_sigma_deg"]
    np.testing.assert_allclose(cal.theta[2:], current_ne, atol=0.01)


def test_one_heading_only_leaves_the_misalignment_at_its_prior():
    from adaptnav.fusion.aiding.dvl import StraightLegs

    # GIVEN legs all on one heading (a transit): the cross current and the misalignment are
    # one lateral velocity, which no single heading splits
    cal = _lawnmower_dvl(DvlCalibration(0.005, 0.01, straight_legs=StraightLegs()), math.radians(0.4),
                         (0.0, 0.1), np.random.default_rng(3), headings_deg=(30.0,), legs=3)
    rep = cal.report()
    # THEN the estimate does not claim to know ψ (its σ stays near the prior's 0.57°)
    assert rep["misalignment_sigma_deg"] > 0.4
    assert abs(rep["misalignment_deg"] - 0.4) < 3.0 * rep["misalignment_sigma_deg"]


def test_the_track_corrected_with_an_older_misalignment_stays_in_the_published_covariance():
    # GIVEN a fix, then 300 m of DVL track north corrected with ψ = 0
    cal = DvlCalibration(0.005, 0.01)
    cal.on_fix(0.0, (0.0, 0.0), 1.0)
    t = _track(cal, 0.0, (1.5, 0.0), 200)
    before = cal.position_cov_ne()
    # WHEN the estimate learns ψ = 0.5° and its σ shrinks to 0.05° (a straight-leg update)
    cal.theta = np.array([0.0, math.radians(0.5), 0.0, 0.0])
    cal.P = np.diag([0.005**2, math.radians(0.05)**2, 0.01, 0.01])
    after = cal.position_cov_ne()
    # THEN the 300 m already travelled with ψ = 0 keep their 2.6 m across-track error in the
    # covariance (known, not moved): σ_E stays ≥ 300 m × 0.5°, not 300 m × 0.05°
    assert math.sqrt(after[1, 1]) >= 300.0 * math.radians(0.5) * 0.99
    assert after[1, 1] < before[1, 1]
    # AND a further 300 m corrected with the new ψ add only its σ's share
    _track(cal, t, (1.5, 0.0), 200)
    grown = cal.position_cov_ne()
    assert math.sqrt(grown[1, 1]) == pytest.approx(math.hypot(300.0 * math.radians(0.5), 600.0 * math.radians(0.05)),
                                                   rel=0.02)

