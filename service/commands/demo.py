"""`adaptnav demo` (being built; see the issue tracker)."""
HELP = "demo (not built yet)"


def add_arguments(parser):
    pass


def run(args):
    raise SystemExit("adaptnav demo: not built yet")
