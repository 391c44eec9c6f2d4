"""The association's shortcuts (:mod:`adaptnav.sonar.association`) change no result: the pairs a
bound on their covariances' traces places beyond the wide gate, the searches that cannot found a
set, against the whole computation on seeded random surveys (edge cases among the covariances)."""
from __future__ import annotations

import numpy as np
import pytest

from adaptnav.sonar import association
from adaptnav.sonar.association import LegAssociator
from adaptnav.sonar.objects import ObjectSighting


def test_the_traces_bound_never_drops_a_pair_the_full_distance_keeps():
    """:func:`_beyond_by_traces` over the sums of two covariances from round to near-singular,
    asymmetric, negative definite, indefinite and NaN, at distances around four times the gate
    by the traces: every pair it drops is dropped by the closed form or beyond the gate by the
    inverse, and it drops most pairs far away."""
    from adaptnav.sonar.association import _beyond_by_traces, _m2, _plain_traces, _surely_beyond

    rng = np.random.default_rng(11)
    n_old, n_new = 300, 40

    def covs(n):
        A = rng.normal(size=(n, 2, 2)) * rng.uniform(0.01, 30.0, size=(n, 1, 1))
        S = A @ A.transpose(0, 2, 1) + rng.uniform(0.0, 1.0, size=(n, 1, 1)) * np.eye(2)
        k = n // 12
        S[:k] *= np.array([[1.0, 0.0], [0.0, 1e-8]])                 # near-singular
        S[k:2 * k, 0, 1] += rng.normal(size=k) * 1e-3                # not symmetric
        S[2 * k:3 * k] = -S[2 * k:3 * k]                            # negative definite
        S[3 * k:4 * k, 1, 1] *= -1.0                                 # indefinite
        S[4 * k, 0, 0] = np.nan
        S[4 * k + 1, 1, 1] = np.inf
        S[4 * k + 2] *= np.array([[1.0, 0.0], [0.0, 2e-6]])          # at the conditioning limit
        return S

    A, B = covs(n_old), covs(n_new)
    gate = 9.0 * 13.8
    tr = np.abs(np.trace(A, axis1=1, axis2=2))[None] + np.abs(np.trace(B, axis1=1, axis2=2))[:, None]
    u = rng.normal(size=(n_new, n_old, 2))
    u /= np.linalg.norm(u, axis=2, keepdims=True)
    d = u * np.sqrt(4.0 * gate * np.nan_to_num(tr, nan=1.0, posinf=1.0) * rng.uniform(0.5, 3.0, (n_new, n_old)))[..., None]
    d[0, 0] = np.nextafter(d[0, 0], 0.0)
    dropped = _beyond_by_traces((d ** 2).sum(axis=2), _plain_traces(A), _plain_traces(B), gate)
    S = A[None] + B[:, None]
    j, k = np.nonzero(dropped & ~_surely_beyond(d, S, gate))
    with np.errstate(all="ignore"):
        assert np.all(_m2(d[j, k], S[j, k]) > gate)
    # ...and drops every pair of plain covariances a little beyond its bound, none of others
    plain = ~np.isnan(_plain_traces(A))[None] & ~np.isnan(_plain_traces(B))[:, None]
    far = plain & ((d ** 2).sum(axis=2) > 4.01 * gate * np.trace(S, axis1=2, axis2=3))
    assert dropped.sum() > 1000 and dropped[far].all()
    assert not dropped[~plain].any()


def _sighting(rng, t_s, pos, weak=False, nav_cov=None):
    det = rng.normal(size=(2, 2)) * 0.3
    return ObjectSighting(t_s=float(t_s), side="starboard", ground_range_m=20.0, height_m=rng.uniform(0.3, 0.6),
                          shadow_length_m=1.0, length_along_m=rng.uniform(0.8, 1.2), width_across_m=0.5,
                          contrast=10.0, altitude_m=10.0, pos_n_m=np.asarray(pos, float) + rng.normal(0.0, 0.25, 2),
                          nav_cov=np.eye(2) * rng.uniform(0.5, 6.0) if nav_cov is None else nav_cov,
                          det_cov=det @ det.T + 0.05 * np.eye(2), jump_n_m=rng.normal(0.0, 0.1, 2),
                          vel_cov=np.eye(2) * rng.uniform(0.01, 0.2) ** 2, weak=weak)


