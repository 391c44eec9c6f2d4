"""Side-scan landmark sightings with unknown positions: FastSLAM map, association, EM."""
import math
from dataclasses import dataclass

import numpy as np
import pytest

from adaptnav.fusion.motion_model import MotionParams, propagate, sample_velocities
from adaptnav.calibration.em import EMOptions, freeze_landmarks, run_em
from adaptnav.calibration.mstep import MStepOptions
from adaptnav.calibration.particle_filter import run_particle_filter
from adaptnav.calibration.sensors import (FixedLandmarkObservation, HeadingObservation, LandmarkAssociator,
                                 LandmarkSighting, sighting_from_sonar)


@dataclass(frozen=True)
class FakeLandmarkObservation:
    """Same field names as sonar.landmarks.LandmarkObservation (written by the sonar helper)."""

    t_s: float
    side: str
    ground_range_m: float
    along_track_m: float
    descriptor: np.ndarray
    track_id: int | None
    response: float = 1.0


def lawnmower(rng, truth_params, steps=90, dt=2.0):
    """Two long legs joined by a U-turn; returns controls and the true poses."""
    v = np.full(steps, 1.5)
    w = np.zeros(steps)
    w[40:50] = math.pi / (10 * dt)  # 180° turn over 10 steps
    poses = np.zeros((steps + 1, 3))
    for t in range(steps):
        V, W, S = sample_velocities(truth_params, v[t], w[t], rng)
        poses[t + 1] = propagate(poses[t], V, W, S, dt)
    return v, w, dt, poses


def side_scan(rng, poses, landmarks, descriptors, max_along=1.6, max_range=40.0, noise=(0.3, 0.3)):
    """Observations of every landmark abeam of a pose (|along| < max_along)."""
    obs = [[] for _ in poses]
    for t, (x, y, th) in enumerate(poses):
        c, s = math.cos(th), math.sin(th)
        for i, (lx, ly) in enumerate(landmarks):
            along = c * (lx - x) + s * (ly - y)
            across = -s * (lx - x) + c * (ly - y)
            if abs(along) < max_along and 3.0 < abs(across) < max_range:
                obs[t].append(FakeLandmarkObservation(
                    float(t), "starboard" if across > 0 else "port",
                    abs(across) + noise[1] * rng.standard_normal(), along + noise[0] * rng.standard_normal(),
                    descriptors[i] + 0.01 * rng.standard_normal(descriptors.shape[1]), None))
    return obs


@pytest.fixture(scope="module")
def scene():
    rng = np.random.default_rng(21)
    truth = MotionParams(var_vv=0.08**2, k_v=0.8, var_s=0.02**2, var_w1=0.002**2)
    v, w, dt, poses = lawnmower(rng, truth)
    # landmarks between the two legs (both passes see them), and some outside
    xs = rng.uniform(5, 90, 40)
    ys = rng.uniform(-25, 25, 40) + poses[45, 1] / 2
    landmarks = np.column_stack([xs, ys])
    descriptors = rng.normal(size=(40, 16))
    sonar = side_scan(rng, poses, landmarks, descriptors)
    assoc = LandmarkAssociator(max_distance=0.5)
    sightings = [[sighting_from_sonar(o, assoc.assign(o), 0.3, 0.3) for o in obs_t] for obs_t in sonar]
    heading = [[HeadingObservation(float(p[2] + 0.005 * rng.standard_normal()), 0.005)] for p in poses]
    observations = [s + h for s, h in zip(sightings, heading)]
    return truth, v, w, dt, poses, landmarks, sonar, sightings, observations


def test_descriptor_association_reuses_ids(scene):
    *_, sonar, sightings, _ = scene
    ids = [s.track_id for obs in sightings for s in obs]
    counts = np.bincount(np.array(ids) - min(ids))
    assert counts.max() >= 2  # landmarks re-observed on the second leg got the same id
    with pytest.raises(ValueError):
        sighting_from_sonar(FakeLandmarkObservation(0.0, "up", 1.0, 0.0, np.zeros(2), 3), None)


def test_fastslam_map_places_landmarks(scene):
    truth, v, w, dt, poses, landmarks, sonar, sightings, observations = scene
    rng = np.random.default_rng(1)
    init = np.zeros((500, 3)) + 0.05 * rng.standard_normal((500, 3))
    fr = run_particle_filter(truth, v, w, dt, observations, init, rng, 500, map_landmarks=True)
    fixed = fr.landmark_map.fixed_map(fr.log_w[-1])
    # which true landmark each track belongs to: the nearest to where it was first seen from truth
    errs = []
    for t, obs_t in enumerate(sightings):
        for s in obs_t:
            if s.track_id in fixed:
                c, sn = math.cos(poses[t, 2]), math.sin(poses[t, 2])
                seen = poses[t, :2] + np.array([c * s.along_m - sn * s.across_m, sn * s.along_m + c * s.across_m])
                true_lm = landmarks[np.argmin(np.linalg.norm(landmarks - seen, axis=1))]
                errs.append(np.linalg.norm(fixed[s.track_id][0] - true_lm))
    assert len(errs) > 10
    assert np.median(errs) < 3.0
    obs_fixed = freeze_landmarks(truth, v, w, dt, observations, init, rng, 500)
    assert any(isinstance(o, FixedLandmarkObservation) for obs in obs_fixed for o in obs)
    assert not any(isinstance(o, LandmarkSighting) for obs in obs_fixed for o in obs)


def test_em_with_side_scan_landmarks_learns_speed_scale(scene):
    truth, v, w, dt, poses, landmarks, sonar, sightings, observations = scene
    rng = np.random.default_rng(2)
    init = np.zeros((600, 3)) + 0.05 * rng.standard_normal((600, 3))
    start = MotionParams(var_vv=0.1**2, k_v=1.0, var_s=0.02**2, var_w1=0.002**2)
    opts = EMOptions(n_particles=600, n_smoothed=50, max_iterations=8,
                     mstep=MStepOptions(fit_b_w=False))
    res = run_em(start, v, w, dt, observations, init, rng, opts)
    # the re-observed landmarks tie the two legs together: k_V moves from 1.0 towards 0.8
    assert abs(res.params.k_v - 0.8) < 0.1, res.params


def test_calibrator_releases_a_k_v_taught_by_landmarks_alone(scene):
    # GIVEN a window whose only position information is side-scan landmarks seen on both
    # legs, water with k_V 0.8, and a calibrator still at 1.0
    from adaptnav.calibration.online import CalibratorConfig, calibrate_window

    truth, v, w, dt, poses, landmarks, sonar, sightings, observations = scene
    rng = np.random.default_rng(3)
    init = np.zeros((600, 3)) + 0.05 * rng.standard_normal((600, 3))
    start = MotionParams(var_vv=0.1**2, k_v=1.0, var_s=0.02**2, var_w1=0.002**2)
    cfg = CalibratorConfig(n_particles=600, n_smoothed=50, em_iterations=5, fit_b_w=False, step_s=dt,
                           model_step_s=dt, fit_current=False, ll_tolerance=0)
    rel = calibrate_window(start, v, w, dt, observations, init, cfg, rng)
    # THEN EM's k_V toward 0.8 is released with a log-likelihood not below the old one's
    # (ll_tolerance 0): landmarks alone teach the speed scale through the whole release path
    assert rel.accepted, rel.reason
    assert abs(rel.params.k_v - 0.8) < 0.1, rel.params
