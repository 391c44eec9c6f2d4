"""`adaptnav sonar` (being built; see the issue tracker)."""
HELP = "sonar (not built yet)"


def add_arguments(parser):
    pass


def run(args):
    raise SystemExit("adaptnav sonar: not built yet")
