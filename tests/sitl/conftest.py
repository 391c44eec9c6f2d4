"""Live tests against the real ArduSub SITL: they pace on the wall clock (minutes), so they
run only when asked for (``make test-sitl``, i.e. ``pytest -m sitl tests/sitl``), never in
the default ``pytest tests`` run, and skip cleanly when the binary is absent."""
import pytest

from .ardusub import BINARY


def pytest_collection_modifyitems(config, items):
    asked = "sitl" in (config.getoption("-m") or "")
    for item in items:
        if "sitl" not in item.keywords:
            continue
        if not asked:
            item.add_marker(pytest.mark.skip(reason="live ArduSub SITL test: run `make test-sitl`"))
        elif not BINARY.is_file():
            item.add_marker(pytest.mark.skip(reason=f"ArduSub SITL binary absent: {BINARY}"))
