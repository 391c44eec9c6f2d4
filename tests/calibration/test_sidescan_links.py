"""The calibrator learns k_V from side-scan objects re-found on reciprocal legs
(calibration/sidescan.py): after one fix and no more, the pairs the filter associated
(ObjectBatch.links) are its only position information; they move k_V to the truth."""
from __future__ import annotations

import math

import numpy as np

from adaptnav.calibration.online import CalibratorConfig, OnlineCalibrator
from adaptnav.calibration.sidescan import ObjectBatch
from adaptnav.fusion.frames import GeoOrigin
from adaptnav.fusion.motion_model import MotionParams, RpmSpeedTable
from adaptnav.fusion.samples import GnssSample, HeadingSample, RpmSample
from adaptnav.sonar.objects import ObjectSighting

K_TRUE = 0.9          # the water's speed scale; the calibrator starts from 1.0
RPM = 1200.0          # 1.5 m/s reported, 1.35 m/s true
LEG_M, SPACING_M = 300.0, 50.0
ORIGIN = GeoOrigin(math.radians(43.0), math.radians(5.0))


def _track(duration_s: float, dt: float = 0.5, k_before: float = K_TRUE, t_change_s: float = math.inf):
    """Reciprocal lawnmower (north, turn east, south, ...) at the true speed: t, pos (n, e), yaw.
    The water's speed scale is ``k_before`` until ``t_change_s``, :data:`K_TRUE` after."""
    table = RpmSpeedTable()
    r = SPACING_M / 2.0
    t = np.arange(0.0, duration_s, dt)
    pos = np.zeros((t.size, 2))
    yaw = np.zeros(t.size)
    p, th, along, leg, turning = np.zeros(2), 0.0, 0.0, 0, False
    for i in range(t.size):
        pos[i], yaw[i] = p, th
        speed = (k_before if t[i] < t_change_s else K_TRUE) * table.speed(RPM)
        ds = speed * dt
        if not turning:
            p = p + ds * np.array([math.cos(th), math.sin(th)])
            along += ds
            if along >= LEG_M:
                turning, along = True, 0.0
        else:
            w = (1.0 if leg % 2 == 0 else -1.0) * speed / r
            mid = th + 0.5 * w * dt
            p = p + ds * np.array([math.cos(mid), math.sin(mid)])
            th += w * dt
            along += ds
            if along >= math.pi * r:
                turning, along, leg = False, 0.0, leg + 1
                th = 0.0 if leg % 2 == 0 else math.pi
    return t, pos, yaw


def _sightings(t, pos, yaw, rng, t_first_s: float):
    """Objects between every two consecutive legs, each seen abeam from both: (a, b) pairs."""
    straight = np.abs(np.gradient(np.unwrap(yaw), t)) < 1e-6
    legs, start = [], None
    for i, s in enumerate(straight):
        if s and start is None:
            start = i
        elif not s and start is not None:
            legs.append((start, i))
            start = None
    if start is not None:
        legs.append((start, len(t)))
    pairs = []
    for (a0, a1), (b0, b1) in zip(legs[:-1], legs[1:]):
        east_a = pos[a0, 1]
        for north in rng.uniform(30.0, LEG_M - 30.0, 6):
            g_a = rng.uniform(8.0, SPACING_M - 8.0)
            obj = np.array([north, east_a + g_a])
            out = []
            for i0, i1 in ((a0, a1), (b0, b1)):
                k = i0 + int(np.argmin(np.abs(pos[i0:i1, 0] - obj[0])))
                c, s = math.cos(yaw[k]), math.sin(yaw[k])
                rel = obj - pos[k]
                across = -s * rel[0] + c * rel[1]   # starboard positive
                R = np.array([[c, -s], [s, c]])
                out.append(ObjectSighting(
                    t_s=float(t[k]), side="starboard" if across > 0 else "port",
                    ground_range_m=abs(across) + rng.normal(0.0, 0.2), height_m=0.5, shadow_length_m=1.0,
                    length_along_m=1.0, width_across_m=0.5, contrast=10.0, altitude_m=10.0,
                    heading_rad=float(yaw[k]), det_cov=R @ np.diag([0.3 ** 2, 0.2 ** 2]) @ R.T))
            if out[0].t_s > t_first_s:
                pairs.append(tuple(out))
    return pairs


