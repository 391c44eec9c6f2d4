"""The daemon's calibrator child (service/calibrator/live.py) returns the side-scan object
sightings it detects by the route its releases take (poll), for the estimator."""
from __future__ import annotations

import dataclasses
import time

from adaptnav.service.compose import make_live_calibrator
from adaptnav.service.runtime.replay import build_config
from adaptnav.sim.scenario import load_scenario
from adaptnav.sim.simulator import simulate


def test_child_returns_object_batches():
    sc = load_scenario("survey", ["seed=2", "duration_s=120.0", "dvl.enabled=false", "sonar.enabled=true"])
    res = simulate(sc)
    cfg = build_config(sc)
    cfg = dataclasses.replace(cfg, calibrator=dataclasses.replace(cfg.calibrator, latency_s=0.0))
    cal = make_live_calibrator(cfg, cfg.motion.params0, batch_s=0.0)
    cal.start()
    try:
        assert cal.wait_running(120.0), "calibrator child did not start"
        pings = 0
        for item in res.iter_blocks():
            if item.KIND == "truth":
                continue
            pings += item.KIND == "sonar"
            cal.observe(item)
            while cal._in_q.qsize() > 50:  # the child's pace: none dropped on a full queue
                time.sleep(0.001)
        cal.flush()
        expected = pings // 160 - 1  # blocks of 160 pings (+ 20 of context) completed
        got: list = []
        deadline = time.monotonic() + 120.0  # the child's pace, not a wall-clock assumption
        while time.monotonic() < deadline and not got:
            got += [x for x in cal.poll(float("inf")) if x.KIND == "sonar_objects"]
            time.sleep(0.05)
        # the front end's counts for the daemon's health: every ping taken, none refused
        while time.monotonic() < deadline and (cal.side_scan or {}).get("pings") != pings:
            time.sleep(0.05)
        report = cal.side_scan
    finally:
        cal.stop()
    assert expected >= 2
    assert got, "no object batch came back"
    batch = got[0]
    assert batch.sightings and all(o.side in ("port", "starboard") and o.ground_range_m > 0 for o in batch.sightings)
    assert batch.links == []  # the estimator fills them
    assert cal.dropped == 0
    assert report is not None and report["pings"] == pings and report["resampled"] == 0
    assert report["blocks"] >= expected and "bad geometry" not in report["rejected"]
