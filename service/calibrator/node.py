"""The calibrator on the bus: :func:`run_node` is ``adaptnav run --calibrator-only`` (the
same calibrator as its own bus node — another computer, or shore-side through a router —
subscribing to the sensor topics and publishing releases on
``adaptnav/<v>/calibration/params``); :class:`RemoteCalibrator` is the daemon's side of it
(``calibrator.location = "remote"``).
"""
from __future__ import annotations

import logging
import queue
import threading
from collections import Counter
from typing import Any

from adaptnav.service.calibrator.heap import keep_freed_heap
from adaptnav.service.compose import make_calibrator
from adaptnav.service.transport import codec

log = logging.getLogger(__name__)


def run_node(cfg: Any, stop: threading.Event) -> int:
    """``adaptnav run --calibrator-only``: calibrate from the bus, publish releases."""
    import json

    from adaptnav.service.calibrator.lagged import side_scan_report
    from adaptnav.service.transport.bus import Bus, nonblocking_enqueue
    from adaptnav.service.runtime.persistence import load_state

    restored = load_state(cfg.state_dir)
    params0 = restored.params if restored and restored.params else cfg.motion.params0
    keep_freed_heap()  # a process of EM iterations: their arrays stay mapped (heap.py)
    calibrator = make_calibrator(cfg, params0, cfg.calibrator.seed)
    # a node, not a second daemon: a Zenoh *client* of the router, or of the daemon's peer
    # (which then routes between it and the other programs: peers behind one peer do not
    # see each other without gossip), listening nowhere, so it can share the config file
    bus = Bus(cfg.zenoh.as_client(), cfg.vehicle.name)
    inbox: queue.Queue = queue.Queue(maxsize=cfg.calibrator.queue_size)
    overflow: Counter[str] = Counter()
    bus.subscribe_samples(nonblocking_enqueue(inbox, overflow))
    # the daemon's free-inertial velocity: the surge-noise evidence (calibration.inertial)
    bus.subscribe_samples(nonblocking_enqueue(inbox, overflow), key=bus.keys.nav_inertial,
                         kinds={"inertial_velocity"})
    # what the status query answers with; its keys fixed here (the query reads it from a Zenoh
    # thread). "side_scan": what the object front end made of the pings, as the daemon's health
    # has it for a calibrator child (OnlineCalibrator.side_scan_report; null before the first
    # ping and without side-scan), refreshed by this loop after each ping
    last: dict[str, Any] = {"params": params0.to_dict(), "side_scan": side_scan_report(calibrator)}
    received: Counter[str] = Counter()  # samples taken, by kind
    errors: Counter[str] = Counter()  # samples the calibrator failed on, by kind (logged, not taken)
    # one lock over `last` and `received`: a status taken between a ping's count and its
    # side-scan report would say the node took a ping its front end has not seen
    status_lock = threading.Lock()

    def status() -> bytes:
        with status_lock:
            doc = {"type": "calibrator_status", "schema_version": 1, **last, "received": dict(received),
                   "errors": dict(errors), "overflow": dict(overflow), "malformed": dict(bus.malformed)}
        return json.dumps(doc).encode()

    bus.queryable("calibrator", status)
    log.info("calibrator node up for vehicle %s", cfg.vehicle.name)
    try:
        while not stop.is_set():
            try:
                sample = inbox.get(timeout=0.2)
            except queue.Empty:
                sample = None
            if sample is not None:
                kind = getattr(sample, "KIND", type(sample).__name__)
                try:
                    calibrator.observe(sample)
                except Exception as exc:  # one bad sample must not end the node (as the runner's items)
                    with status_lock:
                        errors[kind] += 1
                    if errors[kind] <= 10:
                        log.exception("calibrator node: error taking a %s sample at t=%s: %s", kind,
                                      getattr(sample, "t_s", "?"), exc)
                    continue
                report = side_scan_report(calibrator) if kind == "sonar" else None
                with status_lock:
                    received[kind] += 1
                    if report is not None:
                        last["side_scan"] = report
            for release in calibrator.poll():
                if release.KIND != "calibration_release":
                    continue  # side-scan objects for a filter: a remote node has none (calibration.sidescan)
                if release.accepted and release.params is not None:
                    params = release.params.to_dict()
                    with status_lock:
                        last["params"] = params
                bus.put(bus.keys.params, codec.encode(release))
    finally:
        bus.close()
    return 0


class RemoteCalibrator:
    """The daemon's calibrator when it runs as a bus node (``calibrator.location = "remote"``).

    The node learns from the sensor topics itself, so :meth:`observe` sends nothing; its
    releases arrive on ``adaptnav/<v>/calibration/params`` (decoded in the Zenoh callback,
    malformed ones counted in ``bus.malformed["calibration_params"]``) and :meth:`poll`
    hands them to the runner — the same route as the child's
    (:class:`adaptnav.service.calibrator.live.CalibratorProcess`). The node stamps no data
    time: a release is applied at the first poll after it arrives.
    """

    state = "remote"
    restarts = 0
    dropped = 0

    def __init__(self, bus: Any) -> None:
        from collections import deque

        self._bus = bus
        self._held: Any = deque()
        self.received = 0
        bus.subscribe_raw(bus.keys.params, self._on_release)

    def _on_release(self, key: str, payload: bytes) -> None:  # Zenoh thread: decode, keep
        try:
            release = codec.decode(payload)
        except codec.SampleError as e:
            self._bus.malformed["calibration_params"] += 1
            log.debug("malformed release on %s: %s", key, e)
            return
        if codec.kind_of(release) != "calibration_release":
            self._bus.malformed["calibration_params"] += 1
            return
        self._held.append(release)  # deque.append: thread-safe
        self.received += 1

    def observe(self, sample: Any) -> None:
        """Nothing to send: the node subscribes to the sensor topics."""

    def poll(self, data_time_s: float) -> list:
        """Every release received so far (the node stamps no data time to hold them by)."""
        held, out = self._held, []
        while held:
            out.append(held.popleft())
        return out

    def pid(self) -> None:
        return None

    def supervise(self) -> None:
        """Nothing to supervise here (the node is another program)."""

    def stop(self) -> None:
        """Nothing to stop (the subscription closes with the bus)."""
