"""ServiceConfig: the shipped deploy config loads, overrides work, errors name the key."""
from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import pytest

from adaptnav.fusion.motion_model import MotionParams
from adaptnav.fusion.typed_config import ConfigError
from adaptnav.service.config import ServiceConfig, config_dict, load_config

DEPLOY_TOML = Path(__file__).resolve().parents[2] / "deploy" / "adaptnav.toml"


def _flat(d, prefix=""):
    out = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flat(v, f"{prefix}{k}."))
        elif isinstance(v, list):
            out.update({f"{prefix}{k}[{i}]": x for i, x in enumerate(v)})
            out[f"{prefix}{k}#"] = len(v)
        else:
            out[prefix + k] = v
    return out


def test_deploy_config_loads_and_matches_defaults():
    cfg = load_config(DEPLOY_TOML)
    # the documented file states the defaults: loading it changes nothing
    got, want = _flat(config_dict(cfg)), _flat(config_dict(ServiceConfig()))
    assert got.keys() == want.keys()
    for key, value in want.items():
        assert got[key] == (pytest.approx(value, rel=1e-12, nan_ok=True) if isinstance(value, float) else value), key
    assert cfg.outputs.nav_rate_hz == 10.0 and cfg.outputs.health_rate_hz == 1.0
    assert cfg.zenoh.mode == "peer" and cfg.zenoh.scouting is False
    assert isinstance(cfg.motion.params0, MotionParams)


def test_learned_velocity_updates_on_the_output_epochs_are_named(caplog):
    """Allowed, but each would delay an epoch's nav state: the warning says so and where
    they would lie between the epochs."""
    with caplog.at_level("WARNING", logger="adaptnav.service.config"):
        load_config(DEPLOY_TOML, [])  # 1 Hz at +0.05 s, 10 Hz epochs: between them
        assert "phase_s" not in caplog.text
        load_config(DEPLOY_TOML, ["outputs.nav_rate_hz=20"])
    assert "phase_s = 0.05 s puts updates at or next to the output epochs" in caplog.text
    assert "0.025 s lies between" in caplog.text
    caplog.clear()
    with caplog.at_level("WARNING", logger="adaptnav.service.config"):
        load_config(DEPLOY_TOML, ["outputs.nav_rate_hz=20", "filter.learned_velocity.phase_s=0.025"])
        load_config(DEPLOY_TOML, ["outputs.nav_rate_hz=20", "filter.learned_velocity.enabled=false"])
    assert "phase_s" not in caplog.text
    with caplog.at_level("WARNING", logger="adaptnav.service.config"):  # 3 ms after each epoch
        load_config(DEPLOY_TOML, ["filter.learned_velocity.phase_s=0.003"])
    assert "phase_s = 0.003 s puts updates at or next to the output epochs" in caplog.text


def test_overrides_typed_and_nested(tmp_path):
    cfg = load_config(DEPLOY_TOML, ["zenoh.mode=client", 'zenoh.connect=["tcp/10.0.0.1:7447"]',
                                    "motion.params0.k_v=1.2", "mavlink.enabled=true",
                                    "mavlink.convert.thrusters.curve.neutral_us=1490",
                                    f'state_dir="{tmp_path}"'])
    assert cfg.zenoh.mode == "client" and cfg.zenoh.connect == ("tcp/10.0.0.1:7447",)
    assert cfg.motion.params0.k_v == 1.2
    assert cfg.mavlink.enabled is True
    assert cfg.mavlink.convert.thrusters.curve.neutral_us == 1490.0
    assert cfg.state_dir == str(tmp_path)


@pytest.mark.parametrize("override, needle", [
    ("zenoh.mode=satellite", "zenoh.mode"),
    ("zenoh.mode=client", "connect"),
    ("outputs.nav_rate_hz=0", "nav_rate_hz"),
    ("motion.params0.var_vv=-1", "var_vv"),
    ("vehicle.nam=x", "nam"),
    ("mavlink.output_rate_hz=1", "output_rate_hz"),
    ("filter.depth.sigma_mm=1", "sigma_mm"),
    ('zenoh.listen=["localhost"]', "endpoint"),
])
def test_bad_values_name_the_key(override, needle):
    with pytest.raises(ConfigError, match=needle):
        load_config(None, [override])


