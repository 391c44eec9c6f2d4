"""The service config on the command line, the same for every verb that reads it:
``--config FILE`` and repeatable ``--set section.key=value``."""
from __future__ import annotations


def add_config_arguments(parser, config_help: str = "service config (TOML); defaults when omitted") -> None:
    parser.add_argument("--config", metavar="FILE", help=config_help)
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="override a config key, e.g. --set zenoh.mode=client (repeatable)")


def load_config_or_report(args, verb: str):
    """The service config from ``args``, or None after a one-line error naming the key
    (the verb then exits 2). Imports lazily: ``warmup`` sets numba's cache first."""
    import sys

    from adaptnav.fusion.typed_config import ConfigError
    from adaptnav.service.config import load_config

    try:
        return load_config(args.config, args.overrides)
    except ConfigError as e:
        print(f"adaptnav {verb}: config error: {e}", file=sys.stderr)
        return None
