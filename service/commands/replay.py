"""`adaptnav replay` (being built; see the issue tracker)."""
HELP = "replay (not built yet)"


def add_arguments(parser):
    pass


def run(args):
    raise SystemExit("adaptnav replay: not built yet")
