"""`adaptnav replay` end to end: MCAP logs written by the simulator's writer, bad input,
truncated files, the in-memory scenario source, comparisons, the calibrator in-process
and a real MAVLink log with corrupt frames."""
from __future__ import annotations

import csv
import json
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from adaptnav.fusion.samples import DepthSample, ImuSample
from adaptnav.fusion.typed_config import as_dict
from adaptnav.service.runtime import replay as rp
from adaptnav.service.cli import main as cli_main
from adaptnav.service.transport.logs import write_mcap
from adaptnav.service.runtime.sources import simulate
from adaptnav.sim.scenario import load_scenario

DATA = Path(__file__).resolve().parents[3] / "shared" / "data"
DURATION_S = 60.0
REQUIRED_TRAJ = ("t_s", "north_m", "east_m", "down_m", "vel_n_m_s", "vel_e_m_s", "vel_d_m_s",
                 "roll_rad", "pitch_rad", "yaw_rad", "sigma_north_m", "sigma_east_m")
REQUIRED_METRICS = ("final_horizontal_error_m", "rms_horizontal_error_m", "distance_travelled_m",
                    "drift_percent_since_fix", "current_error_m_s", "nees_mean", "nees_fraction_in_95")
REQUIRED_SUMMARY = ("messages_read", "samples_used", "corrupt_frames", "rejected_samples", "duration_s",
                    "wall_s", "missing_streams")


@pytest.fixture(scope="module")
def sim60():
    scenario = load_scenario("short", [f"duration_s={DURATION_S}"])
    return scenario, simulate(scenario)


def _metadata(scenario):
    return {"scenario": as_dict(scenario), "scenario_name": scenario.name}


@pytest.fixture(scope="module")
def mcap60(sim60, tmp_path_factory):
    scenario, result = sim60
    path = tmp_path_factory.mktemp("logs") / "short60.mcap"
    counts = write_mcap(path, result.iter_blocks(), _metadata(scenario))
    return path, sum(counts.values())


def _rows(path: Path) -> list[dict]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def _replay(path_or_inp, out, **kw):
    inp = rp.open_log(path_or_inp) if isinstance(path_or_inp, Path) else path_or_inp
    cfg = rp.build_config(inp.scenario)
    return rp.replay(inp, cfg, out, progress=False, plots=kw.pop("plots", False), **kw)


