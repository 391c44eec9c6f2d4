"""The daemon's bus samples between output epochs run in one burst (:class:`LiveBurst`): the
same nav states, bit for bit, as each sample run as it arrives; the epoch's own sample still
runs alone; and a burst held when the IMU stops is run all the same."""
from __future__ import annotations

import itertools

import numpy as np
import pytest

from adaptnav.fusion.samples import ImuBatch
from adaptnav.fusion.typed_config import as_dict, build
from adaptnav.service.config import ServiceConfig
from adaptnav.service.daemon import Daemon
from adaptnav.service.runtime.rehearsal import EpochRehearsal
from adaptnav.service.runtime.replay import build_config
from adaptnav.service.runtime.runner import Runner
from adaptnav.service.runtime.sinks import Sink
from adaptnav.service.transport.bus import Bus, decode_sample, encode_sample
from adaptnav.service.runtime.sources import simulate
from adaptnav.sim.scenario import load_scenario

from .test_daemon_support import free_port, wait_until

pytestmark = pytest.mark.timeout(300)


class _States(Sink):
    def __init__(self) -> None:
        self.states: list = []
        self.learned_velocity: list[float] = []  # the times of the learned-velocity updates

    def on_nav(self, state) -> None:
        self.states.append(state)

    def on_aid(self, statuses) -> None:
        self.learned_velocity += [s.t_s for s in statuses if s.source == "learned_velocity"]


def _payloads(duration_s: float):
    """A 200 Hz survey with a DVL, depth, heading and RPM between the IMU samples, as the
    daemon's Zenoh callback gets it (encoded bus payloads)."""
    scenario = load_scenario("survey", ["imu.rate_hz=200", "dvl.enabled=true", "sonar.enabled=false",
                                        f"duration_s={duration_s}"])
    out = []
    for item in simulate(scenario).iter_blocks():
        samples = item.samples() if isinstance(item, ImuBatch) else [item]
        out.extend(encode_sample(s) for s in samples if s.KIND != "truth")
    return scenario, out


def _run_inline(scenario, payloads, tmp_path, burst: bool, rehearsed: list | None = None):
    """The daemon's callback path without its threads (nothing queued, the lock free): every
    payload decoded and handed to ``_from_transport``, as Zenoh's callback does. ``rehearsed``:
    the output epochs rehearsed (:class:`EpochRehearsal`, on a clock that is the data time),
    each planned one run at its time; their outcomes appended there, one per payload."""
    cfg = build(ServiceConfig, as_dict(build_config(scenario, None, [
        f'zenoh.listen=["tcp/127.0.0.1:{free_port()}"]', "zenoh.scouting=false", f'state_dir="{tmp_path}"',
        "vehicle.name=burst", "calibrator.enabled=false"])))
    d = Daemon(cfg)
    d.estimator = d._make_estimator()
    d.bus = Bus(cfg.zenoh, cfg.vehicle.name)
    states = _States()
    d._runner = Runner(d.estimator, [*d.sinks(), states], d.clock, None, output_rate_hz=cfg.outputs.nav_rate_hz,
                       health=d.health)
    fed: list[str] = []
    feed = d._runner.feed

    def counting_feed(item):
        fed.append(type(item).__name__)
        feed(item)

    d._runner.feed = counting_feed
    if not burst:
        d.burst.hold = lambda item, loop: False
    now = [0.0]
    lead_s = 0.0015
    d.rehearsal = (EpochRehearsal(d._runner_lock, d._rehearse, lead_s, clock=lambda: now[0])
                   if rehearsed is not None else None)
    # per payload: its kind, items fed, states emitted, learned-velocity updates made
    calls: list[tuple[str, int, int, int]] = []
    try:
        for p in payloads:
            sample = decode_sample(p)
            n_fed, n_states, n_lv = len(fed), len(states.states), len(states.learned_velocity)
            now[0] = max(now[0], sample.t_s)  # it comes at its data time
            d._from_transport(sample)
            if rehearsed is not None:  # the rehearsal thread wakes at the planned time
                now[0] = max(now[0], sample.t_s + d._runner.loop.imu_period_s - lead_s)
                rehearsed.append(d.rehearsal.run_due())
            calls.append((sample.KIND, len(fed) - n_fed, len(states.states) - n_states,
                          len(states.learned_velocity) - n_lv))
        assert not d.burst.items or burst
        d.burst.run(d.source.take, d._runner.feed)
    finally:
        d.bus.close()
    return states.states, fed, calls


