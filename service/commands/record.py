"""`adaptnav record --out FILE.mcap [--duration S]`: record all bus traffic of a vehicle.

Subscribes to ``adaptnav/<v>/**`` (sensor samples, nav states, aid statuses, calibrator
releases, health) as a Zenoh peer connecting to the daemon's endpoints (or ``--connect``)
and writes every message to MCAP through :func:`adaptnav.service.transport.logs.write_mcap` — the format
``adaptnav replay`` reads. Messages that are not valid adaptnav JSON are counted and
reported, not written. Ends after ``--duration`` seconds or on SIGINT/SIGTERM.
"""
from __future__ import annotations

from adaptnav.service.commands.config_args import add_config_arguments, load_config_or_report

HELP = "record all Zenoh bus traffic of a vehicle to an MCAP file"


def add_arguments(parser):
    parser.add_argument("--out", required=True, metavar="FILE.mcap", help="output MCAP file")
    parser.add_argument("--duration", type=float, default=None, metavar="S",
                        help="stop after S seconds (default: until Ctrl-C / SIGTERM)")
    add_config_arguments(parser, "service config (vehicle name, zenoh)")
    parser.add_argument("--connect", action="append", default=[], metavar="ENDPOINT",
                        help="Zenoh endpoint to connect to (default: the daemon's listen endpoints)")


def recorder_zenoh(cfg, connect=()):
    """Zenoh config of the recorder: a *client* of the daemon's peer (or of the router),
    listening nowhere — the daemon routes every program's traffic to its clients, so the
    recorder sees what other nodes publish too (a plain peer would only see the daemon's);
    with the config's TLS and user/password identity (``ZenohConfig.as_client``)."""
    return cfg.zenoh.as_client(tuple(connect))


def record(bus, out, stop, duration_s=None, metadata=None, origin=None):
    """Record ``adaptnav/<v>/**`` from ``bus`` into ``out`` until ``stop`` or the duration.

    Log times are the wall clock at reception (Foxglove's timeline shows when it happened);
    with ``origin`` (:class:`GeoOrigin` of the daemon's NED frame) the nav solution, aid
    statuses and releases are also written in Foxglove's well-known schemas
    (:func:`adaptnav.service.runtime.foxglove.bus_message_encoder`).

    Returns ``(counts_by_kind, malformed_count)``.
    """
    import queue
    import time

    from adaptnav.fusion.samples import SampleError
    from adaptnav.service.transport import codec
    from adaptnav.service.transport.logs import LOG_CLOCK_KEY, RECEPTION_WALL_CLOCK, write_mcap

    inbox: queue.Queue = queue.Queue()
    malformed = [0]

    def on_message(key, payload):  # Zenoh thread: decode and enqueue only
        try:
            inbox.put(codec.decode(payload))
        except SampleError:
            malformed[0] += 1

    bus.subscribe_raw(bus.keys.all, on_message)
    deadline = None if duration_s is None else time.monotonic() + duration_s

    def messages():
        while True:
            if stop.is_set() or (deadline is not None and time.monotonic() >= deadline):
                break
            try:
                yield inbox.get(timeout=0.1)
            except queue.Empty:
                continue
        while True:  # what already arrived is written too
            try:
                yield inbox.get_nowait()
            except queue.Empty:
                return

    extra = None
    if origin is not None:
        from adaptnav.service.runtime.foxglove import TimeBase, bus_message_encoder

        extra = bus_message_encoder(origin, TimeBase.wall())
    metadata = {**(metadata or {}), LOG_CLOCK_KEY: RECEPTION_WALL_CLOCK}
    counts = write_mcap(out, messages(), metadata=metadata, log_time_ns=lambda _t: time.time_ns(), extra=extra)
    return counts, malformed[0]


def run(args):
    import logging
    import math
    import signal
    import sys
    import threading

    from adaptnav.service.transport.bus import Bus, _strict
    from adaptnav.service.config import config_dict

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    cfg = load_config_or_report(args, "record")
    if cfg is None:
        return 2
    from adaptnav.service.commands.paths import output_file_problem

    problem = output_file_problem(args.out)
    if problem:  # before connecting: the file was opened once the session was up
        print(f"adaptnav record: --out {args.out}: {problem}", file=sys.stderr)
        return 2
    if args.duration is not None and not 0.0 < args.duration < math.inf:  # (NaN: never stopped)
        print(f"adaptnav record: --duration must be a positive number of seconds, got {args.duration:g}",
              file=sys.stderr)
        return 2
    import zenoh

    from adaptnav.service.daemon import startup_error

    try:
        bus = Bus(recorder_zenoh(cfg, args.connect), cfg.vehicle.name)
    except zenoh.ZError as e:
        print(f"adaptnav record: cannot connect: {startup_error(e)}", file=sys.stderr)
        return 2
    stop = threading.Event()
    # Ctrl-C and SIGTERM end the recording in order (the file closed); the caller's handlers
    # come back after it (in-process callers, tests: a handler left here reached every child
    # they forked later, which then outlived its terminate)
    previous = {s: signal.signal(s, lambda *_: stop.set()) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        print(f"recording adaptnav/{cfg.vehicle.name}/** to {args.out} "
              f"({'until Ctrl-C' if args.duration is None else f'{args.duration:g} s'})", file=sys.stderr)
        counts, malformed = record(bus, args.out, stop, args.duration,
                                   metadata={"recorded_by": "adaptnav record", "vehicle": cfg.vehicle.name,
                                             "service_config": _strict(config_dict(cfg))},
                                   origin=cfg.origin.geo())
    except OSError as e:  # a full disk, an I/O error: said in one line, not a traceback
        print(f"adaptnav record: cannot write {args.out}: {e.strerror or e}; the recording stopped there",
              file=sys.stderr)
        return 1
    finally:
        bus.close()
        for signum, handler in previous.items():
            signal.signal(signum, handler)
    total = sum(n for k, n in counts.items() if k != "skipped")
    print(f"wrote {total} messages to {args.out}: "
          + ", ".join(f"{k} {n}" for k, n in sorted(counts.items()))
          + (f"; {malformed} malformed messages skipped" if malformed else ""), file=sys.stderr)
    return 0
