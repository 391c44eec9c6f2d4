"""What the ATTITUDE heading is worth next to a navigation-grade INS, learned from its
variability against the gyro (fusion/aiding/attitude.py HeadingSource): an INS-class heading
(PHINS/SPRINT) is recognised and fused with its class's accuracy, a magnetic one never;
the error models are the generator's (sim/navgrade.py) on a lawnmower's heading profile."""
from __future__ import annotations

import math

import numpy as np
import pytest

from adaptnav.fusion.aiding.attitude import HeadingSource
from adaptnav.fusion.config import AttitudeConfig
from adaptnav.sim.navgrade import COMPASS_AHRS, ahrs_attitude, ins_ahrs_errors

LAT_DEG = 59.4


def _lawnmower_yaw(t_s: np.ndarray) -> np.ndarray:
    """Legs of 130 s joined by 180° turns of 35 s (the AUV generator's profile), rad, wrapped."""
    yaw = np.zeros_like(t_s)
    heading, t_prev = 0.3, t_s[0]
    for i, t in enumerate(t_s):
        phase = t % 165.0
        if phase >= 130.0:  # turning at π/35 rad/s, alternately left and right
            heading += (-1) ** int(t // 165.0) * math.pi / 35.0 * (t - t_prev)
        yaw[i] = heading
        t_prev = t
    return (yaw + math.pi) % (2 * math.pi) - math.pi


def _judge(errors, seed: int, duration_s: float = 360.0) -> tuple[HeadingSource, list]:
    """Feed a source with ``errors`` (sim.navgrade.AhrsErrors) at 10 Hz against a gyro heading
    that is the truth plus a navigation-grade drift (0.01 °/h); the decisions over time."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, duration_s, 0.1)
    yaw = _lawnmower_yaw(t)
    euler = np.column_stack([0.01 * rng.standard_normal(len(t)), 0.02 + 0.01 * rng.standard_normal(len(t)), yaw])
    src = ahrs_attitude(t, euler, errors, rng)[:, 2]
    gyro = yaw + math.radians(0.01 / 3600.0) * t + 0.7  # any constant: the gyro heading is relative
    hs = HeadingSource(AttitudeConfig(), math.radians(LAT_DEG))
    decisions = []
    for k in range(len(t)):
        hs.observe(1000.0 + t[k], float(src[k]), float(gyro[k]))
        decisions.append(hs.r_rad2(1000.0 + t[k]))
    return hs, decisions


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_an_ins_class_heading_is_recognised_and_fused_with_its_class_accuracy(seed):
    cfg = AttitudeConfig()
    hs, decisions = _judge(ins_ahrs_errors(LAT_DEG), seed)
    # nothing is decided before learn_min_s of data
    assert all(d is None for d in decisions[: int(cfg.learn_min_s * 10) - 1])
    # then an INS's heading throughout, turns included
    assert all(d is not None for d in decisions[int(cfg.learn_min_s * 10) + 1:])
    # the variance fused is the class's accuracy at this latitude (0.05° sec L), not the
    # milli-degree variability the gyro sees: a constant offset does not show against it
    floor = (cfg.ins_sigma_yaw_rad / math.cos(math.radians(LAT_DEG))) ** 2
    assert decisions[-1] == pytest.approx(floor)
    assert math.degrees(math.sqrt(hs.var_rad2)) < 0.02


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_a_magnetic_heading_is_never_fused_next_to_a_navigation_grade_gyro(seed):
    hs, decisions = _judge(COMPASS_AHRS, seed)
    assert all(d is None for d in decisions)
    assert math.degrees(math.sqrt(hs.var_rad2)) > 0.1


def test_a_source_that_starts_to_vary_is_dropped_and_a_repeated_time_changes_nothing():
    cfg = AttitudeConfig()
    hs = HeadingSource(cfg, math.radians(LAT_DEG))
    rng = np.random.default_rng(7)
    t = 0.0
    for _ in range(600):  # a minute of an INS's heading across ±180°
        hs.observe(t, math.remainder(math.pi - 0.001 + 1e-4 * rng.standard_normal(), 2 * math.pi), math.pi - 0.001)
        t += 0.1
    assert hs.r_rad2(t) is not None
    before = (hs.mean_rad, hs.var_rad2)
    hs.observe(t - 0.1, 1.0, 0.0)  # a re-fusion of the past sees a sample again: ignored
    assert (hs.mean_rad, hs.var_rad2) == before
    for _ in range(600):  # then 0.5° of noise against the gyro (a compass behind it)
        hs.observe(t, math.pi - 0.001 + math.radians(0.5) * rng.standard_normal(), math.pi - 0.001)
        t += 0.1
    assert hs.r_rad2(t) is None