def _run(with_links: bool, seed: int = 4, k_before: float = K_TRUE, t_change_s: float = math.inf,
         duration: float = 1500.0, with_sightings: bool = False):
    rng = np.random.default_rng(seed)
    t, pos, yaw = _track(duration, k_before=k_before, t_change_s=t_change_s)
    cfg = CalibratorConfig(n_particles=200, n_smoothed=30, em_iterations=2, origin_lat_deg=43.0,
                           origin_lon_deg=5.0)
    cal = OnlineCalibrator(cfg, MotionParams(k_v=k_before if math.isfinite(t_change_s) else 1.0), RpmSpeedTable(),
                           np.random.default_rng(seed))
    items = [(0.0, 0, GnssSample(0.0, ORIGIN.lat_rad, ORIGIN.lon_rad, 1.0))]  # at the origin
    for ti, yi in zip(t[::2], yaw[::2]):  # 1 Hz
        items.append((float(ti), 1, RpmSample(float(ti), RPM)))
        items.append((float(ti), 2, HeadingSample(float(ti), float(yi + rng.normal(0.0, 0.005)))))
    if with_links:
        pairs = _sightings(t, pos, yaw, rng, 0.0)
        # the filter's association comes back after the later sighting, a block + latency later,
        # in sets of up to 4 pairs (one loop closure each)
        pairs.sort(key=lambda p: p[1].t_s)
        for i in range(0, len(pairs), 4):
            chunk = tuple(pairs[i:i + 4])
            t_back = max(p[1].t_s for p in chunk) + 80.0
            sightings = tuple(o for pair in chunk for o in pair) if with_sightings else ()
            items.append((t_back, 3, ObjectBatch(t_back, sightings, [chunk])))
    items.sort(key=lambda x: (x[0], x[1]))
    releases = []
    for _, _, sample in items:
        cal.observe(sample)
        releases += [r for r in cal.poll() if r.KIND == "calibration_release"]
    return releases


def test_links_teach_k_v_without_fixes():
    releases = _run(with_links=True)
    taught = [r for r in releases if r.accepted and "landmarks" in r.teachers]
    assert taught, [r.reason for r in releases]
    assert abs(taught[-1].params.k_v - K_TRUE) / K_TRUE < 0.03, [round(r.params.k_v, 4) for r in taught]


def test_the_calibrator_reads_a_batchs_links_not_its_sightings():
    # the replay's calibrator child is sent the filter's object batches without their
    # sightings (service/calibrator/lagged.py for_child): what it learns must not depend on them
    def learned(with_sightings: bool) -> list:
        return [(r.t_s, r.accepted, r.reason, r.params.to_dict())
                for r in _run(with_links=True, duration=900.0, with_sightings=with_sightings)]

    plain = learned(False)
    assert any(accepted for _, accepted, *_ in plain)
    assert learned(True) == plain


def test_without_links_k_v_stays():
    releases = _run(with_links=False)
    k = [r.params.k_v for r in releases if r.accepted]
    # one fix says nothing about the speed scale: k_V is not moved toward 0.9
    assert all(abs(kv - 1.0) < 0.02 for kv in k), k


def test_links_follow_a_change_of_water():
    # GIVEN the right k_V 1.0 until the water changes at 15 min (k_V 0.9), no fix after the
    # first: pairs of reciprocal legs whose two sightings straddle the change carry the old
    # k_V out and the new one back (their along-track dead reckoning no longer cancels)
    t_change = 900.0
    releases = _run(with_links=True, k_before=1.0, t_change_s=t_change, duration=t_change + 900.0)
    taught = [r for r in releases if r.accepted and "landmarks" in r.teachers and r.t_s > t_change]
    assert taught, [r.reason for r in releases]
    # THEN 15 min after the change the calibrator's k_V is within 3 % of the new water's
    # (with 6 objects per pair of 300 m legs, 10 min after it leaves 0.96-0.97: the pairs
    # with both sightings after the change come back only from the third leg on)
    assert abs(taught[-1].params.k_v - K_TRUE) / K_TRUE < 0.03, [(r.t_s, round(r.params.k_v, 4)) for r in taught]


def test_links_follow_a_change_of_water_within_ten_minutes():
    # GIVEN the right k_V 1.0 until the water changes at 15 min (k_V 0.9), no fix after the
    # first, on 8 draws of the objects and the heading noise
    t_change = 900.0
    errors = []
    for seed in range(1, 9):
        releases = _run(with_links=True, seed=seed, k_before=1.0, t_change_s=t_change, duration=t_change + 600.0)
        taught = [r for r in releases if r.accepted and "landmarks" in r.teachers and r.t_s > t_change]
        assert taught, [r.reason for r in releases]
        errors.append(abs(taught[-1].params.k_v - K_TRUE) / K_TRUE)
    # THEN 10 min after the change the calibrator's k_V is within 4 % of the new water's on
    # every draw (2 % on average): the fit takes k_V as a random walk (the pairs straddling the
    # change tell the new k_V from the old one instead of averaging them under the forgetting
    # of their later pose) and the release keeps the fit's k_V (ECME: EM's smoother sees the
    # pairs only through a frozen map). With one k_V under forgetting and EM's k_V released:
    # mean 3.4 %, worst 8.2 %.
    assert max(errors) < 0.04 and np.mean(errors) < 0.02, np.round(errors, 4)
