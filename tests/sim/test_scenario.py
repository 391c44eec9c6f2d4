"""Scenario files and loader: required keys, the survey of issue 2, strict overrides."""
import math

import pytest

from adaptnav.fusion.typed_config import ConfigError
from adaptnav.sim.scenario import available_scenarios, load_scenario

REQUIRED_KEYS = {
    "seed": "5", "duration_s": "600.0", "imu.grade": '"consumer"', "imu.rate_hz": "50.0",
    "dvl.enabled": "true", "usbl.period_s": "30.0", "usbl.lost_after_s": "100.0",
    "current.speed_m_s": "0.2", "current.direction_deg": "90.0",
    "environment.change_at_s": "120.0", "environment.k_v_after": "0.8",
    "motion.sigma_vv_after": "0.2",
}


def _get(obj, dotted):
    for part in dotted.split("."):
        obj = getattr(obj, part)
    return obj


def test_builtin_scenarios_load():
    assert {"survey", "short", "demo"} <= set(available_scenarios())
    for name in ("survey", "short", "demo"):
        assert load_scenario(name).name == name


@pytest.mark.parametrize("key, text", sorted(REQUIRED_KEYS.items()))
def test_required_keys_exist_and_override(key, text):
    s = load_scenario("short", [f"{key}={text}"])
    expected = {"true": True}.get(text, None)
    if expected is None:
        expected = text.strip('"') if text.startswith('"') else float(text)
    assert _get(s, key) == expected


def test_survey_is_the_issue_scenario():
    s = load_scenario("survey")
    assert s.duration_s == 3600 and s.trajectory.pattern == "lawnmower"
    assert s.trajectory.speed_m_s == 1.5
    assert (s.imu.grade, s.imu.rate_hz) == ("tactical", 100.0)
    assert s.heading.enabled and s.heading.sigma_deg == 0.5 and s.depth.enabled
    assert s.current.speed_m_s == 0.1
    assert s.gnss.fix_times_s == (0.0,)
    assert (s.usbl.sigma_m, s.usbl.period_s, s.usbl.lost_after_s) == (2.0, 60.0, 2400.0)
    assert not s.dvl.enabled
    assert s.environment.change_at_s == 1800.0
    before, after = s.params_before(), s.params_after()
    assert before.k_v == 1.0 and after.k_v == 0.9
    assert math.isclose(math.sqrt(before.var_vv), 0.05) and math.isclose(math.sqrt(after.var_vv), 0.15)
    assert before.var_ww == after.var_ww  # only what the change names changes


def test_unknown_override_key_is_a_clear_error():
    with pytest.raises(ConfigError, match=r"unknown key\(s\) in \[usbl\]: perid_s"):
        load_scenario("short", ["usbl.perid_s=10"])
    with pytest.raises(ConfigError, match="unknown key"):
        load_scenario("short", ["sede=3"])


def test_bad_values_are_clear_errors():
    with pytest.raises(ConfigError, match="imu.grade"):
        load_scenario("short", ['imu.grade="military"'])
    with pytest.raises(ConfigError, match="integer"):
        load_scenario("short", ["imu.rate_hz=33.3"])  # step_s × rate must be whole
    with pytest.raises(ConfigError, match="not found"):
        load_scenario("no_such_scenario")
