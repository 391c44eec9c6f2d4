"""`adaptnav experiment landmarks`: side-scan objects re-found on reciprocal legs, and what they buy.

The survey scenario (reciprocal lawnmower legs 50 m apart, side-scan of 50 m range at 10 m
altitude, so every seabed point between two legs is seen from both at ground ranges g and
≈ 50 − g) with USBL lost after 20 min and no DVL, simulated once; two filters run over it
side by side:

* **with landmarks**: every ping is placed by this filter's navigation (position, its
  covariance, heading); :class:`adaptnav.sonar.objects.ObjectFrontEnd` detects objects in
  blocks, :class:`adaptnav.sonar.association.LegAssociator` associates each block with the
  earlier legs inside the filter's covariance, and every loop closure is fused by the filter
  at its clones (:meth:`adaptnav.service.loop_closures.SideScanEstimator.fuse_closure`, which
  also gets the pings: its navigation and jumps there);
* **without**: the same filter without the side-scan.

Scored against the simulator's truth (the seabed's objects, the true track):

* ``objects_in_common_swath``: objects that two consecutive (reciprocal) legs both pass
  abeam at a ground range within ``[min_range_m, max_range_m]`` (the usable swath: nearer
  the nadir a shadow is too short to measure);
* ``objects_reassociated_fraction``: of those, the fraction in at least one accepted pair
  whose two sightings are truly that object, one from each of the two legs;
* ``false_link_fraction``: accepted pairs whose sightings are not the same object;
* ``links_per_km``: loop closures per km travelled;
* ``sightings`` / ``sightings_on_objects``: the detector's sightings that may found a set (and of
  them on a true object); ``weak_sightings`` / ``weak_sightings_on_objects``: the weak ones
  (:attr:`adaptnav.sonar.objects.ObjectSighting.weak`, only added to accepted sets), ``weak_pairs``
  / ``weak_false_pairs``: the closures' pairs with a weak sighting
  (:attr:`adaptnav.sonar.association.LoopClosure.weak_pairs`: scored like the others, in ``pairs``
  and ``false_pairs`` too, but not fused nor given to the calibrator);
* ``drift_percent_with_landmarks`` / ``drift_percent_without_landmarks``: horizontal error
  at the end / distance travelled since the last USBL fix, %.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

# the survey, shortened to 40 min, USBL lost after 20 min, side-scan on, no DVL
BASE_OVERRIDES = ("duration_s=2400.0", "usbl.lost_after_s=1200.0", "dvl.enabled=false",
                  "sonar.enabled=true")


@dataclass(frozen=True)
class LandmarkScore:
    """What :func:`run` measures (see the module docstring)."""

    objects_in_common_swath: int
    objects_reassociated: int
    pairs: int
    false_pairs: int
    loop_closures: int
    loop_closures_fused: int
    distance_km: float
    drift_percent_with_landmarks: float
    drift_percent_without_landmarks: float
    sightings: int
    sightings_on_objects: int
    seed: int
    extra: dict = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        n = self.objects_in_common_swath
        return {
            "seed": self.seed,
            "objects_in_common_swath": n,
            "objects_reassociated_fraction": self.objects_reassociated / n if n else None,
            "false_link_fraction": self.false_pairs / self.pairs if self.pairs else 0.0,
            "links_per_km": self.loop_closures / self.distance_km if self.distance_km > 0 else None,
            "drift_percent_with_landmarks": self.drift_percent_with_landmarks,
            "drift_percent_without_landmarks": self.drift_percent_without_landmarks,
            "pairs": self.pairs,
            "false_pairs": self.false_pairs,
            "loop_closures": self.loop_closures,
            "loop_closures_fused": self.loop_closures_fused,
            "sightings": self.sightings,
            "sightings_on_objects": self.sightings_on_objects,
            **self.extra,
        }


def load(overrides=()) -> Any:
    """The experiment's scenario: survey + :data:`BASE_OVERRIDES` + ``overrides``."""
    from adaptnav.sim.scenario import load_scenario

    return load_scenario("survey", list(BASE_OVERRIDES) + list(overrides))


