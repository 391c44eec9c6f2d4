"""A sample the daemon took from MAVLink goes on the bus for the other nodes only, and only
while one subscribes (:meth:`Bus.publish_sample_to_others`, real Zenoh sessions on loopback):
nothing is encoded for nobody, nothing comes back to the daemon's own subscribers, and a
recorder that subscribes gets every sample from then on."""
from __future__ import annotations

import pytest

from adaptnav.fusion.samples import DepthSample
from adaptnav.service.config import ZenohConfig
from adaptnav.service.transport.bus import Bus

from .test_daemon_support import free_port, peer, wait_until

pytestmark = pytest.mark.timeout(120)


def test_samples_go_to_other_nodes_only_while_one_subscribes():
    port = free_port()
    daemon_side = Bus(ZenohConfig(listen=(f"tcp/127.0.0.1:{port}",), scouting=False), "others")
    own: list = []
    daemon_side.subscribe_samples(own.append)  # the daemon's own bus input
    recorder = None
    try:
        # nobody else: not published (and not back to the daemon's own subscriber)
        assert daemon_side.publish_sample_to_others(DepthSample(1.0, 101325.0)) is False
        recorder = peer(port, "others")
        got: list = []
        recorder.subscribe_samples(got.append)
        encodings: list[str] = []
        recorder.session.declare_subscriber(recorder.keys.sensor("depth"), lambda z: encodings.append(str(z.encoding)))
        # the subscription reaches the daemon's session: from then on every sample goes out
        assert wait_until(lambda: daemon_side.publish_sample_to_others(DepthSample(2.0, 101325.0)), 30.0)
        sent = [DepthSample(3.0 + 0.1 * i, 101325.0 + 100.0 * i) for i in range(50)]
        assert all(daemon_side.publish_sample_to_others(s) for s in sent)
        assert wait_until(lambda: len(got) >= 51, 30.0)
        assert [s.pressure_pa for s in got[-50:]] == [s.pressure_pa for s in sent]
        assert own == []
        # declared as a driver's publisher of that key is (the schema in its encoding), so a
        # recorder or a remote calibrator cannot tell the two apart
        recorder.publish_sample(DepthSample(9.0, 101325.0))
        assert wait_until(lambda: len(encodings) >= 52, 30.0)
        assert set(encodings) == {encodings[-1]} and "adaptnav.depth" in encodings[-1]
    finally:
        if recorder is not None:
            recorder.close()
        daemon_side.close()
