"""`adaptnav experiment` (being built; see the issue tracker)."""
HELP = "experiment (not built yet)"


def add_arguments(parser):
    pass


def run(args):
    raise SystemExit("adaptnav experiment: not built yet")
