"""`adaptnav run --config FILE [--set section.key=value ...] [--calibrator-only]`.

Starts the live navigation daemon (:mod:`service.daemon`): Zenoh bus, runner thread
with the ESKF, calibrator child process, MAVLink bridge when enabled. With
``--calibrator-only`` it runs just the EM calibrator as a bus node (for another
computer or shore-side): it subscribes to ``adaptnav/<v>/sensor/*`` and publishes
releases on ``adaptnav/<v>/calibration/params``; the daemon then uses
``calibrator.location = "remote"``.
"""
from __future__ import annotations

from adaptnav.service.commands.config_args import add_config_arguments, load_config_or_report

HELP = "run the live navigation daemon (Zenoh, calibrator process, MAVLink bridge)"


def add_arguments(parser):
    add_config_arguments(parser)
    parser.add_argument("--calibrator-only", action="store_true",
                        help="run only the EM calibrator as a bus node")
    parser.add_argument("--print-config", action="store_true",
                        help="print the effective config as JSON and exit")


def run(args):
    import json

    from adaptnav.service.config import config_dict

    cfg = load_config_or_report(args, "run")
    if cfg is None:
        return 2
    if args.print_config:
        from adaptnav.service.transport.bus import _strict

        print(json.dumps(_strict(config_dict(cfg)), indent=2, sort_keys=True))
        return 0
    from adaptnav.service import daemon

    if args.calibrator_only:
        return daemon.serve_calibrator(cfg)
    return daemon.serve(cfg)
