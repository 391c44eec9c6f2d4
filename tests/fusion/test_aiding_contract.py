"""Contract of every aiding source: shapes, units, and H = ∂h/∂δx by finite differences."""
import math

import numpy as np
import pytest

from adaptnav.fusion.aiding import attitude, depth, dvl, gnss, heading, learned_velocity, range as rng, usbl, visual_motion
from adaptnav.fusion.frames import GRAVITY_M_S2, GeoOrigin, euler_to_quat, wrap_angle
from adaptnav.fusion.motion_model import MotionParams
from adaptnav.fusion.samples import (AttitudeSample, DepthSample, DvlSample, GnssSample, HeadingSample, RangeSample,
                            UsblSample, VisualMotionSample)
from adaptnav.fusion.state import N_ERR, inject, initial_nominal

ORIGIN = GeoOrigin(math.radians(43.0), math.radians(5.0))


def _state(seed=0):
    rng = np.random.default_rng(seed)
    x = initial_nominal(rng.normal(size=3) * 10, rng.normal(size=3), euler_to_quat(0.1, -0.2, 2.5))
    x[10:13] = rng.normal(size=3) * 0.01
    x[13:16] = rng.normal(size=3) * 1e-3
    x[16:18] = (0.2, -0.1)
    x[18] = 1.05
    return x


OMEGA = np.array([0.01, -0.02, 0.1])
LEVER = np.array([0.5, 0.1, 0.3])
R_DB = dvl.rotation_db((0.0, 0.02, math.pi / 4))
PARAMS = MotionParams()

# (name, h(x), measurement(x), angular) — h must not reuse the code under test's Jacobian
CASES = {
    "learned_velocity": (lambda x: learned_velocity.predict(x, 1.5),
                         lambda x: learned_velocity.measure(x, 1.5, 0.05, PARAMS, 0.05)),
    "learned_velocity_flow": (lambda x: learned_velocity.predict(x, 1.5, 0.0, 0.08),
                              lambda x: learned_velocity.measure(x, 1.5, 0.05, MotionParams(heave_per_surge=0.08), 0.05)),
    "dvl": (lambda x: dvl.predict(x, OMEGA - (x[13:16] - _state()[13:16]), LEVER, R_DB),
            lambda x: dvl.measure(DvlSample(0.0, (1.0, 0.0, 0.1)), x, OMEGA, LEVER, R_DB, 0.01)),
    "depth": (depth.predict, lambda x: depth.measure(DepthSample(0.0, 2e5), x, 0.05, 1025.0, 101325.0)),
    "heading": (heading.predict, lambda x: heading.measure(HeadingSample(0.0, 2.4), x, 0.01)),
    "attitude": (attitude.predict, lambda x: attitude.measure(AttitudeSample(0.0, 0.1, -0.2, 2.5), x, 0.01, 0.03)),
    "gnss": (gnss.predict, lambda x: gnss.measure(GnssSample(0.0, ORIGIN.lat_rad, ORIGIN.lon_rad, 3.0), x, ORIGIN)),
    "usbl": (lambda x: usbl.predict(x, True),
             lambda x: usbl.measure(UsblSample(0.0, ORIGIN.lat_rad, ORIGIN.lon_rad, 10.0, 2.0, 0.5), x, ORIGIN)),
    "usbl_h": (lambda x: usbl.predict(x, False),
               lambda x: usbl.measure(UsblSample(0.0, ORIGIN.lat_rad, ORIGIN.lon_rad, 10.0, 2.0), x, ORIGIN)),
    "range": (lambda x: rng.predict(x, (30.0, -20.0, 40.0)),
              lambda x: rng.measure(RangeSample(0.0, 1, (30.0, -20.0, 40.0), 50.0, 2.0), x)),
    "visual_motion": (visual_motion.predict,
                      lambda x: visual_motion.measure(VisualMotionSample(2.0, 1.0, 1.4, 0.1, 0.0, (0.01, 0, 0, 0, 0.01, 0, 0, 0, 1e-4)), x)),
}


@pytest.mark.parametrize("name", sorted(CASES))
def test_shapes_and_covariance(name):
    h, meas = CASES[name]
    x = _state()
    m = meas(x)
    z, H, R = m[:3]
    k = z.size
    assert z.shape == (k,) and H.shape == (k, N_ERR) and R.shape == (k, k) and m.h.shape == (k,)
    assert np.allclose(R, R.T) and np.all(np.linalg.eigvalsh(R) > 0)
    np.testing.assert_allclose(m.h, h(x), atol=1e-12)


