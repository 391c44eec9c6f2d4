"""The calibrator release rule live (adaptnav.service.calibrator.process.CalibratorProcess): a
release computed at data time τ reaches the runner (``poll()``) only once the runner's
data time has reached τ + calibrator.latency_s — real spawn child, real calibrator."""
from __future__ import annotations

import math
import time

import numpy as np
import pytest

from adaptnav.service.runtime import replay as rp
from adaptnav.service.calibrator.process import CalibratorProcess, make_calibrator
from adaptnav.service.runtime.sources import simulate
from adaptnav.sim.scenario import load_scenario

pytestmark = pytest.mark.timeout(120)


def _t_last(it) -> float:
    return float(np.atleast_1d(np.asarray(it.t_s, dtype=float))[-1])


def test_live_releases_are_held_until_the_data_time_reaches_tau_plus_the_latency():
    scenario = load_scenario("short", ["duration_s=260"])
    result = simulate(scenario)
    lag = 40.0
    cfg = rp.build_config(scenario, None, [f"calibrator.latency_s={lag}"])
    items = [it for it in rp.SimSource(scenario, result) if getattr(it, "KIND", None) != "truth"]
    # reference τ of each release: the same calibrator and seed in this process
    ref = make_calibrator(cfg, cfg.motion.params0, cfg.calibrator.seed)
    tau, pose_t, now = [], [], -math.inf
    for it in items:
        ref.observe(it)
        now = max(now, _t_last(it))
        for r in ref.poll():
            tau.append(now)
            pose_t.append(r.t_s)
    assert len(tau) >= 2
    # WHEN the items go through the live calibrator as the runner passes them, paced so
    # that the child keeps up (live data come in real time)
    proc = CalibratorProcess(cfg, cfg.motion.params0, None, batch_s=0.01)
    proc.start()
    got = []   # (data time at the poll that returned it, release)
    try:
        deadline = time.monotonic() + 60
        while proc.state != "running" and time.monotonic() < deadline:
            time.sleep(0.05)
        now = -math.inf
        for i, it in enumerate(items):
            proc.observe(it)
            now = max(now, _t_last(it))
            got += [(now, r) for r in proc.poll()]
            if i % 200 == 0:
                time.sleep(0.02)
    finally:
        proc.stop()
    # THEN every release came out in order, none before its τ + L
    assert got, "no release reached the runner"
    assert [rel.t_s for _, rel in got] == pose_t[:len(got)]   # the same releases, in order
    for k, (t_poll, rel) in enumerate(got):
        assert t_poll >= tau[k] + lag, (k, t_poll, tau[k])
