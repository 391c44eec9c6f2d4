"""``adaptnav simulate SCENARIO --live zenoh|mavlink``: a simulated vehicle feeding a running
daemon as a real one would — the documented way to try the live service without hardware.

- ``zenoh``: a Zenoh *client* of the daemon (``--connect``) publishing every sensor sample on
  ``adaptnav/<v>/sensor/<kind>`` at ``--speed`` × real time (what a vehicle's drivers do);
- ``mavlink``: an ArduSub-like autopilot (:class:`adaptnav.service.tools.sitl_vehicle.SitlVehicle`)
  on ``--url``, for a daemon with ``[mavlink] enabled = true``.

Truth never goes on the bus (a vehicle has none). Ctrl-C stops it.
"""
from __future__ import annotations

import logging
import math
import signal
import sys
import threading
import time
from typing import Any, Iterable

log = logging.getLogger(__name__)


def publish_paced(bus: Any, samples: Iterable[Any], speed: float, stop: threading.Event) -> dict[str, int]:
    """Publish ``samples`` (time order) on ``bus`` at ``speed`` data seconds per wall second
    (0: as fast as possible); returns the count per kind. Truth is skipped."""
    counts: dict[str, int] = {}
    t0 = wall0 = None
    for sample in samples:
        if stop.is_set():
            break
        kind = sample.KIND
        if kind == "truth":
            continue
        t = float(sample.t_s)
        if speed > 0 and math.isfinite(t):
            if t0 is None:
                t0, wall0 = t, time.monotonic()
            due = wall0 + (t - t0) / speed
            delay = due - time.monotonic()
            if delay > 0 and stop.wait(delay):  # pacing the vehicle's own sensors
                break
        bus.publish_sample(sample)
        counts[kind] = counts.get(kind, 0) + 1
    return counts


def run_live(scenario: Any, args: Any) -> int:
    import zenoh

    from adaptnav.sim.simulator import simulate

    if not (args.speed >= 0 and math.isfinite(args.speed)):
        print("adaptnav simulate: --speed must be ≥ 0", file=sys.stderr)
        return 2
    stop = threading.Event()
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    result = simulate(scenario)
    if args.live == "mavlink":
        from adaptnav.service.tools.sitl_vehicle import SitlVehicle, SitlVehicleConfig

        vehicle = SitlVehicle(result.iter_samples(), SitlVehicleConfig(url=args.url, speed=args.speed))
        vehicle.start()
        print(f"simulated ArduSub vehicle on {args.url}: {scenario.name}, {scenario.duration_s:.0f} s of data at "
              f"{args.speed:g}× real time (Ctrl-C stops)", file=sys.stderr)
        while not (vehicle.done.wait(0.5) or stop.is_set()):
            pass
        vehicle.stop()
        print(f"done: ODOMETRY received from the daemon: {vehicle.received['odometry']}", file=sys.stderr)
        return 0 if vehicle.error is None else 1

    from adaptnav.service.config import ZenohConfig
    from adaptnav.service.daemon import startup_error
    from adaptnav.service.transport.bus import Bus

    try:
        bus = Bus(ZenohConfig(mode="client", connect=(args.connect,), listen=(), scouting=False,
                              connect_timeout_s=10.0), args.vehicle)
    except zenoh.ZError as e:
        print(f"adaptnav simulate: cannot connect to {args.connect}: {startup_error(e)}", file=sys.stderr)
        return 2
    print(f"publishing {scenario.name} on adaptnav/{args.vehicle}/sensor/* via {args.connect}: "
          f"{scenario.duration_s:.0f} s of data at {args.speed:g}× real time (Ctrl-C stops)", file=sys.stderr)
    try:
        counts = publish_paced(bus, result.iter_samples(), args.speed, stop)
    finally:
        bus.close()
    print("published " + ", ".join(f"{k} {n}" for k, n in sorted(counts.items())), file=sys.stderr)
    return 0
