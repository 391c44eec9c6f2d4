"""Zenoh's thread pools as a Bus opens them (service/transport/bus.py ZENOH_RUNTIME): a real
session pair on loopback in a fresh process, its threads read from /proc."""
import json
import os
import subprocess
import sys

import pytest

pytestmark = pytest.mark.skipif(not os.path.isdir("/proc/self/task"), reason="needs Linux /proc")

PROBE = r"""
import json, os, socket, time
from adaptnav.service.config import ZenohConfig
from adaptnav.service.transport.bus import Bus
with socket.socket() as s:
    s.bind(("127.0.0.1", 0)); port = s.getsockname()[1]
server = Bus(ZenohConfig(listen=(f"tcp/127.0.0.1:{port}",), scouting=False), "probe")
got = []
server.subscribe_raw("adaptnav/probe/x", lambda k, p: got.append(p))
client = Bus(ZenohConfig(mode="client", connect=(f"tcp/127.0.0.1:{port}",), listen=()), "probe")
deadline = time.monotonic() + 20
while not got and time.monotonic() < deadline:  # the link carries a message both ways' setup
    client.put("adaptnav/probe/x", b"{}")
    time.sleep(0.05)
names = sorted(open(f"/proc/self/task/{t}/comm").read().strip() for t in os.listdir("/proc/self/task"))
print(json.dumps({"names": names, "received": bool(got), "env": os.environ.get("ZENOH_RUNTIME")}))
client.close(); server.close()
"""


def _probe(env_runtime=None):
    env = {k: v for k, v in os.environ.items() if k != "ZENOH_RUNTIME"}
    if env_runtime is not None:
        env["ZENOH_RUNTIME"] = env_runtime
    out = subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True, timeout=120, env=env)
    assert out.returncode == 0, out.stderr[-2000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


def _zenoh_threads(names):
    return sorted(n for n in names if n.split("-")[0] in ("app", "acc", "tx", "rx", "net"))


def test_a_bus_runs_zenoh_on_one_receiving_worker_and_the_application_pool():
    res = _probe()
    assert res["received"], "the two sessions did not talk"
    threads = _zenoh_threads(res["names"])
    # the app pool also names the threads tokio starts for blocking calls (app-1, ...)
    assert {n.split("-")[0] for n in threads} == {"app", "rx"} and "rx-1" not in threads, threads


def test_the_environments_own_zenoh_runtime_wins():
    res = _probe("(rx: (worker_threads: 2))")
    assert res["received"]
    assert res["env"] == "(rx: (worker_threads: 2))"
    threads = _zenoh_threads(res["names"])
    assert "rx-1" in threads and "tx-0" in threads, threads