def _legs(t: np.ndarray, yaw: np.ndarray, min_s: float = 60.0, max_rate_rad_s: float = 0.01) -> list[tuple[int, int]]:
    """Index ranges [a, b) of straight legs: the yaw rate (over ±5 s) stays below
    ``max_rate_rad_s`` for at least ``min_s``."""
    y = np.unwrap(yaw)
    k = 5
    rate = np.zeros_like(y)
    if y.size > 2 * k:
        rate[k:-k] = (y[2 * k:] - y[:-2 * k]) / (t[2 * k:] - t[:-2 * k])
        rate[:k], rate[-k:] = rate[k], rate[-k - 1]
    straight = np.abs(rate) < max_rate_rad_s
    legs = []
    edges = np.flatnonzero(np.diff(np.concatenate([[0], straight.astype(int), [0]])))
    for a, b in zip(edges[::2], edges[1::2]):
        if t[b - 1] - t[a] >= min_s:
            legs.append((int(a), int(b)))
    return legs


def run(scenario: Any, *, landmarks: bool = True, min_range_m: float = 5.0,
        max_range_m: float = 45.0, progress: bool = False, guided: bool = True) -> LandmarkScore:
    """Simulate ``scenario`` and score the side-scan landmarks (see the module docstring)."""
    from adaptnav.fusion.state import POS_NE, VEL
    from adaptnav.service.compose import make_estimator
    from adaptnav.service.runtime.replay import build_config
    from adaptnav.sim.simulator import simulate
    from adaptnav.sonar.association import LegAssociator
    from adaptnav.sonar.guided import ImageStore
    from adaptnav.sonar.objects import ObjectFrontEnd

    res = simulate(scenario)
    cfg = build_config(scenario)
    est_with, est_without = make_estimator(cfg), make_estimator(cfg)
    store = ImageStore() if guided else None
    fe = ObjectFrontEnd(store=store)
    assoc = LegAssociator(relative_covs=est_with.relative_position_covariances, images=store)
    assoc.trace = {}
    closures, fused = [], 0
    sightings = []
    for item in res.iter_blocks():
        kind = item.KIND
        if kind == "sonar":
            if not (landmarks and est_with.initialized):
                continue
            est_with.process(item)  # the navigation and its jumps at the ping; clones while pings come
            ns = est_with.nav_state()
            if not ns.valid:
                continue
            dt = item.t_s - ns.t_s
            pos = ns.pos_n_m[:2] + ns.vel_n_m_s[:2] * dt
            batch = fe.push(item, pos, ns.cov[POS_NE, POS_NE], ns.euler_rad()[2], ns.vel_n_m_s[:2],
                            ns.cov[VEL, VEL][:2, :2])
            if batch:
                sightings += batch
                lc = assoc.add(batch)
                if lc is not None:
                    closures.append(lc)
                    if est_with.fuse_closure(lc).fused:  # at the clones, the offset referred to them
                        fused += 1
            continue
        est_with.process(item)
        est_without.process(item)
    return _score(scenario, res, est_with, est_without, sightings, closures, fused,
                  min_range_m, max_range_m, assoc)