@pytest.mark.parametrize("url, why", [
    ("bogus:foo", "port 'foo'"),                      # a scheme typo: pymavlink's "HOST:PORT" as UDP
    ("udpin:0.0.0.0:99999", "port '99999'"),
    ("udpout:192.168.2.1", "udpout needs HOST:PORT"),
    ("serial:/dev/ttyACM0:fast", "baud 'fast'"),
    ("/dev/ttyACM0,115k", "baud '115k'"),
    ("", "empty"),
])
def test_a_mavlink_url_that_can_never_be_opened_is_refused_at_load(url, why):
    """It was accepted and retried forever at run time with pymavlink's "invalid literal for
    int()"; the forms that can be opened (and a device that is only missing now) still load."""
    with pytest.raises(ConfigError, match="mavlink") as e:
        load_config(None, [f'mavlink.url="{url}"'])
    assert why in str(e.value), str(e.value)


@pytest.mark.parametrize("url", ["udpin:127.0.0.1:14550", "udpout:192.168.2.1:14550", "tcp:127.0.0.1:5760",
                                 "udpin:[::1]:14550", "serial:/dev/ttyACM0:115200", "serial:/dev/ttyUSB9",
                                 "/dev/ttyACM0,57600", "/dev/ttyACM0", "COM3", "127.0.0.1:14550"])
def test_the_mavlink_url_forms_the_bridge_opens_load(url):
    assert load_config(None, [f'mavlink.url="{url}"']).mavlink.url == url


