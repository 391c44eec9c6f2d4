"""Streaming side-scan front end on synthetic pings (sim.sidescan) along straight tracks."""
from __future__ import annotations

import math

import numpy as np
import pytest

from adaptnav.sim.seabed import Seabed
from adaptnav.sim.sidescan import SidescanRenderer
from adaptnav.sonar.landmarks import LandmarkObservation
from adaptnav.sonar.motion import VisualMotion
from adaptnav.sonar.ping import SonarPing
from adaptnav.sonar.stream import AnchoredDeadReckoning, FrontEndConfig, SonarFrontEnd, reference_landmark

SPEED = 1.5
RATE_HZ = 4.0
DS = SPEED / RATE_HZ  # 0.375 m between pings, as in the demo scenario


def _pass(renderer, rng, start, yaw, n, t0):
    f = np.array([math.cos(yaw), math.sin(yaw)])
    pos = np.asarray(start, float) + np.outer(np.arange(n) * DS, f)
    t = t0 + np.arange(n) / RATE_HZ
    return renderer.render_track(t, pos, yaw, 8.0, rng, SPEED), pos, t


@pytest.fixture(scope="module")
def world():
    rng = np.random.default_rng(21)
    seabed = Seabed.random((200.0, 80.0), rng, n_objects=90)
    return seabed, SidescanRenderer(seabed, 25.0, 512)


def _true_obs_pos(o, t, pos, yaw):
    p = np.array([np.interp(o.t_s, t, pos[:, 0]), np.interp(o.t_s, t, pos[:, 1])])
    return o.position_n_m(p, yaw)


def _two_passes(ren, seed, nav_error=(0.6, -0.4), sigma_m=None, config=FrontEndConfig()):
    """Two northbound passes 3 m apart through one front end; the second with a nav error
    (of σ ``sigma_m`` per axis when given to the front end)."""
    rng = np.random.default_rng(seed)
    fe = SonarFrontEnd(config)
    nav_error = np.asarray(nav_error, float)
    by_pass = []
    t0 = 0.0
    for start in ((10.0, 38.0), (10.0, 41.0)):
        pings, pos, t = _pass(ren, rng, start, 0.0, 420, t0)
        err = np.zeros(2) if not by_pass else nav_error
        out = []
        for p, x in zip(pings, pos):
            out += fe.push(p, x + err, sigma_m)
        obs = [o for o in out if isinstance(o, LandmarkObservation)]
        by_pass.append([(o, _true_obs_pos(o, t, pos, 0.0)) for o in obs])
        t0 = t[-1] + 60.0
    return by_pass


def test_reobserved_landmarks_keep_their_track_ids(world):
    _, ren = world
    again = same = false_links = second = 0
    for seed in (4, 5, 6):
        pass1, pass2 = _two_passes(ren, seed)
        # about one sighting per landmark and pass: windows overlap but each ping is
        # reported once (an object straddling two windows' emission ranges may give two)
        ids1 = [o.track_id for o, _ in pass1]
        assert None not in ids1 and len(ids1) >= 15 and len(set(ids1)) >= 0.93 * len(ids1)
        true1 = np.array([p for _, p in pass1])
        first = {o.track_id: p for o, p in pass1}
        second += len(pass2)
        for o, p in pass2:
            seen_before = np.min(np.linalg.norm(true1 - p, axis=1)) < 0.7
            linked = o.track_id in first
            if seen_before:
                again += 1
                same += linked and np.linalg.norm(first[o.track_id] - p) < 0.7
            elif linked:
                false_links += 1
    assert again >= 25
    assert same / again >= 0.7
    assert false_links <= 0.1 * second


