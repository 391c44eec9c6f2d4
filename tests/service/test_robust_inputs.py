"""Nothing in the input can stop, hang or blank the navigation (issue 12, items 1–2):
absurd but finite samples are refused at the door and counted by reason, a single
outlier stamp is refused (not taken for a clock jump), a stream that continues from a
new time is a jump (detected, re-based), and a filter that went non-finite anyway
recovers from its last good state instead of dying."""
from __future__ import annotations

import math

import numpy as np
import pytest

from adaptnav.fusion.eskf import Estimator
from adaptnav.fusion.samples import DepthSample, ImuBatch, ImuSample, UsblSample
from adaptnav.service.runtime.clock import LogClock
from adaptnav.service.runtime.health import Health
from adaptnav.service.runtime.replay import build_config
from adaptnav.service.runtime.runner import run
from adaptnav.service.runtime.sinks import Sink
from adaptnav.service.runtime.sources import simulate
from adaptnav.sim.scenario import load_scenario

from .scripted_releases import ReleasesAt

INJECT_AFTER_S = 30.0


@pytest.fixture(scope="module")
def sim60():
    scenario = load_scenario("short", ["duration_s=60"])
    return scenario, simulate(scenario)


class _States(Sink):
    def __init__(self):
        self.states = []

    def on_nav(self, state):
        self.states.append(state)


def _run(sim, inject=lambda t: [], shift=None):
    """The simulation through the runner; ``inject(t)`` adds items before the first IMU
    batch after ``INJECT_AFTER_S``; ``shift(item)`` may rewrite every item."""
    scenario, result = sim
    cfg = build_config(scenario)
    est = Estimator(cfg.filter, cfg.motion.params0, cfg.motion.rpm_table, cfg.origin.geo())
    sink, health = _States(), Health(silent_after_s=cfg.health.sensor_timeout_s)

    def items():
        done = False
        for it in result.iter_blocks():
            if not done and isinstance(it, ImuBatch) and it.t_s[0] > INJECT_AFTER_S:
                done = True
                yield from inject(float(it.t_s[0]))
            yield it if shift is None else shift(it)

    summary = run(items(), est, [sink], LogClock(), output_rate_hz=5.0, health=health)
    return sink.states, health, est, summary


@pytest.fixture(scope="module")
def baseline(sim60):
    return _run(sim60)


def _far_fix(t, origin_lat, origin_lon, north_m):
    return UsblSample(t, origin_lat + north_m / 6.37e6, origin_lon, 10.0, 2.0, 1.0)


ABSURD = {
    "imu_acc_range": lambda t, o: [ImuSample(t - 1e-3, (1e308, 0.0, 0.0), (0.0, 0.0, 0.0))],
    "imu_acc_range ": lambda t, o: [ImuSample(t - 1e-3, (1e6, 0.0, 0.0), (0.0, 0.0, 0.0))],
    "imu_rate_range": lambda t, o: [ImuSample(t - 1e-3, (0.0, 0.0, -9.8), (1e4, 0.0, 0.0))],
    "time_ahead": lambda t, o: [ImuSample(t + 20.0, (0.0, 0.0, -9.8), (0.0, 0.0, 0.0))],
    "time_ahead ": lambda t, o: [DepthSample(1e17, 2e5)],
    "time_behind": lambda t, o: [ImuSample(t - 3600.0, (0.0, 0.0, -9.8), (0.0, 0.0, 0.0))],
    "depth_range": lambda t, o: [DepthSample(t - 1e-3, 1e12)],
    "fix_far_from_origin": lambda t, o: [_far_fix(t - 1e-3, o.lat_rad, o.lon_rad, 4.755e6)],
}


@pytest.mark.parametrize("reason", sorted(ABSURD))
def test_an_absurd_sample_is_refused_counted_and_leaves_the_track_unchanged(sim60, baseline, reason):
    base, _, _, _ = baseline
    origin = build_config(sim60[0]).origin.geo()
    states, health, est, summary = _run(sim60, lambda t: ABSURD[reason](t, origin))
    assert health.rejected_by_reason().get(reason.strip(), 0) == 1, health.rejected_by_reason()
    assert not summary.errors and not summary.clock_jumps
    # nothing blanked: the same output epochs, the same track (to the centimetre)
    assert [s.t_s for s in states] == [s.t_s for s in base]
    err = max(np.max(np.abs(s.pos_n_m - b.pos_n_m)) for s, b in zip(states, base))
    assert err < 0.01
    assert all(s.valid == b.valid for s, b in zip(states, base))


