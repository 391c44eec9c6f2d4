"""The calibrator's heap (:mod:`adaptnav.service.calibrator.heap`): with its thresholds raised,
a second particle filter of the benchmark's size takes no new pages; without, it takes
every page of its arrays again (the control: what the setting is for). Page faults are
counted, not timed, so the machine's speed does not enter."""
from __future__ import annotations

import json
import subprocess
import sys
import textwrap

import pytest

pytestmark = pytest.mark.timeout(120)

_CHILD = textwrap.dedent("""
    import json, resource, sys
    import numpy as np
    from adaptnav.service.calibrator.heap import keep_freed_heap
    from adaptnav.calibration.particle_filter import run_particle_filter
    from adaptnav.calibration.thesis import ThesisRow, simulate, _init_cloud

    kept = keep_freed_heap() if sys.argv[1] == "keep" else None
    data = simulate(ThesisRow(0.05, 0.05, 0.2, 0.05, 2.0, steps=100), np.random.default_rng(1))
    rng = np.random.default_rng(2)
    init = _init_cloud(1000, rng)
    faults = []
    for _ in range(3):
        before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
        fr = run_particle_filter(data.params_initial, data.v, data.w, data.dt, data.observations, init, rng, 1000)
        del fr
        faults.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
    print(json.dumps({"kept": kept, "faults": faults}))
""")


def _faults(mode: str) -> dict:
    out = subprocess.run([sys.executable, "-c", _CHILD, mode], check=True, capture_output=True, text=True)
    return json.loads(out.stdout)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt and Linux page-fault counts")
def test_em_arrays_stay_mapped_between_iterations():
    kept = _faults("keep")
    assert kept["kept"] is True
    # the arrays (cloud, weights, ancestors, normals: ~7.6 MB, ~1850 pages) are reused
    assert max(kept["faults"][1:]) < 100, kept
    # the control: glibc's defaults give the pages back, so each filter faults them in again
    # (~1850 here; fewer where transparent huge pages back the arrays, never none)
    control = _faults("default")
    assert min(control["faults"][1:]) > max(kept["faults"][1:]), (kept, control)
