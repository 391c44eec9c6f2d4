"""The association's reuse of work within a call (:mod:`adaptnav.sonar.association`) changes no
number: one design matrix for a drift's residuals and their covariances, views of the leading
stored rows in place of copies, against the plain computations on seeded random inputs (NaN,
inf, empty, single, out-of-order)."""
from __future__ import annotations

import numpy as np
import pytest

from adaptnav.sonar import association
from adaptnav.sonar.association import Drift, LegAssociator
from tests.sonar.test_association_shortcuts import _record, _relative_covs, _survey


def _drift(rng, t_a_s=100.0, t_b_s=700.0):
    A = rng.normal(size=(6, 6))
    return Drift(t_a_s, t_b_s, rng.normal(size=6), A @ A.T, np.zeros(6), np.eye(6))


@pytest.mark.parametrize("n", [0, 1, 2, 17])
def test_residuals_are_predict_and_residual_cov_bit_for_bit(n):
    """:meth:`Drift.residuals` (one design matrix for both) against :meth:`Drift.predict` and
    :meth:`Drift.residual_cov`, each building its own, times and offsets with NaN and inf."""
    rng = np.random.default_rng(n)
    drift = _drift(rng)
    t_a = rng.uniform(0.0, 200.0, n)
    t_b = rng.uniform(600.0, 800.0, n)
    diffs = rng.normal(size=(n, 2)) * 5.0
    D = rng.normal(size=(n, 2, 2))
    if n > 2:
        t_a[0], t_b[1], diffs[2, 0], D[1, 0, 1] = np.nan, np.inf, -np.inf, np.nan
    r, R = drift.residuals(diffs, t_a, t_b, D)
    assert np.array_equal(r, diffs - drift.predict(t_a, t_b), equal_nan=True)
    assert np.array_equal(R, drift.residual_cov(t_a, t_b, D), equal_nan=True)
    assert r.shape == (n, 2) and R.shape == (n, 2, 2)


def test_the_leading_rows_are_a_slice_only_when_they_are_the_first():
    """:func:`_leading_or` gives a slice exactly for the indices 0..n−1 (those rows' views), else
    the indices themselves."""
    from adaptnav.sonar.association import _leading_or

    rows = np.arange(20.0).reshape(10, 2)
    for k in ([0, 1, 2], [0], list(range(10)), [], [1, 2, 3], [0, 2, 3], [0, 1, 3], [5], [0, 1, 2, 9]):
        k = np.asarray(k, dtype=np.intp)
        pick = _leading_or(k)
        assert isinstance(pick, slice) == (k.size > 0 and np.array_equal(k, np.arange(k.size)))
        assert np.array_equal(rows[pick], rows[k])


@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("relative", [True, False])
def test_candidates_and_closures_are_those_of_copied_rows(seed, relative, monkeypatch):
    """A survey (its store in time order, and one with sightings shuffled and late: earlier
    sightings not the store's first) with views of the leading rows and with the copies the
    indices take: the same closures and candidates, bit for bit."""
    for shuffle in (False, True):
        rng = np.random.default_rng(seed)
        batches = _survey(seed)
        if shuffle:  # (and a sighting of every third batch comes two batches late)
            batches = [[b[k] for k in rng.permutation(len(b))] for b in batches]
            for k in range(0, len(batches) - 2, 3):
                if len(batches[k]) > 1:
                    batches[k + 2].append(batches[k].pop(0))
        rel = _relative_covs if relative else None
        fast, plain = LegAssociator(relative_covs=rel), LegAssociator(relative_covs=rel)
        closures = 0
        for batch in batches:
            ordinary = [o for o in batch if not o.weak]
            got_c = fast.candidates(ordinary)
            got = _record(fast.add(batch))
            with monkeypatch.context() as m:
                m.setattr(association, "_leading_or", lambda k: k)
                want_c = plain.candidates(ordinary)
                want = _record(plain.add(batch))
            assert got == want
            closures += got is not None
            (out, clutter), (out_w, clutter_w) = got_c, want_c
            assert [(i, j, m2) for i, j, m2, _ in out] == [(i, j, m2) for i, j, m2, _ in out_w]
            assert all(np.array_equal(S, S_w, equal_nan=True) for (*_, S), (*_, S_w) in zip(out, out_w))
            assert all(np.array_equal(clutter[k], clutter_w[k], equal_nan=k != "j") for k in clutter)
        assert closures >= 2


def test_smooth_positions_are_each_sightings_own():
    """:func:`_smooth_positions` (one subtraction of the stacked arrays) against each sighting's
    ``smooth_pos_n_m``, bit for bit: with jumps, some without, single, empty, NaN and inf."""
    from dataclasses import replace

    from adaptnav.sonar.association import _smooth_positions
    from tests.sonar.test_association_shortcuts import _sighting

    rng = np.random.default_rng(5)
    sightings = [_sighting(rng, t, rng.uniform(-1e4, 1e4, 2)) for t in rng.uniform(0.0, 3600.0, 30)]
    sightings = [replace(o, jump_n_m=o.jump_n_m * 1e3) for o in sightings]
    sightings[3] = replace(sightings[3], pos_n_m=np.array([np.nan, 1.0]))
    sightings[4] = replace(sightings[4], jump_n_m=np.array([np.inf, -2.0]))
    for group in (sightings, [replace(o, jump_n_m=None) if k % 4 == 0 else o for k, o in enumerate(sightings)],
                  sightings[5:6], [replace(sightings[6], jump_n_m=None)], []):
        got = _smooth_positions(group)
        assert got.shape == (len(group), 2)
        for k, o in enumerate(group):
            assert np.array_equal(got[k], o.smooth_pos_n_m, equal_nan=True)
        assert np.array_equal(_smooth_positions(group, np.array([o.pos_n_m for o in group]).reshape(-1, 2)), got,
                              equal_nan=True)
