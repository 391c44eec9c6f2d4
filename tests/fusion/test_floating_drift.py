"""A vehicle floating at the surface before its dive drifts with the water.

Its depth reads as on deck, its thrusters are idle and its IMU is quiet: the rest detector's
zero-velocity update had the drift the surface fixes showed learnt as no current, at a σ of
0.01 m/s, and the dive then carried none: 90 s under water the position was outside its 99 %
ellipse. Where position fixes come they say whether it moves.
"""
import csv

import numpy as np
import pytest

# a minute afloat with surface fixes at 5 Hz (the simulator's receiver, white), 0.1 m/s of
# current at 45°, then the dive and a lawnmower leg with no aid for the horizontal position
FLOAT_THEN_DIVE = ["duration_s=150", "trajectory.start_delay_s=60", "gnss.rate_hz=5", "gnss.sigma_m=2.0",
                   "usbl.enabled=false"]


def _replay(tmp_path, seed, **stationary):
    from dataclasses import replace

    from adaptnav.service.runtime import replay as rp

    inp = rp.open_scenario("short", FLOAT_THEN_DIVE + [f"seed={seed}"])
    cfg = rp.build_config(inp.scenario)
    # the fixes' shared-error floor at half their σ (as at stop 30; the default keeps all of it,
    # which leaves the current learnt afloat less sure and the rest update's error inside a
    # wider ellipse): the mechanism under test is the rest update, not the floor
    cfg = replace(cfg, filter=replace(cfg.filter, gnss=replace(cfg.filter.gnss, correlated_fraction=0.5)))
    if stationary:
        cfg = replace(cfg, filter=replace(cfg.filter, stationary=replace(cfg.filter.stationary, **stationary)))
    out = tmp_path / f"seed_{seed}_{sorted(stationary.items())}"
    rp.replay(inp, cfg, out, progress=False, plots=False)
    with open(out / "trajectory.csv") as f:
        rows = list(csv.DictReader(f))
    at_dive = next(r for r in rows if float(r["t_s"]) >= 60.0)
    current_error = np.hypot(float(at_dive["current_n_m_s"]) - float(at_dive["truth_current_n_m_s"]),
                             float(at_dive["current_e_m_s"]) - float(at_dive["truth_current_e_m_s"]))
    end = rows[-1]
    error_ne = np.array([float(end["north_m"]) - float(end["truth_north_m"]),
                         float(end["east_m"]) - float(end["truth_east_m"])])
    sigma_ne = np.array([float(end["sigma_north_m"]), float(end["sigma_east_m"])])
    return float(current_error), float(np.sum((error_ne / sigma_ne) ** 2))


@pytest.mark.parametrize("seed", [31, 32])
def test_the_drift_afloat_is_learnt_as_current_not_as_rest(tmp_path, seed):
    current_error, end_q = _replay(tmp_path, seed)
    # the rest update on a floating vehicle: the whole 0.1 m/s missed, and 90 s under water
    # the position is outside its 99 % ellipse (χ²₂ 9.21)
    old_current_error, old_end_q = _replay(tmp_path, seed, fix_holdoff_s=0.0)
    assert old_current_error > 0.08 and old_end_q > 9.21, (old_current_error, old_end_q)
    # the fixes' drift is the current (seeds 31–40: within 0.013–0.054 m/s after a minute of
    # 2 m fixes), and the error under water, the uncalibrated speed scale's too, stays inside
    # the ellipse (seeds 31–40: χ² 0.04–0.36; before 30–45)
    assert current_error < 0.06 and end_q < 9.21, (current_error, end_q)


# afloat, the hull also drifts with the wind and the waves (leeway, the top layer's wind and
# Stokes drift): 0.15 m/s towards 200° over the current at depth (0.1 m/s towards 45°), gone
# below 2 m. The surface fixes see current and drift together.
LEEWAY = ["current.surface_drift_speed_m_s=0.15", "current.surface_drift_direction_deg=200"]


def _outside_under_water(tmp_path, seed, correlated_fraction=None):
    """Fraction of the valid epochs below the surface layer outside their 99 % ellipse."""
    from dataclasses import replace

    from adaptnav.service.runtime import replay as rp

    inp = rp.open_scenario("short", FLOAT_THEN_DIVE + LEEWAY + [f"seed={seed}"])
    cfg = rp.build_config(inp.scenario)
    if correlated_fraction is not None:
        cfg = replace(cfg, filter=replace(cfg.filter, gnss=replace(cfg.filter.gnss,
                                                                   correlated_fraction=correlated_fraction)))
    out = tmp_path / f"leeway_{seed}_{correlated_fraction}"
    rp.replay(inp, cfg, out, progress=False, plots=False)
    with open(out / "trajectory.csv") as f:
        rows = [r for r in csv.DictReader(f)
                if r["valid"] in ("1", "True", "true") and float(r["truth_down_m"]) > 2.0]
    err = np.array([[float(r["north_m"]) - float(r["truth_north_m"]),
                     float(r["east_m"]) - float(r["truth_east_m"])] for r in rows])
    sig = np.array([[float(r["sigma_north_m"]), float(r["sigma_east_m"])] for r in rows])
    assert len(rows) > 500
    return float(np.mean(np.sum((err / sig) ** 2, axis=1) > 9.21))


@pytest.mark.parametrize("seed", [33])
def test_a_leeway_seen_afloat_is_not_taken_to_depth_as_a_sure_current(tmp_path, seed):
    # the surface fixes taken as independent learn current + leeway to a few mm/s and carry
    # it under water: seeds 31–36, 98 % of the valid epochs below 2 m outside their ellipse
    assert _outside_under_water(tmp_path, seed, correlated_fraction=0.0) > 0.5
    # a fix's shared error kept (the default) leaves the current afloat unsure (σ 0.23 m/s
    # after the minute): seeds 31–36, none outside (σ_h 27 m at the end against 5–7 m of error)
    assert _outside_under_water(tmp_path, seed) < 0.01
