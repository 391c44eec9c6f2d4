"""`adaptnav bench service`'s `mavlink_cpu` refuses a run in which the daemon did not navigate
ArduSub's stream (:func:`unnavigated_reason`): the CPU share of an idle daemon is no figure."""
from __future__ import annotations

from adaptnav.service.tools.benchmarks.service import unnavigated_reason


def test_a_navigated_session_passes_and_an_idle_daemon_does_not():
    # stop 38's run: 75 s of the SITL session's frames (136/s), the bridge's health after it
    assert unnavigated_reason(10200, 8963, "RAW_IMU") == ""
    assert "no IMU stream" in unnavigated_reason(10200, 0, None)  # the bridge never heard the autopilot
    assert "no IMU stream" in unnavigated_reason(10200, 2000, None)  # pressure and thrust alone
    assert "took 40 samples" in unnavigated_reason(10200, 40, "RAW_IMU")  # the link died early
