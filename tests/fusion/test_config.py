"""The filter configuration is a strict typed tree."""
import pytest

from adaptnav.fusion.config import FilterConfig
from adaptnav.fusion.typed_config import ConfigError, as_dict, build, load_toml

TOML = """
gate_sigma = 4.0
[dvl]
lever_arm_b_m = [0.5, 0.0, 0.2]
[depth]
water_density_kg_m3 = 1000.0
"""


def test_toml_with_overrides_builds_the_tree():
    cfg = load_toml(FilterConfig, TOML, ["learned_velocity.rate_hz=2", "imu.gyro_noise_rad_s_rthz=1e-4"])
    assert cfg.dvl.lever_arm_b_m == (0.5, 0.0, 0.2)
    assert cfg.depth.water_density_kg_m3 == 1000.0
    assert cfg.learned_velocity.rate_hz == 2.0 and cfg.imu.gyro_noise_rad_s_rthz == 1e-4
    assert build(FilterConfig, as_dict(cfg)) == cfg


@pytest.mark.parametrize("text, where", [("[dvl]\nlever_arm = [0, 0, 0]", "dvl"),
                                          ("gate_sigma = -1.0", "gate_sigma"),
                                          ("covariance_step_s = 5.0", "covariance_step_s"),
                                          ("[learned_velocity]\nphase_s = 1.0", "phase_s"),
                                          ("[learned_velocity]\nphase_s = -0.05", "phase_s")])
def test_bad_keys_and_values_are_errors_that_name_them(text, where):
    with pytest.raises(ConfigError, match=where):
        load_toml(FilterConfig, text)


def test_gate_is_the_chi_square_equivalent_of_n_sigma():
    cfg = FilterConfig()
    assert cfg.gate_threshold(1) == pytest.approx(25.0, rel=1e-6)   # 5σ in one dimension
    assert cfg.gate_threshold(3) > cfg.gate_threshold(2) > cfg.gate_threshold(1)
