"""The calibrator release rule live (adaptnav.service.calibrator.live.CalibratorProcess): a
release computed at data time τ reaches the runner (``poll(data_time_s)``) only once the runner's
data time has reached τ + calibrator.latency_s — real spawn child, real calibrator.

Deterministic at any machine load: the test never paces the child. Where the reference
calibrator (same config and seed, in this process) released, the test flushes and waits
(event-driven, generous timeout) until the child's release has come back to the parent,
so every release is known to the parent before the data time reaches its τ + L, and the
rule is checked exactly: each release comes out at the first poll whose data time
reaches τ + L, not before, not later."""
from __future__ import annotations

import math
import time

import numpy as np
import pytest

from adaptnav.service.runtime import replay as rp
from adaptnav.service.calibrator.live import CalibratorProcess
from adaptnav.service.compose import make_calibrator
from adaptnav.service.runtime.sources import simulate
from adaptnav.sim.scenario import load_scenario

pytestmark = pytest.mark.timeout(300)

_WAIT_S = 120.0  # generous: the child runs one EM window per release on a loaded machine


def _t_last(it) -> float:
    return float(np.atleast_1d(np.asarray(it.t_s, dtype=float))[-1])


def _wait_received(proc: CalibratorProcess, n: int) -> None:
    deadline = time.monotonic() + _WAIT_S
    while proc.received < n:
        assert proc.alive(), "calibrator child died"
        assert time.monotonic() < deadline, f"release {n} did not come back within {_WAIT_S} s"
        time.sleep(0.01)  # waiting for a condition, not pacing: the data do not move meanwhile


def test_live_releases_are_held_until_the_data_time_reaches_tau_plus_the_latency():
    scenario = load_scenario("short", ["duration_s=260"])
    result = simulate(scenario)
    lag = 40.0
    # a queue that cannot fill: a dropped batch would change the child's data (and releases)
    cfg = rp.build_config(scenario, None, [f"calibrator.latency_s={lag}", "calibrator.queue_size=10000000"])
    items = [it for it in rp.SimSource(scenario, result) if getattr(it, "KIND", None) != "truth"]
    # reference τ of each release and the item that produced it: the same calibrator and
    # seed in this process
    ref = make_calibrator(cfg, cfg.motion.params0, cfg.calibrator.seed)
    tau, pose_t, at_item, now = [], [], [], -math.inf
    for i, it in enumerate(items):
        ref.observe(it)
        now = max(now, _t_last(it))
        for r in ref.poll():
            tau.append(now)
            pose_t.append(r.t_s)
            at_item.append(i)
    assert len(tau) >= 2
    # WHEN the items go through the live calibrator as the runner passes them
    proc = CalibratorProcess(cfg, cfg.motion.params0, batch_s=0.01)
    proc.start()
    got = []   # (data time at the poll that returned it, data time at the poll before, release)
    try:
        assert proc.wait_running(_WAIT_S), "calibrator child did not start"
        now = prev = -math.inf
        k = 0
        for i, it in enumerate(items):
            proc.observe(it)
            prev, now = now, max(now, _t_last(it))
            got += [(now, prev, r) for r in proc.poll(now)]
            while k < len(at_item) and at_item[k] == i:  # the child releases here too
                proc.flush()
                k += 1
                _wait_received(proc, k)
    finally:
        proc.stop()
    assert proc.dropped == 0
    # THEN every release due by the end came out, in order, at the first poll at or after τ + L
    due = [t for t in tau if t + lag <= now]
    assert len(got) == len(due), (len(got), len(due))
    assert [rel.t_s for _, _, rel in got] == pose_t[:len(got)]   # the same releases, in order
    for k, (t_poll, t_before, _) in enumerate(got):
        assert t_poll >= tau[k] + lag, (k, t_poll, tau[k])
        assert t_before < tau[k] + lag, (k, t_before, tau[k])  # not held longer than the rule says
    # every release was back before the data time reached its τ + L: none counted late
    assert proc.late_report() == {"releases": 0, "products": 0, "max_s": 0.0}


def _reference_releases(cfg, items) -> tuple[list[float], list[int]]:
    """τ of each release of the same calibrator and seed in this process, and the item it came after."""
    ref = make_calibrator(cfg, cfg.motion.params0, cfg.calibrator.seed)
    tau, at_item, now = [], [], -math.inf
    for i, it in enumerate(items):
        ref.observe(it)
        now = max(now, _t_last(it))
        for _ in ref.poll():
            tau.append(now)
            at_item.append(i)
    return tau, at_item


@pytest.mark.parametrize("lag", [0.0, 40.0])
def test_live_releases_that_come_back_after_their_due_time_are_counted_late(lag, caplog):
    """A release back after the runner's data time passed τ + L is handed over at the next
    poll, later than the rule (a replay of the log would apply it earlier): health's
    ``calibrator.late`` counts it with its lateness. Made certain without pacing: the child
    gets the sample a release comes from only once the runner's data time is past its τ —
    past τ + L with L = 0 (every release late), within L = 40 s of it otherwise (none late)."""
    scenario = load_scenario("short", ["duration_s=260"])
    result = simulate(scenario)
    cfg = rp.build_config(scenario, None, [f"calibrator.latency_s={lag}", "calibrator.product_latency_s=0",
                                           "calibrator.queue_size=10000000"])
    items = [it for it in rp.SimSource(scenario, result) if getattr(it, "KIND", None) != "truth"]
    tau, at_item = _reference_releases(cfg, items)
    assert len(tau) >= 2
    proc = CalibratorProcess(cfg, cfg.motion.params0, batch_s=1e9)  # sent when the test says (or 500 pile up)
    proc.start()
    lateness = []  # the runner's data time when each release could come back, less its τ
    try:
        assert proc.wait_running(_WAIT_S), "calibrator child did not start"
        now = -math.inf
        k = 0
        held_back = False
        for i, it in enumerate(items):
            if k < len(at_item) and at_item[k] == i:
                proc.flush()  # what came before; this sample stays here until the data time passed τ
                held_back = True
            proc.observe(it)
            now = max(now, _t_last(it))
            proc.poll(now)
            if held_back and now > tau[k]:
                proc.flush()
                lateness.append(now - tau[k])
                k += 1
                _wait_received(proc, k)
                held_back = k < len(at_item) and at_item[k] <= i
    finally:
        proc.stop()
    assert proc.dropped == 0
    assert k == len(tau)
    report = proc.late_report()
    said = [r for r in caplog.records if "calibrator behind" in r.getMessage()]
    if lag == 0.0:
        assert report["releases"] == len(tau) and report["products"] == 0, report
        assert report["max_s"] == pytest.approx(max(lateness), abs=1e-3), (report, lateness)
        # said in the log when it first happened (and when the lateness doubled), not per release
        assert 1 <= len(said) <= len(tau) and said[0].levelname == "WARNING", [r.getMessage() for r in said]
    else:  # back while the data time was past τ, but short of τ + L: on time
        assert max(lateness) < lag, lateness
        assert report == {"releases": 0, "products": 0, "max_s": 0.0}, report
        assert not said
