"""with_navigation's scalar offset, np.dot covariance and field copy (objects._replaced) against
the steps they replaced (37da4aa: the offset as an array, R @ diag @ R.T, dataclasses.replace):
the same sightings, pickled byte for byte."""
from __future__ import annotations

import math
import pickle
from dataclasses import replace

import numpy as np
import pytest

from adaptnav.sonar.objects import ObjectDetectorConfig, ObjectSighting, _replaced, with_navigation


def _reference(obj, pos_n_m, nav_cov, yaw_rad, config, jump_n_m=None, vel_cov=None):
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    sign = 1.0 if obj.side == "starboard" else -1.0
    offset = sign * obj.ground_range_m * np.array([-s, c])
    along = obj.length_along_m if math.isfinite(obj.length_along_m) else 1.0
    s_al = config.sigma_along_m + config.size_fraction * along
    s_ac = config.sigma_across_m + config.size_fraction * obj.width_across_m
    R = np.array([[c, -s], [s, c]])
    det_cov = R @ np.diag([s_al ** 2, s_ac ** 2]) @ R.T
    p = np.asarray(pos_n_m, float)[:2] + offset
    jump = None if jump_n_m is None else np.asarray(jump_n_m, float).reshape(2).copy()
    vc = None if vel_cov is None else np.asarray(vel_cov, float).reshape(2, 2).copy()
    return replace(obj, pos_n_m=p, nav_cov=np.asarray(nav_cov, float).reshape(2, 2).copy(), det_cov=det_cov,
                   heading_rad=float(yaw_rad), jump_n_m=jump,
                   vel_cov=vc if vc is not None and np.isfinite(vc).all() else None)


def _sightings(n, rng):
    for k in range(n):
        yield ObjectSighting(t_s=float(rng.uniform(0, 1e4)), side="starboard" if k % 2 else "port",
                             ground_range_m=float(rng.uniform(0.0, 60.0)), height_m=float(rng.uniform(0, 2)),
                             shadow_length_m=float(rng.uniform(0, 5)),
                             length_along_m=math.nan if k % 7 == 3 else float(rng.uniform(0, 4)),
                             width_across_m=float(rng.uniform(0.1, 3)), contrast=float(rng.uniform(1, 20)),
                             altitude_m=float(rng.uniform(2, 30)), row=float(rng.uniform(0, 200)),
                             weak=bool(k % 5 == 0))


@pytest.mark.parametrize("with_jump", [False, True])
def test_with_navigation_is_the_reference(with_jump):
    rng = np.random.default_rng(11)
    config = ObjectDetectorConfig()
    for k, o in enumerate(_sightings(500, rng)):
        yaw = float(rng.uniform(-8.0, 8.0))
        pos = (float(rng.normal(0, 500)), float(rng.normal(0, 500))) if k % 3 else rng.normal(0, 500, 3)
        cov = np.array([[4.0, 0.3], [0.3, 2.5]]) * float(rng.uniform(0.01, 10))
        jump = rng.normal(0, 3, 2) if with_jump else None
        vc = np.full((2, 2), np.nan) if k % 4 == 0 else np.eye(2) * float(rng.uniform(1e-4, 1e-2))
        got = with_navigation(o, pos, cov, yaw, config, jump, vc)
        want = _reference(o, pos, cov, yaw, config, jump, vc)
        assert pickle.dumps(got) == pickle.dumps(want), k
        assert got.offset_n_m(yaw).tobytes() == (want.pos_n_m - np.asarray(pos, float)[:2]).tobytes() or \
            np.allclose(got.offset_n_m(yaw), want.pos_n_m - np.asarray(pos, float)[:2])
        assert got.detector_covariance(yaw, config).tobytes() == want.det_cov.tobytes()


def test_replaced_is_dataclasses_replace():
    rng = np.random.default_rng(5)
    for o in _sightings(50, rng):
        before = pickle.dumps(o)
        for changes in ({"weak": True}, {"weak": False, "row": 3.5}, {"pos_n_m": np.array([1.0, 2.0]), "t_s": 7.0}, {}):
            got, want = _replaced(o, **changes), replace(o, **changes)
            assert type(got) is ObjectSighting and got is not o
            assert pickle.dumps(got) == pickle.dumps(want)
            assert list(vars(got)) == list(vars(want))
        assert pickle.dumps(o) == before  # the original untouched
