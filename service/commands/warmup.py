"""`adaptnav warmup [--config FILE]`: compile the numba kernels into their on-disk cache.

Run once at install (``make``) and before every start of the systemd unit
(``ExecStartPre``): the daemon and its calibrator child then load compiled kernels
(a fraction of a second) instead of compiling them (~20 s here, a minute on a
Raspberry Pi) before their first solution. The cache is where numba puts it:
``NUMBA_CACHE_DIR`` when set (the unit sets ``/var/cache/adaptnav``, since the
installed package directory is read-only to the service), else ``__pycache__`` next to
the sources. A no-op when the cache is already current.
"""
from __future__ import annotations

HELP = "compile the numba kernels into their cache (install step; the unit's ExecStartPre)"


def add_arguments(parser):
    parser.add_argument("--config", metavar="FILE", help="service config (TOML); defaults when omitted")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="override a config key (repeatable)")


def run(args):
    import sys
    import time

    from adaptnav.fusion.typed_config import ConfigError
    from adaptnav.service.config import load_config

    try:
        cfg = load_config(args.config, args.overrides)
    except ConfigError as e:
        print(f"adaptnav warmup: config error: {e}", file=sys.stderr)
        return 2
    from adaptnav.service.daemon import warm_up_filter

    t_filter = warm_up_filter(cfg)
    t0 = time.monotonic()
    from adaptnav.service.calibrator.preload import warm_kernels

    warm_kernels()
    print(f"adaptnav warmup: filter kernels {t_filter:.1f} s, calibrator kernels "
          f"{time.monotonic() - t0:.1f} s")
    return 0
