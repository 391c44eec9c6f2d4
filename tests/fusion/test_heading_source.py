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
    """Legs of 130 s joined by 180° turns of 35 s (the AUV generator's profile), alternately
    left and right, rad, wrapped; exact at any time (a shifted clock is a shifted profile)."""
    t = np.asarray(t_s, dtype=float)
    n = np.floor(t / 165.0)
    phase = t - 165.0 * n
    done = np.where(n % 2 == 1, math.pi, 0.0)  # the completed turns: +π, −π, +π, ...
    turning = np.clip(phase - 130.0, 0.0, 35.0) * math.pi / 35.0 * np.where(n % 2 == 0, 1.0, -1.0)
    return (0.3 + done + turning + math.pi) % (2 * math.pi) - math.pi


def _judge(errors, seed: int, duration_s: float = 360.0, lag_s: float = 0.0) -> tuple[HeadingSource, list]:
    """Feed a source with ``errors`` (sim.navgrade.AhrsErrors) at 10 Hz against a gyro heading
    that is the truth plus a navigation-grade drift (0.01 °/h); the decisions over time.
    ``lag_s``: the source's clock is that much late against the IMU's (its heading at ``t`` is
    the truth at ``t − lag_s``)."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, duration_s, 0.1)
    yaw = _lawnmower_yaw(t)
    lagged = _lawnmower_yaw(t - lag_s)
    euler = np.column_stack([0.01 * rng.standard_normal(len(t)), 0.02 + 0.01 * rng.standard_normal(len(t)), lagged])
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


def test_a_time_offset_between_the_source_and_the_imu_is_learned_from_the_turns():
    # an INS's heading stamped 50 ms late against the FOG (two clocks mapped onto one): 0.26°
    # off in the turns, which without the offset would read as a compass's variability
    hs, decisions = _judge(ins_ahrs_errors(LAT_DEG), seed=4, lag_s=0.05, duration_s=310.0)  # ends in a turn
    assert hs.lag_s == pytest.approx(-0.05, abs=0.01)
    assert all(d is not None for d in decisions[int(AttitudeConfig().learn_min_s * 10) + 1:])
    # the heading fused is the source's shifted to its time stamp: the truth there is the
    # source's plus 50 ms of the turn (−π/35 rad/s, the second turn is to the left)
    assert hs.rate_rad_s == pytest.approx(-math.pi / 35.0, rel=0.01)
    assert abs(hs.heading_rad(0.0) - 0.05 * (-math.pi / 35.0)) < math.radians(0.05)
