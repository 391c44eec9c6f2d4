"""``adaptnav`` command line: one verb per job, each in ``service/commands/<verb>.py``.

A command module defines ``HELP`` (one line), ``add_arguments(parser)`` and
``run(args) -> int``. Heavy imports (zenoh, cv2, numba) stay inside ``run`` so that
``adaptnav --help`` is instant.
"""
from __future__ import annotations

import argparse
import importlib
import sys

VERBS = ("simulate", "replay", "run", "record", "demo", "experiment", "sonar", "bench", "warmup")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="adaptnav",
        description="Model-aided inertial navigation for AUVs with an online-learned motion model.",
    )
    sub = parser.add_subparsers(dest="verb", metavar="VERB", required=True)
    for verb in VERBS:
        module = importlib.import_module(f"adaptnav.service.commands.{verb}")
        p = sub.add_parser(verb, help=module.HELP, description=module.HELP)
        module.add_arguments(p)
        p.set_defaults(_run=module.run)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return int(args._run(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
