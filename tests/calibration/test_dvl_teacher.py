"""The DVL as teacher (calibration/dvl_teacher.py): k_V and the flow angle learned from the DVL
while it has lock, releases that name their teacher, the model held through a DVL outage."""
import math

import numpy as np
import pytest

from adaptnav.calibration.dvl_teacher import DvlWaterVelocity, teach
from adaptnav.calibration.mstep import MStepOptions
from adaptnav.fusion.motion_model import MotionParams


def test_teacher_recovers_k_v_variances_and_flow_angle_from_rows():
    # GIVEN rows drawn from a known model (k_V 0.92, σ_Vv 0.04, sway σ 0.03, flow angle tan α 0.07:
    # the body heave is 0.07 × the surge the DVL measures, not × the commanded speed)
    rng = np.random.default_rng(5)
    T = 400
    v = rng.choice([1.0, 1.5, 2.0], T)
    w = rng.normal(0.0, 0.02, T)
    V = 0.92 * v + 0.04 * v * rng.standard_normal(T)
    S = 0.03 * rng.standard_normal(T)
    H = 0.07 * V + 0.005 * rng.standard_normal(T)
    # WHEN the teacher fits them from the default model
    res = teach(MotionParams(), v, w, V, S, H, np.ones(T), MStepOptions(prior_tau=math.inf))
    # THEN it finds them, says the DVL taught each, and the fit is more likely than the start
    assert res.params.k_v == pytest.approx(0.92, abs=0.006)
    assert math.sqrt(res.params.var_vv) == pytest.approx(0.04, rel=0.15)
    assert math.sqrt(res.params.var_s) == pytest.approx(0.03, rel=0.1)
    assert res.params.heave_per_surge == pytest.approx(0.07, abs=0.002)
    assert res.teachers["k_v"] == "DVL" and res.ll_new > res.ll_old


def test_teacher_learns_the_turn_speed_loss_with_k_v():
    # GIVEN legs (yaw rate ~0) and turns (±0.1 rad/s) of a vehicle that loses speed in turns:
    # V = 0.95 v (1 − 3 w²), 3 % slower at 0.1 rad/s
    rng = np.random.default_rng(7)
    T = 400
    v = np.full(T, 1.5)
    w = np.where(rng.random(T) < 0.2, rng.choice([-0.1, 0.1], T), rng.normal(0.0, 0.01, T))
    V = 0.95 * v * (1.0 - 3.0 * w * w) + 0.01 * rng.standard_normal(T)
    # AND that skids in turns: sway −0.25 v w (to port in a starboard turn) + 4 mm/s of noise,
    # seen by a DVL whose head is misaligned by −0.4° (a crab of −0.7 % of the surge)
    S = -0.007 * V - 0.25 * v * w + 0.004 * rng.standard_normal(T)
    H = np.zeros(T)
    res = teach(MotionParams(var_vv=1e-4, var_v1=1e-5), v, w, V, S, H, np.ones(T),
                MStepOptions(prior_tau=math.inf))
    # THEN both the speed scale of the legs and the loss in turns, taught by the DVL
    assert res.params.k_v == pytest.approx(0.95, abs=0.002)
    assert res.params.turn_speed_loss == pytest.approx(3.0, abs=0.3)
    assert res.teachers["turn_speed_loss"] == "DVL"
    # AND the skid, with the sway noise left once it is removed (not the skid's spread)
    assert res.params.sway_per_turn == pytest.approx(-0.25, abs=0.01)
    assert res.params.sway_per_surge == pytest.approx(-0.007, abs=0.001)
    assert math.sqrt(res.params.var_s) == pytest.approx(0.004, rel=0.15)
    # AND one scale for legs and turns (the model without the term) is slower than the legs
    flat = teach(MotionParams(var_vv=1e-4, var_v1=1e-5), v, w, V, S, H, np.ones(T),
                 MStepOptions(prior_tau=math.inf), fit_turn_loss=False)
    assert flat.params.turn_speed_loss == 0.0 and flat.params.k_v < 0.95 - 0.003


