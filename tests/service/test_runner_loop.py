"""The runner loop with the real estimator over a seeded simulation: output epochs,
calibrator releases, errors that must not stop the loop, stop requests, health."""
from __future__ import annotations

import csv
import math
import threading
from pathlib import Path

import numpy as np
import pytest

from adaptnav.calibration.online import Release
from adaptnav.fusion.eskf import Estimator
from adaptnav.fusion.samples import DepthSample, ImuBatch, ImuSample
from adaptnav.service.runtime.clock import LogClock
from adaptnav.service.runtime.health import Health
from adaptnav.service.runtime.replay import build_config
from adaptnav.service.runtime.runner import run
from adaptnav.service.runtime.sinks import ParamsCsvSink, Sink, TrajectoryCsvSink
from adaptnav.service.runtime.sources import simulate
from adaptnav.sim.scenario import load_scenario

from .scripted_releases import ReleasesAt

DURATION_S = 60.0


@pytest.fixture(scope="module")
def sim60():
    scenario = load_scenario("short", [f"duration_s={DURATION_S}"])
    return scenario, simulate(scenario)


def _estimator(scenario):
    cfg = build_config(scenario)
    return cfg, Estimator(cfg.filter, cfg.motion.params0, cfg.motion.rpm_table, cfg.origin.geo())


class _NavTimes(Sink):
    def __init__(self):
        self.t = []
        self.closed = False

    def on_nav(self, state):
        self.t.append(state.t_s)

    def close(self):
        self.closed = True


def _read_csv(path: Path) -> list[dict]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def test_nav_states_come_at_the_exact_output_rate_until_the_end(sim60, tmp_path):
    scenario, result = sim60
    cfg, est = _estimator(scenario)
    times = _NavTimes()
    summary = run(result.iter_blocks(), est, [times, TrajectoryCsvSink(tmp_path / "t.csv")], LogClock(),
                  output_rate_hz=5.0)
    t = np.asarray(times.t)
    # every emitted state sits on a 5 Hz epoch (IMU at 100 Hz has a sample on each)
    assert np.allclose(t * 5.0, np.round(t * 5.0), atol=1e-6)
    assert np.allclose(np.diff(t), 0.2, atol=1e-6)
    assert t[-1] == pytest.approx(DURATION_S)
    assert summary.nav_states == len(t) == len(_read_csv(tmp_path / "t.csv"))
    assert summary.imu_samples == len(result.imu)
    assert times.closed


def test_releases_are_applied_when_accepted_and_all_recorded(sim60, tmp_path):
    scenario, result = sim60
    cfg, est = _estimator(scenario)
    p0 = cfg.motion.params0
    from dataclasses import replace

    good = Release(20.0, replace(p0, k_v=0.8), -10.0, True, "ok", 3)
    bad = Release(40.0, replace(p0, k_v=1.4), -99.0, False, "log-likelihood worse", 3)
    calibrator = ReleasesAt((good.t_s, good), (bad.t_s, bad))

    health = Health()
    summary = run(result.iter_blocks(), est, [ParamsCsvSink(tmp_path / "params.csv", p0)], LogClock(), calibrator,
                  health=health)
    assert est.motion_params.k_v == 0.8          # the accepted one, not the rejected one
    assert summary.releases == 2 and summary.releases_accepted == 1
    rows = _read_csv(tmp_path / "params.csv")
    assert [r["reason"] for r in rows] == ["initial", "ok", "log-likelihood worse"]
    assert [float(r["k_v"]) for r in rows] == [p0.k_v, 0.8, 1.4]
    assert [r["accepted"] for r in rows] == ["1", "1", "0"]
    rep = health.report()["calibrator"]
    assert rep["releases"] == 2 and rep["last_release"]["reason"] == "log-likelihood worse"


