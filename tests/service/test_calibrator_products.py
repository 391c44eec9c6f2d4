"""The calibrator's side products (side-scan objects for the filter): due after their own
latency (``calibrator.product_latency_s``), not the releases' minute, and the last, incomplete
block of pings detected when the data end (``OnlineCalibrator.finish``)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from adaptnav.calibration.online import Release
from adaptnav.calibration.sidescan import CalibratorSonar, ObjectBatch
from adaptnav.fusion.motion_model import MotionParams
from adaptnav.service.calibrator.lagged import InlineBackend, LaggedCalibrator
from adaptnav.sim.scenario import load_scenario
from adaptnav.sim.simulator import simulate


class _Sample:
    KIND = "sonar"

    def __init__(self, t_s):
        self.t_s = t_s


class _Scripted:
    """A calibrator that, when it sees the sample at ``t_out``, has a release and an object
    batch of that data time."""

    def __init__(self, t_out):
        self.t_out = t_out
        self.out = []
        self.finished = 0

    def observe(self, sample):
        if sample.t_s == self.t_out:
            self.out += [Release(self.t_out, MotionParams(), 0.0, True, "ok", 1),
                         ObjectBatch(self.t_out, ())]

    def poll(self):
        out, self.out = self.out, []
        return out

    def finish(self):
        self.finished += 1


def _kinds(outs):
    return [o.KIND for o in outs]


def test_products_are_due_after_their_own_latency_releases_after_theirs():
    cal = LaggedCalibrator(InlineBackend(_Scripted(100.0)), 60.0, 5.0)
    for t in (99.0, 100.0):
        cal.observe(_Sample(t))
        assert cal.poll(t) == []
    assert cal.poll(104.9) == []
    assert _kinds(cal.poll(105.0)) == ["sonar_objects"]  # the objects: τ + L_p
    assert cal.poll(159.9) == []
    assert _kinds(cal.poll(160.0)) == ["calibration_release"]  # the release: τ + L, as before


def test_without_a_product_latency_products_wait_as_releases_do():
    cal = LaggedCalibrator(InlineBackend(_Scripted(100.0)), 60.0)
    cal.observe(_Sample(100.0))
    assert cal.poll(159.9) == []
    assert _kinds(cal.poll(160.0)) == ["calibration_release", "sonar_objects"]


def test_the_end_of_the_data_finishes_the_calibrator():
    scripted = _Scripted(-1.0)
    cal = LaggedCalibrator(InlineBackend(scripted), 60.0, 5.0)
    cal.observe(_Sample(10.0))
    cal.poll(math.inf)
    assert scripted.finished == 1


@pytest.fixture(scope="module")
def pings():
    sc = load_scenario("survey", ["seed=3", "duration_s=400.0", "trajectory.leg_length_m=150.0",
                                  "dvl.enabled=false", "sonar.enabled=true"])
    return [s for s in simulate(sc).iter_blocks() if s.KIND == "sonar"]


def test_the_last_incomplete_block_of_pings_is_detected_at_the_end(pings):
    """A block completes only with the next block's first context pings: the objects of the
    pings after the last complete block were never detected (nor fused, nor learned from)."""
    block = CalibratorSonar().front_end.config.block_pings
    # end the data where an incomplete block holds an object: try the ends of the pings
    for n_end in range(len(pings), len(pings) - 12 * block, -block // 4):
        sonar = CalibratorSonar()
        batches = [b for b in (sonar.push(p) for p in pings[:n_end]) if b is not None]
        last = max((o.t_s for b in batches for o in b.sightings), default=-math.inf)
        tail = sonar.finish()
        if tail is not None:
            break
    assert tail is not None, "no object in any incomplete last block"
    assert tail.sightings and all(o.t_s > last for o in tail.sightings)
    assert tail.t_s == pytest.approx(pings[n_end - 1].t_s)
    # detected in the pings after the last complete block, not again in a complete one
    assert sonar.finish() is None