def test_cli_replay_of_a_simulated_log_writes_every_output(mcap60, sim60, tmp_path):
    path, n_messages = mcap60
    scenario, result = sim60
    out = tmp_path / "out"
    assert cli_main(["replay", str(path), "--out", str(out), "--no-progress"]) == 0
    for name in ("trajectory.csv", "aid_status.csv", "params.csv", "metrics.json", "summary.json",
                 "config.json", "track.png", "params.png", "innovations.png"):
        assert (out / name).is_file() and (out / name).stat().st_size > 0, name
    rows = _rows(out / "trajectory.csv")
    assert set(REQUIRED_TRAJ) <= set(rows[0]) and "truth_north_m" in rows[0]
    summary = json.loads((out / "summary.json").read_text())
    assert set(REQUIRED_SUMMARY) <= set(summary)
    assert summary["messages_read"] == n_messages
    assert summary["corrupt_frames"] == 0
    assert summary["duration_s"] == pytest.approx(DURATION_S)
    assert "dvl" in summary["missing_streams"]        # the scenario has no DVL
    metrics = json.loads((out / "metrics.json").read_text())
    assert set(REQUIRED_METRICS) <= set(metrics)
    # the metrics agree with the truth the simulator holds, computed here independently
    last = rows[-1]
    dense = result.dense
    # the truth columns are filled (truth at the nav rate; it arrives after the state of its epoch)
    with_truth = [r for r in rows if r["truth_north_m"]]
    assert len(with_truth) >= 0.95 * len(rows)
    r = with_truth[len(with_truth) // 2]
    j = int(np.argmin(np.abs(dense.t_s - float(r["t_s"]))))
    assert float(r["truth_north_m"]) == pytest.approx(dense.pos_n_m[j, 0], abs=0.05)
    assert float(r["truth_east_m"]) == pytest.approx(dense.pos_n_m[j, 1], abs=0.05)
    i = int(np.argmin(np.abs(dense.t_s - float(last["t_s"]))))
    err = math.hypot(float(last["north_m"]) - dense.pos_n_m[i, 0], float(last["east_m"]) - dense.pos_n_m[i, 1])
    assert metrics["final_horizontal_error_m"] == pytest.approx(err, abs=0.02)
    t_first = float(rows[0]["t_s"])
    sel = (dense.t_s >= t_first) & (dense.t_s <= float(last["t_s"]))
    path_m = np.sum(np.hypot(*np.diff(dense.pos_n_m[sel, :2], axis=0).T))
    assert metrics["distance_travelled_m"] == pytest.approx(path_m, rel=0.01)
    # the filter was configured from the log's scenario metadata
    cfg = json.loads((out / "config.json").read_text())
    assert cfg["filter"]["heading"]["sigma_rad"] == pytest.approx(math.radians(scenario.heading.sigma_deg))
    assert cfg["motion"]["params0"]["k_v"] == scenario.motion.k_v


def test_two_replays_are_byte_identical_and_log_equals_simulator(mcap60, sim60, tmp_path):
    path, _ = mcap60
    scenario, result = sim60
    _replay(path, tmp_path / "a")
    _replay(path, tmp_path / "b")
    inp = rp.ReplayInput(rp.SimSource(scenario, result), scenario, "sim", scenario.duration_s)
    _replay(inp, tmp_path / "c")
    for name in ("trajectory.csv", "aid_status.csv"):
        a = (tmp_path / "a" / name).read_bytes()
        assert len(a.splitlines()) > 100
        assert a == (tmp_path / "b" / name).read_bytes(), name
        assert a == (tmp_path / "c" / name).read_bytes(), name   # readers ≡ simulators


def test_bad_input_replays_to_the_end_with_counters(sim60, tmp_path):
    scenario, result = sim60
    samples = list(result.iter_samples())
    imu_idx = [i for i, s in enumerate(samples) if s.KIND == "imu"]
    bad = list(samples)
    nan_at = imu_idx[2000:5001:1000]                  # 4 NaN IMU samples, in INS mode
    for i in nan_at:
        s = bad[i]
        bad[i] = replace(s, specific_force_b_m_s2=(math.nan, s.specific_force_b_m_s2[1], math.inf))
    dup_at = imu_idx[2500:5000:1000]                  # 3 duplicated IMU samples
    for i in sorted(dup_at, reverse=True):
        bad.insert(i + 1, bad[i])
    # out of order: two IMU samples swapped (inside the re-order window) ...
    j = [i for i, s in enumerate(bad) if s.KIND == "imu"][4200]
    bad[j], bad[j + 1] = bad[j + 1], bad[j]
    # ... and one depth sample 10 s late in the file (beyond the window: fused too late)
    k = next(i for i, s in enumerate(bad) if s.KIND == "depth" and s.t_s >= 40.0)
    late = bad.pop(k)
    at = next(i for i, s in enumerate(bad) if s.t_s >= late.t_s + 10.0)
    bad.insert(at, late)
    path = tmp_path / "bad.mcap"
    write_mcap(path, bad, _metadata(scenario))

    res = _replay(path, tmp_path / "out")
    s = res.summary
    assert s["messages_read"] == len(bad)
    assert s["late_samples"] == 1
    rej = s["rejected_samples"]
    assert rej.get("non_finite", 0) == len(nan_at)
    assert rej.get("duplicate", 0) == len(dup_at)
    assert rej.get("too_late", 0) == 1
    rows = _rows(tmp_path / "out" / "trajectory.csv")
    assert float(rows[-1]["t_s"]) == pytest.approx(DURATION_S)
    assert all(math.isfinite(float(r["north_m"])) for r in rows)
    assert res.metrics["final_horizontal_error_m"] < 20.0


def test_truncated_log_replays_what_is_there(mcap60, tmp_path):
    path, _ = mcap60
    cut = tmp_path / "cut.mcap"
    data = path.read_bytes()
    cut.write_bytes(data[: int(len(data) * 0.6)])
    res = _replay(cut, tmp_path / "out")
    s = res.summary
    assert s["rejected_samples"].get("decode:truncated") == 1
    assert 0 < s["duration_s"] < DURATION_S
    assert s["nav_states"] > 0
    assert (tmp_path / "out" / "summary.json").is_file()


def test_realtime_replay_is_paced(sim60, tmp_path):
    scenario, result = sim60
    short = load_scenario("short", ["duration_s=10"])
    inp = rp.ReplayInput(rp.SimSource(short), short, "sim", short.duration_s)
    res = _replay(inp, tmp_path / "rt", realtime=50.0)
    assert res.summary["wall_s"] >= 10.0 / 50.0 * 0.95


def test_compare_runs_pure_ins_static_wrong_and_given(tmp_path):
    out = tmp_path / "cmp"
    rc = cli_main(["replay", "--scenario", "short", "--set", "duration_s=40", "--compare", "--no-plots",
                   "--no-progress", "--out", str(out)])
    assert rc == 0
    table = json.loads((out / "comparison.json").read_text())
    assert sorted(table) == ["given", "pure_ins", "static_wrong"]
    assert all("final_horizontal_error_m" in m for m in table.values())
    pure = json.loads((out / "pure_ins" / "config.json").read_text())
    assert pure["filter"]["learned_velocity"]["enabled"] is False
    wrong = json.loads((out / "static_wrong" / "config.json").read_text())
    given = json.loads((out / "given" / "config.json").read_text())
    assert wrong["motion"]["params0"]["k_v"] == pytest.approx(1.1 * given["motion"]["params0"]["k_v"])
    # pure INS fuses no velocity aid at all
    sources = {r["source"] for r in _rows(out / "pure_ins" / "aid_status.csv") if r["fused"] == "1"}
    assert "learned_velocity" not in sources and sources


def test_replay_with_the_calibrator_in_process_records_releases(tmp_path):
    scenario = load_scenario("short", ["duration_s=130"])
    inp = rp.ReplayInput(rp.SimSource(scenario), scenario, "sim", scenario.duration_s)
    res = _replay(inp, tmp_path / "cal", calibrate=True)
    rows = _rows(tmp_path / "cal" / "params.csv")
    assert rows[0]["reason"] == "initial"
    assert res.summary["releases"] == len(rows) - 1 >= 1
    assert all(r["accepted"] in ("0", "1") and r["log_likelihood"] != "" for r in rows[1:])


@pytest.mark.realdata
def test_real_tlog_with_corrupt_frames_replays_with_counters(tmp_path):
    path = DATA / "mavlink" / "ardusub-4.1.0-corrupt-frames.tlog"
    if not path.is_file():
        pytest.skip(f"{path} absent")
    out = tmp_path / "tlog"
    assert cli_main(["replay", str(path), "--out", str(out), "--no-progress", "--no-plots"]) == 0
    s = json.loads((out / "summary.json").read_text())
    assert s["corrupt_frames"] == 1967                  # known from the file's README
    # all but 4 were logged by QGC with trailing zeros cut after the CRC: restored, not lost
    assert sum(s["repaired_frames"].values()) == 1963
    assert s["rejected_samples"]["corrupt_frame"] == 4
    assert s["messages_read"] > 10000
    assert s["samples_used"] > 0 and s["duration_s"] > 300.0
    assert s["missing_streams"]                         # no strapdown-rate IMU, no position fixes
    assert s["errors"] == {}
    assert len(_rows(out / "trajectory.csv")) > 100


# -- deterministic calibrator application (adaptnav.service.calibrator.lagged.LaggedCalibrator) -----
CAL_S = 260.0   # 24 five-second steps before the first EM window, then one a minute


@pytest.fixture(scope="module")
def sim_cal():
    scenario = load_scenario("short", [f"duration_s={CAL_S}"])
    return scenario, simulate(scenario)


def _cal_replay(sim_cal, out, location, latency_s=10.0):
    scenario, result = sim_cal
    inp = rp.ReplayInput(rp.SimSource(scenario, result), scenario, "sim", scenario.duration_s)
    cfg = rp.build_config(scenario, None, [f"calibrator.latency_s={latency_s}"])
    return rp.replay(inp, cfg, out, calibrate=True, calibrator_location=location, progress=False, plots=False)


def test_calibrated_replay_is_deterministic_and_the_same_in_a_child_process_or_inline(sim_cal, tmp_path):
    # GIVEN the same simulated mission replayed twice with the calibrator in a child process
    # and once with it in-process
    runs = {name: _cal_replay(sim_cal, tmp_path / name, loc)
            for name, loc in (("a", "process"), ("b", "process"), ("inline", "inline"))}
    # THEN the releases were applied (the filter's motion model changed) ...
    assert runs["a"].summary["releases_accepted"] >= 1
    # ... and trajectory and parameter history are byte-identical across the three runs
    for f in ("trajectory.csv", "params.csv"):
        ref = (tmp_path / "a" / f).read_bytes()
        assert (tmp_path / "b" / f).read_bytes() == ref, f
        assert (tmp_path / "inline" / f).read_bytes() == ref, f


def test_a_release_is_applied_at_the_data_time_it_was_computed_at_plus_the_latency(sim_cal):
    from adaptnav.service.calibrator.lagged import InlineBackend, LaggedCalibrator
    from adaptnav.service.compose import make_calibrator

    scenario, result = sim_cal
    cfg = rp.build_config(scenario)
    items = [it for it in rp.SimSource(scenario, result) if getattr(it, "KIND", None) != "truth"]

    def t_last(it):
        return float(np.atleast_1d(np.asarray(it.t_s, dtype=float))[-1])

    # reference: the data time (latest sample time) at which a plain calibrator with the
    # same seed produced each release
    ref_cal = make_calibrator(cfg, cfg.motion.params0, cfg.calibrator.seed)
    tau, now = [], -math.inf
    for it in items:
        ref_cal.observe(it)
        now = max(now, t_last(it))
        tau += [now] * len(ref_cal.poll())
    assert len(tau) >= 2
    lag = 17.0
    lagged = LaggedCalibrator(InlineBackend(make_calibrator(cfg, cfg.motion.params0, cfg.calibrator.seed)), lag)
    # THEN each release comes right after the item that brings the data time to τ + L
    k, now, before = 0, -math.inf, -math.inf
    for it in items:
        lagged.observe(it)                     # what the runner does with an item ...
        before, now = now, max(now, t_last(it))
        for _ in lagged.poll(now):             # ... and then, with its data time
            assert before < tau[k] + lag <= now, (k, tau[k], before, now)
            k += 1
    assert k == len(tau)