def test_detecting_on_the_emission_rows_only_finds_and_relinks_the_same_landmarks(world):
    # GIVEN the calibrator's cheaper front end: SIFT on the emission part ± 8 pings only
    _, ren = world
    cheap = FrontEndConfig(register=False, detect_margin_pings=8)
    for seed in (4, 5):
        full1, full2 = _two_passes(ren, seed)
        crop1, crop2 = _two_passes(ren, seed, config=cheap)
        # THEN the sightings are those of the whole-window detection (same ping time and
        # range), most of them: the strongest of each emission part ...
        for full, crop in ((full1, crop1), (full2, crop2)):
            ref = np.array([(o.t_s, o.ground_range_m) for o, _ in full])
            got = np.array([(o.t_s, o.ground_range_m) for o, _ in crop])
            assert len(got) >= 0.7 * len(ref)
            common = sum(np.any((np.abs(ref[:, 0] - t) < 0.05) & (np.abs(ref[:, 1] - r) < 0.2)) for t, r in got)
            assert common >= 0.9 * len(got)
        # ... and the second pass relinks about as many to their first-pass tracks, no
        # more wrongly
        again_f, same_f, wrong_f = _relinked(full1, full2)
        again_c, same_c, wrong_c = _relinked(crop1, crop2)
        assert same_c >= 0.8 * same_f and wrong_c <= wrong_f


def _relinked(pass1, pass2):
    """(re-observed sightings, those linked to the right track, links to a track ≥ 2 m away)."""
    true1 = np.array([p for _, p in pass1])
    first = {o.track_id: p for o, p in pass1}
    again = same = wrong = 0
    for o, p in pass2:
        if np.min(np.linalg.norm(true1 - p, axis=1)) < 0.7:
            again += 1
            same += o.track_id in first and np.linalg.norm(first[o.track_id] - p) < 0.7
        wrong += o.track_id in first and np.linalg.norm(first[o.track_id] - p) >= 2.0
    return again, same, wrong


def test_navigation_sigma_widens_the_association_gate(world):
    # a 2.4 m navigation error between the passes: outside the fixed 1.5 m gate, inside
    # the gate a 0.7 m σ per axis opens (3·√2·0.7 ≈ 3 m). The price of the wider gate:
    # a few more links to a similar-looking landmark nearby (bounded here).
    _, ren = world
    err = (2.2, -1.0)
    again, same_fixed, _ = _relinked(*_two_passes(ren, 7, err))
    pass1, pass2 = _two_passes(ren, 7, err, sigma_m=0.7)
    again2, same_sigma, wrong = _relinked(pass1, pass2)
    assert again == again2 >= 8
    assert same_fixed <= 0.5 * again
    assert same_sigma >= 0.75 * again
    assert wrong <= 0.2 * len(pass2)


def _ping(t_s, speed_m_s, yaw_rad):
    z = np.zeros(16, np.float32)
    return SonarPing(t_s=t_s, port=z, starboard=z, slant_range_m=20.0, altitude_m=5.0, heading_rad=yaw_rad,
                     pitch_rad=0.0, roll_rad=0.0, sensor_depth_m=10.0, speed_m_s=speed_m_s)


