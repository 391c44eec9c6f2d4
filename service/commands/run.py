"""`adaptnav run` (being built; see the issue tracker)."""
HELP = "run (not built yet)"


def add_arguments(parser):
    pass


def run(args):
    raise SystemExit("adaptnav run: not built yet")
