"""freeze_landmarks: landmarks sighted once carry no motion information and are dropped."""
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
    assert len(kept) == 2 and all(isinstance(o, FixedLandmarkObservation) for o in kept)
    assert out[2] == []  # track 9 was seen once


def test_only_singletons_leaves_no_landmarks():
    observations = [[LandmarkSighting(1, 0.0, 5.0)], [LandmarkSighting(2, 0.0, 5.0)]]
    out = freeze_landmarks(MotionParams(), np.ones(1), np.zeros(1), 1.0, observations,
                           np.zeros((50, 3)), np.random.default_rng(0), 50)
    assert out == [[], []]