def test_teacher_holds_the_turn_speed_loss_on_a_straight_line():
    # no turns: the rows cannot tell a turn's cost, κ stays as it was and k_V is fitted with it
    rng = np.random.default_rng(8)
    T = 200
    v = np.full(T, 1.5)
    w = rng.normal(0.0, 0.002, T)
    V = 0.95 * v + 0.01 * rng.standard_normal(T)
    res = teach(MotionParams(var_vv=1e-4, var_v1=1e-5, turn_speed_loss=2.0), v, w, V, np.zeros(T) + 0.01,
                np.zeros(T), np.ones(T), MStepOptions(prior_tau=math.inf))
    assert res.params.turn_speed_loss == 2.0 and "turn_speed_loss" not in res.teachers
    assert any(n.startswith("held turn_speed_loss") for n in res.notes)
    assert "sway_per_turn" not in res.teachers and any(n.startswith("held sway_per_turn") for n in res.notes)
    assert res.params.k_v == pytest.approx(0.95, abs=0.002)


def test_teacher_holds_k_v_when_the_speeds_do_not_inform_it():
    # a vehicle at rest: the rows say nothing about the speed per RPM
    rng = np.random.default_rng(1)
    T = 100
    v = np.zeros(T)
    res = teach(MotionParams(), v, np.zeros(T), 0.01 * rng.standard_normal(T), 0.01 * rng.standard_normal(T),
                np.zeros(T), np.ones(T))
    assert res.params.k_v == 1.0 and "k_v" not in res.teachers
    assert any(n.startswith("held k_v") for n in res.notes)


def test_water_velocity_removes_current_and_lever_arm():
    wv = DvlWaterVelocity(lever_arm_b_m=(0.5, 0.0, 0.0))
    # heading east, current 0.1 m/s north-east each, turning at 0.1 rad/s: the head sees the
    # body's surge 1.5 plus ω × l = 0.05 to starboard, plus the current (0.1 along, −0.1 across)
    body = wv.body((1.5 + 0.1, 0.05 - 0.1, 0.0), False, math.pi / 2, 0.1, (0.1, 0.1))
    assert body == pytest.approx([1.5, 0.0, 0.0], abs=1e-12)
    # water track is already relative to the water: no current removed
    assert wv.body((1.5, 0.05, 0.0), True, math.pi / 2, 0.1, (0.1, 0.1)) == pytest.approx([1.5, 0.0, 0.0])


@pytest.fixture(scope="module")
def change_replay(tmp_path_factory):
    """10 min with a DVL, no USBL, k_V 1.0 → 0.9 at 3 min; the calibrator (inline) learns."""
    from adaptnav.service.runtime import replay as rp

    inp = rp.open_scenario("short", ["duration_s=600", "environment.change_at_s=180", "dvl.enabled=true",
                                     "usbl.enabled=false", "seed=11"])
    cfg = rp.build_config(inp.scenario)
    return rp.replay(inp, cfg, tmp_path_factory.mktemp("dvl_teacher"), calibrate=True, progress=False,
                     plots=False, calibrator_location="inline")


def test_dvl_teacher_recovers_k_v_after_a_change(change_replay):
    import csv

    rows = list(csv.DictReader(open(change_replay.out_dir / "params.csv")))
    accepted = [r for r in rows if r["accepted"] in ("1", "True", "true")]
    before = [float(r["k_v"]) for r in accepted if 120.0 <= float(r["t_s"]) < 180.0]
    after = [float(r["k_v"]) for r in accepted if float(r["t_s"]) >= 540.0]
    assert before and after
    # GIVEN no position fix after the start, WHEN the DVL teaches, THEN k_V follows 1.0 → 0.9
    assert all(abs(k - 1.0) < 0.03 for k in before)
    assert all(abs(k - 0.9) < 0.02 for k in after)
    # AND the releases say the DVL taught them
    assert all("from the DVL" in r["reason"] for r in accepted if float(r["t_s"]) >= 180.0)
