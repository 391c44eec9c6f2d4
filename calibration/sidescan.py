r"""The calibrator's side-scan: object sightings out, the filter's cross-leg links back in.

Where the side-scan work runs. The object detector (:mod:`adaptnav.sonar.objects`) is the
costly part of side-scan (a ground-range waterfall per block of pings), so it runs where
the calibrator runs — its child process, off the filter's thread — and its sightings go back
to the runner by the one route a release takes (``calibrator.poll``) as an
:class:`ObjectBatch`. The runner hands the batch to the estimator like a sample; the
estimator (:class:`adaptnav.service.loop_closures.SideScanEstimator`) places every sighting
with *its* navigation at the ping, associates it with earlier legs inside *its* covariance
(:class:`adaptnav.sonar.association.LegAssociator`) and fuses each loop closure
(:mod:`adaptnav.fusion.aiding.loop_closure`). It writes the pairs it accepted into the batch
(:attr:`ObjectBatch.links`), and the batch goes on to the calibrator (:meth:`observe`), which
learns from those pairs. One association, gated by the filter's covariance, teaches both.

What the calibrator learns from a pair. Two sightings ``a`` (earlier leg) and ``b`` of one
object, abeam at body offsets ``z_a``, ``z_b`` (forward, starboard), give the vehicle's true
displacement between the two times without any absolute position:

.. math:: p_b − p_a = R(θ_a) z_a − R(θ_b) z_b

This is evidence on the speed scale k_V and the current: between reciprocal legs the
displacement across the legs (the turn, ``leg_spacing`` long) scales with k_V, the one along
them with the current times the time between the sightings. It enters the calibrator twice:

* as :class:`~adaptnav.calibration.sensors.LandmarkSighting` observations sharing one track id
  at the window poses of ``a`` and ``b``, which the EM's landmark map scores (every sighting
  against the map of the *earlier* sightings only: :func:`adaptnav.calibration.em.freeze_landmarks`);
* as relative-displacement rows of the closed-form (k_V, current) fit that warm-starts EM
  (:func:`adaptnav.calibration.fix_regression.fix_regression`, :func:`landmark_rows`): a frozen
  map during an outage carries the whole absolute uncertainty of the earlier pose and says
  little, while the displacement itself is exact in the pair. The calibrator keeps the
  controls, headings and linked sightings over a memory longer than its EM window
  (``landmark_memory_steps``): the two sightings of a pair of reciprocal 500 m legs are up to
  12 min apart, and the link comes back a block and the calibrator's latency later.

The pairs of one loop closure share most of their dead-reckoning error (their sightings are
seconds apart on each leg), so they are one piece of evidence: :attr:`LandmarkSighting.group`
names the closure and the fit shares one weight among a group's pairs.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np


@dataclass(frozen=True, eq=False)
class ObjectBatch:
    """Object sightings of one block of side-scan pings (a calibrator's side product).

    Attributes
    ----------
    t_s : float
        Time of the ping that completed the block (s): the data time it is known at.
    sightings : tuple of :class:`adaptnav.sonar.objects.ObjectSighting`
        The block's objects; positions from the calibrator's own ping dead reckoning (the
        filter places them again with its navigation).
    links : list of (ObjectSighting, ObjectSighting)
        Filled by the filter's association before the batch goes on to the calibrator:
        every accepted (earlier, new) pair, as the filter placed them; one list per loop
        closure (``links[k]`` is a tuple of pairs).
    """

    KIND: ClassVar[str] = "sonar_objects"
    t_s: float
    sightings: tuple
    links: list = field(default_factory=list)


class CalibratorSonar:
    """Pings → :class:`ObjectBatch` in the calibrator (the object front end and its ping
    dead reckoning, which sets the image's along-track spacing and is tied to the fixes)."""

    def __init__(self, dead_reckoning=None) -> None:
        """``dead_reckoning``: an :class:`adaptnav.sonar.dead_reckoning.AnchoredDeadReckoning`
        that has been given the fixes so far (default a new one)."""
        from adaptnav.sonar.dead_reckoning import AnchoredDeadReckoning
        from adaptnav.sonar.objects import ObjectFrontEnd

        self.front_end = ObjectFrontEnd()
        self.dead_reckoning = AnchoredDeadReckoning() if dead_reckoning is None else dead_reckoning

    def push(self, ping) -> ObjectBatch | None:
        """Take one ping; an :class:`ObjectBatch` when a block completes (None otherwise,
        also for a block without objects)."""
        pn, pe, sigma = self.dead_reckoning.push_floats(ping)
        s = sigma if math.isfinite(sigma) else 1e3
        var = s * s
        # (Python floats: the isotropic covariance's entries as ObjectFrontEnd.push takes them
        # from an array)
        sightings = self.front_end.push_floats(ping, pn, pe, (var, 0.0, 0.0, var), float(ping.heading_rad))
        return ObjectBatch(float(ping.t_s), tuple(sightings)) if sightings else None

    def finish(self) -> ObjectBatch | None:
        """The data ended: the objects of the block not yet complete
        (:meth:`adaptnav.sonar.objects.ObjectFrontEnd.flush`). A block completes only with the
        next one's context pings, so without this the objects of the last 16-18 s were never
        detected (landmark survey seed 7: the inline pipeline's last loop closure, which its
        block boundary happened to catch, corrected the end position by 2.3 m). None when
        there is no such object."""
        sightings, t_last_ping_s = self.front_end.flush()
        return ObjectBatch(t_last_ping_s, tuple(sightings)) if sightings else None


def body_sigmas_m(sighting) -> tuple[float, float]:
    """(along, across) 1-σ (m) of a placed sighting's detector offset (its ``det_cov``
    rotated back into the body frame at its heading)."""
    c, s = math.cos(sighting.heading_rad), math.sin(sighting.heading_rad)
    fwd, stb = np.array([c, s]), np.array([-s, c])
    D = np.asarray(sighting.det_cov, float)
    return math.sqrt(max(float(fwd @ D @ fwd), 1e-6)), math.sqrt(max(float(stb @ D @ stb), 1e-6))


class LinkIds:
    """Track ids of linked sightings: a sighting keeps the id it was first given, and the
    other sighting of a new pair takes it (an object re-found on legs 1–2 and 2–3 is one
    landmark). Sightings are known by (time, side); bounded to the last ``max_keys``."""

    def __init__(self, first_id: int = 2_000_000, max_keys: int = 20_000) -> None:
        self._ids: dict[tuple[float, str], int] = {}
        self._next = first_id
        self._next_group = 0
        self.max_keys = max_keys

    @staticmethod
    def key(sighting) -> tuple[float, str]:
        return (round(float(sighting.t_s), 3), str(sighting.side))

    def new_group(self) -> int:
        self._next_group += 1
        return self._next_group

    def pair(self, a, b) -> tuple[int, bool, bool]:
        """(track id, a is new, b is new) for the pair ``(a, b)``."""
        ka, kb = self.key(a), self.key(b)
        ia, ib = self._ids.get(ka), self._ids.get(kb)
        tid = ia if ia is not None else ib
        if tid is None:
            tid = self._next
            self._next += 1
        for k in (ka, kb):
            self._ids.setdefault(k, tid)
        while len(self._ids) > self.max_keys:  # oldest first (dicts keep insertion order)
            del self._ids[next(iter(self._ids))]
        return tid, ia is None, ib is None


def landmark_pairs(observations, headings_rad) -> list[tuple[int, int, np.ndarray, float, int]]:
    """Relative displacements from landmark sightings in a window (module docstring).

    For every track id, each sighting after the first with its predecessor: ``(a, b,
    Δ, var, group)`` — pose indices a < b, the displacement ``p_b − p_a`` (2,) implied by the
    two body offsets at the poses' headings (m), its variance per axis (m², the two
    sightings' σ, isotropic), and the closure group of the later sighting.
    """
    from adaptnav.calibration.sensors import LandmarkSighting

    th = np.asarray(headings_rad, dtype=float)
    last: dict[int, tuple[int, np.ndarray, float]] = {}
    out = []
    for t, obs in enumerate(observations):
        for o in obs or ():
            if not isinstance(o, LandmarkSighting):
                continue
            c, s = math.cos(th[t]), math.sin(th[t])
            off = np.array([c * o.along_m - s * o.across_m, s * o.along_m + c * o.across_m])
            var = 0.5 * (o.sigma_along_m ** 2 + o.sigma_across_m ** 2)
            prev = last.get(o.track_id)
            if prev is not None and prev[0] < t:
                out.append((prev[0], t, prev[1] - off, prev[2] + var, int(o.group)))
            last[o.track_id] = (t, off, var)
    return out


def landmark_rows(v_m_s, dt_s, headings_rad, observations, params, step_weights):
    """Rows of the (k_V, current) regression (:func:`adaptnav.calibration.fix_regression.fix_regression`)
    from the landmark pairs among ``observations`` (T+1 pose lists) over steps ``v_m_s`` (T,):
    ``p_b − p_a = k_V D_ab + u τ_ab``, whitened by the covariance of the pair's two sightings
    plus that of the dead reckoning between the poses, weight ``λ_b`` (forgetting at the later
    pose) shared by the pairs of a closure.

    The dead reckoning's covariance is not isotropic: the surge noise (``σ_Vv v``, ``σ_V1``)
    acts along the heading of each step, the sway's (``σ_S``) across it. On reciprocal legs the
    displacement *across* the legs (the turn) carries k_V, and it is hardly touched by the
    surge noise of minutes along the legs that makes the along-track part metres uncertain.

    Returns ``(X (2K, 3), y (2K,), w (2K,), X_k (2K, T))``: ``X_k`` is the k_V column of ``X``
    split by step (column t: the whitened unit-speed displacement of step t when it lies between
    the pair's poses; ``X_k.sum(axis=1) == X[:, 0]``), for a k_V that changes along the memory
    (:func:`adaptnav.calibration.fix_regression.fix_regression`, ``k_v_walk_var_per_step``).
    """
    from adaptnav.calibration.fix_regression import dead_reckoning

    pairs = landmark_pairs(observations, headings_rad)
    v = np.asarray(v_m_s, dtype=float)
    if not pairs:
        return np.empty((0, 3)), np.empty(0), np.empty(0), np.empty((0, v.size))
    dt = np.broadcast_to(np.asarray(dt_s, dtype=float), v.shape)
    th = np.asarray(headings_rad, dtype=float)
    cum_d, cum_t, _ = dead_reckoning(v, dt, th, params)
    d_step = np.diff(cum_d, axis=0)  # (T, 2) unit-speed displacement of each step
    phi = th[:-1] + 0.5 * ((np.diff(th) + np.pi) % (2.0 * np.pi) - np.pi)
    u = np.column_stack([np.cos(phi), np.sin(phi)])
    q_along = dt ** 2 * (v ** 2 * params.var_vv + params.var_v1)
    q_across = dt ** 2 * params.var_s
    Q = (q_along - q_across)[:, None, None] * np.einsum("ti,tj->tij", u, u) + q_across[:, None, None] * np.eye(2)
    cum_Q = np.concatenate([np.zeros((1, 2, 2)), np.cumsum(Q, axis=0)])
    lam = np.asarray(step_weights, dtype=float)
    group_size: dict[int, int] = {}
    for *_, g in pairs:
        group_size[g] = group_size.get(g, 0) + 1
    X, y, w, Xk = [], [], [], []
    for a, b, delta, var_pair, g in pairs:
        D = cum_d[b] - cum_d[a]
        tau = cum_t[b] - cum_t[a]
        L = np.linalg.cholesky(var_pair * np.eye(2) + cum_Q[b] - cum_Q[a])
        Xw = np.linalg.solve(L, np.array([[D[0], tau, 0.0], [D[1], 0.0, tau]]))
        yw = np.linalg.solve(L, np.asarray(delta, float))
        per_step = np.zeros((2, v.size))
        per_step[:, a:b] = np.linalg.solve(L, d_step[a:b].T)
        wt = lam[b - 1] / (group_size[g] if g >= 0 else 1)
        X += Xw.tolist()
        y += yw.tolist()
        w += [wt, wt]
        Xk.append(per_step)
    return np.array(X), np.array(y), np.array(w), np.vstack(Xk)


__all__ = ["ObjectBatch", "CalibratorSonar", "LinkIds", "landmark_pairs", "landmark_rows", "body_sigmas_m"]