def _score(scenario, res, est_with, est_without, sightings, closures, fused, min_range_m, max_range_m,
           assoc=None) -> LandmarkScore:
    dense = res.dense
    t = dense.t_s
    step = max(int(round(1.0 / (t[1] - t[0]))), 1)  # 1 Hz truth is plenty
    tt, pp, yy = t[::step], dense.pos_n_m[::step, :2], dense.euler_rad[::step, 2]
    sb = res.seabed
    objs = sb.seabed.objects_n_m + np.asarray(sb.origin_n_m)[None, :]
    radius = sb.seabed.objects_radius_m

    def truth_object(o) -> int:
        p = np.array([np.interp(o.t_s, tt, pp[:, 0]), np.interp(o.t_s, tt, pp[:, 1])])
        q = p + o.offset_n_m(float(np.interp(o.t_s, tt, yy)))
        d = np.linalg.norm(objs - q[None], axis=1) - radius
        k = int(np.argmin(d))
        return k if d[k] <= 1.5 else -1

    legs = _legs(tt, yy)
    leg_of_t = np.full(tt.size, -1)
    for i, (a, b) in enumerate(legs):
        leg_of_t[a:b] = i

    def leg(ts: float) -> int:
        return int(leg_of_t[min(int(np.searchsorted(tt, ts)), tt.size - 1)])

    # objects both of two consecutive legs pass abeam within the usable swath
    common: dict[int, tuple[int, int]] = {}
    abeam = [_abeam_range(pp[a:b], objs) for a, b in legs]
    for i in range(len(legs) - 1):
        ga, gb = abeam[i], abeam[i + 1]
        ok = (ga >= min_range_m) & (ga <= max_range_m) & (gb >= min_range_m) & (gb <= max_range_m)
        for k in np.flatnonzero(ok):
            common.setdefault(int(k), (i, i + 1))
    found: set[int] = set()
    n_pairs = n_false = 0
    for lc in closures:
        for a, b in tuple(lc.pairs) + tuple(lc.weak_pairs):
            n_pairs += 1
            ka, kb = truth_object(a), truth_object(b)
            if ka < 0 or ka != kb:
                n_false += 1
                continue
            if ka in common and {leg(a.t_s), leg(b.t_s)} == set(common[ka]):
                found.add(ka)
    truth = [truth_object(o) for o in sightings]
    # weak sightings (ObjectSighting.weak: near the nadir, unfiltered image) only join sets the
    # others founded: the detector's precision is the others', the weak ones reported apart
    on_obj = sum(k >= 0 for k, o in zip(truth, sightings) if not o.weak)
    n_weak = sum(o.weak for o in sightings)
    weak_pairs = [(a, b) for lc in closures for a, b in lc.weak_pairs]
    extra = {"weak_sightings": n_weak,
             "weak_sightings_on_objects": sum(k >= 0 for k, o in zip(truth, sightings) if o.weak),
             "weak_pairs": len(weak_pairs),
             "weak_false_pairs": sum(truth_object(a) < 0 or truth_object(a) != truth_object(b) for a, b in weak_pairs)}
    guided = [(a, b) for a, b in weak_pairs if a.guided or b.guided]
    extra["guided_pairs"] = len(guided)
    extra["guided_false_pairs"] = sum(truth_object(a) < 0 or truth_object(a) != truth_object(b) for a, b in guided)
    if assoc is not None:
        extra["guided_tests"] = dict(sorted(assoc.guided_tests.items(), key=lambda kv: -kv[1]))
    if assoc is not None and assoc.trace is not None:
        extra["budget"] = _budget(sightings, truth, [leg(o.t_s) for o in sightings], common, found, abeam,
                                  assoc, min_range_m, max_range_m)
    t_fix = scenario.usbl.lost_after_s if scenario.usbl.enabled and scenario.usbl.lost_after_s else 0.0
    i0 = int(np.searchsorted(tt, t_fix))
    dist_outage = float(np.sum(np.linalg.norm(np.diff(pp[i0:], axis=0), axis=1)))
    dist_all = float(np.sum(np.linalg.norm(np.diff(pp, axis=0), axis=1)))

    def drift(est) -> float:
        ns = est.nav_state()
        k = min(int(np.searchsorted(t, ns.t_s)), t.size - 1)
        err = float(np.linalg.norm(ns.pos_n_m[:2] - dense.pos_n_m[k, :2]))
        return 100.0 * err / dist_outage if dist_outage > 0 else math.nan

    return LandmarkScore(
        objects_in_common_swath=len(common), objects_reassociated=len(found), pairs=n_pairs,
        false_pairs=n_false, loop_closures=len(closures), loop_closures_fused=fused,
        distance_km=dist_all / 1000.0, drift_percent_with_landmarks=drift(est_with),
        drift_percent_without_landmarks=drift(est_without), sightings=len(sightings) - n_weak,
        sightings_on_objects=int(on_obj), seed=int(scenario.seed), extra=extra)


BANDS_M = (5.0, 10.0, 20.0, 30.0, 40.0, 45.0)


