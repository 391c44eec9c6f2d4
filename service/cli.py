"""``adaptnav`` command line: one verb per job, each in ``service/commands/<verb>.py``.

A command module defines ``HELP`` (one line), ``add_arguments(parser)`` and
``run(args) -> int``. Heavy imports (zenoh, cv2, numba) stay inside ``run`` so that
``adaptnav --help`` is instant.

Options every verb takes, before or after the verb: ``--version``, ``-v/--verbose``
(repeatable), ``-q/--quiet`` (errors only, no progress), ``--log-level LEVEL`` (one of
:data:`adaptnav.service.console.LEVELS`; anything else is refused), ``--log-json`` (one JSON
object per log line, for journald). Logs, warnings and progress go to stderr
(:mod:`adaptnav.service.console`); stdout carries a verb's result only.
"""
from __future__ import annotations

import argparse
import importlib
import sys

VERBS = ("simulate", "replay", "run", "record", "demo", "experiment", "sonar", "bench", "warmup")
# verbs that run as services: INFO by default (lifecycle events); the others WARNING
SERVICE_VERBS = ("run", "record")


def _log_level(text: str) -> str:
    from adaptnav.service.console import LEVELS

    level = text.upper()
    if level not in LEVELS:
        raise argparse.ArgumentTypeError(f"unknown log level {text!r} (choose from {', '.join(LEVELS)})")
    return level


def _common(parser: argparse.ArgumentParser, suppress: bool) -> None:
    """The options of every verb; on a verb's parser their defaults are suppressed so that
    ``adaptnav -v run`` and ``adaptnav run -v`` mean the same."""
    d = (lambda v: argparse.SUPPRESS) if suppress else (lambda v: v)
    parser.add_argument("-v", "--verbose", action="count", default=d(0),
                        help="more log output (-v: one level more, -vv: debug)")
    parser.add_argument("-q", "--quiet", action="store_true", default=d(False),
                        help="errors only, no progress")
    parser.add_argument("--log-level", type=_log_level, default=d(None), metavar="LEVEL",
                        help="DEBUG, INFO, WARNING, ERROR or CRITICAL (overrides -v/-q)")
    parser.add_argument("--log-json", action="store_true", default=d(False),
                        help="log lines as JSON objects (for journald and log collectors)")


def _version() -> str:
    from adaptnav import __version__

    return __version__


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="adaptnav",
        description="Model-aided inertial navigation for AUVs with an online-learned motion model.",
    )
    parser.add_argument("--version", action="version", version=f"adaptnav {_version()}")
    _common(parser, suppress=False)
    sub = parser.add_subparsers(dest="verb", metavar="VERB", required=True)
    for verb in VERBS:
        module = importlib.import_module(f"adaptnav.service.commands.{verb}")
        p = sub.add_parser(verb, help=module.HELP, description=module.HELP)
        _common(p, suppress=True)
        module.add_arguments(p)
        p.set_defaults(_run=module.run)
    return parser


def main(argv: list[str] | None = None) -> int:
    from adaptnav.service.console import level_for, setup_logging

    args = build_parser().parse_args(argv)
    default = "INFO" if args.verb in SERVICE_VERBS else "WARNING"
    setup_logging(level_for(args.log_level, args.verbose, args.quiet, default), args.log_json, args.quiet)
    try:
        return int(args._run(args) or 0)
    except KeyboardInterrupt:  # Ctrl-C: a clean stop, never a traceback
        print("adaptnav: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
