"""The daemon's MAVLink link to a real ArduSub (SITL on loopback) drops for 10 s mid-lane.

Nothing arrives meanwhile; the autopilot's boot clock runs on, so the stream comes back
10 s later. The live door used to take that for a step of the data's clock and re-base
the filter "as if no time had passed": the position missed the metres the vehicle drove
during the dropout, and its covariance did not say so. The wall clock ran with the data,
so it is data missing: the filter coasts through it, its uncertainty growing.

The link runs through a relay on loopback (:class:`LinkRelay`) that drops every datagram,
both ways, for the dropout. Figures to ``$ADAPTNAV_SITL_OUT/dropout.json``.
"""
from __future__ import annotations

import json
import math
import os
import selectors
import socket
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from adaptnav.fusion.frames import GeoOrigin

from .ardusub import HOME, free_udp_port
from .bin_drive import dive
from .test_ardusub_live import GCS_RATES, ardusub_session, start_daemon, truth_ned

pytestmark = [pytest.mark.sitl, pytest.mark.timeout(900)]

DROPOUT_S = 10.0


class LinkRelay(threading.Thread):
    """A UDP link between the autopilot (``port``: its SERIAL1 sends here) and the daemon's
    bridge on ``daemon_port``, that can be cut (:meth:`cut`): every datagram, both ways,
    dropped until it is whole again."""

    def __init__(self, daemon_port: int) -> None:
        super().__init__(daemon=True)
        self.daemon_addr = ("127.0.0.1", daemon_port)
        self.outer = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.outer.bind(("127.0.0.1", 0))
        self.port = self.outer.getsockname()[1]
        self.inner = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.inner.bind(("127.0.0.1", 0))
        self.autopilot_addr = None
        self.cut_until = -math.inf
        self.dropped = 0
        self._halt = threading.Event()

    def cut(self, seconds: float) -> None:
        self.cut_until = time.monotonic() + seconds

    def run(self) -> None:
        sel = selectors.DefaultSelector()
        sel.register(self.outer, selectors.EVENT_READ)
        sel.register(self.inner, selectors.EVENT_READ)
        while not self._halt.is_set():
            for key, _ in sel.select(0.1):
                data, addr = key.fileobj.recvfrom(65535)
                if time.monotonic() < self.cut_until:
                    self.dropped += 1
                    continue
                if key.fileobj is self.outer:
                    self.autopilot_addr = addr
                    self.inner.sendto(data, self.daemon_addr)
                elif self.autopilot_addr is not None:
                    self.outer.sendto(data, self.autopilot_addr)
        sel.close()

    def stop(self) -> None:
        self._halt.set()
        self.join(2.0)
        self.outer.close()
        self.inner.close()


def _sigma_h_m(state: dict) -> float:
    cov = np.asarray(state["cov"], dtype=float).reshape(18, 18)
    return float(math.sqrt(cov[0, 0] + cov[1, 1]))


def test_a_link_dropout_mid_lane_is_coasted_through(tmp_path):
    out = Path(os.environ.get("ADAPTNAV_SITL_OUT", tmp_path))
    out.mkdir(parents=True, exist_ok=True)
    origin = GeoOrigin(math.radians(HOME[0]), math.radians(HOME[1]), 0.0)
    daemon_port = free_udp_port()
    relay = LinkRelay(daemon_port)
    relay.start()
    try:
        with ardusub_session(tmp_path, relay.port) as (sub, gcs, navlog):
            report: dict = {}
            daemon = None
            try:
                for mtype, hz in GCS_RATES.items():
                    gcs.interval(mtype, hz)
                daemon = start_daemon(tmp_path, daemon_port, tmp_path / "state")
                navlog.daemon_ref = daemon
                gcs.wait(lambda: daemon.sink.latest_state is not None and daemon.sink.latest_state["valid"], 120,
                         "a valid solution")
                dive(gcs)
                gcs.stick = {"x": 600, "y": 0, "z": 500, "r": 0}  # a lane, held by the ground station's thread
                time.sleep(25.0)
                t_cut = time.time()
                relay.cut(DROPOUT_S)
                time.sleep(DROPOUT_S + 15.0)  # the dropout, then 15 s of the lane after it
                gcs.stick = {"x": 0, "y": 0, "z": 500, "r": 0}
                time.sleep(3.0)
                health = daemon._health_report()
                report["rejected"] = {k: v for k, v in health["rejected"].items() if k in ("data_gap", "clock_jump")}
                report["datagrams_dropped"] = relay.dropped

                truth = truth_ned(gcs, origin)
                t_unix, pos, valid = navlog.arrays("t_unix_s")
                states = [s for s in navlog.states if s.get("t_unix_s") is not None and s["pos_n_m"][0] is not None]

                def error_at(wall_s: float) -> tuple[float, float]:
                    k = int(np.argmin(np.abs(truth[:, 0] - wall_s)))
                    ours = [np.interp(wall_s, t_unix, pos[:, i]) for i in range(2)]
                    s = min(states, key=lambda st: abs(st["t_unix_s"] - wall_s))
                    return math.hypot(ours[0] - truth[k, 1], ours[1] - truth[k, 2]), _sigma_h_m(s)

                def moved(a: float, b: float) -> float:
                    ka, kb = (int(np.argmin(np.abs(truth[:, 0] - w))) for w in (a, b))
                    return math.hypot(truth[kb, 1] - truth[ka, 1], truth[kb, 2] - truth[ka, 2])

                t_back = t_cut + DROPOUT_S
                err_before, sigma_before = error_at(t_cut - 0.5)
                err_after, sigma_after = error_at(t_back + 2.0)
                err_late, sigma_late = error_at(t_back + 14.0)
                report.update(moved_during_dropout_m=round(moved(t_cut, t_back), 2),
                              error_before_m=round(err_before, 2), sigma_h_before_m=round(sigma_before, 2),
                              error_2s_after_m=round(err_after, 2), sigma_h_2s_after_m=round(sigma_after, 2),
                              error_14s_after_m=round(err_late, 2), sigma_h_14s_after_m=round(sigma_late, 2),
                              truth_depth_m=round(float(truth[-1, 3]), 2))
            finally:
                (out / "dropout.json").write_text(json.dumps(report, indent=2, default=str) + "\n")
                print(json.dumps(report, indent=2, default=str))
                if daemon is not None:
                    daemon.stop()
    finally:
        relay.stop()

    assert report["datagrams_dropped"] > 100 and report["truth_depth_m"] > 1.0
    assert report["rejected"].get("data_gap") == 1 and not report["rejected"].get("clock_jump"), report["rejected"]
    moved_m = report["moved_during_dropout_m"]
    assert moved_m > 3.0, "the vehicle drove through the dropout"
    # coasted at the lane's velocity: re-based, the error would have grown by what it drove
    assert report["error_2s_after_m"] < report["error_before_m"] + 0.3 * moved_m
    assert report["sigma_h_2s_after_m"] > report["sigma_h_before_m"]  # and it says it is less sure
    assert report["error_2s_after_m"] < 3.0 * report["sigma_h_2s_after_m"]
