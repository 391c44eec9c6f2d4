"""A real ArduSub autopilot (software in the loop) driven freely: navigate on what it sends.

``../shared/data/mavlink/ardusub-sitl-freedrive.tlog`` (see its README): RAW_IMU and
ATTITUDE at 50 Hz, pressure, thruster PWM; truth in SIM_STATE. No DVL, and the simulated
GNSS is ignored under water, so while submerged the position comes from the consumer IMU
and the thruster outputs through the motion model (the vehicle's thrust → speed calibration
in ``deploy/vehicles/bluerov2-sitl.toml``).
"""
from pathlib import Path

import pytest

from adaptnav.service.runtime.replay import build_config, open_log, replay

from .freedrive import FREEDRIVE, at_default_rates, score

PROFILE = Path(__file__).resolve().parents[2] / "deploy" / "vehicles" / "bluerov2-sitl.toml"


@pytest.mark.realdata
def test_freedrive_submerged_error_within_5_percent_of_distance_and_15_m(tmp_path):
    if not FREEDRIVE.is_file():
        pytest.skip(f"real data absent: {FREEDRIVE}")
    cfg = build_config(None, PROFILE)
    result = replay(open_log(FREEDRIVE), cfg, tmp_path, progress=False, plots=False)
    s = score(tmp_path)
    # THEN the heading was not seeded from ArduSub's pre-alignment yaw (0°): no divergence,
    # and the error at the last submerged epoch is ≤ 5 % of the distance, ≤ 15 m at worst
    assert s["distance_travelled_m"] > 150.0
    assert s["end_error_percent"] <= 5.0, s
    assert s["max_error_submerged_m"] <= 15.0, s
    # AND the consumer IMU was recognised from its 1 mg / 1 mrad/s quantisation
    f = result.summary["filter"]
    assert f["imu_grade"] == "consumer" and f["imu_quantized"]
    # AND the solution was valid while submerged (nothing says its covariance lies)
    assert s["valid_fraction_submerged"] > 0.9, s


@pytest.mark.realdata
def test_freedrive_with_the_defaults_is_honest_where_it_says_valid(tmp_path):
    """The class without a vehicle profile: the embedded thrust table is another vehicle's."""
    if not FREEDRIVE.is_file():
        pytest.skip(f"real data absent: {FREEDRIVE}")
    result = replay(open_log(FREEDRIVE), build_config(None, None), tmp_path, progress=False, plots=False)
    s = score(tmp_path)
    assert s["end_error_percent"] <= 5.0 and s["max_error_submerged_m"] <= 15.0, s
    # THEN the motion model is taken for what it is on this vehicle ...
    assert result.summary["motion_prior"].startswith("uncalibrated"), result.summary["motion_prior"]
    # ... and where the solution says valid, the truth is inside its 99 % ellipse about as often
    # as a consistent filter's is (1 % outside; 2 % allowed: 10 Hz epochs are far from
    # independent); with the calibrated σ of the embedded table 5.9 % were outside, 5–6 m off at
    # σ 1.7 m
    assert s["valid_outside_99_fraction"] <= 0.02, s
    # ... and valid while submerged: ArduSub's simulator streams its 10 Hz barometer at 20 Hz,
    # each reading twice; fused twice, the depth failed its innovation test (nis:depth) and the
    # solution was invalid for 55 % of the submerged time
    assert s["valid_fraction_submerged"] >= 0.95, s
    depth = result.summary["message_types"]["SCALED_PRESSURE2"]
    assert depth["samples"] == pytest.approx(depth["messages"] / 2, rel=0.01), depth


@pytest.mark.realdata
def test_at_default_stream_rates_the_attitude_drives_the_strapdown_and_says_valid_only_where_it_is(tmp_path):
    """The same autopilot logged as a ground station does by default (RAW_IMU and thruster outputs
    at 2 Hz, ATTITUDE at 10 Hz: :data:`tests.fusion.freedrive.DEFAULT_RATES_HZ`, a real BlueROV2
    log's): no IMU to integrate, the attitude's increments drive the strapdown."""
    if not FREEDRIVE.is_file():
        pytest.skip(f"real data absent: {FREEDRIVE}")
    log = at_default_rates(FREEDRIVE, tmp_path / "default_rates.tlog")
    # WHEN replayed with the vehicle's calibrated motion model (its profile)
    result = replay(open_log(log), build_config(None, PROFILE), tmp_path / "profile", progress=False, plots=False)
    s = score(tmp_path / "profile", log)
    # THEN it navigates on the attitude and the thrust: the 5 % / 15 m, valid under water,
    # the truth inside the 99 % ellipse where it says valid (measured: 2.2 %, 4.4 m, 0 outside;
    # 4.3 %, 8.7 m before the profile's linear thruster curve and coast, stop 28)
    assert result.summary["filter"]["imu_grade"] == "attitude"
    assert s["end_error_percent"] <= 5.0 and s["max_error_submerged_m"] <= 15.0, s
    assert s["valid_fraction_submerged"] > 0.9 and s["valid_outside_99_fraction"] <= 0.02, s
    # AND with the defaults (a thrust table nobody calibrated for this vehicle: 1.7× its speed, 24 %
    # off at the end) the track is kept but called valid only while the surface fix still holds it
    replay(open_log(log), build_config(None, None), tmp_path / "defaults", progress=False, plots=False)
    s = score(tmp_path / "defaults", log)
    assert s["valid_fraction_submerged"] <= 0.05 and s["valid_outside_99_fraction"] <= 0.02, s