def _survey(seed):
    """Batches of two legs over the same objects (the second offset by a drifting error), a few
    objects seen once and weak sightings among them; some navigation covariances degenerate."""
    rng = np.random.default_rng(seed)
    objs = np.column_stack([np.arange(40) * 6.0, 20.0 + rng.uniform(-3.0, 3.0, 40)])
    odd = [np.full((2, 2), np.nan), np.array([[4.0, 0.0], [0.0, -1.0]]), np.array([[1e6, 0.0], [0.0, 1e-6]]),
           -np.eye(2), np.array([[1.0, 2.0], [0.0, 1.0]])]
    batches, t = [], 1000.0
    for leg, (t0, err) in enumerate([(1000.0, np.zeros(2)), (1500.0, np.array([1.5, -2.0]))]):
        order = range(40) if leg == 0 else range(39, -1, -1)
        batch = []
        for i, o in enumerate(order):
            t = t0 + 4.0 * i
            if rng.random() < 0.85:
                nav = odd[rng.integers(len(odd))] if rng.random() < 0.05 else None
                batch.append(_sighting(rng, t, objs[o] + err + 0.002 * (t - t0), nav_cov=nav))
            if rng.random() < 0.5:
                on_object = rng.random() < 0.5  # (else speckle)
                pos = objs[o] + err + rng.normal(0.0, 0.3, 2) if on_object else objs[o] + rng.normal(0.0, 4.0, 2)
                batch.append(_sighting(rng, t + 0.5, pos, weak=True))
            if len(batch) >= rng.integers(1, 8):
                batches.append(batch)
                batch = []
        batches.append(batch)
    return [b for b in batches if b]


def _relative_covs(t_old, t_new):
    """A filter's answer, a function of the times: some unknown, some not finite, one indefinite."""
    t_old = np.asarray(t_old, float)
    s = 0.5 + 0.01 * np.abs(t_new - t_old)
    cov = s[:, None, None] * np.eye(2) + 0.1 * np.sin(t_old)[:, None, None] * np.array([[0.0, 1.0], [1.0, 0.0]])
    known = (np.round(t_old) % 7) != 0
    cov[np.round(t_old) % 11 == 0] = np.nan
    cov[np.round(t_old) % 13 == 0] = np.array([[1.0, 0.0], [0.0, -0.5]])
    return cov, known


def _record(lc):
    if lc is None:
        return None
    pairs = tuple((id(a), id(b)) for a, b in tuple(lc.pairs) + tuple(lc.weak_pairs))
    return (lc.t_a_s, lc.t_b_s, lc.offset_n_m.tobytes(), np.asarray(lc.cov).tobytes(), lc.n_objects, repr(lc.nis),
            pairs)


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("relative", [True, False])
def test_the_shortcuts_change_no_closure_nor_candidate(seed, relative, monkeypatch):
    """Every batch of a survey with and without the shortcuts (the traces' bound: off; the
    searches of too few sightings: made, as a trace makes them): the same closures, and the
    candidates of every batch the same, bit for bit."""
    batches = _survey(seed)
    rel = _relative_covs if relative else None
    fast = LegAssociator(relative_covs=rel)
    full = LegAssociator(relative_covs=rel)
    full.trace = {}  # (the trace notes every pair of every search: none skipped)
    fast_candidates = []
    closures = 0
    for batch in batches:
        ordinary = [o for o in batch if not o.weak]
        fast_candidates.append(fast.candidates(ordinary))
        got = _record(fast.add(batch))
        with monkeypatch.context() as m:
            m.setattr(association, "_beyond_by_traces", lambda d2, *_: np.zeros(d2.shape, bool))
            want_candidates = full.candidates(ordinary)
            want = _record(full.add(batch))
        assert got == want
        closures += got is not None
        (out, clutter), (out_w, clutter_w) = fast_candidates[-1], want_candidates
        assert [(i, j, m2) for i, j, m2, _ in out] == [(i, j, m2) for i, j, m2, _ in out_w]
        assert all(np.array_equal(S, S_w, equal_nan=True) for (*_, S), (*_, S_w) in zip(out, out_w))
        assert clutter.keys() == clutter_w.keys()
        assert all(np.array_equal(clutter[k], clutter_w[k], equal_nan=k != "j") for k in clutter)
    assert closures >= 2
    assert sum(len(c[0]) for c in fast_candidates) > 20