def test_an_item_that_raises_is_counted_and_the_loop_goes_on(sim60):
    scenario, result = sim60
    cfg, est = _estimator(scenario)
    # a malformed sample (as a buggy bridge could produce): the estimator raises on it
    broken = ImuSample(30.0101, ("x", 0.0, -9.8), (0.0, 0.0, 0.0))

    def stream():
        done = False
        for item in result.iter_blocks():
            yield item
            if not done and not isinstance(item, ImuBatch) and item.KIND == "depth" and item.t_s >= 30.0:
                done = True
                yield broken

    health = Health()
    times = _NavTimes()
    summary = run(stream(), est, [times], LogClock(), health=health)
    assert summary.errors == {"imu": 1}
    assert health.report()["rejected"].get("error:imu") == 1
    assert times.t[-1] == pytest.approx(DURATION_S)  # navigation continued to the end
    assert est.nav_state().valid


def test_stop_ends_the_loop_and_still_closes_sinks(sim60):
    scenario, result = sim60
    cfg, est = _estimator(scenario)
    stop = threading.Event()
    times = _NavTimes()

    class StopAt(Sink):
        def on_nav(self, state):
            if state.t_s >= 10.0:
                stop.set()

    summary = run(result.iter_blocks(), est, [times, StopAt()], LogClock(), stop=stop)
    assert summary.stopped
    assert times.closed
    assert 10.0 <= summary.last_t_s < 11.0


def test_health_sees_rates_and_estimator_rejections(sim60):
    scenario, result = sim60
    cfg, est = _estimator(scenario)
    nan_imu = (None, np.array([[math.nan, 0.0, -9.8]]), np.zeros((1, 3)))

    def stream():
        done = False
        for item in result.iter_blocks():
            yield item
            if not done and isinstance(item, ImuBatch) and item.t_s[-1] >= 20.0:
                done = True
                yield ImuBatch(item.t_s[-1:] + 0.0005, *nan_imu[1:])
                yield DepthSample(math.nan, 2.0e5)       # no usable time at all

    health = Health(silent_after_s=5.0)
    summary = run(stream(), est, [], LogClock(), health=health)
    assert summary.errors == {}
    rep = health.report()
    assert rep["sensors"]["imu"]["rate_hz"] == pytest.approx(scenario.imu.rate_hz, rel=0.02)
    assert rep["sensors"]["depth"]["rate_hz"] == pytest.approx(scenario.depth.rate_hz, rel=0.05)
    assert rep["sensors"]["gnss"]["silent"]          # one fix at the start only
    assert not rep["sensors"]["imu"]["silent"]
    # the NaN IMU sample and the NaN-time depth sample, by the estimator's reason
    assert rep["rejected"].get("non_finite", 0) >= 2
    assert sum(rep["rejected"].values()) == sum(est.rejected.values())


def test_state_of_an_epoch_goes_out_with_the_imu_sample_at_that_epoch(sim60):
    """Live latency: the state of t_k must not wait for the first sample after t_k."""
    scenario, result = sim60
    cfg, est = _estimator(scenario)
    imu_t = [s.t_s for s in result.iter_samples() if s.KIND == "imu"]
    times = _NavTimes()
    seen_at_emit: list[float] = []  # time of the last item the source handed out

    def source():
        for s in result.iter_samples():
            seen_at_emit.append(s.t_s)
            yield s

    late: list[tuple[float, float]] = []  # (state time, time of the sample that released it)

    class _Probe(Sink):
        def on_nav(self, state):
            times.on_nav(state)
            if abs(seen_at_emit[-1] - state.t_s) > 1e-9:
                late.append((state.t_s, seen_at_emit[-1]))

    run(source(), est, [_Probe()], LogClock(), output_rate_hz=5.0)
    assert times.t and not late, late[:3]
    on_grid = [t for t in times.t if abs(t * 5.0 - round(t * 5.0)) < 1e-9]
    assert len(on_grid) > 0.9 * len(times.t) and max(imu_t) >= times.t[-1]


