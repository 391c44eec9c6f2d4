r"""Initial alignment: levelling from the accelerometers at rest, heading from an aid.

At rest the specific force is ``f_b = −R_nbᵀ g_n``, so (Groves 2013 §14.2.1)::

    roll = atan2(−f_y, −f_z),   pitch = atan2(f_x, √(f_y² + f_z²))

averaged over the last ``n_samples`` IMU samples of an unbroken run (no gap larger
than ``imu_gap_s``) whose spread is below ``max_acc_std_m_s2`` (otherwise the vehicle
is not at rest and the window keeps sliding). Heading cannot be observed by a tactical
IMU's gyros (earth rate ≪ gyro noise), so it comes from the first heading/attitude aid.
"""
from __future__ import annotations

import math

import numpy as np


class Aligner:
    """Sliding window of IMU specific force for levelling."""

    def __init__(self, n_samples: int, max_acc_std_m_s2: float, imu_gap_s: float):
        self.n_samples = int(n_samples)
        self.max_acc_std_m_s2 = max_acc_std_m_s2
        self.imu_gap_s = imu_gap_s
        self._f = np.empty((0, 3))
        self._w = np.empty((0, 3))
        self._t = np.empty(0)
        self.t_last_s = -math.inf

    def add(self, t_s: np.ndarray, f_b_m_s2: np.ndarray, w_b_rad_s: np.ndarray | None = None) -> None:
        """Add clean (finite, increasing) samples; a gap restarts the window."""
        if t_s.size == 0:
            return
        w_b_rad_s = np.zeros_like(f_b_m_s2) if w_b_rad_s is None else w_b_rad_s
        dt = np.diff(np.concatenate(([self.t_last_s], t_s)))
        gaps = np.nonzero(dt > self.imu_gap_s)[0]
        if gaps.size:
            self._f = np.empty((0, 3))
            self._w = np.empty((0, 3))
            self._t = np.empty(0)
            t_s, f_b_m_s2, w_b_rad_s = t_s[gaps[-1]:], f_b_m_s2[gaps[-1]:], w_b_rad_s[gaps[-1]:]
        self._f = np.concatenate((self._f, f_b_m_s2))[-self.n_samples:]
        self._w = np.concatenate((self._w, w_b_rad_s))[-self.n_samples:]
        self._t = np.concatenate((self._t, t_s))[-self.n_samples:]
        self.t_last_s = float(t_s[-1])

    def window(self) -> tuple[np.ndarray, np.ndarray, float]:
        """(f_b (N, 3), ω_b (N, 3), mean sample interval s) of the current window."""
        dt = float(np.mean(np.diff(self._t))) if self._t.size > 1 else math.nan
        return self._f, self._w, dt

    def level(self) -> tuple[float, float] | None:
        """(roll, pitch) in rad once the window is full and at rest, else None."""
        if len(self._f) < self.n_samples:
            return None
        if np.max(np.std(self._f, axis=0)) > self.max_acc_std_m_s2:
            return None
        fx, fy, fz = np.mean(self._f, axis=0)
        return math.atan2(-fy, -fz), math.atan2(fx, math.hypot(fy, fz))
