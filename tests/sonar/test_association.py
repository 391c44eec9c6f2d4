"""Cross-leg association (:mod:`adaptnav.sonar.association`) on placed sightings: the drift of a
set's offset along its legs, from the navigation's velocity covariance and fitted on the set."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from adaptnav.sonar.association import LegAssociator
from adaptnav.sonar.objects import ObjectSighting


def _placed(t_s, pos_n_m, rng, vel_sigma_m_s=None, height_m=0.5, length_m=1.0):
    """A sighting at ``pos_n_m`` (+ 0.25 m detector noise), navigation σ 2 m, the velocity σ given."""
    vel_cov = None if vel_sigma_m_s is None else np.eye(2) * vel_sigma_m_s ** 2
    return ObjectSighting(t_s=t_s, side="starboard", ground_range_m=20.0, height_m=height_m, shadow_length_m=1.0,
                          length_along_m=length_m, width_across_m=0.5, contrast=10.0, altitude_m=10.0,
                          pos_n_m=np.asarray(pos_n_m, float) + rng.normal(0.0, 0.25, 2),
                          nav_cov=np.eye(2) * 4.0, det_cov=np.eye(2) * 0.3 ** 2, jump_n_m=np.zeros(2),
                          vel_cov=vel_cov)


def _objects(rng, n=10, spacing_m=7.0):
    return np.column_stack([np.arange(n) * spacing_m, 20.0 + rng.uniform(-3.0, 3.0, n)])


def test_a_set_whose_old_leg_drifts_is_one_set_with_its_drift_fitted():
    """Before the first fix the jump-free track drifts ~0.1 m/s (the navigation's velocity
    error): over the 36 s of one leg's stretch the offsets of true pairs spread by 3.6 m. A
    fixed allowance (0.015 m/s) split them and kept a few; with the drift the sightings'
    velocity covariance allows, fitted on the set, all ten are one set and the closure's
    offset is the error difference at its own two times."""
    rng = np.random.default_rng(3)
    objs = _objects(rng)
    e_a0, u_a, e_b = np.array([0.5, -1.0]), np.array([0.08, -0.06]), np.array([-2.5, 1.5])

    def e_a(t):
        return e_a0 + u_a * (t - 1000.0)

    assoc = LegAssociator()
    assoc.add([_placed(1000.0 + 4.0 * i, p + e_a(1000.0 + 4.0 * i), rng, 0.15) for i, p in enumerate(objs)])
    lc = assoc.add([_placed(1300.0 + 4.0 * (9 - i), p + e_b, rng, 0.03) for i, p in enumerate(objs)])
    assert lc is not None and lc.n_objects >= 9
    assert all(np.allclose(a.pos_n_m - e_a(a.t_s), b.pos_n_m - e_b, atol=1.5) for a, b in lc.pairs)
    r = lc.offset_n_m - (e_a(lc.t_a_s) - e_b)
    assert float(r @ np.linalg.solve(lc.cov, r)) < 13.8  # χ²₂ 99.9 %
    assert np.linalg.norm(r) < 0.5


@pytest.mark.parametrize("displaced_m", [0.0, 2.5])
def test_a_wide_velocity_prior_does_not_let_a_displaced_pair_continue_a_closure(displaced_m):
    """The old leg's velocity σ is 0.2 m/s (before the first fix): 8–12 s from the closure,
    its prior alone would allow metres. The set just accepted fitted the drift (it has none
    here), so two objects of the next block join it where they fit and not when displaced by
    2.5 m (survey seed 3 once extended a closure with a pair 6.6 m off in truth)."""
    rng = np.random.default_rng(7)
    objs = _objects(rng)
    e_a, e_b = np.array([0.5, -1.0]), np.array([-2.5, 1.5])
    assoc = LegAssociator()
    assoc.add([_placed(1000.0 + 4.0 * i, p + e_a, rng, 0.2) for i, p in enumerate(objs)])
    first = assoc.add([_placed(1300.0 + 4.0 * (9 - i), objs[i] + e_b, rng, 0.03) for i in range(4, 10)])
    assert first is not None and first.n_objects >= 5
    shift = np.array([displaced_m, 0.0])
    lc = assoc.add([_placed(1300.0 + 4.0 * (9 - i), objs[i] + e_b + shift, rng, 0.03) for i in (2, 3)])
    if displaced_m == 0.0:
        assert lc is not None and lc.n_objects == 2
        assert np.linalg.norm(lc.offset_n_m - (e_a - e_b)) < 1.0
    else:
        assert lc is None


@pytest.mark.parametrize("seed", range(6))
def test_no_closure_between_unrelated_sightings_with_a_wide_velocity_prior(seed):
    """Two legs over different objects, as dense as the gates allow (2 m navigation σ, a
    0.2 m/s velocity σ on both legs: every old sighting within the prior's reach of every new
    one): the drift fitted to wrong pairs must not pass the chance bound."""
    rng = np.random.default_rng(100 + seed)
    old = _objects(rng, 14, 3.0)
    new = np.column_stack([rng.uniform(0.0, 42.0, 14), 20.0 + rng.uniform(-3.0, 3.0, 14)])
    assoc = LegAssociator()
    assoc.add([_placed(1000.0 + 2.0 * i, p, rng, 0.2) for i, p in enumerate(old)])
    closures = [assoc.add([_placed(1300.0 + 2.0 * (13 - i) + 0.5 * k, p, rng, 0.2) for k, p in enumerate(new[i:i + 4])])
                for i in range(0, 14, 4)]
    assert all(lc is None for lc in closures), [lc.n_objects for lc in closures if lc is not None]


def test_a_pair_far_in_time_from_the_set_must_fit_the_drift_of_the_others():
    """Three true pairs within 14 s and a fourth 31–39 s away whose new sighting is a false
    detection 7.4 m along-track from the object (survey seed 4, these offsets): the three
    trend 0.7 m along-track, the fourth alone sets the rest of the drift and fits it exactly,
    and the set passed the joint test with the drift 1.5–2.4 σ of its prior. Tested against
    the drift of the other three it is over 3 σ off and is dropped (and three pairs are too
    few for a set)."""
    objs = np.array([[0.0, 20.0], [10.0, 18.0], [21.0, 21.0], [68.0, 19.0]])
    t_old = np.array([936.0, 943.2, 950.0, 981.4])
    t_new = np.array([1293.2, 1284.2, 1277.5, 1238.6])
    # the pairs' offsets on the jump-free tracks (old − new), as measured
    diffs = np.array([[1.16, -0.72], [0.65, -0.47], [0.49, -0.56], [-6.95, -1.49]])
    along = np.diag([0.04 ** 2, 0.006 ** 2])  # legs north-south: the velocity error along-track
    det = np.diag([0.45 ** 2, 0.32 ** 2])
    rng = np.random.default_rng(5)

    def sighting(t, p):
        return replace(_placed(t, p, rng), pos_n_m=np.asarray(p, float), vel_cov=along, det_cov=det)

    assoc = LegAssociator()
    assoc.add([sighting(t, p + d) for t, p, d in zip(t_old, objs, diffs)])
    new = [sighting(t, p) for t, p in zip(t_new, objs)]
    lc = assoc.add(new)
    assert lc is None or all(b is not new[3] for _, b in lc.pairs)


def test_the_gate_s_shortcut_never_drops_a_pair_the_full_distance_keeps():
    """Candidates skip the Mahalanobis distance where a closed-form bound says a pair lies beyond
    the wide gate: on covariances from round to near-singular, asymmetric, negative definite and
    indefinite, and residuals on and around the gate, every pair it skips is beyond the gate by the
    full computation, and it skips most pairs far away."""
    from adaptnav.sonar.association import _m2, _surely_beyond

    rng = np.random.default_rng(7)
    n = 20000
    A = rng.normal(size=(n, 2, 2)) * rng.uniform(0.01, 30.0, size=(n, 1, 1))
    S = A @ A.transpose(0, 2, 1) + rng.uniform(0.0, 1.0, size=(n, 1, 1)) * np.eye(2)
    S[: n // 10] *= np.array([[1.0, 0.0], [0.0, 1e-8]])          # near-singular
    S[n // 10: n // 5, 0, 1] += rng.normal(size=n // 10) * 1e-3   # not symmetric
    S[n // 5: n // 4] = -S[n // 5: n // 4]                        # negative definite
    S[n // 4: n // 3, 1, 1] *= -1.0                               # indefinite
    gate = 9.0 * 13.8
    # residuals at m² from well inside to far beyond the gate, in random directions
    L = np.linalg.cholesky(np.where(np.linalg.eigvalsh(0.5 * (S + S.transpose(0, 2, 1)))[:, :1, None] > 0, S,
                                    np.eye(2)))
    u = rng.normal(size=(n, 2))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    r = np.einsum("kij,kj->ki", L, u) * np.sqrt(gate * rng.uniform(0.2, 8.0, size=(n, 1)))
    skipped = _surely_beyond(r, S, gate)
    assert np.all(_m2(r[skipped], S[skipped]) > gate)
    far = _m2(r, S) > 4.0 * gate
    assert skipped[far].mean() > 0.5


def test_near_pairs_in_a_box_are_every_pair_the_norm_passes():
    """:func:`_near_pairs` takes the norm only inside a box a margin wider than the radius: the
    same booleans as the norm of every pair, pairs on the radius and just outside it included
    (along an axis, where a box without the margin would drop what the rounded norm passes),
    and nothing outside ``mask``."""
    from adaptnav.sonar.association import _near_pairs

    rng = np.random.default_rng(3)
    offset = np.array([0.3, -0.7])
    p_new = rng.uniform(-30.0, 30.0, (40, 2))
    p_old = np.concatenate([rng.uniform(-30.0, 30.0, (200, 2)),
                            # on the radius along an axis, a hair inside and outside it, diagonally
                            p_new[:4] + offset + np.array([[10.0, 0.0], [0.0, -10.0],
                                                           [np.nextafter(10.0, 0.0), 0.0],
                                                           [np.nextafter(10.0, 11.0), 0.0]]),
                            p_new[4:5] + offset + 10.0 / np.sqrt(2.0)])
    mask = rng.random((len(p_old), len(p_new))) < 0.9
    mask[200:, :5] = True
    d = p_old[:, None] - p_new[None] - offset
    want = mask & (np.linalg.norm(d.reshape(-1, 2), axis=1).reshape(mask.shape) <= 10.0)
    got = _near_pairs(p_old, p_new, offset, 10.0, mask)
    assert np.array_equal(got, want)
    assert want[200:, :5].any() and want.sum() > 100


def test_median_of_a_batchs_times_is_numpys():
    """:func:`_median` (the batch's median time the gate's clones are asked at) gives
    ``float(np.median(...))`` bit for bit: odd and even counts, ties, numpy floats, the mean
    of two middle values that do not halve exactly, and non-finite values (numpy's answer)."""
    from adaptnav.sonar.association import _median

    rng = np.random.default_rng(5)
    cases = [[1.0], [2.0, 1.0], [0.1, 0.2], [1e308, 1.7e308], [3.0, 3.0, 1.0, 3.0],
             [1.0, float("nan"), 2.0], [1.0, float("inf")], [-float("inf"), 0.0, 1.0]]
    for n in range(1, 40):
        t = rng.uniform(0.0, 3600.0, n)
        cases += [t.tolist(), list(t), np.round(t, 1).tolist(), (t * 0.1 + 1e-9).tolist()]
    for v in cases:
        with np.errstate(over="ignore"):  # (numpy's sum of the two largest overflows to inf: so does ours)
            got, want = _median(v), float(np.median(v))
        assert type(got) is float
        assert got == want or (np.isnan(got) and np.isnan(want)), (v, got, want)