def test_anchored_dead_reckoning_follows_fixes_through_a_current():
    # lawnmower legs north/south at 1.5 m/s through the water, 0.1 m/s current at 45°;
    # the pings carry the ground speed and the *heading* (not the course): pure dead
    # reckoning drifts ~0.07 m/s across the track. USBL-like fixes (σ 2 m) once a minute.
    rng = np.random.default_rng(11)
    cur = 0.1 * np.array([math.cos(math.pi / 4), math.sin(math.pi / 4)])
    nav = AnchoredDeadReckoning()
    pos = np.zeros(2)
    errs, z_scores, dr_err = [], [], []
    t, dt = 0.0, 0.25
    dr = np.zeros(2)
    for k in range(int(1500 / dt)):
        t = k * dt
        yaw = 0.0 if int(t // 200) % 2 == 0 else math.pi
        v_g = 1.5 * np.array([math.cos(yaw), math.sin(yaw)]) + cur
        if k:
            pos = pos + v_g * dt
            dr = dr + np.linalg.norm(v_g) * dt * np.array([math.cos(yaw), math.sin(yaw)])
        if k and k % int(60 / dt) == 0:
            nav.fix(t, pos + 2.0 * rng.standard_normal(2), 2.0)
        p, sigma = nav.push(_ping(t, float(np.linalg.norm(v_g)), yaw))
        if t > 600:  # after ten fixes
            errs.append(np.linalg.norm(p - pos))
            z_scores.append(np.abs(p - pos) / sigma)
            dr_err.append(np.linalg.norm(dr - pos))
    assert nav.fixes_used == 24
    assert np.sqrt(np.mean(np.square(errs))) < 2.0 < 0.1 * np.mean(dr_err)  # fixes alone: σ 2 m
    assert np.mean(np.array(z_scores) < 3.0) > 0.95  # σ covers the error


def test_anchored_dead_reckoning_before_a_fix_and_bad_pings():
    nav = AnchoredDeadReckoning()
    p, sigma = nav.push(_ping(0.0, 1.0, 0.0))
    assert math.isnan(sigma)
    p, _ = nav.push(_ping(10.0, 1.0, 0.0))
    assert np.allclose(p, [10.0, 0.0])
    p2, _ = nav.push(_ping(5.0, 1.0, 0.0))  # out of order: ignored
    assert np.allclose(p2, p)
    nav.fix(10.0, [math.nan, 0.0], 1.0)  # non-finite fix: ignored
    nav.fix(12.0, [20.0, 3.0], 1.0)
    p, sigma = nav.push(_ping(14.0, 1.0, 0.0))
    assert nav.fixes_used == 1 and 0.9 < sigma < 2.0
    assert np.allclose(p, [22.0, 3.0], atol=0.5)


def test_dead_reckoned_landmarks_and_visual_motion_along_a_straight_track(world):
    seabed, ren = world
    rng = np.random.default_rng(9)
    yaw = math.radians(2.0)
    start = np.array([12.0, 40.0])
    pings, pos, t = _pass(ren, rng, start, yaw, 500, 100.0)
    cfg = FrontEndConfig()
    fe = SonarFrontEnd(cfg)
    fe_start = start.copy()
    out = []
    out += fe.push(pings[0], fe_start)  # the start position; dead reckoning afterwards
    for p in pings[1:]:
        out += fe.push(p)
    obs = [o for o in out if isinstance(o, LandmarkObservation)]
    motions = [m for m in out if isinstance(m, VisualMotion)]
    assert fe.windows == (500 - cfg.window_pings) // cfg.step_pings + 1
    assert len(obs) >= 15 and len({o.track_id for o in obs}) >= 0.93 * len(obs)
    # dead reckoning from the pings' speed and heading ends where the vehicle is
    assert np.linalg.norm(fe.pos_n_m - pos[-1]) < 0.05
    # every window pair overlaps by half: the next window sits S pings ahead, not across
    assert len(motions) >= 0.8 * (fe.windows - 1)
    along = np.array([m.along_m for m in motions])
    across = np.array([m.across_m for m in motions])
    true_along = cfg.step_pings * DS
    assert np.median(np.abs(along - true_along)) < 0.1 * true_along
    assert np.median(np.abs(across)) < 0.3
    assert all(m.t_s > m.t0_s for m in motions)
    # each sighting is reported once, with the latency the front end announces
    assert fe.latency_s == pytest.approx(0.5 * (cfg.window_pings + cfg.step_pings) / RATE_HZ)


def test_bad_pings_are_counted_and_skipped():
    fe = SonarFrontEnd(FrontEndConfig(window_pings=8, step_pings=4, register=False))
    ok = SonarPing(1.0, np.ones(64), np.ones(64), 20.0, altitude_m=5.0, speed_m_s=1.0)
    assert fe.push(ok) == []
    fe.push(SonarPing(math.nan, np.ones(64), np.ones(64), 20.0))
    fe.push(SonarPing(0.5, np.ones(64), np.ones(64), 20.0))          # goes back in time
    fe.push(SonarPing(2.0, np.ones(64), np.ones(64), 0.0))           # no range
    fe.push(SonarPing(3.0, np.ones(32), np.ones(32), 20.0))          # other sample count: kept
    assert dict(fe.rejected) == {"non-finite time": 1, "non-increasing time": 1, "bad geometry": 1}
    assert fe.resampled == 1


def test_a_change_of_range_mid_stream_keeps_the_visual_motion_going(world):
    """The operator (or the sonar's auto-range) changes range and sample count mid-survey:
    every later ping was rejected ("sample count or range changed") and the side-scan went
    blind for the rest of the mission. Now they are put on the stream's geometry."""
    seabed, ren = world
    wider = SidescanRenderer(seabed, 30.0, 700)
    rng = np.random.default_rng(9)
    yaw = math.radians(2.0)
    start = np.array([12.0, 40.0])
    n, n_before = 520, 150  # the pass runs 195 m of the 200 m seabed
    first, pos, t = _pass(ren, rng, start, yaw, n, 100.0)
    second = wider.render_track(t[n_before:], pos[n_before:], yaw, 8.0, rng, SPEED)
    pings = list(first[:n_before]) + list(second)
    cfg = FrontEndConfig()
    fe = SonarFrontEnd(cfg)
    out = fe.push(pings[0], start)
    for p in pings[1:]:
        out += fe.push(p)
    assert not fe.rejected and fe.resampled == n - n_before
    after = [m for m in out if isinstance(m, VisualMotion) and m.t_s > t[n_before]]  # mixed windows too
    windows_after = fe.windows - (n_before - cfg.window_pings) // cfg.step_pings - 1
    assert windows_after >= 4 and len(after) >= 0.8 * windows_after, (len(after), windows_after)
    true_along = cfg.step_pings * DS
    along = np.array([m.along_m for m in after])
    assert np.median(np.abs(along - true_along)) < 0.1 * true_along
    assert np.median(np.abs([m.across_m for m in after])) < 0.3
    obs_after = [o for o in out if isinstance(o, LandmarkObservation) and o.t_s > t[n_before]]
    assert len(obs_after) >= 5


def test_a_ping_resampled_onto_another_geometry_keeps_its_echo_at_its_range():
    rng = np.random.default_rng(4)
    port = rng.random(512).astype(np.float32)
    stbd = rng.random(512).astype(np.float32)
    stbd[300] = 50.0  # a strong target at (300.5 / 512) × 25 m
    ping = SonarPing(1.0, port, stbd, 25.0)
    for n, r in ((700, 30.0), (256, 25.0), (1024, 20.0)):
        moved = ping.resampled(n, r)
        assert moved.n_samples == n and moved.slant_range_m == r and moved.t_s == ping.t_s
        k = int(np.nanargmax(moved.starboard))
        assert abs((k + 0.5) * r / n - 300.5 * 25.0 / 512) <= r / n + 25.0 / 512
        covered = min(r, 25.0)
        # the echo over the common range is kept (mean over the bins that have data)
        kept = moved.port[: int(covered / (r / n))]
        assert np.nanmean(kept) == pytest.approx(np.mean(port[: int(covered / (25.0 / 512))]), rel=0.02)
        assert np.all(np.isnan(moved.port[int(math.ceil(25.0 / (r / n))):]))  # beyond its range: no data
    assert ping.resampled(512, 25.0) is ping
    with pytest.raises(ValueError):
        FrontEndConfig(window_pings=16, step_pings=32)


def test_reference_landmark_moves_the_sighting_to_a_grid_pose():
    o = LandmarkObservation(10.0, "port", 7.0, 3.0, np.zeros(128), 5)
    r = reference_landmark(o, 8.0, 1.5)
    assert r.along_track_m == pytest.approx(3.0) and r.track_id == 5 and r.ground_range_m == 7.0
