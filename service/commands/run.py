"""`adaptnav run --config FILE [--set section.key=value ...] [--calibrator-only]`.

Starts the live navigation daemon (:mod:`service.daemon`): Zenoh bus, runner thread
with the ESKF, calibrator child process, MAVLink bridge when enabled. With
``--calibrator-only`` it runs just the EM calibrator as a bus node (for another
computer or shore-side): it subscribes to ``adaptnav/<v>/sensor/*`` and publishes
releases on ``adaptnav/<v>/calibration/params``; the daemon then uses
``calibrator.location = "remote"``.
"""
from __future__ import annotations

HELP = "run the live navigation daemon (Zenoh, calibrator process, MAVLink bridge)"


def add_arguments(parser):
    parser.add_argument("--config", metavar="FILE", help="service config (TOML); defaults when omitted")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="override a config key, e.g. --set zenoh.mode=client (repeatable)")
    parser.add_argument("--calibrator-only", action="store_true",
                        help="run only the EM calibrator as a bus node")
    parser.add_argument("--print-config", action="store_true",
                        help="print the effective config as JSON and exit")


def run(args):
    import json
    import sys

    from adaptnav.fusion.typed_config import ConfigError
    from adaptnav.service.config import config_dict, load_config

    try:
        cfg = load_config(args.config, args.overrides)
    except ConfigError as e:
        print(f"adaptnav run: config error: {e}", file=sys.stderr)
        return 2
    if args.print_config:
        from adaptnav.service.transport.bus import _strict

        print(json.dumps(_strict(config_dict(cfg)), indent=2, sort_keys=True))
        return 0
    from adaptnav.service import daemon

    if args.calibrator_only:
        return daemon.serve_calibrator(cfg)
    return daemon.serve(cfg)
