"""The first side-scan object batch imports nothing: the estimator loads what placing and
associating objects needs when it is made. (Importing the sonar package in the first batch
cost that batch's bus callback 25 ms live — the largest latency of a survey with pings.)
Run in a fresh interpreter, where nothing else has imported the sonar package."""
from __future__ import annotations

import json
import subprocess
import sys
import textwrap

import pytest

pytestmark = pytest.mark.timeout(180)

_CHILD = textwrap.dedent("""
    import json, sys, tempfile
    from pathlib import Path
    from adaptnav.service.loop_closures import SideScanEstimator
    from adaptnav.service.runtime.replay import build_config, open_scenario, replay

    batches = []
    place = SideScanEstimator._objects

    def spy(self, batch):
        before = set(sys.modules)
        out = place(self, batch)
        batches.append({"sightings": len(batch.sightings), "navigation": bool(self._nav),
                        "imported": sorted(set(sys.modules) - before)})
        return out

    SideScanEstimator._objects = spy
    inp = open_scenario("survey", ["dvl.enabled=true", "sonar.enabled=true", "duration_s=60"])
    with tempfile.TemporaryDirectory() as tmp:
        replay(inp, build_config(inp.scenario), Path(tmp) / "r", calibrate=True,
               calibrator_location="inline", progress=False, plots=False)
    print(json.dumps(batches))
""")


def test_object_batches_import_nothing():
    out = subprocess.run([sys.executable, "-c", _CHILD], check=True, capture_output=True, text=True)
    batches = json.loads(out.stdout.strip().splitlines()[-1])
    placed = [b for b in batches if b["sightings"] and b["navigation"]]
    assert placed, batches  # the survey's pings gave objects the filter placed
    assert all(not b["imported"] for b in batches), batches
