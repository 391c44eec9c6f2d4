"""Side-scan loop closures in the service: the estimator that takes side-scan object
sightings like any other input (:class:`SideScanEstimator`, built by
:func:`adaptnav.service.compose.make_estimator`).

The path, live and in replay (the runner does nothing special for it):

1. every side-scan ping reaches the estimator as a sample does; the estimator has no use for
   the image, but records its own navigation at the ping (position, its covariance, heading,
   velocity, and the jumps its updates made — :attr:`adaptnav.sonar.objects.ObjectSighting.jump_n_m`)
   and keeps horizontal-position clones while pings come
   (:meth:`adaptnav.fusion.eskf.Estimator.clone_position`);
2. the calibrator, which gets the pings too, runs the object detector where its EM runs (its
   child process: off the filter's thread) and returns each block's sightings by the route
   a release takes (:class:`adaptnav.calibration.sidescan.ObjectBatch`,
   :meth:`adaptnav.service.runtime.runner._Loop.product`);
3. the estimator places them with the navigation it recorded at their pings, associates them
   with the earlier legs inside its own covariance (:class:`adaptnav.sonar.association.LegAssociator`,
   gated by the covariance of the error difference of its clones), fuses each loop closure
   (:mod:`adaptnav.fusion.aiding.loop_closure`) and returns its aid status (source
   ``loop_closure``) like any aid; the accepted pairs go into the batch, which the runner
   then hands back to the calibrator (it learns k_V and the current from them).

The detector runs where the calibrator runs, so there are loop closures only with a
calibrator in the same runner: the daemon's child, ``adaptnav replay --calibrate``. A remote
calibrator node (:mod:`adaptnav.service.calibrator.node`) has no filter to hand its objects
to and drops them (it still detects them: a cost on the node's computer).

Nothing is recorded and no clone kept while no object sightings can come (``objects=False``:
a replay without a calibrator, whose pings had cost the filter a fifth of its time in
clones that nothing would ever fuse); the outputs are the same either way (clones are
consider states: they change no estimate until a closure is fused).

Memory is bounded: the navigation record covers ``nav_keep_s`` of pings, the associator keeps
sightings for at most the clones' horizon (older ones could not be fused) and at most
``AssociationConfig.max_sightings``.
"""
from __future__ import annotations

import bisect
import math
from collections import deque
from itertools import chain, islice
from operator import itemgetter
from typing import Any

import numpy as np

from adaptnav.fusion.eskf import Estimator
from adaptnav.fusion.state import VEL, X_POS_NE, X_VEL

VEL_NE = slice(VEL.start, VEL.start + 2)
X_VEL_NE = slice(X_VEL.start, X_VEL.start + 2)  # north, east of the state's velocity

# clones are kept (each costs a little per covariance step) while a ping came this recently (s)
SONAR_ACTIVE_S = 30.0


def _ping_at_or_before(nav: deque, t_s: float) -> int:
    """Index of the last ping of the record ``nav`` (rows whose first item is the time, increasing)
    at or before ``t_s``; 0 when none is. By bisection: walked back from the newest ping, a
    batch's couple of hundred steps were a sixth of placing its sightings."""
    return max(bisect.bisect_right(nav, t_s, key=itemgetter(0)) - 1, 0)


def _interpolated(pings: list, t_s: np.ndarray) -> np.ndarray:
    """The record's columns but the time (rows ``pings``, the time first, increasing) at the
    times ``t_s`` (within the record), each interpolated between the two pings around it: the
    numbers of ``np.interp`` over the whole record per column, which reads those two only (the
    last at or before it and the next). Only those rows are read into an array (as one run of
    floats; np.array of the tuples took twice as long): a batch's sightings lie between a
    couple of dozen of the couple of hundred pings, whose conversion was a third of placing
    them."""
    t_pings = np.fromiter(map(itemgetter(0), pings), float, len(pings))
    at = np.searchsorted(t_pings, t_s, side="right") - 1
    used = [pings[k] for k in np.union1d(at, np.minimum(at + 1, len(pings) - 1)).tolist()]
    rec = np.fromiter(chain.from_iterable(used), float, len(used) * len(used[0])).reshape(len(used), -1).T
    return np.array([np.interp(t_s, rec[0], rec[k]) for k in range(1, rec.shape[0])]).T