@pytest.mark.parametrize("name", sorted(CASES))
def test_jacobian_equals_finite_difference_through_injection(name):
    h, meas = CASES[name]
    x = _state()
    H = meas(x).H
    eps = 1e-6
    H_fd = np.zeros_like(H)
    for i in range(N_ERR):
        d = np.zeros(N_ERR)
        d[i] = eps
        dh = h(inject(x, d)) - h(inject(x, -d))
        ang = meas(x).angular
        dh = np.where(ang, wrap_angle(dh), dh)
        H_fd[:, i] = dh / (2 * eps)
    np.testing.assert_allclose(H, H_fd, atol=1e-6)


def test_units_depth_from_pressure_10_m_sea_water():
    p = 101325.0 + 1025.0 * GRAVITY_M_S2 * 10.0
    assert depth.pressure_to_depth(p, 1025.0, 101325.0) == pytest.approx(10.0, abs=1e-9)
    # fresh water: the same pressure reads deeper
    assert depth.pressure_to_depth(p, 1000.0, 101325.0) == pytest.approx(10.25, abs=1e-9)


def test_units_gnss_one_arcminute_north_is_about_1852_m():
    x = _state()
    m = gnss.measure(GnssSample(0.0, ORIGIN.lat_rad + math.radians(1 / 60), ORIGIN.lon_rad, 3.0), x, ORIGIN)
    assert m.z[0] == pytest.approx(1852.0, rel=0.01) and abs(m.z[1]) < 1e-6
    assert m.R[0, 0] == pytest.approx(9.0)


def test_learned_velocity_variance_follows_motion_model():
    x = _state()
    p = MotionParams(var_vv=0.04**2, var_vw=0.2**2, var_v1=0.01**2, var_s=0.02**2)
    m = learned_velocity.measure(x, 1.5, 0.1, p, 0.05)
    assert m.R[0, 0] == pytest.approx(1.5**2 * 0.04**2 + 0.1**2 * 0.2**2 + 0.01**2)
    assert m.R[1, 1] == pytest.approx(0.02**2) and m.R[2, 2] == pytest.approx(0.05**2)
    assert m.z[0] == pytest.approx(p.k_v * 1.5)


def test_the_flow_angle_row_carries_no_speed():
    # GIVEN a vehicle flying nose-up at an angle of attack α (tan α = 0.08): the water meets the
    # body from below, v_b = U (1, 0, tan α) / ‖·‖, at two speeds U
    tan_a = 0.08
    p = MotionParams(heave_per_surge=tan_a)
    for speed in (1.0, 1.5):
        x = initial_nominal(vel_n_m_s=speed * np.array([1.0, 0.0, 0.0]), q_nb=euler_to_quat(0.0, math.atan(tan_a), 0.0))
        m = learned_velocity.measure(x, 1.2, 0.0, p, 0.05)
        # THEN the heave row agrees whatever the speed (the RPM says 1.2 m/s), and moving along
        # the flow does not change it: the speed is the surge row's alone
        assert m.z[2] - m.h[2] == pytest.approx(0.0, abs=1e-12)
        along_flow = x[3:6] / np.linalg.norm(x[3:6])
        assert m.H[2, 3:6] @ along_flow == pytest.approx(0.0, abs=1e-12)


def test_heading_innovation_wraps():
    x = initial_nominal(q_nb=euler_to_quat(0.0, 0.0, math.pi - 0.01))
    m = heading.measure(HeadingSample(0.0, -math.pi + 0.01), x, 0.01)
    assert m.innovation()[0] == pytest.approx(0.02, abs=1e-9)


def test_dvl_invalid_gives_none():
    assert dvl.measure(DvlSample(0.0, (0, 0, 0), valid=False), _state(), OMEGA, LEVER, R_DB, 0.01) is None


# -- the aid registry against the sensor table ---------------------------------------------
# One example sample per aid source: the row a new aid adds here (with its CASES row above).
EXAMPLES = {
    "attitude": AttitudeSample(1.0, 0.0, 0.0, 0.5),
    "depth": DepthSample(1.0, 101325.0),
    "dvl": DvlSample(1.0, (0.0, 0.0, 0.0)),
    "gnss": GnssSample(1.0, ORIGIN.lat_rad, ORIGIN.lon_rad, 3.0),
    "heading": HeadingSample(1.0, 0.5),
    "range": RangeSample(1.0, 1, (30.0, 40.0, 0.0), 50.0, 2.0),
    "usbl": UsblSample(1.0, ORIGIN.lat_rad, ORIGIN.lon_rad, 0.0, 2.0),
    "visual_motion": VisualMotionSample(1.0, 0.0, 0.0, 0.0, 0.0, (0.01, 0, 0, 0, 0.01, 0, 0, 0, 1e-4)),
}
# sample kinds with the role "aid" in the sensor table that no aid source fuses yet
NOT_YET_FUSED: set[str] = set()


