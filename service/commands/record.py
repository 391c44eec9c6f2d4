"""`adaptnav record` (being built; see the issue tracker)."""
HELP = "record (not built yet)"


def add_arguments(parser):
    pass


def run(args):
    raise SystemExit("adaptnav record: not built yet")
