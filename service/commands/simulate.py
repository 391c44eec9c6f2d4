"""`adaptnav simulate SCENARIO [--set k=v ...] --out FILE.mcap`: a scenario to an MCAP log.

Writes every sensor sample and the ground truth (see :mod:`adaptnav.service.transport.logs`) with the
effective scenario config in the file's metadata, shows a progress bar, and prints a
one-line summary (samples per kind, duration).
"""
from __future__ import annotations

HELP = "simulate a scenario (sim/scenarios/*.toml) to an MCAP log with ground truth"


def add_arguments(parser):
    parser.add_argument("scenario", help="scenario name (survey, short, demo, ...) or path to a .toml")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="override a scenario key, e.g. --set dvl.enabled=true (repeatable)")
    parser.add_argument("--out", help="output .mcap file (required unless --live)")
    parser.add_argument("--live", choices=("zenoh", "mavlink"),
                        help="feed a running daemon instead of writing a file, as a vehicle would: "
                             "'zenoh' publishes the samples on adaptnav/<v>/sensor/* (a Zenoh client of "
                             "--connect), 'mavlink' plays an ArduSub autopilot on --url")
    parser.add_argument("--connect", default="tcp/127.0.0.1:7447", metavar="ENDPOINT",
                        help="--live zenoh: the daemon's (or router's) endpoint (default tcp/127.0.0.1:7447)")
    parser.add_argument("--vehicle", default="auv1", help="--live zenoh: the vehicle name in the keys (default auv1)")
    parser.add_argument("--url", default="udpout:127.0.0.1:14550", metavar="URL",
                        help="--live mavlink: where the daemon's bridge listens (default udpout:127.0.0.1:14550)")
    parser.add_argument("--speed", type=float, default=1.0, metavar="X",
                        help="--live: data seconds per wall second (default 1 = real time)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def run(args):
    import sys
    import time

    from adaptnav.service.console import progress

    from adaptnav.fusion.typed_config import ConfigError, as_dict
    from adaptnav.service.transport.logs import write_mcap
    from adaptnav.service.runtime.foxglove import TimeBase, bus_message_encoder
    from adaptnav.sim.scenario import load_scenario, start_unix_s
    from adaptnav.sim.simulator import simulate

    try:
        scenario = load_scenario(args.scenario, args.overrides)
    except ConfigError as e:
        print(f"adaptnav simulate: {e}", file=sys.stderr)
        return 2
    if args.live:
        from adaptnav.service.tools.live_vehicle import run_live

        return run_live(scenario, args)
    if not args.out:
        print("adaptnav simulate: give --out FILE.mcap (or --live zenoh|mavlink)", file=sys.stderr)
        return 2
    from adaptnav.service.commands.paths import output_file_problem

    problem = output_file_problem(args.out)
    if problem:  # before the simulation: a traceback came after all of it
        print(f"adaptnav simulate: --out {args.out}: {problem}", file=sys.stderr)
        return 2
    if not scenario.start_utc:  # the log (and every replay of it) starts now on Foxglove's timeline
        from dataclasses import replace
        from datetime import datetime, timezone

        scenario = replace(scenario, start_utc=datetime.now(timezone.utc).replace(microsecond=0).isoformat())
    t0 = time.perf_counter()
    result = simulate(scenario)
    t_sim = time.perf_counter() - t0
    for note in result.notes:
        print(f"note: {note}", file=sys.stderr)
    total = sum(result.counts().values())
    metadata = {"scenario": as_dict(scenario), "scenario_name": scenario.name, "generator": "adaptnav simulate"}
    t1 = time.perf_counter()
    bar = progress(total, f"writing {args.out}", "msg", not args.no_progress)
    tb = TimeBase(unix_s=start_unix_s(scenario.start_utc), data_s=0.0)
    try:
        counts = write_mcap(args.out, result.iter_blocks(), metadata, progress=bar.update if bar else None,
                            log_time_ns=tb.ns, extra=bus_message_encoder(scenario.origin.geo(), tb))
    except OSError as e:  # a full disk, an I/O error: said in one line, not a traceback after the simulation
        print(f"adaptnav simulate: cannot write {args.out}: {e.strerror or e}", file=sys.stderr)
        return 1
    finally:
        if bar is not None:
            bar.close()
    t_write = time.perf_counter() - t1
    per_kind = " ".join(f"{k}={v}" for k, v in sorted(counts.items()))
    print(f"{args.out}: {scenario.name} {scenario.duration_s:.0f} s simulated, {sum(counts.values())} "
          f"messages ({per_kind}); simulate {t_sim:.1f} s, write {t_write:.1f} s")
    return 0