class SideScanEstimator(Estimator):
    """:class:`~adaptnav.fusion.eskf.Estimator` that also takes side-scan pings and object
    batches (module docstring). Same constructor, plus:

    Parameters
    ----------
    nav_keep_s : float
        Navigation at pings is kept this long (s): longer than a detection block plus the
        calibrator's latency (the sightings come back that late).
    association : adaptnav.sonar.association.AssociationConfig, optional
        Gates of the association (default: its defaults, memory capped at the clone horizon).
    objects : bool
        Object sightings may come (a calibrator in the same runner detects them): record the
        navigation at pings and keep clones. ``False``: pings are only counted.
    """

    def __init__(self, *args: Any, nav_keep_s: float = 300.0, association: Any = None, objects: bool = True,
                 **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.objects = bool(objects)
        self.nav_keep_s = float(nav_keep_s)
        # made here, not with the first object batch: importing the sonar package then cost
        # that batch's bus callback 25 ms (a live latency spike at the survey's first objects)
        self.associator: Any = self._make_associator(association) if self.objects else None
        # (t, north, east, yaw unwrapped, cov 2×2 (4), jump north, jump east, velocity cov 2×2 (4)) per ping
        self._nav: deque = deque()
        # the accumulated jumps at the last ping (north, east; m) and (t, position NE, velocity
        # NE) there: Python floats, the same arithmetic as numpy's on two elements at a tenth of
        # the cost per ping
        self._jump: tuple[float, float] = (0.0, 0.0)
        self._last_vel: tuple[float, tuple[float, float], tuple[float, float]] | None = None
        # clone time → the accumulated jumps then (as at a ping): a closure is referred from its
        # sightings' times to its clones' (:meth:`fuse_closure`)
        self._clone_jump: dict[float, np.ndarray] = {}
        self._t_ping = -math.inf
        self.side_scan = {"pings": 0, "batches": 0, "sightings": 0, "closures": 0, "closures_fused": 0}

    # ---------------------------------------------------------------- the one entry
    def process(self, sample: Any) -> list:
        kind = sample.KIND
        if kind == "sonar":
            if self.config.loop_closure.enabled:
                self._ping(sample)
            return []
        if kind == "sonar_objects":
            return self._objects(sample) if self.config.loop_closure.enabled else []
        out = Estimator.process(self, sample)  # (super() resolved per sample costs more)
        if (kind == "imu_batch" or kind == "imu") and self._t_ping > -math.inf:
            t = float(self._clock[0])
            clones = self._clones.t_s
            # (a clone at most every clone period: clone_position() would return False at once)
            if t - self._t_ping < SONAR_ACTIVE_S and not (clones and t - clones[-1] < self._clones.period_s) \
                    and self.clone_position():
                self._keep_clone_jump()
        return out

    def shift_time(self, delta_s: float) -> None:
        super().shift_time(delta_s)
        self._nav.clear()  # its times are in the old base; the record refills within a block
        self._last_vel = None
        self._clone_jump = {t + delta_s: j for t, j in self._clone_jump.items()}

    # ---------------------------------------------------------------- internals
    def _ping(self, ping: Any) -> None:
        """Record the navigation at the ping (extrapolated from the state's time with its velocity)."""
        t = float(ping.t_s)
        if not (self.initialized and math.isfinite(t)):
            return
        self.side_scan["pings"] += 1
        if not self.objects:
            return  # nothing will place sightings or fuse closures: no record, no clones
        self._t_ping = t
        ns = self.horizontal_nav()  # the numbers of nav_state(), what the record needs of it
        if ns is None:  # not valid
            return
        t_s, (p0, p1), vel, yaw, ((c00, c01), (c10, c11)), ((v00, v01), (v10, v11)) = ns
        dt = t - t_s
        v0, v1 = vel
        pos0, pos1 = p0 + v0 * dt, p1 + v1 * dt
        # the accumulated jumps here (_jump_at, inlined: the same arithmetic, a call less per ping)
        j0, j1 = self._jump
        last = self._last_vel
        if last is not None and t > last[0]:
            t0, (q0, q1), (u0, u1) = last
            d = t - t0
            j0, j1 = j0 + (pos0 - (q0 + 0.5 * (u0 + v0) * d)), j1 + (pos1 - (q1 + 0.5 * (u1 + v1) * d))
            self._jump = (j0, j1)
        self._last_vel = (t, (pos0, pos1), vel)
        nav = self._nav
        if nav:
            last = nav[-1]
            if t <= last[0]:
                return
            yaw = last[3] + math.remainder(yaw - last[3], 2.0 * math.pi)
        nav.append((t, pos0, pos1, yaw, c00, c01, c10, c11, j0, j1, v00, v01, v10, v11))
        t_keep = t - self.nav_keep_s
        while nav and nav[0][0] < t_keep:
            nav.popleft()

    def _jump_at(self, t: float, pos: tuple[float, float], vel: tuple[float, float]) -> tuple[float, float]:
        """The accumulated jumps at ``t`` (m): those of the last ping plus what the velocity does
        not explain of the position since (trapezoid)."""
        if self._last_vel is None or not t > self._last_vel[0]:
            return self._jump
        t0, p0, v0 = self._last_vel
        dt = t - t0
        (j0, j1), (q0, q1), (u0, u1) = self._jump, p0, v0
        return (j0 + (pos[0] - (q0 + 0.5 * (u0 + vel[0]) * dt)), j1 + (pos[1] - (q1 + 0.5 * (u1 + vel[1]) * dt)))

    def _keep_clone_jump(self) -> None:
        """The jumps at the clone just made (its time is the state's), as a ping would record them
        from :meth:`nav_state`'s position and velocity: without an output point those are the
        state's own (read from it: the whole state, its covariance and validity, was two thirds
        of this per clone), else nav_state's at that point."""
        if self._out_arm is None:
            x = self._x
            pos, vel = x[X_POS_NE].tolist(), x[X_VEL_NE].tolist()
        else:
            ns = self.nav_state()
            pos, vel = ns.pos_n_m[:2].tolist(), ns.vel_n_m_s[:2].tolist()
        t = float(self._clones.t_s[-1])
        self._clone_jump[t] = np.array(self._jump_at(t, pos, vel))
        horizon = t - self._clones.horizon_s
        if next(iter(self._clone_jump)) < horizon:  # oldest first (insertion order)
            self._clone_jump = {k: v for k, v in self._clone_jump.items() if k >= horizon}

    def fuse_closure(self, lc: Any):
        """Fuse a loop closure at the clones nearest its sightings' times, its offset referred to
        them (:meth:`adaptnav.sonar.association.LoopClosure.offset_at`).

        A clone lies up to ``clone_period_s`` from a sighting, and an update between the two —
        a USBL fix — moves the filter's position by metres: fused at the sightings' times, a
        closure whose clone was on the other side of a fix was that fix's jump off (survey
        seed 3: 1.9 m across track, 6σ of the closure's covariance). The velocity error over
        those seconds is added to the covariance (``Δt² P_vv`` at each end)."""
        cl = self._clones
        a, b = cl.nearest(lc.t_a_s), cl.nearest(lc.t_b_s)
        if a is None or b is None:
            return self.fuse_loop_closure(lc.t_a_s, lc.t_b_s, lc.offset_n_m, lc.cov)  # too late: rejected
        t_a, t_b = cl.t_s[a], cl.t_s[b]
        j_a, j_b = self._clone_jump.get(t_a), self._clone_jump.get(t_b)
        if j_a is None or j_b is None:
            return self.fuse_loop_closure(lc.t_a_s, lc.t_b_s, lc.offset_n_m, lc.cov)
        p_vv = self._P[VEL_NE, VEL_NE]
        cov = np.asarray(lc.cov, float) + ((t_a - lc.t_a_s) ** 2 + (t_b - lc.t_b_s) ** 2) * 0.5 * (p_vv + p_vv.T)
        return self.fuse_loop_closure(t_a, t_b, lc.offset_at(j_a, j_b), cov)

    def _make_associator(self, association: Any) -> Any:
        """The cross-leg associator (``association``: its config, default its defaults), its
        memory capped at the clone horizon: a pair older than the clones cannot be fused."""
        import dataclasses

        from adaptnav.sonar.association import AssociationConfig, LegAssociator

        cfg = association if association is not None else AssociationConfig()
        cfg = dataclasses.replace(cfg, memory_s=min(cfg.memory_s, self.config.loop_closure.clone_horizon_s))
        return LegAssociator(cfg, relative_covs=self.relative_position_covariances)

    def _objects(self, batch: Any) -> list:
        """Place, associate, fuse (module docstring); the accepted pairs go into ``batch.links``."""
        from adaptnav.sonar.objects import ObjectDetectorConfig, with_navigation

        self.side_scan["batches"] += 1
        if not self._nav or not self.initialized:
            return []
        det = ObjectDetectorConfig()
        t0, t1 = self._nav[0][0], self._nav[-1][0]
        inside = []
        for o in batch.sightings:
            if t0 <= float(o.t_s) <= t1:
                inside.append(o)
            else:
                self.rejected["side_scan_no_navigation"] += 1
        if not inside:
            return []
        # every sighting of the batch interpolated in one call per column (np.interp is
        # point by point: the same numbers as one call per sighting and column), over the
        # record from the ping at or before the earliest sighting (the same bracketing pings:
        # the same numbers as over the whole record, which holds minutes more)
        t = np.array([float(o.t_s) for o in inside])
        nav = self._nav
        first = _ping_at_or_before(nav, float(t.min()))
        # (the rows taken from the right, where they are)
        pings = list(islice(reversed(nav), len(nav) - first))
        pings.reverse()
        rows = _interpolated(pings, t).tolist()
        # (the covariances as their four floats: with_navigation makes them 2×2 arrays)
        placed = [with_navigation(o, row[0:2], row[3:7], row[2], det, row[7:9], row[9:13])
                  for o, row in zip(inside, rows)]
        if not placed:
            return []
        self.side_scan["sightings"] += len(placed)
        lc = self.associator.add(placed)
        if lc is None:
            return []
        self.side_scan["closures"] += 1
        batch.links.append(tuple(lc.pairs))
        status = self.fuse_closure(lc)
        self.side_scan["closures_fused"] += int(status.fused)
        return [status]


__all__ = ["SideScanEstimator", "SONAR_ACTIVE_S"]
