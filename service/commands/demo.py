"""``adaptnav demo``: simulated ArduSub vehicle → MAVLink/Zenoh → daemon + calibrator →
ODOMETRY back; then pure INS / static model / learned model compared (service/tools/demo.py)."""
from __future__ import annotations

HELP = "the whole system on this machine against a simulated 20-min mission; table + plots"


def add_arguments(parser):
    parser.add_argument("--out", default="out", metavar="DIR", help="plots and outputs (default: out/)")
    parser.add_argument("--speed", type=float, default=20.0, metavar="X",
                        help="live run pace, data seconds per wall second (default 20)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="scenario override on sim/scenarios/demo.toml, e.g. duration_s=180 "
                             "(a 'scenario.' prefix is accepted; repeatable)")
    parser.add_argument("--json", action="store_true", help="print the summary as JSON")
    parser.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")


def run(args):
    import json
    import logging
    import math
    import sys

    from adaptnav.fusion.typed_config import ConfigError

    from adaptnav.service.tools.demo import format_demo_table, run_demo, scenario_overrides

    logging.basicConfig(level=logging.WARNING, stream=sys.stderr,
                        format="%(levelname)s %(name)s: %(message)s")
    if not (args.speed > 0 and math.isfinite(args.speed)):
        print("adaptnav demo: --speed must be a positive number", file=sys.stderr)
        return 2
    try:
        summary = run_demo(scenario_overrides(args.set), args.out, args.speed,
                           progress=not args.no_progress, plots=not args.no_plots)
    except (ConfigError, ValueError, FileNotFoundError) as e:
        print(f"adaptnav demo: {e}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps(summary, indent=2, default=str))
        return 0
    sc = summary["scenario"]
    learned = summary["learned"]
    print(f"adaptnav demo: {sc['name']}, {sc['duration_s']:.0f} s, environment change at "
          f"{sc['change_at_s']:.0f} s (k_V {sc['params_before']['k_v']:.3g} → {sc['params_after']['k_v']:.3g})")
    print(format_demo_table(summary))
    print(f"live: {learned['nav_states_received']} nav states over Zenoh, "
          f"{learned['odometry_received_by_vehicle']} ODOMETRY at the vehicle, "
          f"{learned['sonar_pings_published']} side-scan pings, "
          f"{learned['releases_accepted']}/{learned['releases']} calibrator releases accepted")
    if summary.get("plots"):
        print(f"plots in {args.out}/: {', '.join(summary['plots'])}")
    print(f"wall time {summary['wall_s']:.0f} s")
    return 0