def test_every_aid_kind_of_the_sensor_table_has_one_aid_source():
    from adaptnav.fusion.aiding import AIDS
    from adaptnav.fusion.samples import kinds

    aid_kinds = set(kinds(role="aid"))
    assert set(AIDS) | NOT_YET_FUSED == aid_kinds
    assert not set(AIDS) & NOT_YET_FUSED, "fused now: remove it from NOT_YET_FUSED"
    assert set(EXAMPLES) == set(AIDS), "one example sample per aid source"


@pytest.mark.parametrize("kind", sorted(EXAMPLES))
def test_each_aid_source_has_its_config_section_and_is_dispatched_by_its_kind(kind):
    import dataclasses

    from adaptnav.fusion.aiding import AIDS
    from adaptnav.fusion.config import FilterConfig
    from adaptnav.fusion.eskf import Estimator
    from adaptnav.fusion.motion_model import RpmSpeedTable
    from adaptnav.fusion.samples import ImuBatch

    aid = AIDS[kind]
    section = {f.name: f for f in dataclasses.fields(FilterConfig)}.get(kind)
    assert section is not None, f"FilterConfig has no section {kind!r}"
    assert isinstance(getattr(FilterConfig(), kind), aid.config_type)
    assert isinstance(getattr(FilterConfig(), kind).enabled, bool)

    def aligned(cfg):
        est = Estimator(cfg, PARAMS, RpmSpeedTable(), ORIGIN)
        n = 100
        est.process(ImuBatch(np.arange(1, n + 1) / 100.0, np.tile([0.0, 0.0, -GRAVITY_M_S2], (n, 1)),
                             np.zeros((n, 3))))
        est.process(HeadingSample(1.0, 0.5))
        assert est.initialized
        return est

    def with_enabled(flag):
        return dataclasses.replace(FilterConfig(), **{kind: dataclasses.replace(getattr(FilterConfig(), kind),
                                                                                enabled=flag)})

    out = aligned(with_enabled(True)).process(EXAMPLES[kind])
    assert [(s.source, s.reason) for s in out] in ([(kind, "")], [(kind, "gate")])
    assert [(s.source, s.reason) for s in aligned(with_enabled(False)).process(EXAMPLES[kind])] == [(kind, "disabled")]


def test_the_one_pass_attitude_and_heading_rows_are_the_general_models():
    """attitude.euler_rows and heading.yaw_row (the per-sample paths, 10–50 Hz) give the
    floats of the general model (common.dcm → euler_of / euler_jacobian): the same
    operations — attitude exactly, heading to the last bits (its trigonometry is libm's,
    math.*, which rounds atan2/asin/tan differently from numpy for some inputs; both of the
    estimator's heading paths use it). Random attitudes up to ±88° of pitch, quaternions
    slightly off unit norm (between normalisations), the gimbal clip."""
    from adaptnav.fusion.aiding.common import dcm, euler_jacobian, euler_of

    rng = np.random.default_rng(7)
    for k in range(3000):
        e = rng.uniform(-math.pi, math.pi, 3)
        e[1] *= 0.49
        x = initial_nominal(rng.normal(size=3), rng.normal(size=3), euler_to_quat(*e))
        x[6:10] *= 1.0 + 1e-6 * rng.normal()
        if k == 0:
            x[6:10] = (math.sqrt(0.5), 0.0, math.sqrt(0.5) * 1.0000001, 0.0)  # pitch past 90°: clipped
        R = dcm(x)
        roll, pitch, yaw, m_inv = attitude.euler_rows(x)
        assert np.array_equal(np.array([roll, pitch, yaw]), euler_of(R))
        assert np.array_equal(np.array(m_inv), euler_jacobian(R))
        psi, h_x, h_y = heading.yaw_row(x)
        np.testing.assert_allclose(psi, euler_of(R)[2], rtol=1e-15, atol=1e-15)
        np.testing.assert_allclose((h_x, h_y), euler_jacobian(R)[2, :2], rtol=1e-13, atol=1e-15)
        assert euler_jacobian(R)[2, 2] == 1.0
    m = attitude.measure(AttitudeSample(0.0, 0.1, -0.2, 3.1), x, 0.01, 0.03)  # the last state
    assert np.array_equal(m.H[:, 6:9], euler_jacobian(R)) and np.array_equal(m.h, euler_of(R))
    assert np.array_equal(m.innovation(), wrap_angle(np.array([0.1, -0.2, 3.1]) - euler_of(R)))