def _aids_ahead(payloads, lead: int = 3, offset_s: float = 0.0371):
    """The aids moved off the epochs (``offset_s`` later: the survey's fall on them, where the
    IMU samples run singly) and each arriving ``lead`` IMU samples before its time (a sensor of
    another process ahead of the IMU stream: the daemon's queue source holds it)."""
    import dataclasses

    samples = [decode_sample(p) for p in payloads]
    samples = [s if s.KIND == "imu" else dataclasses.replace(s, t_s=s.t_s + offset_s) for s in samples]
    samples.sort(key=lambda s: (s.t_s, s.KIND != "imu"))
    out = [encode_sample(s) for s in samples]
    for i in range(len(out)):
        if decode_sample(out[i]).KIND != "imu":
            j, moved = i, 0
            while j > 0 and moved < lead:
                if decode_sample(out[j - 1]).KIND == "imu":
                    moved += 1
                out[j - 1], out[j] = out[j], out[j - 1]
                j -= 1
    return out


@pytest.mark.parametrize("aids_ahead", [False, True])
def test_a_burst_gives_the_states_of_samples_run_as_they_come(tmp_path, aids_ahead):
    scenario, payloads = _payloads(150.0)
    if aids_ahead:
        payloads = _aids_ahead(payloads)
    single, fed_single, _ = _run_inline(scenario, payloads, tmp_path / "single", burst=False)
    burst, fed_burst, calls = _run_inline(scenario, payloads, tmp_path / "burst", burst=True)
    # the aids that come right after an epoch's state (sampled on the epoch) wait for the
    # burst: nothing runs between a state and the next IMU sample, when its delivery needs the core
    after_state = [fed for i, (kind, _, emitted, _) in enumerate(calls) if emitted and i > 2000
                   for kind2, fed, _, _ in itertools.takewhile(lambda c: c[0] != "imu", calls[i + 1:])]
    assert not any(after_state)
    assert aids_ahead or len(after_state) > 500  # (moved off the epochs: none come there)
    # nor does a learned-velocity update run on the way to an epoch's state (its updates lie
    # between the epochs, filter.learned_velocity.phase_s): they run in the bursts
    assert not any(lv for _, _, emitted, lv in calls if emitted)
    assert sum(lv for *_, lv in calls) > 100  # (one a second: they were made)
    assert "ImuBatch" not in fed_single
    # most IMU samples went in batches: the bursts happened (20 IMU samples per 0.1 s epoch)
    assert fed_burst.count("ImuBatch") > 0.8 * 150 * 10
    assert fed_burst.count("ImuSample") < 0.5 * fed_single.count("ImuSample")
    assert len(burst) == len(single) > 1400
    valid = sum(s.valid for s in single)
    assert valid > 0.9 * len(single)
    for a, b in zip(single, burst):
        assert a.t_s == b.t_s and a.valid == b.valid and a.invalid_reasons == b.invalid_reasons
        for name in ("pos_n_m", "vel_n_m_s", "q_nb", "bias_acc_b_m_s2", "bias_gyro_b_rad_s", "current_n_m_s", "cov"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=f"{name} at {a.t_s}")


def test_a_rehearsed_epoch_changes_no_state(tmp_path):
    """Each output epoch rehearsed right before its IMU sample: the states are those of a
    daemon without rehearsals, bit for bit, and the rehearsals fall where they are meant to,
    after the sample before an epoch's (each is followed by the sample that emits a state)."""
    scenario, payloads = _payloads(60.0)
    plain, _, _ = _run_inline(scenario, payloads, tmp_path / "plain", burst=True)
    rehearsed: list = []
    states, _, calls = _run_inline(scenario, payloads, tmp_path / "rehearsed", burst=True, rehearsed=rehearsed)
    assert len(states) == len(plain) > 500
    for a, b in zip(plain, states):
        assert a.t_s == b.t_s and a.valid == b.valid and a.invalid_reasons == b.invalid_reasons
        for name in ("pos_n_m", "vel_n_m_s", "q_nb", "bias_acc_b_m_s2", "bias_gyro_b_rad_s", "current_n_m_s", "cov"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=f"{name} at {a.t_s}")
    done = [i for i, outcome in enumerate(rehearsed) if outcome == "done"]
    # (before the filter started there is nothing to rehearse)
    assert not {o for o in rehearsed if o is not None} - {"done", "not_ready"}
    # after the alignment (the filter is an INS), nearly every epoch was rehearsed …
    after_start = [i for i, c in enumerate(calls) if c[2]]
    assert len(done) > 0.9 * len(after_start)
    # … right before its own sample: the next IMU sample after each rehearsal emits a state
    for i in done:
        nxt = next(c for c in calls[i + 1:] if c[0] == "imu")
        assert nxt[2] == 1, f"rehearsal after payload {i} was not followed by the epoch's sample"