def test_a_sample_ahead_does_not_make_flowing_sensors_silent(sim60):
    # 45 s ahead of 30 s: past the end of the data by more than the silence limit (10 s)
    _, health, _, _ = _run(sim60, lambda t: [ImuSample(t + 45.0, (0.0, 0.0, -9.8), (0.0, 0.0, 0.0)),
                                             DepthSample(t + 45.0, 2e5)])
    _, base_health, _, _ = _run(sim60)  # gnss: surface fixes at the start only
    assert health.silent_sensors() == base_health.silent_sensors()
    assert not {"imu", "depth", "rpm"} & set(health.silent_sensors())
    assert health.t_s <= 60.0 + 1e-6


def test_a_stream_continuing_from_a_new_time_is_a_clock_jump_re_based(sim60, baseline):
    base, _, _, _ = baseline
    jump = 1000.0

    def shift(item):  # from 30 s on, every sample is stamped 1000 s later
        if isinstance(item, ImuBatch):
            t = np.asarray(item.t_s, dtype=float)
            return ImuBatch(np.where(t > INJECT_AFTER_S, t + jump, t), item.specific_force_b_m_s2,
                            item.omega_b_rad_s)
        if item.t_s > INJECT_AFTER_S:
            from dataclasses import replace
            return replace(item, t_s=item.t_s + jump)
        return item

    states, health, est, summary = _run(sim60, shift=shift)
    assert len(summary.clock_jumps) == 1 and summary.clock_jumps[0] == pytest.approx(jump, abs=1.0)
    assert health.rejected_by_reason().get("clock_jump") == 1
    # output goes on at the new time to the end of the data, the solution stays sound
    assert states[-1].t_s == pytest.approx(60.0 + jump, abs=0.5)
    after = [s for s in states if s.t_s > INJECT_AFTER_S + jump]
    assert len(after) >= 0.9 * 5.0 * (60.0 - INJECT_AFTER_S)
    assert all(np.all(np.isfinite(s.pos_n_m)) for s in states)
    assert np.linalg.norm(states[-1].pos_n_m[:2] - base[-1].pos_n_m[:2]) < 5.0
    assert not {"imu", "depth", "rpm"} & set(health.silent_sensors())


@pytest.mark.timeout(60)
def test_a_far_future_imu_stamp_does_not_hang_the_estimator(sim60):
    """The learned-velocity epoch used to be stepped one period at a time up to the stamp."""
    _, _, est, _ = _run(sim60)
    t_2100 = 4.1e9  # 2100 in UNIX seconds
    est.process(ImuSample(t_2100, (0.0, 0.0, -9.80665), (0.0, 0.0, 0.0)))
    assert est.nav_state().t_s == pytest.approx(t_2100)


def _recovering_run(sim60, settle: bool):
    """The estimator alone through ``sim60`` with one IMU sample of 1e308 m/s² after
    ``INJECT_AFTER_S``; ``settle``: :meth:`Estimator.settle` after every item, as the
    runner calls it (else :meth:`Estimator.process` does it first). Returns the estimator,
    the validity after the injection and the nav state after every item from then on."""
    scenario, result = sim60
    cfg = build_config(scenario)
    est = Estimator(cfg.filter, cfg.motion.params0, cfg.motion.rpm_table, cfg.origin.geo())
    injected = False
    valid_after, states = [], []
    for it in result.iter_blocks():
        if it.KIND == "truth":
            continue
        if not injected and isinstance(it, ImuBatch) and it.t_s[0] > INJECT_AFTER_S:
            injected = True
            est.process(ImuSample(float(it.t_s[0]) - 1e-3, (1e308, 0.0, 0.0), (0.0, 0.0, 0.0)))
            est.process(it)
            assert est.rejected["filter_recovered"] == 1
            assert not est.nav_state().valid  # until it has converged again
        else:
            est.process(it)
        if settle:
            est.settle()
        if injected:
            states.append(est.nav_state())
            valid_after.append(states[-1].valid)
    return est, valid_after, states


