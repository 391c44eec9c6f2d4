"""Side-scan loop closures through the service path (service/loop_closures.py): a replay of a
survey with side-scan runs the object detector where the calibrator runs, the association in
the estimator (make_estimator), and fuses leg-to-leg loop closures, reported in the aid
statuses like any source; they remove drift accumulated after the USBL fixes stopped."""
from __future__ import annotations

import csv
import dataclasses
import json

import numpy as np
import pytest

from adaptnav.service.runtime.replay import ReplayInput, SimSource, build_config, replay
from adaptnav.sim.scenario import load_scenario
from adaptnav.sim.simulator import simulate

# reciprocal legs of 150 m (100 s each) so that a few minutes hold several leg pairs; USBL
# fixes stop at 200 s; no DVL: the navigation error grows from then on
OVERRIDES = ["seed=3", "duration_s=480.0", "trajectory.leg_length_m=150.0", "usbl.lost_after_s=200.0",
             "dvl.enabled=false", "sonar.enabled=true"]


@pytest.fixture(scope="module")
def survey():
    sc = load_scenario("survey", OVERRIDES)
    return sc, simulate(sc)


def _replay(survey, out_dir, loop_closures: bool):
    sc, res = survey
    cfg = build_config(sc)
    cfg = dataclasses.replace(cfg, filter=dataclasses.replace(
        cfg.filter, loop_closure=dataclasses.replace(cfg.filter.loop_closure, enabled=loop_closures)))
    inp = ReplayInput(SimSource(sc, res), sc, "survey with side-scan", sc.duration_s)
    replay(inp, cfg, out_dir, calibrate=True, calibrator_location="inline", progress=False, plots=False)
    with open(out_dir / "aid_status.csv") as fh:
        rows = [r for r in csv.DictReader(fh) if r["source"] == "loop_closure"]
    summary = json.loads((out_dir / "summary.json").read_text())
    with open(out_dir / "trajectory.csv") as fh:
        traj = [r for r in csv.DictReader(fh) if float(r["t_s"]) >= sc.usbl.lost_after_s]
    err = np.hypot([float(r["north_m"]) - float(r["truth_north_m"]) for r in traj],
                   [float(r["east_m"]) - float(r["truth_east_m"]) for r in traj])
    return rows, summary, float(np.sqrt(np.mean(err ** 2)))


def test_replay_fuses_loop_closures_and_reports_them(survey, tmp_path):
    rows, summary, err_with = _replay(survey, tmp_path / "with", True)
    fused = [r for r in rows if r["fused"] == "1"]
    assert len(fused) >= 2, rows
    assert summary["side_scan"]["closures"] >= len(fused)
    # gated like every aid: the fused ones passed the χ² test
    assert all(float(r["test_ratio"]) <= 1.0 for r in fused)
    rows_off, _, err_without = _replay(survey, tmp_path / "without", False)
    assert rows_off == []
    # the closures took out part of the drift since the last fix: RMS horizontal error over the
    # outage. (The error at the end alone was decided by what followed the last closure — a
    # calibrator release at ~400 s moved it 4-5 m either way: end-error ratio 0.47 / 0.81 for
    # two detector versions whose RMS ratios were 0.74 / 0.72; seeds 1 and 2 ended at 0.74 and
    # 1.03 with the same code.)
    assert err_with < 0.8 * err_without, (err_with, err_without)