def test_bad_file(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text("[zenoh\nmode = 'peer'\n")
    with pytest.raises(ConfigError, match="TOML"):
        load_config(bad)
    with pytest.raises(ConfigError, match="not found"):
        load_config(tmp_path / "missing.toml")


@pytest.mark.parametrize("override, key", [
    ("outputs.nav_rate_hz=inf", "nav_rate_hz"),       # the runner died
    ("outputs.nav_rate_hz=1e308", "nav_rate_hz"),     # the runner hung
    ("filter.gate_sigma=nan", "gate_sigma"),          # every aid rejected
    ("filter.gate_sigma=inf", "gate_sigma"),          # nothing gated
    ("health.queue_size=0", "queue_size"),            # an unbounded queue
    ("calibrator.queue_size=-1", "queue_size"),
    ("health.sensor_timeout_s=nan", "sensor_timeout_s"),
    ("filter.dvl.lever_arm_b_m=[0.0, inf, 0.0]", "lever_arm_b_m"),
    ("filter.max_delay_s=1e9", "max_delay_s"),
    ("persistence.period_s=0", "period_s"),
    ("outputs.rehearsal_lead_s=nan", "rehearsal_lead_s"),
    ("outputs.rehearsal_lead_s=-0.001", "rehearsal_lead_s"),
    ("outputs.rehearsal_lead_s=0.2", "rehearsal_lead_s"),  # its caches cold again by the sample
])
def test_config_refuses_non_finite_and_out_of_range_values_naming_the_key(override, key):
    with pytest.raises(ConfigError, match=key):
        load_config(None, [override])


def test_a_nan_default_may_be_given_as_nan_and_the_shipped_config_loads():
    cfg = load_config(None, ["calibrator.online.origin_lat_deg=nan"])
    assert math.isnan(cfg.calibrator.online.origin_lat_deg)
    load_config(Path(__file__).resolve().parents[2] / "deploy" / "adaptnav.toml")


def _mean_dvl_delta(converter, t_boot_s: float, dt_s: float) -> list:
    """One "mean" VISION_POSITION_DELTA (1 m/s forward over ``dt_s``) from BlueOS's DVL
    (system 255, ``time_usec = 0``: placed by the boot clock of the ATTITUDE just before)."""
    from adaptnav.service.transport.mavlink_convert import mavlink2

    ap, dvl = mavlink2.MAVLink(None, 1, 1), mavlink2.MAVLink(None, 255, 0)
    for mav, msg in ((ap, ap.heartbeat_encode(mavlink2.MAV_TYPE_SUBMARINE, mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                              0, 0, 4)),
                     (ap, ap.attitude_encode(int(t_boot_s * 1000), 0, 0, 0, 0, 0, 0)),
                     (dvl, dvl.vision_position_delta_encode(0, int(dt_s * 1e6), [0, 0, 0], [dt_s, 0, 0], 100.0))):
        out = converter.convert(mav.decode(bytearray(msg.pack(mav))))
    return out


def test_a_mean_dvl_the_filter_would_reject_as_too_late_is_refused_at_load():
    import numpy as np

    from adaptnav.fusion.eskf import Estimator
    from adaptnav.fusion.frames import GRAVITY_M_S2, GeoOrigin
    from adaptnav.fusion.motion_model import RpmSpeedTable
    from adaptnav.fusion.samples import HeadingSample, ImuBatch
    from adaptnav.service.transport.mavlink_convert import MavlinkConverter

    # GIVEN "mean" deltas (valid at mid-interval) and the default 5 s longest interval: a
    # 0.2 Hz DVL's would land 2.5 s in the past, beyond filter.max_delay_s = 1 s
    with pytest.raises(ConfigError, match=r"max_delay_s = 1 s.*raise filter.max_delay_s to 2.5 or lower "
                                          r"mavlink.convert.dvl_max_interval_s to 2"):
        load_config(overrides=['mavlink.convert.dvl_delta="mean"'])
    # WHEN configured as the error says
    cfg = load_config(overrides=['mavlink.convert.dvl_delta="mean"', "mavlink.convert.dvl_max_interval_s=2.0"])
    est = Estimator(cfg.filter, MotionParams(), RpmSpeedTable(), GeoOrigin(math.radians(59.0), math.radians(10.0)))
    t = 10.0 + np.arange(1, 101) / 100.0
    est.process(ImuBatch(t, np.tile([0.0, 0.0, -GRAVITY_M_S2], (100, 1)), np.zeros((100, 3))))
    est.process(HeadingSample(11.0, 0.0))
    assert est.initialized
    t = 11.0 + np.arange(1, 301) / 100.0  # the filter at t = 14 s
    est.process(ImuBatch(t, np.tile([0.0, 0.0, -GRAVITY_M_S2], (300, 1)), np.zeros((300, 3))))
    # THEN the slowest DVL the converter accepts (0.5 Hz: valid 1 s before it arrives) reaches
    # the filter in time (fused or gated, never too late) ...
    conv = MavlinkConverter(cfg.mavlink.convert)
    (dvl,) = _mean_dvl_delta(conv, 14.0, 2.0)
    assert dvl.t_s == pytest.approx(13.0)
    (status,) = est.process(dvl)
    assert status.reason != "too_late" and est.rejected["too_late"] == 0
    # ... and a slower one is refused where it is read, with its reason (counted by the source)
    assert _mean_dvl_delta(conv, 14.0, 2.5) == []
    assert conv.accounting()["VISION_POSITION_DELTA"]["rejected"] == {"dvl_bad_interval": 1}
    # (with the old default it came through and was lost in the filter as too late)
    old = MavlinkConverter(replace(cfg.mavlink.convert, dvl_max_interval_s=5.0))
    (late,) = _mean_dvl_delta(old, 14.0, 2.5)
    assert est.process(late)[0].reason == "too_late"


def test_motion_prior_widens_the_embedded_table_for_an_autopilot_only():
    from adaptnav.fusion.motion_model import MotionParams, RpmSpeedTable
    from adaptnav.service.config import MotionConfig

    embedded = MotionConfig()
    # an autopilot's thrust through the embedded table: surge σ 7 % of speed, sway 0.03 m/s
    p, why = embedded.initial_params(autopilot_thrust=True)
    assert why.startswith("uncalibrated") and p.var_vv == pytest.approx(0.07 ** 2) and p.var_s == pytest.approx(0.03 ** 2)
    assert p.k_v == embedded.params0.k_v and p.var_ww == embedded.params0.var_ww  # nothing else
    # the simulator's or a DVL vehicle's RPM, a vehicle's own table, or said calibrated: as given
    assert embedded.initial_params(autopilot_thrust=False)[0] == embedded.params0
    own = MotionConfig(rpm_table=RpmSpeedTable((0.0, 1000.0), (0.0, 1.0)))
    assert own.initial_params(autopilot_thrust=True) == (own.params0, "calibrated (auto: motion.rpm_table is this vehicle's)")
    assert MotionConfig(prior="calibrated").initial_params(True)[0] == embedded.params0
    # widened, never narrowed: a looser params0 stays as it is
    loose = MotionConfig(prior="uncalibrated", params0=MotionParams(var_vv=0.3 ** 2))
    assert loose.initial_params(False)[0].var_vv == pytest.approx(0.3 ** 2)
    with pytest.raises(ConfigError, match="uncalibrated_sigma_surge"):
        load_config(None, ["motion.uncalibrated_sigma_surge=0"])
    with pytest.raises(ConfigError, match="prior"):
        load_config(None, ["motion.prior=maybe"])


def test_a_simulated_vehicle_is_calibrated_even_behind_a_simulated_autopilot():
    # the demo's daemon gets the simulated AUV's thrust as PWM from a simulated ArduSub: the
    # embedded table is that vehicle's own (taken as uncalibrated, the demo's learned row went
    # ~3 → ~5.5 m)
    from adaptnav.service.runtime.replay import build_config
    from adaptnav.sim.scenario import load_scenario

    cfg = build_config(load_scenario("demo"), None, ["mavlink.enabled=true"])
    assert cfg.motion.initial_params(autopilot_thrust=True) == (cfg.motion.params0, "calibrated (motion.prior)")


def test_a_vehicle_that_may_crab_does_not_take_its_dvl_lateral_for_misalignment():
    from adaptnav.fusion.aiding.dvl import AID

    # an ROV (thrust from an autopilot: ArduSub's vectored frames) resolves "auto" to "free"
    rov, auv = ServiceConfig().resolved(autopilot_thrust=True), ServiceConfig().resolved(autopilot_thrust=False)
    assert rov.filter.dvl.hull_sideslip == "free" and auv.filter.dvl.hull_sideslip == "none"
    assert AID.setup(rov.filter.dvl).calibration.straight_legs is None
    assert AID.setup(auv.filter.dvl).calibration.straight_legs is not None
    # a configured choice is kept
    cfg = ServiceConfig()
    cfg = replace(cfg, filter=replace(cfg.filter, dvl=replace(cfg.filter.dvl, hull_sideslip="none")))
    assert cfg.resolved(autopilot_thrust=True).filter.dvl.hull_sideslip == "none"
    with pytest.raises(ConfigError, match="hull_sideslip"):
        load_config(None, ['filter.dvl.hull_sideslip="torpedo"'])


def test_an_uncalibrated_vehicle_gets_the_wider_k_speed_and_the_thrust_transient():
    from adaptnav.fusion.config import FilterConfig

    # the thrust of an autopilot through the embedded table: uncalibrated (motion.prior auto)
    rov = ServiceConfig().resolved(autopilot_thrust=True).filter
    auv = ServiceConfig().resolved(autopilot_thrust=False).filter
    assert rov.initial.sigma_k_speed == pytest.approx(0.3) and rov.learned_velocity.transient_time_s == 2.0
    assert rov.learned_velocity.skid_sigma_s == 2.0  # the unknown skid in a turn
    assert rov.learned_velocity.heave_sigma_per_vertical_speed == 1.0  # may heave on vertical thrusters
    # a calibrated vehicle keeps the filter's own figures
    base = FilterConfig()
    assert auv.initial.sigma_k_speed == base.initial.sigma_k_speed
    assert auv.learned_velocity.transient_time_s == base.learned_velocity.transient_time_s == 0.0
    assert auv.learned_velocity.skid_sigma_s == base.learned_velocity.skid_sigma_s == 0.0
    assert auv.learned_velocity.heave_sigma_per_vertical_speed == 0.0
    # resolving twice changes nothing
    once = ServiceConfig().resolved(autopilot_thrust=True)
    assert once.resolved(autopilot_thrust=True) == once


def test_a_slowest_imu_rate_the_gap_rule_would_turn_into_all_gaps_is_refused():
    """min_imu_rate_hz 1 with imu_gap_s 0.2: a 5 Hz stream was kept, every interval a gap,
    and the filter never started (no nav state in a whole log, no word why)."""
    from dataclasses import replace

    from adaptnav.fusion.config import FilterConfig

    filt = FilterConfig()
    with pytest.raises(ValueError, match="min_imu_rate_hz"):
        replace(filt, alignment=replace(filt.alignment, min_imu_rate_hz=4.0)).validate()
    replace(filt, alignment=replace(filt.alignment, min_imu_rate_hz=8.0)).validate()
