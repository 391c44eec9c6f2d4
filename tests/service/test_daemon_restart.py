"""`adaptnav run` as a real subprocess: SIGKILLed and restarted, it restores what it
learned (motion params from a calibrator release and the filter's slow states)."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from adaptnav.fusion.motion_model import MotionParams
from adaptnav.service.transport.release import release_to_dict
from adaptnav.service.runtime.persistence import load_state

from .test_daemon_support import Feeder, free_port, peer, wait_until

pytestmark = pytest.mark.timeout(150)

ADAPTNAV = Path(sys.executable).with_name("adaptnav")


def _start(cfg_path: Path, log_path: Path) -> subprocess.Popen:
    log = open(log_path, "ab")
    return subprocess.Popen([str(ADAPTNAV), "run", "--config", str(cfg_path)], stdout=log, stderr=log)


def test_sigkill_then_restart_restores_learned_state(tmp_path):
    port = free_port()
    state_dir = tmp_path / "state"
    cfg_path = tmp_path / "adaptnav.toml"
    cfg_path.write_text(f"""
state_dir = "{state_dir}"
[vehicle]
name = "testauv"
[zenoh]
listen = ["tcp/127.0.0.1:{port}"]
scouting = false
[calibrator]
location = "remote"
[persistence]
period_s = 0.3
""")
    log_path = tmp_path / "daemon.log"
    proc = _start(cfg_path, log_path)
    bus = peer(port)
    feeder = None
    try:
        assert wait_until(lambda: bus.get("config", timeout_s=0.5), timeout_s=60), log_path.read_text()
        feeder = Feeder(bus)
        feeder.start()
        assert wait_until(lambda: (s := bus.get("state", timeout_s=0.5)) and s.get("t_s") is not None, 30)
        learned = MotionParams(var_vv=0.004, var_ww=0.003, k_v=1.15, b_w=0.001)
        from adaptnav.calibration.online import Release

        rel = Release(t_s=feeder.t_s, params=learned, log_likelihood=-12.5, accepted=True,
                              reason="", iterations=3)
        assert bus.wait_subscribed(bus.keys.params)
        bus.put(bus.keys.params, json.dumps(release_to_dict(rel)).encode())
        got = wait_until(lambda: (p := bus.get("params", timeout_s=0.5)) and p["params"]["k_v"] == 1.15 and p, 60)
        assert got, "the daemon did not apply the release"
        # wait for a periodic write that carries the release (no clean shutdown follows)
        assert wait_until(lambda: (st := load_state(state_dir)) and st.params == learned, 60)
        k_speed_before = bus.get("state")["k_speed"]
        feeder.stop()
        proc.send_signal(signal.SIGKILL)
        proc.wait(10)
        assert proc.returncode == -signal.SIGKILL

        proc = _start(cfg_path, log_path)
        assert wait_until(lambda: bus.get("config", timeout_s=0.5), timeout_s=60), log_path.read_text()
        params = bus.get("params")
        assert params["restored"] is True
        assert MotionParams.from_dict(params["params"]) == learned
        feeder = Feeder(bus, t0_s=1000.0)
        feeder.start()
        state = wait_until(lambda: (s := bus.get("state", timeout_s=0.5)) and s.get("t_s") and s, 60)
        # the slow state k_speed survives the restart (fresh filter would start at 1.0)
        assert state["k_speed"] == pytest.approx(k_speed_before, rel=1e-6)
        assert abs(state["k_speed"] - 1.0) > 0.05
    finally:
        if feeder is not None:
            feeder.stop()
        bus.close()
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(15)
            except subprocess.TimeoutExpired:
                proc.kill()
    assert proc.returncode == 0, log_path.read_text()[-3000:]  # SIGTERM: clean shutdown


def test_systemd_notify_ready_watchdog_stopping(tmp_path):
    """With NOTIFY_SOCKET set (as systemd Type=notify does), the daemon says READY=1,
    feeds the watchdog while it runs and says STOPPING=1 on SIGTERM."""
    import socket

    sock_path = str(tmp_path / "notify.sock")
    srv = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    srv.bind(sock_path)
    srv.settimeout(60)
    port = free_port()
    env = dict(os.environ, NOTIFY_SOCKET=sock_path, WATCHDOG_USEC="400000")
    proc = subprocess.Popen([str(ADAPTNAV), "run", "--set", f'zenoh.listen=["tcp/127.0.0.1:{port}"]',
                             "--set", f'state_dir="{tmp_path}/state"', "--set", "calibrator.enabled=false"],
                            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    got: list[str] = []
    try:
        while not any("READY=1" in m for m in got):
            got.append(srv.recv(4096).decode())
        srv.settimeout(30)
        while sum("WATCHDOG=1" in m for m in got) < 2:
            got.append(srv.recv(4096).decode())
        proc.send_signal(signal.SIGTERM)
        while not any("STOPPING=1" in m for m in got):
            got.append(srv.recv(4096).decode())
        assert proc.wait(20) == 0, proc.stderr.read().decode()[-2000:]
    finally:
        if proc.poll() is None:
            proc.kill()
        srv.close()
    assert (tmp_path / "state" / "learned_state.json").exists()  # written at shutdown


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split(")")[-1].split()[0] != "Z"  # a zombie is dead
    except FileNotFoundError:
        return False


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="parent-death signal is Linux's")
def test_the_calibrator_child_dies_with_a_sigkilled_daemon(tmp_path):
    """It used to live on (192 MB, parent 1) after the daemon was SIGKILLed."""
    port = free_port()
    cfg_path = tmp_path / "adaptnav.toml"
    cfg_path.write_text(f"""
state_dir = "{tmp_path / 'state'}"
[vehicle]
name = "testauv"
[zenoh]
listen = ["tcp/127.0.0.1:{port}"]
scouting = false
""")
    log_path = tmp_path / "daemon.log"
    proc = _start(cfg_path, log_path)
    child = None
    try:
        bus = peer(port)
        try:
            health = wait_until(lambda: (h := bus.get("health", timeout_s=0.5)) and h["calibrator"].get("pid")
                                and h, timeout_s=90)
        finally:
            bus.close()
        assert health, log_path.read_text()[-2000:]
        child = int(health["calibrator"]["pid"])
        assert _alive(child)
        proc.send_signal(signal.SIGKILL)
        proc.wait(10)
        assert wait_until(lambda: not _alive(child), timeout_s=20), "the calibrator outlived its daemon"
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
        if child is not None and _alive(child):
            os.kill(child, signal.SIGKILL)
