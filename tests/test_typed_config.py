from dataclasses import dataclass, field
from typing import Literal

import pytest

from adaptnav.fusion.typed_config import ConfigError, as_dict, load_toml


@dataclass(frozen=True)
class Imu:
    grade: Literal["consumer", "tactical", "navigation"] = "tactical"
    rate_hz: float = 100.0

    def validate(self):
        if self.rate_hz <= 0:
            raise ValueError("rate_hz must be > 0")


@dataclass(frozen=True)
class Top:
    seed: int = 0
    imu: Imu = field(default_factory=Imu)
    table: tuple[float, ...] = (1.0, 2.0)


def test_defaults_toml_and_overrides():
    cfg = load_toml(Top, "seed = 3\n[imu]\nrate_hz = 50\n", ["imu.grade=navigation", "table=[1, 5]"])
    assert cfg == Top(seed=3, imu=Imu("navigation", 50.0), table=(1.0, 5.0))
    assert as_dict(cfg)["imu"]["grade"] == "navigation"


@pytest.mark.parametrize("text, overrides, msg", [
    ("sead = 1", [], "unknown key.*sead"),
    ("[imu]\nrate = 1", [], r"unknown key.*\[imu\].*rate"),
    ("", ["imu.grade=mems"], "imu.grade.*not one of"),
    ("", ["seed=1.5"], "seed: expected an integer"),
    ("", ["imu.rate_hz=-1"], "rate_hz must be > 0"),
    ("seed = ", [], "TOML syntax"),
])
def test_errors_name_the_key(text, overrides, msg):
    with pytest.raises(ConfigError, match=msg):
        load_toml(Top, text, overrides)