def test_a_rehearsal_is_planned_before_the_epochs_sample_and_skipped_when_late():
    """The plan: ``lead_s`` before the sample after this one when that one completes the next
    epoch; none when the IMU is too fast for the lead; a late or busy one is skipped, counted."""
    import threading

    class Loop:  # the runner's epoch bookkeeping at 200 Hz, next epoch at 1.0 s
        next_k, imu_period_s = 10, 0.005

        @staticmethod
        def due_s():
            return 1.0 - 0.0025

    now = [100.0]
    lock = threading.Lock()
    ran: list[float] = []

    def rehearse(dt_s: float) -> bool:
        ran.append(dt_s)
        return True

    r = EpochRehearsal(lock, rehearse, 0.0015, clock=lambda: now[0])
    assert not r.plan(100.0, 0.990, Loop)  # two samples before the epoch's: nothing yet
    assert r.plan(100.0, 0.995, Loop)      # the one before: the next one is the epoch's
    assert r.run_due() is None             # not its time yet
    now[0] = 100.0035                      # 5 ms − 1.5 ms after the sample came
    assert r.run_due() == "done" and ran == [0.005]
    assert r.run_due() is None             # once
    now[0] = 100.1                         # the next epoch's: a sample comes at 100.1
    assert r.plan(100.1, 0.995, Loop)
    now[0] = 100.1035 + 0.001              # woke more than half the lead late: not run
    assert r.run_due() == "late" and ran == [0.005]
    now[0] = 100.2
    assert r.plan(100.2, 0.995, Loop)
    with lock:                             # the runner is busy: not run
        now[0] = 100.2035
        assert r.run_due() == "busy"
    Loop.imu_period_s = 0.0025             # 400 Hz: 2.5 ms − 1.5 ms leaves no room for the lead
    now[0] = 200.0
    assert not r.plan(200.0, 0.9965, Loop)
    assert dict(r.counts) == {"done": 1, "late": 1, "busy": 1, "no_room": 1}
    with pytest.raises(ValueError):
        EpochRehearsal(lock, rehearse, 0.0)


def test_the_epochs_own_sample_is_not_held():
    """What a client waits for (the nav state of the epoch's IMU sample) is run as it comes:
    the burst is run at the sample before it."""
    from adaptnav.fusion.samples import ImuSample
    from adaptnav.service.daemon import LiveBurst

    class Loop:  # the runner's epoch bookkeeping at 200 Hz, next epoch at 1.0 s
        next_k, imu_period_s = 10, 0.005

        @staticmethod
        def due_s():
            return 1.0 - 0.0025

    burst = LiveBurst()
    imu = [ImuSample(round(0.9 + 0.005 * i, 6), (0.0, 0.0, -9.8), (0.0, 0.0, 0.0)) for i in range(1, 21)]
    held = [burst.hold(s, Loop) for s in imu]
    # 0.905 … 0.990 held; 0.995 (the one before the epoch's) runs the burst, 1.000 is the epoch's
    assert held == [True] * 18 + [False] * 2
    taken = []
    burst.run(lambda item, feed: taken.append(item), None)
    assert len(taken) == 1 and isinstance(taken[0], ImuBatch)
    assert taken[0].t_s.tolist() == [s.t_s for s in imu[:18]]
    # an aid opens a burst by the IMU samples' rule: one sampled on the last epoch (it came
    # right after that epoch's state) is held, one at the sample before the epoch's runs as
    # it comes; a stream whose period is not known yet runs as it comes
    from adaptnav.fusion.samples import DepthSample

    assert not burst.hold(DepthSample(0.995, 150000.0), Loop)
    assert burst.hold(DepthSample(0.9, 150000.0), Loop) and len(burst) == 1
    assert burst.hold(DepthSample(0.996, 150000.0), Loop)  # inside a burst: held, in its order
    burst.run(lambda item, feed: None, None)
    Loop.imu_period_s = float("nan")
    assert not burst.hold(imu[0], Loop)
    assert not burst.hold(DepthSample(0.9, 150000.0), Loop)


def test_a_burst_held_when_the_imu_stops_is_run(live):
    """The IMU stops mid-interval: the runner thread runs what was held (its health counts
    every sample published), not the next sample that never comes."""
    from adaptnav.fusion.samples import HeadingSample, ImuSample

    daemon, bus, _ = live()
    n = 0
    t = 0.0
    for k in range(1, 4 * 200 + 37):  # 4 s of 200 Hz IMU, ending mid-epoch; a heading every 0.2 s
        t = k * 0.005
        bus.publish_sample(ImuSample(t, (0.0, 0.0, -9.80665), (0.0, 0.0, 0.0)))
        n += 1
        if k % 40 == 0:
            bus.publish_sample(HeadingSample(t + 0.001, 0.3))
    health = wait_until(lambda: (h := bus.get("health")) and h["sensors"].get("imu", {}).get("count") == n and h,
                        timeout_s=60)
    assert health, f"imu count {bus.get('health')['sensors'].get('imu')} != published {n}"
    assert len(daemon.burst) == 0
    # the rehearsals' outcomes are reported (which ones: the pace of this machine's publishing)
    rehearsals = health["epoch_rehearsal"]
    assert set(rehearsals) <= {"done", "not_ready", "late", "busy", "no_room", "failed"} and "failed" not in rehearsals
    state = bus.get("state")
    assert state is not None and state["t_s"] <= t
