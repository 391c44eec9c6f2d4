"""Golden replays against their committed references (tests/golden/golden.py says how
they are made and how to regenerate them after a change of behaviour made on purpose)."""
from __future__ import annotations

import json

import pytest

from . import golden


@pytest.mark.parametrize("case", sorted(golden.CASES))
def test_replay_matches_its_golden_reference(case, tmp_path):
    if not golden.available(case):
        pytest.skip(f"{case}: input absent (../shared/data)")
    ref_path = golden.reference_path(case)
    assert ref_path.exists(), f"no reference for {case}: run `make golden`"
    got = golden.run_case(case, tmp_path)
    diffs = golden.differences(got, json.loads(ref_path.read_text()), case)
    assert not diffs, (f"{len(diffs)} differences from the golden reference (first 15 below). If the change "
                       f"of behaviour is intended, regenerate with `make golden` and say why in the commit:\n"
                       + "\n".join(diffs[:15]))


def test_the_comparison_sees_a_moved_number():
    ref = {"trajectory": [{"t_s": 1.0, "north_m": 10.0, "yaw_rad": 0.5}], "aid_status": {"usbl/1/": 3}}
    assert not golden.differences(json.loads(json.dumps(ref)), ref)
    moved = {"trajectory": [{"t_s": 1.0, "north_m": 10.01, "yaw_rad": 0.5}], "aid_status": {"usbl/1/": 2}}
    diffs = golden.differences(moved, ref)
    assert len(diffs) == 2 and "north_m" in diffs[0] and "tolerance 0.001" in diffs[0]