def test_the_filter_recovers_from_a_non_finite_state(sim60, baseline):
    """No door (the estimator alone): one IMU sample of 1e308 m/s² made the state NaN for
    good and every later IMU sample raise; now the last good state comes back."""
    base, _, _, _ = baseline
    est, valid_after, _ = _recovering_run(sim60, settle=False)
    end = est.nav_state()
    assert np.all(np.isfinite(end.pos_n_m)) and np.all(np.isfinite(end.cov))
    assert valid_after[-1] and not valid_after[0]
    assert np.linalg.norm(end.pos_n_m[:2] - base[-1].pos_n_m[:2]) < 3.0 * math.sqrt(end.cov[0, 0] + end.cov[1, 1])


def test_the_last_good_state_is_the_same_checked_after_the_output_or_before_the_next_sample(sim60):
    """The last good state's check (a Cholesky of its covariance) was on the way to the nav
    state; it runs after the item's output now (``settle``, as the runner calls it), else
    first thing in the next ``process``: the filter recovers to the same state either way."""
    est_a, _, states_a = _recovering_run(sim60, settle=True)
    est_b, _, states_b = _recovering_run(sim60, settle=False)
    assert est_a.rejected == est_b.rejected and len(states_a) == len(states_b) > 100
    for a, b in zip(states_a, states_b):
        assert a.t_s == b.t_s and a.valid == b.valid
        np.testing.assert_array_equal(a.pos_n_m, b.pos_n_m)
        np.testing.assert_array_equal(a.cov, b.cov)


def test_a_release_outside_the_calibrators_bounds_is_refused_counted_and_not_persisted(sim60):
    """k_v = 100 with variances of 1e-30 (a hostile remote node) was applied as it came."""
    from dataclasses import replace

    from adaptnav.calibration.online import Release
    from adaptnav.service.runtime.sinks import ParamsCsvSink  # noqa: F401  (the sinks see it refused)

    scenario, result = sim60
    cfg = build_config(scenario)
    est = Estimator(cfg.filter, cfg.motion.params0, cfg.motion.rpm_table, cfg.origin.geo())
    p0 = cfg.motion.params0
    hostile = Release(20.0, replace(p0, k_v=100.0, **{n: 1e-30 for n in p0.VARIANCE_NAMES}), 0.0, True, "", 1)
    seen = []

    class Releases(Sink):
        def on_release(self, rel):
            seen.append(rel)

    health = Health()
    summary = run(result.iter_blocks(), est, [Releases()], LogClock(), ReleasesAt((20.0, hostile)), health=health)
    assert est.motion_params == p0
    assert summary.releases_refused == 1 and summary.releases_accepted == 0
    assert health.rejected_by_reason() == {"release_refused:var_vv": 1}
    assert len(seen) == 1 and not seen[0].accepted and "var_vv" in seen[0].reason


def test_one_stream_on_a_clock_of_its_own_is_refused_not_taken_for_a_jump(sim60, baseline):
    """From 30 s on the depth sensor's samples are stamped 10 s ahead (its driver's clock off)
    while the IMU and the rest go on at the data clock. Its five samples in a row used to
    confirm a "clock jump": the filter was re-based 10 s ahead and every IMU sample after
    came too late to be used — navigation stopped. The clock cannot have jumped while the
    other streams go on at it: the depth samples are refused, navigation goes on."""
    base, _, _, _ = baseline

    def depth_ahead(item):
        if isinstance(item, DepthSample) and item.t_s > INJECT_AFTER_S:
            return DepthSample(item.t_s + 10.0, item.pressure_pa)
        return item

    states, health, _, summary = _run(sim60, shift=depth_ahead)
    assert not summary.clock_jumps and not summary.errors
    assert health.rejected_by_reason().get("time_ahead", 0) > 100
    # every output epoch of the baseline, to the end of the data
    assert [s.t_s for s in states] == [s.t_s for s in base]
    late = [(s, b) for s, b in zip(states, base) if s.t_s > INJECT_AFTER_S]
    assert all(s.valid for s, _ in late)
    assert max(np.hypot(*(s.pos_n_m[:2] - b.pos_n_m[:2])) for s, b in late) < 1.0