def _band(g: float) -> str:
    for lo, hi in zip(BANDS_M[:-1], BANDS_M[1:]):
        if lo <= g < hi:
            return f"{lo:.0f}-{hi:.0f}"
    return "outside"


def _budget(sightings, truth, legs_of, common, found, abeam, assoc, min_range_m, max_range_m) -> dict:
    """Where the objects of the common swath that were not re-associated were lost.

    * ``missed``: not detected on one of the two legs (by that leg's ground-range band), or both;
    * otherwise the furthest stage the best of their true pairs reached in the associator
      (:data:`adaptnav.sonar.association.STAGES`; ``outside`` = beyond the wide gate);
    * ``recall_by_band``: detections / objects abeam of a leg, by ground range, all legs
      (``recall_by_band_without_weak``: not counting weak sightings);
    * ``pair_scatter``: of the true cross-leg pairs, the median and 90th percentile of the
      height and along-track length differences in the associator's σ units.
    """
    from adaptnav.sonar.association import STAGES

    by = {}  # (object, leg) → sightings
    for o, k, lg in zip(sightings, truth, legs_of):
        if k >= 0:
            by.setdefault((k, lg), []).append(o)
    strong = {key for key, v in by.items() if any(not o.weak for o in v)}
    lost: dict[str, int] = {}

    def count(key):
        lost[key] = lost.get(key, 0) + 1

    h_dev, l_dev = [], []
    cfg = assoc.config
    for k, (i, j) in common.items():
        sa, sb = by.get((k, i), []), by.get((k, j), [])
        for a in sa:
            for b in sb:
                if math.isfinite(a.height_m) and math.isfinite(b.height_m):
                    s = math.hypot(cfg.height_sigma_m + cfg.height_sigma_fraction * a.height_m,
                                   cfg.height_sigma_m + cfg.height_sigma_fraction * b.height_m)
                    h_dev.append(abs(a.height_m - b.height_m) / s)
                if math.isfinite(a.length_along_m) and math.isfinite(b.length_along_m):
                    s = math.hypot(cfg.length_sigma_m + cfg.length_sigma_fraction * a.length_along_m,
                                   cfg.length_sigma_m + cfg.length_sigma_fraction * b.length_along_m)
                    l_dev.append(abs(a.length_along_m - b.length_along_m) / s)
        if k in found:
            continue
        if not sa and not sb:
            count("missed on both legs")
            continue
        if not sa or not sb:
            count(f"missed on one leg at {_band(float(abeam[i if not sa else j][k]))} m")
            continue
        best = -1
        for a in sa:
            for b in sb:
                st = assoc.trace.get((id(a), id(b)))
                best = max(best, STAGES.index(st) if st is not None else -1)
        count("outside the wide gate" if best < 0 else STAGES[best])
    recall: dict[str, list[int]] = {}
    for lg, g in enumerate(abeam):
        for k in np.flatnonzero((g >= min_range_m) & (g <= max_range_m)):
            r = recall.setdefault(_band(float(g[k])), [0, 0, 0])
            r[1] += 1
            r[0] += int((int(k), lg) in by)
            r[2] += int((int(k), lg) in strong)

    def q(v):
        return [float(np.median(v)), float(np.percentile(v, 90))] if v else None

    return {"lost": dict(sorted(lost.items(), key=lambda kv: -kv[1])),
            "recall_by_band": {b: round(n / m, 3) for b, (n, m, _) in sorted(recall.items())},
            "recall_by_band_without_weak": {b: round(n / m, 3) for b, (_, m, n) in sorted(recall.items())},
            "pair_scatter_sigmas": {"height": q(h_dev), "length": q(l_dev)}}


def _abeam_range(track: np.ndarray, objs: np.ndarray) -> np.ndarray:
    """Ground range of each object at its closest approach to a leg; NaN when the closest
    point is an end of the leg (the object is beyond it, not abeam)."""
    d = np.linalg.norm(track[None, :, :] - objs[:, None, :], axis=2)
    k = np.argmin(d, axis=1)
    g = d[np.arange(objs.shape[0]), k]
    g[(k < 3) | (k > track.shape[0] - 4)] = np.nan
    return g
