r"""Object landmarks re-found on another leg: gated candidates, joint compatibility, loop closures.

Each :class:`~adaptnav.sonar.objects.ObjectSighting` carries its position from the
navigation at its ping, ``p̂ = p + e`` (``e`` the navigation error then) plus the detector's
offset, the navigation's covariance ``P`` there and the detector's covariance ``D``. Two
sightings ``a`` (an earlier leg) and ``b`` (the batch just detected) of one object satisfy

.. math:: p̂_a − p̂_b = e_a − e_b + n_a − n_b

1. **Candidates** (individual compatibility): the Mahalanobis distance of ``p̂_a − p̂_b`` in
   ``P_a + P_b + D_a + D_b`` — the navigation's own covariance at both times, so the gate
   grows with the drift; where the filter keeps clones of both epochs (``relative_covs``), the
   covariance of the error *difference* ``Σ_aa + Σ_bb − Σ_ab − Σ_ba`` replaces ``P_a + P_b``
   (during an outage most of the error is common to both legs) — is within the χ²₂ gate, and the view-independent attributes
   agree: height (from the shadow) and along-track length within ``attribute_sigmas``.
   Sightings of the same leg are not compared (``min_gap_s``).
2. **Joint compatibility** (Neira & Tardós 2001, as used for side-scan by Fallon et al.
   ICRA 2011): the navigation error is nearly common to a batch, so true pairs agree on one
   rigid offset ``δ = e_a − e_b`` — on the *jump-free* tracks
   (:attr:`~adaptnav.sonar.objects.ObjectSighting.smooth_pos_n_m`: a USBL fix or a fused
   closure between two sightings of one leg moved the filter's position by metres, and split
   sets that were one; the closure's offset then adds back the jumps at its two times; a translation: the heading
   aid bounds rotation), wrong ones scatter. RANSAC over the candidates (every candidate a hypothesis; one pair per object)
   keeps the largest set whose residuals ``p̂_a − p̂_b − δ`` are each within the gate and
   jointly within χ²₂ₙ₋₂. A jump-free track drifts with the navigation's velocity error,
   nearly constant over a set's minute (before the first fix ~0.2 m/s, in an outage
   ~0.02 m/s): the offset is ``δ₀ + u_a (t_a − t_a0) − u_b (t_b − t_b0)`` (:class:`Drift`),
   the velocity errors ``u`` with the navigation's velocity covariance at the sightings
   (:attr:`~adaptnav.sonar.objects.ObjectSighting.vel_cov`) as prior, fitted on the set: the
   first gate is the prior's (``D_a + D_b`` + the drift it allows), the next ones the
   fitted drift's (``D_a + D_b`` + its prediction's covariance). (A fixed 0.015 m/s
   allowance split the early legs' sets, whose pairs' offsets spread by metres, and cut
   true pairs in the outage, where it is exceeded by 7–15 % of one leg's sighting pairs.)
   Each candidate is a hypothesis with its own times ``t_a``, ``t_b``: its set draws on
   the candidates whose old sighting lies within ``set_span_s`` of ``t_a`` (one stretch of
   the earlier leg; a candidate on a leg an hour older, whose drift allowance spans metres,
   would agree with anything). Chance agreement is bounded per hypothesis, each pair with its own gate: a
   wrong old sighting lies anywhere in the wide region around its new sighting
   (``clutter_scale`` × that pair's gate), so it falls in the hypothesis' inlier region with
   probability (inlier area / wide area), both from that pair's covariances; ``λ``, the sum
   over the wrong old sightings of all new ones (within the span; per new sighting the
   likeliest left out — it may be the match), is the number of chance inliers expected, and
   a set of ``n`` needs ``H · P(Poisson(λ) ≥ n − 1) ≤ chance_probability`` over the ``H``
   hypotheses tried (or the same with the fitted drift's inlier regions, see
   :meth:`LegAssociator._min_objects`: wrong pairs that set the drift are paid for) — a cluttered seabed, a wide gate or many candidates ask for more
   objects, a sparse one does not. (Counting the clutter of all gates against the smallest
   gate's area asked a set of 12 true pairs for more than 12 on survey seed 1.)
   A pair whose sighting has a second candidate that also fits the offset is dropped
   (two neighbouring objects: either could be the match).
   A block often holds only one or two objects of the other leg: when the block alone gives
   no set, the sets are sought among the last ``window_s`` of new sightings not yet used.
   Failing that, the pairs that continue a closure of the last ``window_s`` (its fitted
   drift the hypothesis, not drawn from them) are accepted when chance alone would give as many with
   probability at most ``extend_probability`` (:meth:`LegAssociator.extend`).
3. A set of at least ``min_objects`` is one **loop closure**: times ``t_a``, ``t_b`` (the
   times of one pair's two sightings, the median on the new leg), the fitted drift's offset
   there and its covariance, the number of objects.

Weak sightings (:attr:`~adaptnav.sonar.objects.ObjectSighting.weak`, the detector's finds on
the unfiltered image: mostly speckle) take no part in steps 1–3; once a set is accepted, a pair
with a weak sighting joins its pairs where the set's fitted drift predicts it, the residual far
likelier for the object than for a false weak sighting lying there once weighed by the prior odds
that the other sighting's object is there to be seen (a weak sighting is itself an object once in 25)
(:meth:`LegAssociator._with_weak`): the closure's ``weak_pairs``; its pairs and offset stay the set's.

Reciprocal legs need nothing special here: attributes are view-independent and positions
are in the local frame (the image is not matched, so its along-track order does not matter).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from itertools import chain

import numpy as np
from scipy import special

from adaptnav.fusion.integrity import chi2_quantile
from adaptnav.sonar.objects import ObjectSighting


def poisson_sf(k: float, mu: float) -> float:
    """P(Poisson(``mu``) > ``k``): scipy.stats' ``poisson.sf`` through the special function it
    calls (the same floats; scipy.stats costs the service ~20 MB of resident memory)."""
    return 1.0 if k < 0 else float(special.pdtrc(math.floor(k), mu))


@dataclass(frozen=True)
class AssociationConfig:
    """Gates of :class:`LegAssociator`.

    Attributes
    ----------
    gate_probability : float
        Individual χ²₂ gate of the candidates (navigation + detector covariances).
    inlier_probability : float
        χ²₂ gate of a pair's residual from a set's offset (detector + relative drift).
    joint_probability : float
        Joint χ² gate of an accepted set.
    min_objects : int
        Smallest jointly compatible set accepted as a loop closure.
    min_gap_s : float
        Sightings closer in time are the same leg (not compared).
    attribute_sigmas : float
        Attribute agreement threshold (σ).
    height_sigma_m, height_sigma_fraction : float
        1-σ of a height from the shadow: ``a + b h``.
    length_sigma_m, length_sigma_fraction : float
        1-σ of an along-track length.
    relative_sigma_m_s : float
        The velocity error's σ (m/s, per axis) assumed for sightings without the
        navigation's velocity covariance (:class:`Drift`).
    max_candidates_per_object : int
        The nearest (Mahalanobis) old sightings kept per new one.
    chance_probability : float
        A set is accepted only if so many pairs agreeing with one hypothesis by chance is
        this unlikely (see the module docstring; per hypothesis: the hypotheses overlap, and
        a bound over all of them asked for twice the objects that were needed for no false
        link on the seeds tried).
    memory_s : float
        Old sightings are forgotten after this long.
    max_sightings : int
        …and beyond this many (the oldest first): the store is bounded on any seabed.
    clutter_scale : float
        The clutter (wrong sightings a gate may hold) is counted over this many times the
        gate's area, so that the true match is diluted (see :meth:`LegAssociator.candidates`).
    set_span_s : float
        A set's old sightings lie within this of its hypothesis' old sighting (s): the new
        ones span ``window_s`` plus a block, a reciprocal leg flown at the same speed the same.
    extend_probability : float
        Pairs that continue a recent closure (:meth:`LegAssociator.extend`) are accepted when
        chance would give as many with at most this probability (0: never extended).
    window_s : float
        New sightings not yet in an accepted set stay in play this long (s): a block often
        holds one or two objects of the other leg, fewer than a set needs, so the sets are
        sought among the last ``window_s`` of sightings; a sighting in an accepted set leaves
        the window (each pair enters one loop closure only).
    weak_clutter_per_m2, weak_density_radius_m : float
        A pair with a weak sighting (:attr:`~adaptnav.sonar.objects.ObjectSighting.weak`) joins
        an accepted set only where its residual from the set's prediction is far likelier for the
        object seen again than for a false weak sighting lying there by chance: the likelihood
        ratio ``N(r; 0, R) / ρ`` (:meth:`LegAssociator._with_weak`), ``ρ`` the false weak
        sightings' density, the larger of ``weak_clutter_per_m2`` and the weak sightings' own
        within ``weak_density_radius_m`` of the pair's weak one (false ones gather on rough
        seabed: weak sightings over the whole swath, seeds 6–10, false weak pairs 11 of 104 → 6 of 99).
    weak_prior_odds, weak_weak_prior_odds, weak_posterior_odds : float
        The likelihood ratio is weighed by the prior odds that the object the other sighting
        marks was seen (weakly) there at all: a pair joins when ``prior odds × ratio ≥
        weak_posterior_odds`` (9: at most a 10 % chance that it is false, for the least likely
        pair accepted). The prior odds depend on what the other sighting is: an ordinary
        sighting is an object nine times in ten, a weak one once in 25 (~1000 weak sightings a
        seed, ~40 on objects). Measured (``adaptnav experiment landmarks``, seeds 1–13, the
        pairs inside the gate with agreeing attributes, true/false by the simulator's truth, by
        ratio 1–3 / 3–10 / 10–15 / 15–20): the other sighting ordinary, P(true) 0.56 / 0.73 /
        0.89 / 0.75, odds over ratio 0.74 / 0.49 / 0.65 / 0.17 → ``weak_prior_odds`` 0.5; both
        weak, 1 true of 45 / 0 of 38 / 1 of 4 / 1 of 3, odds 0.013 / 0 / 0.027 / 0.029 →
        ``weak_weak_prior_odds`` 0.03 (a ratio ≥ 300: the largest seen is ~130). With the ratio
        alone ≥ 10 (d8b6e69) seeds 1–15 had 10 false weak pairs of 283 (seed 12: 3 of 18, 2.1 %
        false links): all with ratios 10–17, five of them both weak; the pairs' gates (√det R
        0.22–1.24 m²), residuals, local clutter and attributes overlapped the true ones'. With
        the prior odds: seeds 1–15 false weak pairs 10 of 283 → 0 of 225, false links ≤ 0.54 %
        (was ≤ 2.11 %), re-associated 0–2.1 points less (seed 7 0.744 → 0.725); held out,
        evaluated once (seeds 16–25): false weak pairs 7 of 170 → 0 of 132, false links ≤ 1.04 %
        (was 2.08 % on seed 20), re-associated 0.766–0.849 → 0.736–0.837.
    """

    gate_probability: float = 0.999
    inlier_probability: float = 0.99
    joint_probability: float = 0.99
    min_objects: int = 4
    min_gap_s: float = 60.0
    attribute_sigmas: float = 3.0
    # measured on the survey (seeds 1 and 4, 258 true cross-leg pairs): the difference of two
    # heights has σ ≈ 0.08 / 0.14 / 0.21 m at h ≈ 0.3 / 0.6 / 1.1 m, of two along-track
    # lengths ≈ 0.35 / 0.75 m at 0.9 / 1.8 m (each sighting: ÷ √2)
    height_sigma_m: float = 0.04
    height_sigma_fraction: float = 0.12
    length_sigma_m: float = 0.1
    length_sigma_fraction: float = 0.25
    # on the jump-free track (ObjectSighting.jump_n_m) true pairs of one set scatter about
    # their offset by ≈ 0.2 m within 5 s of the set's centre and 0.8 m at 15–40 s (survey
    # seed 1): ≈ 0.015 m/s per leg and axis beyond the detector's share
    relative_sigma_m_s: float = 0.015
    max_candidates_per_object: int = 8
    memory_s: float = 3600.0
    max_sightings: int = 5000
    chance_probability: float = 0.1
    window_s: float = 60.0
    clutter_scale: float = 9.0
    set_span_s: float = 90.0
    extend_probability: float = 0.01
    # false weak sightings per m² of seabed nearer than 20 m, where most are (survey seeds 1-5:
    # ~900 a seed on 2 x 16 m x 3.6 km; beyond 20 m ~50 a seed)
    weak_clutter_per_m2: float = 0.0077
    weak_prior_odds: float = 0.5
    weak_weak_prior_odds: float = 0.03
    weak_posterior_odds: float = 9.0
    weak_density_radius_m: float = 15.0


@dataclass(frozen=True, eq=False)
class LoopClosure:
    """Two legs' views of the same objects agree on one offset of the navigation error.

    Attributes
    ----------
    t_a_s, t_b_s : float
        The times of one pair's two sightings (s): the pair whose new sighting is the
        median of the set's on the new leg.
    offset_n_m : numpy.ndarray, shape (2,)
        ``δ ≈ e(t_a) − e(t_b)``: the earlier leg's position error minus the new one's
        (north, east; m). A filter that was right at ``t_a`` is off by ``−δ`` at ``t_b``.
    cov : numpy.ndarray, shape (2, 2)
        Covariance of ``offset_n_m`` (m²) from the detector and relative-drift terms.
    n_objects : int
        Objects that agree.
    pairs : tuple of (ObjectSighting, ObjectSighting)
        The (earlier, new) sightings.
    nis : float
        Joint normalised residual (χ² with 2n − 2 degrees of freedom).
    jump_a_n_m, jump_b_n_m : numpy.ndarray or None, shape (2,)
        The navigation's accumulated jumps at ``t_a_s`` and ``t_b_s``
        (:attr:`~adaptnav.sonar.objects.ObjectSighting.jump_n_m`, in ``offset_n_m``; None: not known).
    weak_pairs : tuple of (ObjectSighting, ObjectSighting)
        (earlier, new) pairs with a weak sighting that joined the set where its drift predicts
        them (:meth:`LegAssociator._with_weak`): the objects re-found, not in ``pairs``,
        ``n_objects``, the offset or its covariance. Kept apart from what the navigation and the
        calibrator use: with them among the pairs the calibrator's (k_V, current) fit takes
        (``adaptnav experiment landmarks``, seed 1) its k_V 10 min after the change was
        1.61 % off instead of 0.72 %, the drift over the outage 0.156 % instead of 0.083 %.
    """

    t_a_s: float
    t_b_s: float
    offset_n_m: np.ndarray
    cov: np.ndarray
    n_objects: int
    pairs: tuple = field(default=())
    nis: float = math.nan
    jump_a_n_m: np.ndarray | None = None
    jump_b_n_m: np.ndarray | None = None
    weak_pairs: tuple = field(default=())

    def offset_at(self, jump_a_n_m, jump_b_n_m) -> np.ndarray:
        """The offset between the navigation's errors at two epochs near ``t_a_s`` and ``t_b_s``
        (a filter's clones, seconds away) whose accumulated jumps are ``jump_a_n_m`` and
        ``jump_b_n_m`` (m): ``δ + (J′_a − J_a) − (J′_b − J_b)``.

        Between a sighting and the epoch it is fused at, the filter's error changes by the jumps
        its updates made (a USBL fix: metres) plus its velocity error over those seconds (left
        to the caller's covariance). Unchanged when the sightings' jumps are not known."""
        if self.jump_a_n_m is None or self.jump_b_n_m is None:
            return np.asarray(self.offset_n_m, float).copy()
        return (np.asarray(self.offset_n_m, float) + (np.asarray(jump_a_n_m, float) - self.jump_a_n_m)
                - (np.asarray(jump_b_n_m, float) - self.jump_b_n_m))

    def to_record(self) -> dict:
        """JSON-ready summary."""
        return {"t_a_s": self.t_a_s, "t_b_s": self.t_b_s, "offset_n_m": [float(v) for v in self.offset_n_m],
                "cov": [float(v) for v in np.asarray(self.cov).reshape(4)], "n_objects": self.n_objects,
                "nis": self.nis}


# a box this much larger than a distance gate holds every pair the gate may pass, whatever
# the rounding of the norm (m)
_BOX_MARGIN_M = 1e-3


def _near_pairs(p_old: np.ndarray, p_new: np.ndarray, offset: np.ndarray, radius_m: float,
                mask: np.ndarray) -> np.ndarray:
    """``mask`` (n_old, n_new) where also ``‖p_old[i] − p_new[j] − offset‖ ≤ radius_m``, the norm
    as ``np.linalg.norm`` gives it (the same booleans). The norm only of the pairs within a box
    ``radius_m`` + a margin far above the rounding (outside it one component alone is over the
    radius, so is the norm): of every pair of :meth:`LegAssociator._with_weak` (a weak sighting
    in it) it took 0.155 s of CPU per data hour of the survey, the box 0.103 s."""
    near = mask.copy()
    for k in (0, 1):
        near &= np.abs(p_old[:, k, None] - p_new[None, :, k] - offset[k]) <= radius_m + _BOX_MARGIN_M
    i, j = np.nonzero(near)
    near[i, j] = np.linalg.norm(p_old[i] - p_new[j] - offset, axis=1) <= radius_m
    return near


def _m2(r: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Squared Mahalanobis lengths of residuals ``r`` (n, 2) in covariances ``R`` (n, 2, 2)."""
    return np.einsum("ki,kij,kj->k", r, np.linalg.inv(R), r)


def _sighting_arrays(sightings: list[ObjectSighting]) -> dict[str, np.ndarray]:
    """:meth:`LegAssociator._stored_arrays` of ``sightings``."""
    pos = np.array([o.pos_n_m for o in sightings]).reshape(-1, 2)
    det_cov = np.array([o.det_cov for o in sightings]).reshape(-1, 2, 2)
    return {"t_s": np.array([o.t_s for o in sightings]).reshape(-1),
            "pos_n_m": pos,
            "smooth_pos_n_m": _smooth_positions(sightings, pos),
            "cov": np.array([o.nav_cov for o in sightings]).reshape(-1, 2, 2) + det_cov,
            "det_cov": det_cov,
            "id": np.array([id(o) for o in sightings], dtype=np.int64)}


def _smooth_positions(sightings: list[ObjectSighting], pos: np.ndarray | None = None) -> np.ndarray:
    """The sightings' ``smooth_pos_n_m`` (n, 2) (``pos``: their ``pos_n_m`` as an array, if made
    already). Elementwise, the same numbers as each sighting's own difference: a numpy call
    each was a third of the store, and of :meth:`LegAssociator._with_weak`'s new sightings."""
    jumps = [o.jump_n_m for o in sightings]
    if not all(j is not None for j in jumps):
        return np.array([o.smooth_pos_n_m for o in sightings]).reshape(-1, 2)
    if pos is None:
        pos = np.array([o.pos_n_m for o in sightings]).reshape(-1, 2)
    return pos - np.array(jumps).reshape(-1, 2)


def _kept_from(sightings: list[ObjectSighting], arrays: dict[str, np.ndarray],
               t_from_s: float) -> tuple[list[ObjectSighting], dict[str, np.ndarray]]:
    """The stored ``sightings`` from ``t_from_s`` on, and their ``arrays``
    (:func:`_sighting_arrays`). Nearly always the newest ones: slices then (the copies of
    every array each batch were a twentieth of the association), else picked one by one."""
    keep = np.flatnonzero(arrays["t_s"] >= t_from_s)
    if keep.size and keep[0] + keep.size == len(sightings):
        first = int(keep[0])
        return sightings[first:], {k: v[first:] for k, v in arrays.items()}
    return [sightings[k] for k in keep.tolist()], {k: v[keep] for k, v in arrays.items()}


def _leading_or(k: np.ndarray) -> slice | np.ndarray:
    """What picks the rows ``k`` (increasing indices, as ``np.flatnonzero`` gives them) of the
    stored arrays: ``slice(0, n)`` when they are the first ``n`` rows (the earlier sightings of
    a batch nearly always are: the store is in time order), whose views hold the numbers the
    indices' copies would (the copies of four arrays were a twentieth of the candidates);
    else ``k``."""
    return slice(0, k.size) if k.size and k[-1] == k.size - 1 else k


def _median(values: list[float]) -> float:
    """``float(np.median(values))`` of a non-empty list of floats, the same number: the middle
    one, or the mean of the middle two as numpy takes it (their sum halved); numpy's own for
    non-finite ones (a tenth of the candidates' search was numpy's median of a few times)."""
    v = sorted(values)
    n = len(v)
    if not (math.isfinite(v[0]) and math.isfinite(v[-1])) or any(x != x for x in v):
        return float(np.median(values))
    return float(v[n // 2] if n % 2 else (v[n // 2 - 1] + v[n // 2]) / 2.0)


def _m2_of(r: np.ndarray, R: np.ndarray, n_rows: int) -> np.ndarray:
    """:func:`_m2` of some of the ``n_rows`` rows it would have been given: the same numbers
    (numpy's einsum sums a lone row in another order than two or more: a lone one of several
    goes with a copy of itself)."""
    if len(r) == 1 and n_rows > 1:
        return _m2(np.concatenate([r, r]), np.concatenate([R, R]))[:1]
    return _m2(r, R)


def _surely_beyond(r: np.ndarray, R: np.ndarray, m2_max: float) -> np.ndarray:
    """Where :func:`_m2` of residuals ``r`` (..., 2) in covariances ``R`` (..., 2, 2) exceeds
    ``m2_max`` whatever the rounding: ``R`` symmetric (to 1e-9 of its trace), positive definite
    and conditioned better than 1e6, and the closed form ``rᵀ adj(R) r / det R`` over twice
    ``m2_max`` (it and the inverse's are within 1e-3 of the exact value there). False
    elsewhere (NaN included): those need :func:`_m2`."""
    r00, r01, r10, r11 = R[..., 0, 0], R[..., 0, 1], R[..., 1, 0], R[..., 1, 1]
    x, y = r[..., 0], r[..., 1]
    tr = r00 + r11
    det = r00 * r11 - r01 * r10
    q = r11 * x * x - (r01 + r10) * x * y + r00 * y * y
    return (r00 > 0.0) & (det > 1e-6 * tr * tr) & (np.abs(r01 - r10) <= 1e-9 * tr) & (q > 2.0 * m2_max * det)


def _plain_traces(M: np.ndarray) -> np.ndarray:
    """Traces of the 2×2 covariances ``M`` (..., 2, 2), NaN where one is not plainly a
    covariance: symmetric to 1e-9 of its trace, positive definite, conditioned better than 1e6
    (:func:`_surely_beyond`'s conditions). What :func:`_beyond_by_traces` bounds sums of."""
    m00, m01, m10, m11 = M[..., 0, 0], M[..., 0, 1], M[..., 1, 0], M[..., 1, 1]
    tr = m00 + m11
    plain = (m00 > 0.0) & (m00 * m11 - m01 * m10 > 1e-6 * tr * tr) & (np.abs(m01 - m10) <= 1e-9 * tr)
    return np.where(plain, tr, np.nan)


def _beyond_by_traces(d2: np.ndarray, tr_old: np.ndarray, tr_new: np.ndarray, m2_max: float) -> np.ndarray:
    """Where pairs (rows: new sightings, columns: old ones) with squared distances ``d2`` lie
    beyond ``m2_max`` in every covariance that is the sum of two plain ones (:func:`_plain_traces`)
    with traces ``tr_old`` (per column) and ``tr_new`` (per row): ``m² ≥ |d|² / λ_max ≥ |d|² /
    trace``, over four times ``m2_max`` — the sum is conditioned better than 1e6 like its parts,
    so the closed form (:func:`_surely_beyond`) or the inverse (:func:`_m2`) puts it beyond
    ``m2_max`` too, whatever the rounding. False where a trace is NaN."""
    return d2 > 4.0 * m2_max * (tr_old[None] + tr_new[:, None])


def _block_diag(*blocks: np.ndarray) -> np.ndarray:
    out = np.zeros((2 * len(blocks), 2 * len(blocks)))
    for i, b in enumerate(blocks):
        out[2 * i:2 * i + 2, 2 * i:2 * i + 2] = b
    return out


@dataclass(frozen=True, eq=False)
class Drift:
    r"""How a set's offset changes along its two legs on the jump-free tracks.

    A jump-free track drifts with the navigation's velocity error, nearly constant over a
    set's minute: ``δ(t_a, t_b) = δ₀ + u_a (t_a − t_a0) − u_b (t_b − t_b0)``, with
    ``θ = (δ₀, u_a, u_b)`` (m, m/s, m/s; north, east each). The velocity errors' prior is
    the navigation's velocity covariance at the hypothesis' two sightings; fitted on a set's
    pairs they are known far better than that prior (the drift of true pairs about their
    set's offset, not a fixed allowance: before the first fix the velocity error is
    ~0.2 m/s, in an outage ~0.02 m/s).

    Attributes
    ----------
    t_a_s, t_b_s : float
        Reference times on the earlier and the new leg (s).
    theta : numpy.ndarray, shape (6,)
    cov : numpy.ndarray, shape (6, 6)
        Covariance of ``theta``.
    prior_mean, prior_info : numpy.ndarray, shapes (6,), (6, 6)
        The prior :meth:`fit` combines with pairs (information form; ``δ₀`` free).
    """

    t_a_s: float
    t_b_s: float
    theta: np.ndarray
    cov: np.ndarray
    prior_mean: np.ndarray
    prior_info: np.ndarray

    @classmethod
    def prior(cls, t_a_s: float, t_b_s: float, offset_n_m, det_cov, vel_cov_a, vel_cov_b) -> "Drift":
        """The hypothesis of one pair (its offset, detectors' covariance) and the velocity
        covariances at its two sightings (m²/s²)."""
        theta = np.concatenate([np.asarray(offset_n_m, float), np.zeros(4)])
        info = _block_diag(np.zeros((2, 2)), np.linalg.inv(vel_cov_a), np.linalg.inv(vel_cov_b))
        return cls(float(t_a_s), float(t_b_s), theta, _block_diag(det_cov, vel_cov_a, vel_cov_b), theta.copy(), info)

    def design(self, t_a, t_b) -> np.ndarray:
        """(n, 2, 6): ``∂δ/∂θ`` at the times ``t_a``, ``t_b`` (s)."""
        ta = np.asarray(t_a, float).reshape(-1) - self.t_a_s
        tb = np.asarray(t_b, float).reshape(-1) - self.t_b_s
        J = np.zeros((ta.size, 2, 6))
        J[:, 0, 0] = J[:, 1, 1] = 1.0
        J[:, 0, 2] = J[:, 1, 3] = ta
        J[:, 0, 4] = J[:, 1, 5] = -tb
        return J

    def predict(self, t_a, t_b) -> np.ndarray:
        """Offsets (n, 2) at the times ``t_a``, ``t_b``."""
        return self.design(t_a, t_b) @ self.theta

    def residual_cov(self, t_a, t_b, det_cov) -> np.ndarray:
        """Covariances (n, 2, 2) of pairs' offsets about :meth:`predict`: the detectors' plus
        the prediction's."""
        return self._cov_about(self.design(t_a, t_b), det_cov)

    def _cov_about(self, J: np.ndarray, det_cov) -> np.ndarray:
        """:meth:`residual_cov` of the design matrix ``J`` (:meth:`design`)."""
        return np.asarray(det_cov) + np.einsum("kij,jl,kml->kim", J, self.cov, J)

    def residuals(self, diffs, t_a, t_b, det_cov) -> tuple[np.ndarray, np.ndarray]:
        """Pairs' offsets ``diffs`` (n, 2) less the prediction, and their covariances: those of
        :meth:`predict` and :meth:`residual_cov` from one design matrix (building it was a tenth
        of the association, and each of them built it again)."""
        J = self.design(t_a, t_b)
        return np.asarray(diffs) - J @ self.theta, self._cov_about(J, det_cov)

    def at(self, t_a_s: float, t_b_s: float) -> tuple[np.ndarray, np.ndarray]:
        """The offset at one pair of times and its covariance (2, 2)."""
        J = self.design([t_a_s], [t_b_s])[0]
        return J @ self.theta, J @ self.cov @ J.T

    def fit(self, diffs, W, t_a, t_b, sel) -> tuple["Drift", float]:
        """The prior combined with the pairs ``sel`` (offsets ``diffs``, inverse detector
        covariances ``W``, times ``t_a``, ``t_b``): the posterior (same prior) and its χ²
        (2n − 2 degrees of freedom: 2n offsets and 4 velocity priors, 6 parameters)."""
        J = self.design(t_a[sel], t_b[sel])
        JtW = np.einsum("kji,kjl->kil", J, W[sel])
        info = np.einsum("kil,klm->im", JtW, J) + self.prior_info
        cov = np.linalg.inv(info)
        theta = cov @ (np.einsum("kil,kl->i", JtW, diffs[sel]) + self.prior_info @ self.prior_mean)
        r = diffs[sel] - J @ theta
        d = theta - self.prior_mean
        cost = float(np.einsum("ki,kij,kj->", r, W[sel], r) + d @ self.prior_info @ d)
        return Drift(self.t_a_s, self.t_b_s, theta, 0.5 * (cov + cov.T), self.prior_mean, self.prior_info), cost

    def update(self, diffs, W, t_a, t_b, sel) -> "Drift":
        """This drift (its estimate the prior) updated with more pairs."""
        return Drift(self.t_a_s, self.t_b_s, self.theta, self.cov, self.theta,
                     np.linalg.inv(self.cov)).fit(diffs, W, t_a, t_b, sel)[0]


# how far a pair of sightings got (:attr:`LegAssociator.trace`), in order
STAGES = ("wide gate", "attributes", "candidate", "too few candidates", "not in the set", "chance bound",
          "ambiguous", "accepted")


class LegAssociator:
    """Keeps object sightings and finds loop closures for each new batch.

    Parameters
    ----------
    config : AssociationConfig
    """

    def __init__(self, config: AssociationConfig = AssociationConfig(), relative_covs=None, images=None,
                 guided=None) -> None:
        self.config = config
        # guided re-detection (:mod:`adaptnav.sonar.guided`): the front end's
        # :class:`~adaptnav.sonar.guided.ImageStore` and a GuidedConfig; None: off
        self.images = images
        self.guided_config = guided
        self.guided_pairs = 0
        self.guided_tests: dict[str, int] = {}
        self._paired: set[int] = set()  # ids of the sightings in any accepted pair
        self._tested: set[int] = set()  # ids of the sightings already looked for (once each)
        self.guided_log: list | None = None  # diagnostics: (seen sighting, reason) per attempt
        self._guided_pending: list = []  # guided pairs found after the last closure was returned
        self._spans: dict[int, tuple] = {}  # id(drift) → its set's times (old first, last; new first, last)
        # (t_a (K,), t_b) → (covariances (K, 2, 2), known (K,)) of the navigation's error
        # difference e(t_a) − e(t_b): the filter knows the correlation of its errors at two
        # epochs (its clones); None: not known
        self.relative_covs = relative_covs
        self._gate = chi2_quantile(config.gate_probability, 2)
        self._inlier = chi2_quantile(config.inlier_probability, 2)
        self._old: list[ObjectSighting] = []
        self._stored: tuple[list, dict[str, np.ndarray]] | None = None  # (of _old, arrays)
        self._weak_stored: tuple[list, dict[str, np.ndarray]] | None = None  # (of _weak_old, arrays)
        # candidates() by the ids of its batch, within one add(): the window is searched by
        # associate() and then extend() with the same stored sightings and clones
        self._memo: dict[tuple, tuple] | None = None
        self._pending: list[ObjectSighting] = []  # new sightings still in play (window_s)
        # weak sightings (ObjectSighting.weak): kept apart, only ever added to an accepted set
        self._weak_old: list[ObjectSighting] = []
        self._weak_pending: list[ObjectSighting] = []
        self.weak_pairs = 0
        self._weak_used: set[int] = set()  # ids of the sightings already in a pair with a weak one
        # recent accepted closures as hypotheses for the next sightings (:meth:`extend`):
        # (t_a, t_b, offset on the jump-free tracks, its covariance)
        self._recent: list[tuple[float, float, np.ndarray, np.ndarray]] = []
        self.batches = 0
        # optional diagnostics (the landmark experiment's error budget): (id(old), id(new)) →
        # furthest stage the pair reached, see :data:`STAGES`; None: not kept
        self.trace: dict[tuple[int, int], str] | None = None

    @property
    def sightings(self) -> list[ObjectSighting]:
        return list(self._old)

    def _attributes_agree(self, a: ObjectSighting, b: ObjectSighting) -> bool:
        c = self.config
        k = c.attribute_sigmas
        if math.isfinite(a.height_m) and math.isfinite(b.height_m):
            sa = c.height_sigma_m + c.height_sigma_fraction * a.height_m
            sb = c.height_sigma_m + c.height_sigma_fraction * b.height_m
            if abs(a.height_m - b.height_m) > k * math.hypot(sa, sb):
                return False
        if math.isfinite(a.length_along_m) and math.isfinite(b.length_along_m):
            sa = c.length_sigma_m + c.length_sigma_fraction * a.length_along_m
            sb = c.length_sigma_m + c.length_sigma_fraction * b.length_along_m
            if abs(a.length_along_m - b.length_along_m) > k * math.hypot(sa, sb):
                return False
        return True

    def candidates(self, batch: list[ObjectSighting]) -> tuple[list[tuple[int, int, float, np.ndarray]], dict]:
        """Individually compatible pairs and the clutter around each new sighting.

        Returns
        -------
        pairs : list of (old index, batch index, Mahalanobis d², gate covariance)
        clutter : dict of arrays, one entry per (new sighting, old sighting with agreeing
            attributes inside ``clutter_scale`` × its gate's area — the *wide* region):
            ``j`` (batch index), ``t_old_s`` (the old sighting's time), ``det_cov`` (the two
            detector covariances, (n, 2, 2)), ``t_new_s`` and ``area_m2`` (the wide region's
            area, π · clutter_scale · χ²_gate · √det S, with S that pair's own gate
            covariance). A wrong old sighting lies anywhere in its wide region; the chance
            that it agrees with a hypothesis is its inlier region's area over this one
            (:meth:`associate`).
        """
        c = self.config
        clutter = {"j": np.zeros(0, int), "t_old_s": np.zeros(0), "t_new_s": np.zeros(0),
                   "det_cov": np.zeros((0, 2, 2)), "area_m2": np.zeros(0)}
        if not self._old or not batch:
            return [], clutter
        key = tuple(id(o) for o in batch)
        if self._memo is not None and key in self._memo:
            return self._memo[key]
        t_batch = [o.t_s for o in batch]
        t_new = max(t_batch)
        stored = self._stored_arrays()
        earlier = stored["t_s"] < t_new - c.min_gap_s
        if min(t_batch) < t_new - c.min_gap_s:  # (else no sighting of the batch is that early)
            earlier &= ~np.isin(stored["id"], [id(o) for o in batch])
        k_old = np.flatnonzero(earlier)
        if not k_old.size:
            return [], clutter
        old = k_old.tolist()
        pick = _leading_or(k_old)
        P_old, C_old, D_old, t_old = (stored[k][pick] for k in ("pos_n_m", "cov", "det_cov", "t_s"))
        rel = self._relative(t_old, _median(t_batch))
        if rel is not None:  # the error difference's own covariance where the filter has it
            rel_known, rel_D = rel[1][:, None, None], rel[0] + D_old
        # every new sighting (rows) against every old one (columns) at once
        wide_m2 = c.clutter_scale * self._gate
        other_leg = ~(t_old[None] >= np.array([t - c.min_gap_s for t in t_batch])[:, None])
        p_new = np.array([b.pos_n_m for b in batch])
        D_new = np.array([b.det_cov for b in batch])
        nav_D_new = np.array([b.nav_cov for b in batch]) + D_new
        # a pair's covariance is the old sighting's part (navigation + detector, or the error
        # difference's + detector) plus the new one's (navigation + detector, or detector):
        # only the pairs their traces do not place beyond the wide gate (of ~1500 a batch, ~5)
        # get their 2×2 covariances, the closed form and m² (every pair's were a third of
        # the candidates)
        d_n, d_e = P_old[None, :, 0] - p_new[:, None, 0], P_old[None, :, 1] - p_new[:, None, 1]
        tr_new = _plain_traces(nav_D_new)
        cov_old = C_old
        if rel is not None:
            cov_old = np.where(rel_known, rel_D, C_old)
            tr_new = np.maximum(tr_new, _plain_traces(D_new))  # (NaN where either is not plain)
        jj, kk = np.nonzero(other_leg & ~_beyond_by_traces(d_n * d_n + d_e * d_e, _plain_traces(cov_old), tr_new,
                                                           wide_m2))
        d = P_old[kk] - p_new[jj]  # (d_n, d_e there: the same subtractions)
        S = C_old[kk] + nav_D_new[jj]
        if rel is not None:
            S = np.where(rel_known[kk], rel_D[kk] + D_new[jj], S)
        # m² (an inverse each) only where it may be in the wide gate, and where the pair has a
        # covariance: a degenerate navigation covariance a sighting brought (indefinite, NaN)
        # gives no m² to gate on — a negative one fell inside every gate — and a NaN clutter area
        need = ~_surely_beyond(d, S, wide_m2) & (S[:, 0, 0] > 0.0) & (S[:, 1, 1] > 0.0) \
            & (S[:, 0, 0] * S[:, 1, 1] - S[:, 0, 1] * S[:, 1, 0] > 0.0)
        jj, kk, d, S = jj[need], kk[need], d[need], S[need]
        S_all = np.full(other_leg.shape + (2, 2), np.nan)  # (read only where m² is finite)
        S_all[jj, kk] = S
        rows = list(dict.fromkeys(jj.tolist()))  # (the others have none in the wide gate; jj is in order)
        # m² of every pair needed in one call (an inverse each, as many calls as new sightings
        # were a fifth of the candidates): _m2 sums each row alike whenever it is given two
        # or more, as it was given each new sighting's (a lone one as two, _m2_of); with one
        # old sighting each new one's was a lone row (summed otherwise), kept so
        m2_all = np.full(other_leg.shape, np.inf)
        if len(old) > 1:
            m2_all[jj, kk] = _m2_of(d, S, 2)
        else:
            for p, j in enumerate(jj.tolist()):
                m2_all[j, 0] = _m2(d[p:p + 1], S[p:p + 1])[0]
        out = []
        cl_j: list[int] = []  # (batch index, old index) of the clutter, new sighting by new sighting
        cl_k: list[int] = []
        for j in rows:
            b, m2 = batch[j], m2_all[j]
            wide = np.flatnonzero(m2 <= wide_m2)
            agree = [k for k in wide[np.argsort(m2[wide])].tolist() if self._attributes_agree(self._old[old[k]], b)]
            if self.trace is not None:
                ok = set(agree)
                for k in wide:
                    self._note(self._old[old[k]], b, "candidate" if k in ok and m2[k] <= self._gate
                               else "attributes" if k not in ok else "wide gate")
            cl_j += [j] * len(agree)
            cl_k += agree
            for k in [k for k in agree if m2[k] <= self._gate][: c.max_candidates_per_object]:
                out.append((old[k], j, float(m2[k]), S_all[j, k]))
        if cl_j:  # (the same numbers as row by row: elementwise, and a determinant each)
            j_cl, k_cl = np.array(cl_j), np.array(cl_k)
            clutter = {"j": j_cl, "t_old_s": t_old[k_cl], "t_new_s": np.array(t_batch, float)[j_cl],
                       "det_cov": D_old[k_cl] + D_new[j_cl],
                       "area_m2": math.pi * c.clutter_scale * self._gate * np.sqrt(np.linalg.det(S_all[j_cl, k_cl]))}
        if self._memo is not None:
            self._memo[key] = (out, clutter)
        return out, clutter

    def _stored_arrays(self) -> dict[str, np.ndarray]:
        """The stored sightings' ``t_s``, ``pos_n_m``, ``smooth_pos_n_m``, ``cov`` (navigation +
        detector), ``det_cov`` and ``id`` as arrays (the candidates of every hypothesis search
        of a batch draw on the same ones), built again only when the list was replaced other
        than by :meth:`_store`."""
        if self._stored is None or self._stored[0] is not self._old:
            self._stored = (self._old, _sighting_arrays(self._old))
        return self._stored[1]

    def _weak_arrays(self) -> dict[str, np.ndarray]:
        """:meth:`_stored_arrays` of the stored weak sightings, extended as :meth:`add` appends
        to them (their positions for every accepted set were a third of the association)."""
        w = self._weak_old
        if self._weak_stored is None or self._weak_stored[0] is not w:
            self._weak_stored = (w, _sighting_arrays(w))
        arrays = self._weak_stored[1]
        if len(arrays["t_s"]) < len(w):
            tail = _sighting_arrays(w[len(arrays["t_s"]):])
            arrays = {k: np.concatenate([v, tail[k]]) for k, v in arrays.items()}
            self._weak_stored = (w, arrays)
        return arrays

    def _store(self, batch: list[ObjectSighting], t_from_s: float) -> None:
        """Keep the stored sightings (ordinary and weak) from ``t_from_s`` on, and ``batch``,
        each at most ``max_sightings`` (the newest), and their arrays with them (rebuilding
        them for the whole store every batch grew with the mission)."""
        n = self.config.max_sightings
        old, arrays = _kept_from(self._old, self._stored_arrays(), t_from_s)
        self._old = (old + list(batch))[-n:]
        new = _sighting_arrays(batch)
        self._stored = (self._old, {k: np.concatenate([v, new[k]])[-n:] for k, v in arrays.items()})
        old, arrays = _kept_from(self._weak_old, self._weak_arrays(), t_from_s)
        self._weak_old = old[-n:]
        self._weak_stored = (self._weak_old, {k: v[-n:] for k, v in arrays.items()})

    def _note(self, a: ObjectSighting, b: ObjectSighting, stage: str) -> None:
        key = (id(a), id(b))
        if STAGES.index(stage) > STAGES.index(self.trace.get(key, STAGES[0])):
            self.trace[key] = stage

    def _note_all(self, cand, batch, ks, stage: str) -> None:
        if self.trace is not None:
            for k in ks:
                self._note(self._old[cand[k][0]], batch[cand[k][1]], stage)

    def _relative(self, t_old: np.ndarray, t_new: float):
        """(covariances (K, 2, 2), known (K,)) of e(t_old) − e(t_new) from ``relative_covs``,
        asked at the first old sighting of each distinct second (the clones are seconds apart)."""
        if self.relative_covs is None:
            return None
        # (np.round is Python's round: half to even; unique's indices are first occurrences)
        _, first, at = np.unique(np.round(t_old), return_index=True, return_inverse=True)
        cov, ok = self.relative_covs(t_old[first], t_new)
        ok = ok & np.isfinite(cov).all(axis=(1, 2))  # a non-finite one is not known
        cov = np.where(ok[:, None, None], cov, 0.0)
        # nor is one that is no covariance (a difference of nearly equal covariances can come
        # out indefinite): its pairs' m² could be negative, inside every gate, and their clutter
        # areas NaN, which silenced the chance-inlier bound of the set size (_min_objects)
        off = 0.5 * (cov[:, 0, 1] + cov[:, 1, 0])
        ok = ok & (cov[:, 0, 0] >= 0.0) & (cov[:, 1, 1] >= 0.0) & (cov[:, 0, 0] * cov[:, 1, 1] >= off * off)
        cov = np.where(ok[:, None, None], cov, 0.0)
        at = at.reshape(-1)
        return cov[at], ok[at]

    def _vel_cov(self, o: ObjectSighting) -> np.ndarray:
        """The velocity covariance at a sighting (m²/s²): the navigation's, or
        ``relative_sigma_m_s``² per axis when it gave none."""
        if o.vel_cov is not None:
            return o.vel_cov
        return self.config.relative_sigma_m_s ** 2 * np.eye(2)

    def _arrays(self, cand, batch):
        """Per candidate: offset on the jump-free tracks, the two times, the detectors' covariance
        and the two velocity covariances."""
        old = self._old
        diffs = np.array([old[i].smooth_pos_n_m - batch[j].smooth_pos_n_m for i, j, _, _ in cand])
        t_a = np.array([old[i].t_s for i, _, _, _ in cand])
        t_b = np.array([batch[j].t_s for _, j, _, _ in cand])
        D = np.array([old[i].det_cov + batch[j].det_cov for i, j, _, _ in cand])
        Va = np.array([self._vel_cov(old[i]) for i, _, _, _ in cand])
        Vb = np.array([self._vel_cov(batch[j]) for _, j, _, _ in cand])
        return diffs, t_a, t_b, D, Va, Vb

    def _chance_inliers(self, clutter: dict, ta: float, tb: float, rcov, span_s: float | None = None) -> float:
        """Wrong old sightings expected to agree with one hypothesis (times ``ta``, ``tb``) by chance.

        For every new sighting: the sum over the old sightings of its wide region (within
        ``set_span_s`` of ``ta``: the others cannot join the set) of each one's chance of lying
        in its inlier region — that region's area (``rcov(t_old, t_new, detector covariances)``,
        the residual covariances (n, 2, 2) of the test the set's pairs pass) over its own wide
        region's area — less the largest (the one that may be its match).
        """
        c = self.config
        m = np.abs(clutter["t_old_s"] - ta) <= (c.set_span_s if span_s is None else span_s)
        if not np.any(m):
            return 0.0
        R = rcov(clutter["t_old_s"][m], clutter["t_new_s"][m], clutter["det_cov"][m])
        p = np.minimum(math.pi * self._inlier * np.sqrt(np.linalg.det(R)) / clutter["area_m2"][m], 1.0)
        j = clutter["j"][m]
        n = int(j.max()) + 1
        tot, top = np.zeros(n), np.zeros(n)
        np.add.at(tot, j, p)
        np.maximum.at(top, j, p)
        return float(np.sum(tot - top))

    def _min_objects(self, lam_prior: float, lam_fit, n_hypotheses: int) -> int:
        """Smallest set that ``n_hypotheses`` hypotheses would give by chance with probability
        at most ``chance_probability`` (union bound; the hypothesis' own pair is not by chance).

        Two bounds, the smaller taken: every pair within the prior's gate of the hypothesis
        (``lam_prior`` chance inliers: ``P(Poisson ≥ n − 1)``), or within the gate of the drift
        fitted on the set — which wrong pairs could have set: its four velocity errors take two
        more pairs, chosen among the ``lam_prior`` wrong ones, and the drift they give is known
        as well as from three pairs (``lam_fit``: the chance inliers with the covariance of the
        drift fitted on the set's n pairs × n / 3): ``max(1, λ_prior)² P(Poisson(λ_fit) ≥ n − 3)``."""
        c = self.config
        n = c.min_objects
        while n_hypotheses * min(poisson_sf(n - 2, lam_prior),
                                 max(1.0, lam_prior) ** 2 * poisson_sf(n - 4, lam_fit)) \
                > c.chance_probability:
            n += 1
        return n

    def associate(self, batch: list[ObjectSighting]) -> LoopClosure | None:
        """The largest jointly compatible set of candidate pairs for ``batch`` (or None).

        Every candidate is a hypothesis (its two sightings' times ``t_a``, ``t_b``): the pairs
        whose old sighting lies within ``set_span_s`` of ``t_a`` and whose offset lies within
        the inlier gate of the hypothesis' — detectors plus the drift its velocity covariance
        allows (:class:`Drift`) — are fitted with the drift (offset and the two legs'
        velocity errors), the pairs within the fitted drift's gate re-selected (three rounds),
        then made jointly compatible; the set is accepted when larger than chance agreement
        allows for that hypothesis (:meth:`_chance_inliers`, :meth:`_min_objects`).
        """
        c = self.config
        # a set pairs each old and each new sighting once: too few of them found none, whatever
        # their candidates (not searched: a third of the batches; a trace takes every search
        # the whole way, noting how far each pair got)
        if self.trace is None and len(batch) < c.min_objects:
            return None
        cand, clutter = self.candidates(batch)
        if len(cand) < c.min_objects:
            self._note_all(cand, batch, range(len(cand)), "too few candidates")
            return None
        self._note_all(cand, batch, range(len(cand)), "not in the set")
        if self.trace is None and min(len({i for i, *_ in cand}), len({j for _, j, *_ in cand})) < c.min_objects:
            return None
        # on the jump-free tracks: a fix or a fused closure between two sightings of one leg
        # moves the filter's position, not the seabed
        diffs, t_a, t_b, D, Va, Vb = self._arrays(cand, batch)
        W = np.linalg.inv(D)
        best = None  # (size, cost, set, drift, smallest size, span)
        for h in range(len(cand)):
            span = np.abs(t_a - t_a[h]) <= c.set_span_s
            if np.count_nonzero(span) < c.min_objects:
                continue
            prior = Drift.prior(t_a[h], t_b[h], diffs[h], D[h], Va[h], Vb[h])
            r, R = prior.residuals(diffs, t_a, t_b, D)
            inl = self._one_to_one(cand, np.where(span, _m2(r, R), np.inf))
            if len(inl) < 2:
                continue
            for _ in range(3):  # the drift from these pairs; the pairs within its gate
                drift = prior.fit(diffs, W, t_a, t_b, inl)[0]
                r, R = drift.residuals(diffs, t_a, t_b, D)
                again = self._one_to_one(cand, np.where(span, _m2(r, R), np.inf))
                if sorted(again) == sorted(inl):
                    break
                inl = again
                if len(inl) < 2:
                    break
            if len(inl) < c.min_objects:
                continue
            fit = self._refine(prior, diffs, W, t_a, t_b, inl, c.min_objects)
            if fit is None:
                continue
            sel, drift, cost = fit
            lam_prior = self._chance_inliers(clutter, t_a[h], t_b[h], prior.residual_cov)
            # the drift as well known as from three pairs (what wrong pairs need to set it)
            three = replace(drift, cov=drift.cov * max(1.0, len(sel) / 3.0))
            lam_fit = self._chance_inliers(clutter, t_a[h], t_b[h], three.residual_cov)
            n_min = self._min_objects(lam_prior, lam_fit, len(cand))
            if len(sel) < n_min:
                self._note_all(cand, batch, sel, "chance bound")
                continue
            if best is None or len(sel) > best[0] or (len(sel) == best[0] and cost < best[1]):
                best = (len(sel), cost, sel, drift, n_min, span, prior)
        if best is None:
            return None
        _, cost, sel, drift, n_min, span, prior = best
        self._note_all(cand, batch, sel, "ambiguous")
        r, R = drift.residuals(diffs, t_a, t_b, D)
        sel = self._unambiguous_to(cand, np.where(span, _m2(r, R), np.inf), sel)
        if len(sel) < n_min:
            return None
        drift, cost = prior.fit(diffs, W, t_a, t_b, sel)
        return self._closure(cand, batch, diffs, sel, drift, drift, cost)

    def _closure(self, cand, batch, diffs, sel: list[int], drift: "Drift", keep: "Drift",
                 nis: float) -> LoopClosure:
        """The loop closure of the accepted pairs ``sel`` and their fitted ``drift``; ``keep``
        is remembered as a hypothesis for the next sightings (:meth:`extend`)."""
        self._note_all(cand, batch, sel, "accepted")
        old = self._old
        pairs = tuple((old[cand[k][0]], batch[cand[k][1]]) for k in sel)
        # the closure refers to the filter's positions at the two sightings of one pair (the
        # median on the new leg): the jump-free offset there plus the jumps the filter had made
        # by then. (The median times of the two legs taken separately came from different pairs;
        # with a fix between the old sightings, or a fast drift, that pair of times was not
        # one the jump-free offset holds for: survey seed 3, 2.1 m off the truth.)
        a_med, b_med = sorted(pairs, key=lambda p: p[1].t_s)[(len(pairs) - 1) // 2]
        smooth, cov = drift.at(a_med.t_s, b_med.t_s)
        delta = smooth.copy()
        if a_med.jump_n_m is not None:  # (None: no velocity was given, no jumps known)
            delta = delta + a_med.jump_n_m
        if b_med.jump_n_m is not None:
            delta = delta - b_med.jump_n_m
        self._recent.append((float(a_med.t_s), float(b_med.t_s), keep))
        if self.images is not None:
            # the times its pairs span on either leg (guided re-detection interpolates the drift)
            self._spans[id(keep)] = (min(a.t_s for a, _ in pairs), max(a.t_s for a, _ in pairs),
                                     min(b.t_s for _, b in pairs), max(b.t_s for _, b in pairs))
        return LoopClosure(t_a_s=float(a_med.t_s), t_b_s=float(b_med.t_s),
                           offset_n_m=delta, cov=cov, n_objects=len(sel), pairs=pairs, nis=nis,
                           jump_a_n_m=a_med.jump_n_m, jump_b_n_m=b_med.jump_n_m)

    def extend(self, batch: list[ObjectSighting]) -> LoopClosure | None:
        """Pairs of ``batch`` that continue a recent loop closure (or None).

        A block past an accepted set often holds one to three objects of the other leg, too
        few to found a set of their own, while the set just accepted already gives the
        offset and how it drifts (:class:`Drift`, fitted on its pairs). Each closure of the
        last ``window_s`` is a hypothesis (not drawn from these pairs): a candidate within
        ``window_s`` + ``set_span_s`` of its times whose offset lies within the gate of that
        drift's prediction (detectors + the prediction's covariance, which grows with the
        time from the set as the velocity errors' covariance allows) and unambiguous joins;
        the pairs are accepted when chance alone would give as many with probability at
        most ``extend_probability`` (``P(Poisson(λ) ≥ n)``, λ the chance inliers of that
        hypothesis, :meth:`_chance_inliers`). The new closure's offset and covariance come
        from the new pairs alone (the earlier set was fused already); the hypothesis kept for
        the next sightings is the drift updated with them.
        """
        c = self.config
        if not self._recent or not batch:
            return None
        t_now = max(o.t_s for o in batch)
        self._recent = [r for r in self._recent if r[1] >= t_now - c.window_s - c.set_span_s]
        cand, clutter = self.candidates(batch)
        if not cand or not self._recent:
            return None
        diffs, t_a, t_b, D, Va, Vb = self._arrays(cand, batch)
        W = np.linalg.inv(D)
        reach = c.window_s + c.set_span_s
        for ta, tb, drift in reversed(self._recent):
            span = (np.abs(t_a - ta) <= reach) & (np.abs(t_b - tb) <= reach)
            if not np.any(span):
                continue
            r, R = drift.residuals(diffs, t_a, t_b, D)
            m2 = np.where(span, _m2(r, R), np.inf)
            sel = self._unambiguous_to(cand, m2, self._one_to_one(cand, m2))
            if not sel:
                continue
            lam = self._chance_inliers(clutter, ta, tb, drift.residual_cov, span_s=reach)
            if poisson_sf(len(sel) - 1, lam) * len(self._recent) > c.extend_probability:
                self._note_all(cand, batch, sel, "chance bound")
                continue
            h = sel[len(sel) // 2]
            own, cost = Drift.prior(t_a[h], t_b[h], diffs[h], D[h], Va[h], Vb[h]).fit(diffs, W, t_a, t_b, sel)
            return self._closure(cand, batch, diffs, sel, own, drift.update(diffs, W, t_a, t_b, sel), cost)
        return None

    def _unambiguous_to(self, cand, m2, sel: list[int]) -> list[int]:
        """``sel`` without pairs whose new or old sighting has another candidate inside the
        gate (``m2``: each candidate's from the set's offset): two neighbouring objects, either
        could be the match."""
        fits = m2 <= self._inlier
        return [k for k in sel if not any(fits[m] and m != k and (cand[m][1] == cand[k][1] or cand[m][0] == cand[k][0])
                                          for m in range(len(cand)))]

    def _one_to_one(self, cand, m2) -> list[int]:
        """Inliers (m² within the inlier gate), each old and new sighting used once (best first)."""
        used_a, used_b, out = set(), set(), []
        for k in np.argsort(m2):
            if m2[k] > self._inlier:
                break
            i, j, _, _ = cand[k]
            if i in used_a or j in used_b:
                continue
            used_a.add(i)
            used_b.add(j)
            out.append(int(k))
        return out

    def _refine(self, prior: "Drift", diffs, W, t_a, t_b, sel: list[int], n_min: int):
        """Drop the worst pair until the set is jointly compatible (χ² with 2n − 2 dof: 2n
        offsets and the 4 velocity errors' priors, 6 parameters) and every pair compatible with
        the others: its offset from the drift fitted on the rest within the inlier gate of
        that prediction (``rᵀ (D − J Σ Jᵀ)⁻¹ r``, the same number). A pair far in time from
        the rest sets the drift alone and fits it exactly (survey seed 4: one 7.4 m off in
        truth, 31–39 s from three clustered true pairs, passed the joint test)."""
        sel = list(sel)
        D = np.linalg.inv(W)
        while len(sel) >= n_min:
            drift, cost = prior.fit(diffs, W, t_a, t_b, sel)
            J = drift.design(t_a[sel], t_b[sel])
            r = diffs[sel] - J @ drift.theta  # (drift.predict's numbers from the same J)
            C = D[sel] - np.einsum("kij,jl,kml->kim", J, drift.cov, J)
            # (a pair that alone sets some of the drift has C ≈ 0 there: it cannot be tested)
            m2 = np.einsum("ki,kij,kj->k", r, np.linalg.pinv(C, hermitian=True, rcond=1e-9), r)
            m2 = np.where(np.linalg.det(C) > 1e-9 * np.linalg.det(D[sel]), m2, np.inf)
            if cost <= chi2_quantile(self.config.joint_probability, 2 * len(sel) - 2) and float(m2.max()) <= self._inlier:
                return sel, drift, cost
            sel.pop(int(np.argmax(m2)))
        return None

    def add(self, batch: list[ObjectSighting]) -> LoopClosure | None:
        """Associate ``batch`` with the stored sightings, then store it.

        Every sighting needs ``pos_n_m``, ``nav_cov`` and ``det_cov``
        (:func:`adaptnav.sonar.objects.with_navigation`).
        """
        for o in batch:
            if o.pos_n_m is None or o.nav_cov is None or o.det_cov is None:
                raise ValueError("object sightings need pos_n_m, nav_cov and det_cov (with_navigation)")
        self.batches += 1
        weak = [o for o in batch if o.weak]
        batch = [o for o in batch if not o.weak]
        if weak:  # (kept for the next accepted set; they take no part in finding one)
            self._weak_pending += weak
            self._weak_old += weak
        if not batch:
            return None
        t_new = max(o.t_s for o in batch)
        self._weak_pending = [o for o in self._weak_pending if o.t_s >= t_new - self.config.window_s]
        self._pending = [o for o in self._pending if o.t_s >= t_new - self.config.window_s] + list(batch)
        # the block alone first (its sightings share the least drift), then the window
        self._memo = {}
        try:
            lc = self.associate(list(batch))
            if lc is None and len(self._pending) > len(batch):
                lc = self.associate(list(self._pending))
            if lc is None and self.config.extend_probability > 0:
                lc = self.extend(list(self._pending))
        finally:
            self._memo = None
        if lc is not None:
            used = {id(b) for _, b in lc.pairs}
            self._pending = [o for o in self._pending if id(o) not in used]
            # (a sighting in a pair with a weak one stays in play: the weak pair does not
            # change the closure, a later set may still take it)
            lc = self._with_weak(lc)
            used = {id(b) for _, b in lc.weak_pairs if b.weak}
            self._weak_pending = [o for o in self._weak_pending if id(o) not in used]
        if self.images is not None:  # guided re-detection: every sighting in a pair is skipped
            if lc is not None:
                self._paired |= {id(o) for p in tuple(lc.pairs) + tuple(lc.weak_pairs) for o in p}
            lc = self._guided(lc)
        self._store(batch, t_new - self.config.memory_s)
        if self._spans:
            self._spans = {k: v for k, v in self._spans.items() if any(k == id(r[2]) for r in self._recent)}
        if self._paired or self._tested or self._weak_used:  # (ids of sightings no longer kept could be reused)
            alive = self._kept_ids(self._paired | self._tested | self._weak_used)
            self._paired &= alive
            self._tested &= alive
            self._weak_used &= alive
        return lc

    def _kept_ids(self, ids: set[int]) -> set[int]:
        """Those of ``ids`` that are the id of a kept sighting (stored, weak or not, or pending):
        ``ids & set(map(id, chain(...)))`` over those lists. The stored ones' from their arrays'
        ``id`` columns (a tenth of :meth:`add` was the set of every kept sighting's id, to keep
        the dozen ids in the sets)."""
        alive = ids.intersection(self._stored_arrays()["id"].tolist())
        alive.update(ids.intersection(self._weak_arrays()["id"].tolist()))
        alive.update(ids.intersection(map(id, chain(self._pending, self._weak_pending))))
        return alive

    def _with_weak(self, lc: LoopClosure) -> LoopClosure:
        """``lc`` with the pairs that have a weak sighting and fit the drift of its set.

        A weak sighting (:attr:`~adaptnav.sonar.objects.ObjectSighting.weak`: a small object
        near the nadir, found only on the unfiltered image, where speckle gives many more false
        ones) never founds a set; once a set is accepted its fitted drift predicts where each of
        its legs' objects lies on the other leg to a few decimetres, and a weak sighting there —
        paired with a sighting of the other leg (weak or not) not already in a pair of the set
        nor in an earlier weak pair, within the inlier gate of that prediction, attributes
        agreeing, the only candidate of both its sightings — is that object seen again. Those
        pairs are the closure's ``weak_pairs``; its pairs, offset and covariance stay the set's
        (the navigation and the calibrator get what they got without weak sightings). Only the sightings within
        ``window_s`` + ``set_span_s`` of the set's times are tried, and a pair only where
        its residual is far likelier for the object than for a false weak sighting lying there
        (far from the set, or with a drift known poorly, the prediction spans metres; at the
        gate's edge the residual is unlikely for the object), weighed by the prior odds that the
        other sighting's object was seen there at all (``weak_prior_odds``; a weak sighting is
        itself an object only once in 25: ``weak_weak_prior_odds``), the posterior odds at least
        ``weak_posterior_odds``.
        """
        c = self.config
        if not (self._weak_old or self._weak_pending) or not self._recent:
            return lc
        ta, tb, drift = self._recent[-1]
        reach = c.window_s + c.set_span_s
        in_set = {id(o) for p in lc.pairs for o in p} | self._weak_used
        # the stored sightings (the last quarter hour) near ta by their arrays, ordinary ones first
        stored, weak = self._stored_arrays(), self._weak_arrays()
        k_old = [k for k in np.flatnonzero(np.abs(stored["t_s"] - ta) <= reach).tolist()
                 if id(self._old[k]) not in in_set]
        k_weak = [k for k in np.flatnonzero(np.abs(weak["t_s"] - ta) <= reach).tolist()
                  if id(self._weak_old[k]) not in in_set]
        old = [self._old[k] for k in k_old] + [self._weak_old[k] for k in k_weak]
        new = [o for o in self._pending if abs(o.t_s - tb) <= reach and id(o) not in in_set]
        n_new_ordinary = len(new)
        new += [o for o in self._weak_pending if abs(o.t_s - tb) <= reach and id(o) not in in_set]
        if not old or not new:
            return lc
        # pairs with a weak sighting, of two legs, near the set's offset (within 10 m: the
        # inlier gates are a metre or two)
        p_old = np.concatenate([stored["smooth_pos_n_m"][k_old], weak["smooth_pos_n_m"][k_weak]])
        p_new = _smooth_positions(new)
        # (which are weak by their lists: the ordinary ones first, the weak ones kept apart)
        w_old = np.arange(len(old)) >= len(k_old)
        w_new = np.arange(len(new)) >= n_new_ordinary
        t_old = np.concatenate([stored["t_s"][k_old], weak["t_s"][k_weak]])
        t_new = np.array([o.t_s for o in new])
        near = _near_pairs(p_old, p_new, drift.predict([ta], [tb])[0], 10.0,
                           (w_old[:, None] | w_new[None]) & (t_new[None] - t_old[:, None] >= c.min_gap_s))
        ii, jj = np.nonzero(near)
        if not ii.size:
            return lc
        cand = list(zip(ii.tolist(), jj.tolist()))
        diffs = p_old[ii] - p_new[jj]
        # (the detectors' covariances of the stored ones from their arrays: the same values)
        D_old = np.concatenate([stored["det_cov"][k_old], weak["det_cov"][k_weak]])
        D = D_old[ii] + np.array([o.det_cov for o in new])[jj]
        r, R = drift.residuals(diffs, t_old[ii], t_new[jj], D)
        m2 = _m2(r, R)
        inside = np.flatnonzero(m2 <= self._inlier)
        # the object seen again, against a false weak sighting that happens to lie there: the
        # residual's density under the set's prediction over the false ones' density (a
        # prediction far from the set, or a drift known poorly, spreads over metres, where one
        # lies by chance; so does a residual at the edge of the gate). False weak sightings
        # gather where the seabed is rough (ripples, gravel): the density is the larger of the
        # measured mean and the weak sightings' own around the pair's weak one — needed only
        # for the pairs inside the gate (of all pairs near the offset it was a quarter of this),
        # as is all that follows (each pair's numbers its own)
        i_in, j_in = ii[inside], jj[inside]
        rho = np.full(inside.size, c.weak_clutter_per_m2)
        if self._weak_old and inside.size:
            p_weak = weak["smooth_pos_n_m"]
            rad = c.weak_density_radius_m
            # the pair's weak sighting (the new one if weak), each counted once (it is in many pairs)
            w_key = np.where(w_new[j_in], len(old) + j_in, i_in)
            _, first, at = np.unique(w_key, return_index=True, return_inverse=True)
            p_w = np.where(w_new[j_in[first]][:, None], p_new[j_in[first]], p_old[i_in[first]])
            n = np.count_nonzero(np.sum((p_weak[None] - p_w[:, None]) ** 2, axis=2) <= rad * rad, axis=1) - 1
            rho = np.maximum(rho, (n / (math.pi * rad * rad))[at.reshape(-1)])
        lr = np.exp(-0.5 * m2[inside]) / (2.0 * math.pi * np.sqrt(np.linalg.det(R[inside])) * rho)
        # posterior odds: the prior odds that the other sighting's object is there to be seen
        # (an ordinary sighting is an object nine times in ten, a weak one once in 25)
        prior = np.where(w_old[i_in] & w_new[j_in], c.weak_weak_prior_odds, c.weak_prior_odds)
        likely = inside[prior * lr >= c.weak_posterior_odds].tolist()
        fit = [k for k in likely if self._attributes_agree(old[cand[k][0]], new[cand[k][1]])]
        # the only candidate of both its sightings (two objects near one place: either could be it)
        n_old = np.bincount([cand[k][0] for k in fit], minlength=len(old))
        n_new = np.bincount([cand[k][1] for k in fit], minlength=len(new))
        extra = [(old[cand[k][0]], new[cand[k][1]]) for k in fit
                 if n_old[cand[k][0]] == 1 and n_new[cand[k][1]] == 1]
        if self.trace is not None:  # where each was lost (the experiment's error budget)
            stage = np.full(len(cand), "not in the set", dtype=object)
            stage[inside] = "chance bound"
            stage[likely] = "attributes"
            stage[fit] = "ambiguous"
            for k, st in enumerate(stage):
                self._note(old[cand[k][0]], new[cand[k][1]], st)
        if not extra:
            return lc
        self.weak_pairs += len(extra)
        self._weak_used |= {id(o) for p in extra for o in p}
        if self.trace is not None:
            for a, b in extra:
                self._note(a, b, "accepted")
        return replace(lc, weak_pairs=tuple(extra))

    def _guided(self, lc: LoopClosure | None) -> LoopClosure | None:
        """Guided re-detection (:mod:`adaptnav.sonar.guided`) with the latest accepted set's
        drift, after every batch: the pairs found join the weak pairs of ``lc`` (or of the next
        closure when this batch gave none; scored, not fused). A closure's offset predicts the
        other leg's place of an object only once that place has been imaged: an old sighting's
        often lies on the new leg a block or two ahead."""
        c = self.config
        if self._recent:
            ta, tb, drift = self._recent[-1]
            newest = max([o.t_s for o in self._pending] or [tb])
            if newest - tb <= c.window_s + c.set_span_s:
                self._guided_pending += self._guided_search(ta, tb, drift, () if lc is None else lc.pairs)
        if lc is None or not self._guided_pending:
            return lc
        extra, self._guided_pending = tuple(self._guided_pending), []
        return replace(lc, weak_pairs=tuple(lc.weak_pairs) + extra)

    def _guided_search(self, ta: float, tb: float, drift: "Drift", set_pairs) -> list:
        """The objects of either leg of a set (times ``ta``, ``tb``, its fitted ``drift``) that no
        pair holds, re-detected where the drift predicts them in the other leg's image
        (:func:`adaptnav.sonar.guided.redetect`): (earlier, new) pairs. Only ordinary sightings
        are looked for (a weak one is an object once in 25), each once (every test is a chance of
        a false alarm); not where an ordinary sighting of the other leg already lies inside the
        gate (the associator's own tests saw that pair); a re-detected spot claimed by two
        sightings is ambiguous and dropped."""
        from adaptnav.sonar.guided import GuidedConfig, abeam, redetect

        c = self.config
        gc = self.guided_config or GuidedConfig()
        reach = c.window_s + c.set_span_s
        skip = self._paired | self._tested
        pool = {id(o): o for o in self._old + self._pending if not o.weak}
        pool.update({id(o): o for p in set_pairs for o in p})
        # the set's legs: their headings at its two times (a sighting past a turn is on another leg)
        heading = {}
        for t in (ta, tb):
            r = self.images.rows(t - 1.0, t + 1.0)
            if r is None:
                return []
            heading[t] = float(r["yaw"][0])

        def on_leg(o, t):
            return abs(math.remainder(o.heading_rad - heading[t], 2 * math.pi)) <= gc.max_heading_diff_rad

        near_a = [o for o in pool.values() if abs(o.t_s - ta) <= reach + 60.0 and abs(o.t_s - ta) < abs(o.t_s - tb)
                  and on_leg(o, ta)]
        near_b = [o for o in pool.values() if abs(o.t_s - tb) <= reach + 60.0 and abs(o.t_s - tb) <= abs(o.t_s - ta)
                  and on_leg(o, tb)]
        # the weak sightings already in a pair count as the other leg's sightings too (the
        # object there is re-associated already)
        paired_weak = [o for o in self._weak_old + self._weak_pending if id(o) in self._paired]
        old_all = near_a + [o for o in paired_weak if abs(o.t_s - ta) <= reach + 60.0
                            and abs(o.t_s - ta) < abs(o.t_s - tb) and on_leg(o, ta)]
        new_all = near_b + [o for o in paired_weak if abs(o.t_s - tb) <= reach + 60.0
                            and abs(o.t_s - tb) <= abs(o.t_s - ta) and on_leg(o, tb)]
        # near the set's pairs in time: the drift is interpolated, not carried far (a minute
        # before the set, early in a survey, it was 5 m off with a σ of 0.7 m: seed 3)
        a0, a1, b0, b1 = self._spans.get(id(drift), (ta, ta, tb, tb))
        m = gc.max_extrapolation_s
        old = [o for o in near_a if a0 - m <= o.t_s <= a1 + m and id(o) not in skip]
        new = [o for o in near_b if b0 - m <= o.t_s <= b1 + m and id(o) not in skip]
        found = []  # (seen, re-detected, seen is on the old leg)
        rows_of: dict[float, dict | None] = {}
        for seen, on_old in [(o, True) for o in old] + [(o, False) for o in new]:
            # the other leg's rows: around tb for an old sighting, around ta for a new one
            t_other = tb if on_old else ta
            t0, t1 = t_other - reach, t_other + reach
            if t_other not in rows_of:  # (two windows per search: the rows of either leg)
                rows_of[t_other] = self.images.rows(t0, t1, heading[t_other], gc.max_heading_diff_rad)
            rows = rows_of[t_other]
            if rows is None:
                self._count("no image", seen)
                continue
            # its time on the other leg: the drift at the abeam row, twice
            t_guess = t_other
            target = None
            for _ in range(2):
                d = drift.predict([seen.t_s if on_old else t_guess], [t_guess if on_old else seen.t_s])[0]
                target = seen.smooth_pos_n_m - d if on_old else seen.smooth_pos_n_m + d
                ab = abeam(rows, target)
                if ab is None:
                    break
                t_guess = float(rows["t"][ab[0]])
            if ab is None:
                self._count("not abeam", seen)
                continue
            # the seen sighting's detector error and the template's placement (a row, a column)
            D = seen.det_cov + gc.placement_sigma_m ** 2 * np.eye(2)
            R = drift.residual_cov([seen.t_s if on_old else t_guess], [t_guess if on_old else seen.t_s], D[None])[0]
            others = new_all if on_old else old_all
            if others:
                # (each with its own detector's covariance in place of the template's placement)
                P = np.array([o.smooth_pos_n_m for o in others])
                Ro = (R - gc.placement_sigma_m ** 2 * np.eye(2))[None] + np.array([o.det_cov for o in others])
                if np.any(_m2(P - target[None], Ro) <= self._inlier):
                    self._count("other sighting in the gate", seen)
                    continue
            excl = [o.smooth_pos_n_m for o in others if t0 <= o.t_s <= t1]
            obj, info = redetect(self.images, seen, target, R, t0, t1, gc, exclude_n_m=excl,
                                 heading_rad=heading[t_other], rows=rows)
            self._count(info["reason"], seen)
            if "p" in info:  # tested: once only (each test is a chance of a false alarm)
                self._tested.add(id(seen))
            if obj is not None:
                found.append((seen, obj, on_old))
        if not found:
            return []
        keep = []
        for k, (seen, obj, on_old) in enumerate(found):
            clash = any(m != k and o2.side == obj.side and abs(o2.t_s - obj.t_s) < 5.0
                        and np.linalg.norm(o2.smooth_pos_n_m - obj.smooth_pos_n_m) < 1.5
                        for m, (_, o2, _) in enumerate(found))
            if clash:
                self._count("ambiguous", seen)
                continue
            keep.append((seen, obj) if on_old else (obj, seen))
        self.guided_pairs += len(keep)
        self._paired |= {id(o) for p in keep for o in p}
        return keep

    def _count(self, reason: str, seen=None) -> None:
        self.guided_tests[reason] = self.guided_tests.get(reason, 0) + 1
        if self.guided_log is not None:
            self.guided_log.append((seen, reason))
