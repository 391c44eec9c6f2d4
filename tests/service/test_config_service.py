"""ServiceConfig: the shipped deploy config loads, overrides work, errors name the key."""
from __future__ import annotations

import math
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
])
def test_config_refuses_non_finite_and_out_of_range_values_naming_the_key(override, key):
    with pytest.raises(ConfigError, match=key):
        load_config(None, [override])


def test_a_nan_default_may_be_given_as_nan_and_the_shipped_config_loads():
    cfg = load_config(None, ["calibrator.online.origin_lat_deg=nan"])
    assert math.isnan(cfg.calibrator.online.origin_lat_deg)
    load_config(Path(__file__).resolve().parents[2] / "deploy" / "adaptnav.toml")
