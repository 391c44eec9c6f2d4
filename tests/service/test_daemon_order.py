"""The daemon's queue source restores data order across transports (service.daemon.QueueSource)."""
from __future__ import annotations

import queue
import threading
import time
from types import SimpleNamespace

from adaptnav.fusion.samples import DepthSample, ImuSample


def _imu(t):
    return ImuSample(t, (0.0, 0.0, -9.81), (0.0, 0.0, 0.0))


def _drain(src, n, timeout_s=60.0):
    """What the daemon's runner thread does: wait, then hand everything queued on."""
    out, t0 = [], time.monotonic()
    while len(out) < n and time.monotonic() - t0 < timeout_s:
        src.wait()
        src.drain(out.append)
    return out


def test_a_sample_ahead_of_the_imu_waits_for_it():
    from adaptnav.service.daemon import QueueSource

    q, stop = queue.Queue(), threading.Event()
    src = QueueSource(q, stop, max_hold_s=5.0)
    # arrival order: the depth sample at 0.25 s overtook the IMU samples from 0.22 s on
    for item in (_imu(0.20), _imu(0.21), DepthSample(0.25, 1e5), _imu(0.22), DepthSample(0.10, 1e5),
                 _imu(0.25), _imu(0.26)):
        assert src.put(item)
    got = _drain(src, 7)
    stop.set()
    assert [(g.KIND, g.t_s) for g in got] == [
        ("imu", 0.20), ("imu", 0.21), ("imu", 0.22), ("depth", 0.10),  # a late one passes at once
        ("imu", 0.25), ("depth", 0.25), ("imu", 0.26)]  # replay order: IMU first at equal times
    assert src.counters["held"] == 1 and src.counters["released_on_timeout"] == 0


def test_held_samples_go_out_when_the_imu_stalls():
    from adaptnav.service.daemon import QueueSource

    q, stop = queue.Queue(), threading.Event()
    src = QueueSource(q, stop, max_hold_s=0.2)
    assert src.put(_imu(1.0))
    assert src.put(DepthSample(1.5, 1e5))  # the IMU never gets there
    t0 = time.monotonic()
    got = _drain(src, 2)
    waited = time.monotonic() - t0
    stop.set()
    assert [g.t_s for g in got] == [1.0, 1.5]
    assert 0.2 <= waited  # held for max_hold_s of wall time at least (an upper bound would time the machine)
    assert src.counters["released_on_timeout"] == 1


class _Recorder:
    """Stands in for the runner: what it is fed, in order, and in which thread. Its epochs
    are not known yet (``loop``), so nothing is held for a burst (test_live_burst.py)."""

    def __init__(self) -> None:
        self.fed: list = []
        self.loop = SimpleNamespace(next_k=None, imu_period_s=float("nan"))

    def feed(self, item) -> None:
        self.fed.append((item.t_s, threading.get_ident()))


def test_a_bus_sample_is_run_in_its_callback_only_with_nothing_before_it(tmp_path):
    """Daemon._from_transport (the Zenoh callback): a sample that finds the queue empty and the
    runner free is run at once in the calling thread; one that finds the runner busy is
    queued, and so is a later one behind it although the runner is free by then."""
    from adaptnav.service.daemon import Daemon

    from .test_daemon_support import daemon_config, free_port

    d = Daemon(daemon_config(free_port(), tmp_path))
    d._runner = rec = _Recorder()
    me = threading.get_ident()
    d._from_transport(_imu(0.10))
    assert rec.fed == [(0.10, me)] and d.queue.empty()
    with d._runner_lock:  # the runner thread is draining the queue
        d._from_transport(_imu(0.11))
    assert rec.fed == [(0.10, me)] and d.queue.qsize() == 1
    d._from_transport(_imu(0.12))  # the runner is free, but 0.11 waits in the queue: behind it
    assert rec.fed == [(0.10, me)] and d.queue.qsize() == 2
    d.source.drain(rec.feed)
    assert [t for t, _ in rec.fed] == [0.10, 0.11, 0.12]
    d.stop_event.set()  # after a stop nothing more is run in a callback
    d._from_transport(_imu(0.13))
    assert len(rec.fed) == 3 and d.queue.qsize() == 1
