"""freeze_landmarks: landmarks sighted once carry no motion information and are dropped; a
re-observation is scored against the map of the earlier sightings only (no double counting)."""
import numpy as np

from adaptnav.calibration.em import freeze_landmarks
from adaptnav.calibration.sensors import FixedLandmarkObservation, LandmarkSighting
from adaptnav.fusion.motion_model import MotionParams


def test_singletons_dropped_repeats_frozen():
    T = 4
    v, w, dt = np.full(T, 1.0), np.zeros(T), 1.0
    observations = [[LandmarkSighting(7, 0.0, 5.0)], None, [LandmarkSighting(9, 0.0, -5.0)],
                    [LandmarkSighting(7, -3.0, 5.0)], []]
    init = np.zeros((200, 3)) + np.random.default_rng(0).normal(0, 0.1, (200, 3))
    out = freeze_landmarks(MotionParams(), v, w, dt, observations, init, np.random.default_rng(1), 200)
    kept = [o for obs in out for o in obs]
    # track 7: the first sighting builds the map, the second is scored against it
    assert len(kept) == 1 and all(isinstance(o, FixedLandmarkObservation) for o in kept)
    assert out[0] == [] and out[2] == [] and len(out[3]) == 1  # track 9 was seen once
    fixed = out[3][0]
    # the map is where the first sighting put it (pose 0 + (0, 5) m), not pulled toward the
    # second, and its covariance holds the first sighting's noise plus the poses' spread
    assert np.allclose(fixed.landmark_mean_m, [0.0, 5.0], atol=0.2)
    assert np.all(np.linalg.eigvalsh(fixed.landmark_cov_m2) >= 0.25 - 1e-9)


def test_map_excludes_the_sighting_it_scores():
    """Two sightings that disagree: frozen against a map that contained the second itself, it
    would look half as far off (double counting); against the earlier one alone it does not."""
    T = 2
    v, w, dt = np.zeros(T), np.zeros(T), 1.0
    observations = [[LandmarkSighting(1, 0.0, 5.0, 0.5, 0.5)], [], [LandmarkSighting(1, 0.0, 8.0, 0.5, 0.5)]]
    init = np.zeros((100, 3))
    p = MotionParams(var_vv=1e-8, var_v1=1e-8, var_s=1e-8, var_wv=1e-10, var_ww=1e-10, var_w1=1e-10)
    out = freeze_landmarks(p, v, w, dt, observations, init, np.random.default_rng(2), 100)
    fixed = out[2][0]
    assert np.allclose(fixed.landmark_mean_m, [0.0, 5.0], atol=0.05)


def test_only_singletons_leaves_no_landmarks():
    observations = [[LandmarkSighting(1, 0.0, 5.0)], [LandmarkSighting(2, 0.0, 5.0)]]
    out = freeze_landmarks(MotionParams(), np.ones(1), np.zeros(1), 1.0, observations,
                           np.zeros((50, 3)), np.random.default_rng(0), 50)
    assert out == [[], []]
