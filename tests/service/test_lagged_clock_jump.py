"""Replay's release schedule across a backward clock jump of the input.

The runner's plausibility door confirms a jump (a stream continuing consistently from a new
time) and re-bases what depends on time; the lagged calibrator's schedule must move with it:
a release computed after the jump is applied ``latency_s`` of data after its data time, as
before the jump — not held for as long as the jump (its running maximum stuck in the old time
base), nor released only at the end of the data.

The calibrator here is a scripted stand-in for EM (it releases at given data times) inside
the real :class:`LaggedCalibrator` with its in-process backend and the real runner, door and
filter: what is under test is the schedule, not the learning.
"""
from __future__ import annotations

import math

import pytest

from adaptnav.calibration.online import Release
from adaptnav.fusion.motion_model import MotionParams
from adaptnav.fusion.samples import ImuSample
from adaptnav.service.calibrator.lagged import InlineBackend, LaggedCalibrator
from adaptnav.service.compose import make_estimator
from adaptnav.service.config import load_config
from adaptnav.service.runtime.clock import LogClock
from adaptnav.service.runtime.runner import run
from adaptnav.service.runtime.sinks import Sink

G_M_S2 = 9.80665
LAG_S = 10.0


class ScriptedCalibrator:
    """Releases ``k_v`` when it observes a sample within the second after each scripted time;
    an entry marked ``after_jump`` only once time has gone backwards (in the new time base)."""

    def __init__(self, script: list[tuple[float, float, bool]]) -> None:
        self.script = list(script)  # (data time, k_v, after_jump), in order
        self.due: list[Release] = []
        self.latest_s = -math.inf
        self.jumped = False

    def observe(self, sample) -> None:
        self.jumped |= sample.t_s < self.latest_s
        self.latest_s = max(self.latest_s, sample.t_s)
        if self.script and 0.0 <= sample.t_s - self.script[0][0] < 1.0 and self.jumped >= self.script[0][2]:
            _, k_v, _ = self.script.pop(0)
            self.due.append(Release(t_s=sample.t_s, params=MotionParams(k_v=k_v), log_likelihood=0.0,
                                    accepted=True, reason="", iterations=1))

    def poll(self) -> list:
        out, self.due = self.due, []
        return out


class WhenApplied(Sink):
    """The data time of the last sample the runner had handled when each release came."""

    def __init__(self) -> None:
        self.t_s = math.nan
        self.applied: list[tuple[float, float]] = []  # (k_v, data time)

    def on_sample(self, sample) -> None:
        self.t_s = sample.t_s

    def on_release(self, release) -> None:
        self.applied.append((release.params.k_v, self.t_s))


def imu(t0_s: float, t1_s: float, dt_s: float = 0.1):
    n = int(round((t1_s - t0_s) / dt_s))
    return [ImuSample(t0_s + k * dt_s, (0.0, 0.0, -G_M_S2), (0.0, 0.0, 0.0)) for k in range(n)]


@pytest.mark.parametrize("jump_s", [-1000.0, -40.0])
def test_a_release_after_a_backward_clock_jump_comes_latency_after_its_data(jump_s):
    cfg = load_config(None, ["calibrator.enabled=false"])
    t_jump = 1100.0
    # the first release at 1050 (old time base), the second 20 s after the jump (new base),
    # before the old base's latest time (1100 s)
    new0 = t_jump + jump_s
    t_second = new0 + 20.0
    calibrator = LaggedCalibrator(InlineBackend(ScriptedCalibrator([(1050.0, 1.1, False), (t_second, 1.2, True)])), LAG_S)
    source = imu(1000.0, t_jump) + imu(new0, new0 + 200.0)
    sink = WhenApplied()
    summary = run(iter(source), make_estimator(cfg), [sink], LogClock(), calibrator,
                  health=None)
    assert len(summary.clock_jumps) == 1 and summary.clock_jumps[0] == pytest.approx(jump_s, abs=1.0)
    assert [k for k, _ in sink.applied] == [1.1, 1.2]
    (_, t1), (_, t2) = sink.applied
    assert 1050.0 + LAG_S <= t1 < 1050.0 + LAG_S + 0.2
    # data time of the second release: its own (new base) + L, not the end of the data
    assert t_second + LAG_S <= t2 < t_second + LAG_S + 0.2, (t2, t_second)


def test_the_calibrator_child_moves_its_data_clock_with_the_shift():
    """The child process's τ (what it stamps releases with) follows a shift, after the samples
    sent before it; until the child confirms, the parent re-bases what it reports."""
    from adaptnav.service.calibrator.lagged import ProcessBackend

    cfg = load_config(None, [])
    backend = ProcessBackend(cfg, cfg.motion.params0, seed=0, batch_size=8)
    try:
        for s in imu(1000.0, 1010.0):
            backend.send(s)
        backend.shift_time(-900.0)
        for s in imu(110.0, 112.0):
            backend.send(s)
        backend.finish()  # every sample processed, every message read
        assert backend._child_tau == pytest.approx(111.9)
        assert backend._unacked_shift_s == 0.0
    finally:
        backend.close()


def test_the_live_calibrator_rebases_held_releases_and_its_child():
    """The daemon's calibrator (a supervised child): held releases and the release rule's data
    time move with a shift at once, the child's clock with its next batch (it confirms)."""
    import time

    from adaptnav.service.calibrator.live import CalibratorProcess

    cfg = load_config(None, [f"calibrator.latency_s={LAG_S}"])
    cal = CalibratorProcess(cfg, cfg.motion.params0)
    cal.start()
    try:
        assert cal.wait_running(120.0), "the calibrator child did not start"
        for s in imu(1000.0, 1010.0):
            cal.observe(s)
        cal.flush()
        rel = Release(t_s=1005.0, params=MotionParams(k_v=1.1), log_likelihood=0.0, accepted=True, reason="",
                      iterations=1)
        cal._held.append((1005.0, rel))  # as the reader holds a release stamped τ = 1005 s
        cal.shift_time(-900.0)
        assert cal.poll(1009.9 - 900.0) == []  # due at 105 + L in the new time base, not before
        for s in imu(110.0, 116.0):
            cal.observe(s)
        assert cal.poll(115.9) == [rel]
        cal.flush()
        deadline = time.monotonic() + 60.0
        while (cal._shift_to_send_s or cal._unacked_shift_s) and time.monotonic() < deadline:
            time.sleep(0.02)
        assert (cal._shift_to_send_s, cal._unacked_shift_s) == (0.0, 0.0), "the child never confirmed the shift"
    finally:
        cal.stop()
