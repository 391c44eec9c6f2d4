"""`adaptnav bench TARGET`: speed/memory figures against a peer measured in the same run.

Each target lives in ``service/benchmarks/<target>.py`` with
``add_arguments(parser)`` (optional) and ``run(args) -> dict`` returning the figures;
this verb prints them as a table, or as JSON with ``--json``.
"""
from __future__ import annotations

import importlib
import json
import sys

HELP = "benchmarks (fusion, calibration, sonar, service, soak) with ratios against a peer"
TARGETS = ("fusion", "calibration", "sonar", "service", "soak")


def add_arguments(parser):
    parser.add_argument("target", choices=TARGETS, help="what to measure")
    parser.add_argument("--json", action="store_true", help="print the figures as JSON")
    parser.add_argument("--quick", action="store_true", help="smaller problem sizes (smoke run)")
    parser.add_argument("--only", metavar="PARTS", default=None,
                        help="service: comma-separated parts to measure (replay, floor, latency, mavlink_cpu, "
                             "cold_call, cold_start, memory, live_work; default all)")
    parser.add_argument("--latency-s", metavar="SECONDS", type=float, default=None,
                        help="service: the outside client's latency window per rate (default 60, --quick 15); "
                             "~300 s gives ~3000 nav states, enough for the p99's interval to decide the target")
    from adaptnav.service.tools.benchmarks import soak

    soak.add_arguments(parser)  # --minutes, --sample-s


# the options that belong to one target: given to another, they would be ignored without a word
TARGET_OPTIONS = {"only": "service", "latency_s": "service", "minutes": "soak", "sample_s": "soak"}


def run(args):
    from adaptnav.service.console import heartbeat
    from adaptnav.service.tools.benchmarks import BenchArgsError

    for dest, target in TARGET_OPTIONS.items():
        if getattr(args, dest, None) is not None and args.target != target:
            print(f"adaptnav bench {args.target}: --{dest.replace('_', '-')} is an option of "
                  f"`adaptnav bench {target}` only", file=sys.stderr)
            return 2
    module = importlib.import_module(f"adaptnav.service.tools.benchmarks.{args.target}")
    try:
        with heartbeat(f"bench {args.target}"):  # benchmarks take minutes: say it is alive (stderr)
            figures = module.run(args)
    except BenchArgsError as e:  # (checked before anything is measured)
        print(f"adaptnav bench {args.target}: {e}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps(figures, indent=2, sort_keys=True))
    else:
        width = max(len(k) for k in figures)
        for key, value in figures.items():
            shown = f"{value:.4g}" if isinstance(value, float) else value
            print(f"{key:<{width}}  {shown}")
    return 0