def test_the_stored_arrays_are_each_sightings_own_numbers():
    """:func:`_sighting_arrays` sums and differences whole arrays: each sighting's own
    ``nav_cov + det_cov`` and ``smooth_pos_n_m``, bit for bit, with and without jumps."""
    from dataclasses import replace

    from adaptnav.sonar.association import _sighting_arrays

    rng = np.random.default_rng(2)
    sightings = [_sighting(rng, t, rng.uniform(-1e3, 1e3, 2)) for t in rng.uniform(0.0, 3600.0, 50)]
    sightings = [replace(o, nav_cov=o.nav_cov * rng.uniform(0.1, 10.0, (2, 2)), jump_n_m=o.jump_n_m * 1e3)
                 for o in sightings]
    for group in (sightings, [replace(o, jump_n_m=None) if k % 3 == 0 else o for k, o in enumerate(sightings)],
                  sightings[:1], []):
        arrays = _sighting_arrays(group)
        assert arrays["cov"].shape == (len(group), 2, 2) and arrays["smooth_pos_n_m"].shape == (len(group), 2)
        for k, o in enumerate(group):
            assert np.array_equal(arrays["cov"][k], o.nav_cov + o.det_cov)
            assert np.array_equal(arrays["smooth_pos_n_m"][k], o.smooth_pos_n_m)
            assert np.array_equal(arrays["pos_n_m"][k], o.pos_n_m) and arrays["t_s"][k] == o.t_s


@pytest.mark.parametrize("seed", range(2))
def test_the_weak_sightings_are_kept_apart(seed):
    """The associator's lists of ordinary sightings hold no weak one and its weak lists only
    weak ones (:meth:`LegAssociator._with_weak` tells them apart by their lists)."""
    fast = LegAssociator(relative_covs=_relative_covs)
    weak_seen = 0
    for batch in _survey(seed):
        fast.add(batch)
        assert not any(o.weak for o in fast._old + fast._pending)
        assert all(o.weak for o in fast._weak_old + fast._weak_pending)
        weak_seen += len(fast._weak_pending)
    assert weak_seen > 0 and fast.weak_pairs > 0


def test_an_indefinite_relative_covariance_is_not_taken_as_known():
    """A filter's relative covariance that is no covariance (indefinite: a difference of nearly
    equal covariances) made pairs' m² negative — inside every gate — and their clutter areas NaN,
    so the chance-inlier count was NaN and the bound on the set size (``_min_objects``) never
    rose above its minimum. Such a covariance is not known: every clutter area stays finite."""
    def indefinite(t_old, t_new):
        t_old = np.asarray(t_old, float)
        cov = np.broadcast_to(np.array([[1.0, 0.0], [0.0, -0.5]]), (t_old.size, 2, 2)).copy()
        return cov, np.ones(t_old.size, bool)

    assoc = LegAssociator(relative_covs=indefinite)
    areas = 0
    for batch in _survey(0):
        _, clutter = assoc.candidates([o for o in batch if not o.weak])
        assert np.all(np.isfinite(clutter["area_m2"])), clutter["area_m2"]
        areas += clutter["area_m2"].size
        assoc.add(batch)
    assert areas > 0  # (clutter was met: the test saw areas)


@pytest.mark.parametrize("seed", range(4))
def test_a_degenerate_navigation_covariance_leaves_no_nan_clutter_area(seed):
    """A sighting's navigation covariance that is no covariance (the survey's odd ones: NaN,
    indefinite, negative) gave its pairs no usable m² and a NaN clutter area (seed 3 did): such
    a pair is no candidate, every clutter area stays finite."""
    assoc = LegAssociator()
    for batch in _survey(seed):
        _, clutter = assoc.candidates([o for o in batch if not o.weak])
        assert np.all(np.isfinite(clutter["area_m2"])), clutter["area_m2"]
        assoc.add(batch)