def _restamp(case: str, samples: list) -> list:
    """The simulated samples with their times as an outside client's IMU clock may stamp
    them: shifted off the epochs, UNIX times, seeded jitter, or times accumulated
    ``t += period`` (float rounding puts ~half of them a hair past the epochs)."""
    import dataclasses

    rng = np.random.default_rng(17)
    if case == "accumulated":
        imu = [s for s in samples if s.KIND == "imu"]
        period = imu[1].t_s - imu[0].t_s
        stamps = imu[0].t_s + np.cumsum(np.full(len(imu), period)) - period
        new_t = {s.t_s: float(t) for s, t in zip(imu, stamps)}
        out = [dataclasses.replace(s, t_s=new_t.get(s.t_s, s.t_s)) if s.KIND == "imu" else s for s in samples]
    elif case.startswith("jitter"):
        half_width_s = float(case.split("_")[1]) * 1e-3
        out = [dataclasses.replace(s, t_s=s.t_s + float(rng.uniform(-half_width_s, half_width_s)))
               if s.KIND == "imu" else s for s in samples]
    else:
        out = [dataclasses.replace(s, t_s=s.t_s + float(case)) for s in samples]
    return sorted(out, key=lambda s: s.t_s)


@pytest.mark.parametrize("stamps", ["0.0037", str(1.7e9 + 0.0037), "jitter_0.3", "jitter_1.5", "accumulated"])
def test_state_goes_out_with_the_imu_sample_nearest_each_epoch(sim60, stamps):
    """An IMU clock not aligned with the epochs (an outside client's, a UNIX time too large
    for an exact test) or jittered around them: the state of t_k leaves with the IMU sample
    nearest t_k, at once — never when a later item arrives (one IMU period late, the slow
    mode of issue 17: a stamp a hair past t_k made the epoch wait for the next sample) —
    and every epoch gets one state."""
    scenario, result = sim60
    cfg, est = _estimator(scenario)
    samples = _restamp(stamps, list(result.iter_samples()))
    seen: list[tuple[str, float]] = []  # (kind, time) of the last item the source handed out

    def source():
        for s in samples:
            seen.append((s.KIND, s.t_s))
            yield s

    released_by: list[tuple[float, str, float]] = []

    class _Probe(Sink):
        def on_nav(self, state):
            released_by.append((state.t_s, *seen[-1]))

    run(source(), est, [_Probe()], LogClock(), output_rate_hz=5.0)
    period_s = 1.0 / scenario.imu.rate_hz
    t0 = samples[0].t_s
    n_epochs = math.floor((samples[-1].t_s - t0) * 5.0)
    assert len(released_by) >= n_epochs - 10  # alignment takes a few seconds
    # every state but the last (end of data) goes out with the IMU sample of its own time
    late = [r for r in released_by[:-1] if not (r[1] == "imu" and r[2] == r[0])]
    assert not late, late[:3]
    # one state per epoch, from the IMU sample nearest it (jitter included)
    t = np.array([r[0] for r in released_by[:-1]])
    k = np.round(t * 5.0)
    assert np.all(np.diff(k) == 1), t[1:][np.diff(k) != 1][:5]
    assert np.all(np.abs(t - k / 5.0) <= 0.5 * period_s + 2e-3 + 1e-6)


def _batched(samples: list, max_run: int = 25):
    """Consecutive IMU samples grouped into :class:`ImuBatch` runs (as a log source does)."""
    run_: list = []
    for s in samples + [None]:
        if s is not None and s.KIND == "imu" and len(run_) < max_run:
            run_.append(s)
            continue
        if run_:
            yield ImuBatch(np.array([r.t_s for r in run_]), np.array([r.specific_force_b_m_s2 for r in run_]),
                           np.array([r.omega_b_rad_s for r in run_]))
            run_ = []
        if s is not None and s.KIND == "imu":
            run_.append(s)
        elif s is not None:
            yield s


@pytest.mark.parametrize("stamps", ["jitter_0.3", "accumulated"])
def test_imu_batches_are_split_at_the_sample_nearest_each_epoch(sim60, stamps):
    """A log source's IMU runs give the states of the same times as the samples one by one."""
    scenario, result = sim60
    samples = _restamp(stamps, list(result.iter_samples()))
    by_sample, by_batch = _NavTimes(), _NavTimes()
    run(iter(samples), _estimator(scenario)[1], [by_sample], LogClock(), output_rate_hz=5.0)
    run(_batched(samples), _estimator(scenario)[1], [by_batch], LogClock(), output_rate_hz=5.0)
    assert len(by_sample.t) > 250
    assert by_batch.t == by_sample.t