@pytest.mark.realdata
def test_an_imu_at_10_hz_is_integrated_when_the_motion_model_is_nobody_s_calibration(tmp_path):
    """A ground station that asked for 10 Hz (RAW_IMU, ATTITUDE, thrust, pressure): with a
    motion model calibrated for the vehicle the attitude drives the strapdown (its instants are
    not increments: filter.alignment.min_imu_rate_hz 20 Hz), but with the defaults' embedded table
    nothing would check its scale there — the accelerometer does when the IMU is integrated
    (motion.uncalibrated_min_imu_rate_hz = 8). Measured: 1.86 % of 186 m, max 7.4 m, valid
    throughout; attitude-driven, as before: 22.8 %, 44 m."""
    if not FREEDRIVE.is_file():
        pytest.skip(f"real data absent: {FREEDRIVE}")
    rates = {name: 10.0 for name in ("RAW_IMU", "SCALED_IMU", "SCALED_IMU2", "SCALED_IMU3", "HIGHRES_IMU",
                                     "SERVO_OUTPUT_RAW", "SCALED_PRESSURE", "SCALED_PRESSURE2")}
    log = at_default_rates(FREEDRIVE, tmp_path / "10hz.tlog", rates_hz=rates)
    result = replay(open_log(log), build_config(None, None), tmp_path / "defaults", progress=False, plots=False)
    s = score(tmp_path / "defaults", log)
    assert result.summary["motion_prior"].startswith("uncalibrated")
    assert result.summary["filter"]["imu_grade"] == "consumer"  # integrated, not attitude-driven
    assert s["end_error_percent"] <= 5.0 and s["max_error_submerged_m"] <= 15.0, s
    assert s["valid_fraction_submerged"] > 0.9 and s["valid_outside_99_fraction"] <= 0.02, s
    # AND with the vehicle's profile the same log is attitude-driven, as before
    result = replay(open_log(log), build_config(None, PROFILE), tmp_path / "profile", progress=False, plots=False)
    assert result.summary["filter"]["imu_grade"] == "attitude"


@pytest.mark.realdata
def test_at_default_stream_rates_with_an_underwater_gps_the_defaults_navigate(tmp_path):
    """... and with an underwater GPS (fixes every 2 s, σ 1 m, from the truth; a 60 s outage):
    the fixes measure the motion and calibrate the thrust's scale, which then carries the outage."""
    if not FREEDRIVE.is_file():
        pytest.skip(f"real data absent: {FREEDRIVE}")
    log = at_default_rates(FREEDRIVE, tmp_path / "ugps.tlog", ugps_period_s=2.0, ugps_gap_s=(150.0, 210.0))
    replay(open_log(log), build_config(None, None), tmp_path / "out", progress=False, plots=False)
    s = score(tmp_path / "out", log)
    # measured: max 3.0 m, valid throughout (the scale calibrated by the fixes: k_speed σ under
    # filter.attitude_driven.calibrated_sigma_k_speed; 86 % without that rule), none outside its ellipse
    assert s["max_error_submerged_m"] <= 5.0 and s["rms_error_submerged_m"] <= 2.0, s
    assert s["valid_fraction_submerged"] >= 0.95 and s["valid_outside_99_fraction"] <= 0.02, s


@pytest.mark.realdata
def test_at_default_stream_rates_with_a_dvl_the_defaults_navigate(tmp_path):
    """... and with a DVL (BlueOS's VISION_POSITION_DELTA at 5 Hz, σ 1 cm/s, from the truth): the
    velocity over ground is measured, whatever the thrust table."""
    if not FREEDRIVE.is_file():
        pytest.skip(f"real data absent: {FREEDRIVE}")
    log = at_default_rates(FREEDRIVE, tmp_path / "dvl.tlog", dvl_period_s=0.2)
    result = replay(open_log(log), build_config(None, None), tmp_path / "out", progress=False, plots=False)
    s = score(tmp_path / "out", log)
    # measured: end 0.12 %, max 0.86 m, valid throughout, none outside its ellipse
    assert result.summary["filter"]["imu_grade"] == "attitude"
    assert s["end_error_percent"] <= 1.0 and s["max_error_submerged_m"] <= 2.0, s
    assert s["valid_fraction_submerged"] >= 0.95 and s["valid_outside_99_fraction"] <= 0.02, s


@pytest.mark.realdata
def test_a_dvl_sent_as_odometry_is_a_dvl(tmp_path):
    """The Water Linked DVL extension's ODOMETRY mode (a body velocity, no pose, system 255):
    the same DVL as above, sent that way, navigates as well; it was ignored as "the
    autopilot's own estimate" (the freedrive then ended 22.8 % off)."""
    if not FREEDRIVE.is_file():
        pytest.skip(f"real data absent: {FREEDRIVE}")
    from tests.service.mavlink_wire import dvl_as_odometry

    log = dvl_as_odometry(at_default_rates(FREEDRIVE, tmp_path / "dvl.tlog", dvl_period_s=0.2), tmp_path / "odo.tlog")
    result = replay(open_log(log), build_config(None, None), tmp_path / "out", progress=False, plots=False)
    s = score(tmp_path / "out", log)
    odometry = result.summary["message_types"]["ODOMETRY"]
    assert odometry["status"] == "used" and odometry["samples"] == odometry["messages"] > 1000, odometry
    assert s["end_error_percent"] <= 1.0 and s["max_error_submerged_m"] <= 2.0, s
    assert s["valid_fraction_submerged"] >= 0.95 and s["valid_outside_99_fraction"] <= 0.02, s

