"""AnchoredDeadReckoning's per-ping scalar steps against the textbook filter in numpy matrices."""
from __future__ import annotations

import math

import numpy as np

from adaptnav.sonar.dead_reckoning import AnchoredDeadReckoning
from adaptnav.sonar.ping import SonarPing


class _MatrixDeadReckoning:
    """The reference: the same filter with numpy arrays throughout (x ← F x, P ← F P Fᵀ + Q dt,
    the dead reckoning as a 2-vector), as the class computed it before its scalar steps."""

    def __init__(self, drift_sigma_m_s=0.3, q_offset=1e-4, q_drift=1e-7):
        self.last = None
        self.dr = np.zeros(2)
        self.x = np.zeros(4)
        self.P = np.diag([1e6, 1e6, drift_sigma_m_s ** 2, drift_sigma_m_s ** 2])
        self.Q = np.diag([q_offset, q_offset, q_drift, q_drift])
        self.t_kf = math.nan
        self.pending = []
        self.fixes_used = 0

    def predict(self, t):
        if math.isfinite(self.t_kf) and t > self.t_kf:
            dt = t - self.t_kf
            F = np.eye(4)
            F[0, 2] = F[1, 3] = dt
            self.x = F @ self.x
            self.P = F @ self.P @ F.T + self.Q * dt
        self.t_kf = t if not math.isfinite(self.t_kf) else max(self.t_kf, t)

    def update(self, t, dr, p, sigma):
        self.predict(t)
        H = np.hstack([np.eye(2), np.zeros((2, 2))])
        S = H @ self.P @ H.T + sigma ** 2 * np.eye(2)
        K = self.P @ H.T @ np.linalg.inv(S)
        self.x = self.x + K @ (p - dr - self.x[:2])
        A = np.eye(4) - K @ H
        self.P = A @ self.P @ A.T + sigma ** 2 * K @ K.T
        self.fixes_used += 1

    def push(self, ping):
        t = ping.t_s
        if self.last is not None and not t > self.last[0]:
            return self.dr + self.x[:2], self.sigma()
        speed = ping.speed_m_s if math.isfinite(ping.speed_m_s) else (self.last[1] if self.last else 0.0)
        yaw = ping.heading_rad
        dr0 = self.dr
        if self.last is not None:
            t0, v0, yaw0 = self.last
            mid = yaw0 + 0.5 * math.remainder(yaw - yaw0, 2.0 * math.pi)
            step = 0.5 * (v0 + speed) * (t - t0)
            self.dr = self.dr + np.array([step * math.cos(mid), step * math.sin(mid)])
        t_prev = self.last[0] if self.last is not None else t
        self.last = (t, speed, yaw)
        keep = []
        for tf, p, sig in sorted(self.pending, key=lambda f: f[0]):
            if tf > t:
                keep.append((tf, p, sig))
                continue
            a = 0.0 if t <= t_prev else min(max((tf - t_prev) / (t - t_prev), 0.0), 1.0)
            self.update(max(tf, self.t_kf) if math.isfinite(self.t_kf) else tf, dr0 + a * (self.dr - dr0), p, sig)
        self.pending = keep
        self.predict(t)
        return self.dr + self.x[:2], self.sigma()

    def sigma(self):
        return math.nan if not self.fixes_used else math.sqrt(max(0.5 * (self.P[0, 0] + self.P[1, 1]), 0.0))


def _ping(t_s, speed_m_s, yaw_rad):
    z = np.zeros(16, np.float32)
    return SonarPing(t_s=t_s, port=z, starboard=z, slant_range_m=20.0, altitude_m=5.0, heading_rad=yaw_rad,
                     speed_m_s=speed_m_s)


def test_dead_reckoning_matches_the_matrix_filter_bit_for_bit():
    # irregular ping intervals, speed gaps, turns, fixes late and early, one out-of-order ping
    rng = np.random.default_rng(52)
    nav, ref = AnchoredDeadReckoning(), _MatrixDeadReckoning()
    t, yaw = 100.0, 0.3
    for k in range(3000):
        t += float(rng.uniform(0.02, 0.4))
        yaw = math.remainder(yaw + float(rng.normal(0.0, 0.05)), 2.0 * math.pi)
        speed = math.nan if k % 37 == 5 else float(rng.uniform(0.5, 2.0))
        if k % 53 == 10:
            fix = (t - float(rng.uniform(-0.5, 3.0)), rng.normal(0.0, 50.0, 2), float(rng.uniform(0.5, 5.0)))
            nav.fix(*fix)
            ref.pending.append((fix[0], fix[1], fix[2]))
        ping = _ping(t - 1.0 if k % 401 == 7 else t, speed, yaw)
        (p, sigma), (p_ref, sigma_ref) = nav.push(ping), ref.push(ping)
        assert p.tobytes() == p_ref.tobytes(), k
        assert np.float64(sigma).tobytes() == np.float64(sigma_ref).tobytes(), k
    assert nav.fixes_used == ref.fixes_used > 50
