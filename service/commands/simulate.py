"""`adaptnav simulate` (being built; see the issue tracker)."""
HELP = "simulate (not built yet)"


def add_arguments(parser):
    pass


def run(args):
    raise SystemExit("adaptnav simulate: not built yet")
