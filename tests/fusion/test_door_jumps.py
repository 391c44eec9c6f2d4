"""The door's verdict on a stream that goes on from a later time: a single outlier stamp is
refused; a stream continuing consistently is a confirmed jump, and whoever can tell (the
live clock, a log's own clock) says whether it was data missing — coasted through, nothing
re-based — or a step of the data's clock — re-based by the jump."""
from __future__ import annotations

from adaptnav.fusion.plausibility import Door, PlausibilityConfig
from adaptnav.fusion.samples import DepthSample, ImuSample

G_M_S2 = 9.80665


def _feed(door: Door, times) -> list[tuple[bool, float]]:
    return [door.check(ImuSample(t, (0.0, 0.0, -G_M_S2), (0.0, 0.0, 0.0))) for t in times]


def _stream_with_a_jump(jump_s: float) -> list[float]:
    before = [k * 0.01 for k in range(100)]           # to 0.99 s
    return before + [0.99 + jump_s + k * 0.01 for k in range(1, 11)]


def test_a_lone_stamp_ahead_is_refused_not_a_jump():
    asked = []
    door = Door(PlausibilityConfig(), forward_jump_is_gap=lambda a, b: asked.append((a, b)) or True)
    verdicts = _feed(door, [k * 0.01 for k in range(50)] + [60.0] + [0.5 + k * 0.01 for k in range(50)])
    assert verdicts[50] == (False, 0.0)
    assert door.rejected == {"time_ahead": 1} and not asked and not door.gaps and not door.jumps


def test_a_confirmed_forward_jump_asks_once_and_a_gap_is_coasted():
    asked = []
    door = Door(PlausibilityConfig(), forward_jump_is_gap=lambda a, b: asked.append((a, b)) or True)
    verdicts = _feed(door, _stream_with_a_jump(12.0))
    n = PlausibilityConfig().jump_confirm_samples
    assert [v for v in verdicts[100:100 + n - 1]] == [(False, 0.0)] * (n - 1)
    assert verdicts[100 + n - 1] == (True, 0.0)             # a gap: nothing to re-base
    assert all(v == (True, 0.0) for v in verdicts[100 + n:])
    assert asked == [(0.99, 0.99 + 12.0 + n * 0.01)]
    assert door.gaps == [("imu", 0.99, 0.99 + 12.0 + n * 0.01)] and not door.jumps
    assert door.rejected["data_gap"] == 1 and door.rejected["time_ahead"] == n - 1
    # the data clock moved on: another stream at the new time passes
    assert door.check(DepthSample(13.2, 2e5)) == (True, 0.0)


def test_a_step_of_the_clock_is_re_based_by_its_size():
    for judge in (None, lambda a, b: False):
        door = Door(PlausibilityConfig(), forward_jump_is_gap=judge)
        verdicts = _feed(door, _stream_with_a_jump(1000.0))
        n = PlausibilityConfig().jump_confirm_samples
        ok, jump = verdicts[100 + n - 1]
        assert ok and abs(jump - (1000.0 + n * 0.01)) < 1e-9
        assert door.rejected["clock_jump"] == 1 and not door.gaps


def test_a_backward_jump_is_a_step_whatever_the_judge():
    asked = []
    door = Door(PlausibilityConfig(), forward_jump_is_gap=lambda a, b: asked.append((a, b)) or True)
    verdicts = _feed(door, [100.0 + k * 0.01 for k in range(100)] + [40.0 + k * 0.01 for k in range(10)])
    assert any(jump < -50.0 for _, jump in verdicts) and not asked and not door.gaps
