"""The benchmarks of ``adaptnav bench`` (one module per target: ``run(args) -> dict``)."""


class BenchArgsError(ValueError):
    """An argument a benchmark cannot run with: ``adaptnav bench`` says it in one line, exit 2."""
