"""Estimator._keep_depth's stationary-detection window written in place: the window's first
depth kept and its latest replaced, entry for entry what the list built anew per depth held,
across window ends (_rest_window_end starts the next from the latest depth, or empty)."""
from __future__ import annotations

import types

import numpy as np

from adaptnav.fusion.eskf import Estimator


def _reference(win: list, t_s: float, depth_m: float) -> list:
    """The window as a2e2d6f built it (a new list per depth)."""
    return (win[:2] if win else [t_s, depth_m]) + [t_s, depth_m]


def test_the_window_is_the_list_built_anew():
    rng = np.random.default_rng(55)
    est = types.SimpleNamespace(_depth_win=[], config=types.SimpleNamespace(
        learned_velocity=types.SimpleNamespace(vertical_drift_sigma_per_m=0.0)))
    ref: list = []
    for k in range(2000):
        t_s, depth_m = k * 0.1, float(rng.normal() * 3.0 + 10.0)
        Estimator._keep_depth(est, t_s, depth_m)
        ref = _reference(ref, t_s, depth_m)
        assert est._depth_win == ref and len(est._depth_win) == 4
        if rng.random() < 0.02:  # a window ends (_rest_window_end's hand-over), sometimes empty
            dw = est._depth_win
            est._depth_win = dw[2:] * 2 if rng.random() < 0.7 else []
            ref = list(est._depth_win)
