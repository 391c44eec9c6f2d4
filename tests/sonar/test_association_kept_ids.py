"""The associator keeps in its id sets (sightings in weak pairs, paired, tested) only the ids of
sightings it still holds: :meth:`LegAssociator._kept_ids`, which reads the stored ones from
their arrays' id columns, against the set of every held sighting's id, on seeded surveys whose
stores drop sightings by age and by count (some pending ones no longer stored)."""
from __future__ import annotations

from itertools import chain

import numpy as np
import pytest

from adaptnav.sonar.association import AssociationConfig, LegAssociator
from tests.sonar.test_association_shortcuts import _relative_covs, _survey


def _held_ids(la: LegAssociator) -> set[int]:
    return set(map(id, chain(la._old, la._weak_old, la._pending, la._weak_pending)))


@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("memory", [(3600.0, 5000), (560.0, 5000), (3600.0, 12)])
def test_kept_ids_are_the_held_sightings_ids(seed, memory, monkeypatch):
    memory_s, max_sightings = memory
    cfg = AssociationConfig(memory_s=memory_s, max_sightings=max_sightings)
    fast = LegAssociator(cfg, relative_covs=_relative_covs)
    plain = LegAssociator(cfg, relative_covs=_relative_covs)
    monkeypatch.setattr(plain, "_kept_ids", lambda ids: ids & _held_ids(plain))
    seen: list = []  # (every sighting stays referenced: no id is reused)
    pending_only = dropped = 0
    for batch in _survey(seed):
        seen += batch
        fast.add(batch)
        plain.add(batch)
        held = _held_ids(fast)
        every = set(map(id, seen)) | {0, 1, -5}
        assert fast._kept_ids(every) == every & held
        assert fast._kept_ids(set()) == set()
        assert (fast._weak_used, fast._paired, fast._tested) == (plain._weak_used, plain._paired, plain._tested)
        assert fast._weak_used <= held
        stored = set(map(id, fast._old))
        pending_only += any(id(o) not in stored for o in fast._pending)
        dropped += len(every) - 3 - len(held)
    assert fast.weak_pairs > 0 or memory != (3600.0, 5000)  # (small stores find no set)
    if memory_s < 3600.0 or max_sightings < 100:  # (the stores dropped sightings)
        assert dropped > 0
    if max_sightings < 100:
        assert pending_only > 0


def test_kept_ids_edge_cases():
    """Empty stores and an empty set; a store rebuilt when its list was replaced."""
    la = LegAssociator(relative_covs=_relative_covs)
    assert la._kept_ids({1, 2}) == set()
    batch = _survey(0)[0]
    la.add(batch)
    ids = set(map(id, batch))
    assert la._kept_ids(ids | {3}) == ids & _held_ids(la)
    la._old = list(la._old[:1])  # (replaced: the arrays are built again for the new list)
    assert la._kept_ids(ids) == ids & _held_ids(la)
    assert np.all(la._stored_arrays()["id"] == [id(o) for o in la._old])
