"""Ping-to-ping dead reckoning of the side-scan tied to position fixes
(:class:`AnchoredDeadReckoning`).

Its own module (numpy only, no OpenCV) because the calibrator keeps one from its start
for every position fix, while the image front end of :mod:`adaptnav.sonar.stream`
(OpenCV: ~15 MB) is only needed once side-scan pings arrive.
"""
from __future__ import annotations

import math

import numpy as np

from adaptnav.sonar.ping import SonarPing


class AnchoredDeadReckoning:
    r"""Ping-to-ping dead reckoning tied to position fixes (USBL/GNSS) by a small Kalman filter.

    Between pings the position is dead-reckoned from the pings' speed over ground and
    heading (as in :class:`SonarFrontEnd`), ``p_DR``. Its error ``o = p − p_DR`` is an
    offset that drifts at a nearly constant rate ``d`` (the current across the track,
    which a speed log does not see), so a linear Kalman filter on ``x = (o, d)`` (4
    states, north/east) tracks it from the fixes:

    .. math:: o_{k+1} = o_k + d_k\,Δt + w_o,\quad d_{k+1} = d_k + w_d,\qquad
              z = p_{fix} − p_{DR}(t_{fix}) = o + v,\; v ∼ N(0, σ_{fix}^2 I)

    with random walks of densities ``q_offset`` (m²/s) and ``q_drift`` ((m/s)²/s). The
    position at a ping is ``p_DR + ô`` with σ the RMS per axis of ``P_o``; NaN σ before
    the first fix. A fix is applied once the pings have passed its time (its DR is
    interpolated between the two pings around it).

    Parameters
    ----------
    drift_sigma_m_s : float
        Prior σ of the drift rate per axis (m/s).
    q_offset_m2_s, q_drift_m2_s3 : float
        Random-walk densities of the offset and of the drift.
    """

    def __init__(self, drift_sigma_m_s: float = 0.3, q_offset_m2_s: float = 1e-4,
                 q_drift_m2_s3: float = 1e-7) -> None:
        self.q_offset = float(q_offset_m2_s)
        self.q_drift = float(q_drift_m2_s3)
        self._last: tuple[float, float, float] | None = None  # t, speed, yaw
        # the dead-reckoned position and the state (offset n/e, drift n/e) as Python floats: per
        # ping they are a few scalar steps, which numpy took ~1 µs each for (F @ x: 0.9 µs)
        self._dr = (0.0, 0.0)
        self._x = (0.0, 0.0, 0.0, 0.0)
        # offset prior: vague but finite (1 km σ: an infinite one loses the covariance to round-off)
        self._P = np.diag([1e6, 1e6, drift_sigma_m_s ** 2, drift_sigma_m_s ** 2])
        self._t_kf = math.nan
        # the transition and the noise density of _predict, kept (built afresh per ping they were
        # most of its cost): F's dt entries are set per step, Q is scaled by dt
        self._F = np.eye(4)
        self._F_T = self._F.T  # (a view: F's dt entries set in place show through)
        self._FP = np.empty((4, 4))
        # the predicted P is written into whichever of these two P is not (a new array per ping
        # cost 0.4 of its 1.7 µs matmul); their flat views take Q's diagonal (an integer index
        # into a 1-D array: ~30 ns less per entry than a pair into a 2-D one)
        self._P_out = (np.empty((4, 4)), np.empty((4, 4)))
        self._P_flat = tuple(b.reshape(16) for b in self._P_out)
        self._pending: list[tuple[float, np.ndarray, float]] = []
        self.fixes_used = 0

    def _predict(self, t_s: float) -> None:
        t_kf = self._t_kf
        if t_s > t_kf:  # (False while t_kf is NaN: no ping or fix yet)
            dt = t_s - t_kf
            # x ← F x: offset += drift dt, each a product then a sum, as numpy's F @ x rounds it
            o_n, o_e, d_n, d_e = self._x
            self._x = (o_n + d_n * dt, o_e + d_e * dt, d_n, d_e)
            # P ← F P Fᵀ + Q dt: the products stay BLAS's (whose fused multiply-adds Python floats
            # cannot reproduce), by np.dot: the same dgemm as np.matmul's, bit for bit, for ~0.5 µs
            # less of numpy's dispatch per product; Q is diagonal, its dt-scaled entries added one by one
            F = self._F
            F[0, 2] = F[1, 3] = dt
            np.dot(F, self._P, out=self._FP)
            i = 1 if self._P is self._P_out[0] else 0
            P = self._P_out[i]
            np.dot(self._FP, self._F_T, out=P)
            Pf = self._P_flat[i]
            q_o, q_d = self.q_offset * dt, self.q_drift * dt
            Pf[0] += q_o
            Pf[5] += q_o
            Pf[10] += q_d
            Pf[15] += q_d
            self._P = P
            self._t_kf = t_s
        elif t_kf != t_kf:
            self._t_kf = t_s

    def fix(self, t_s: float, pos_n_m, sigma_m: float) -> None:
        """A position fix (north, east; m) ± ``sigma_m`` at ``t_s``; applied by a later ping."""
        p = np.asarray(pos_n_m, dtype=float).reshape(-1)[:2]
        if np.all(np.isfinite(p)) and math.isfinite(t_s) and math.isfinite(sigma_m) and sigma_m > 0:
            self._pending.append((float(t_s), p, float(sigma_m)))

    def _update(self, t_s: float, dr: np.ndarray, p: np.ndarray, sigma_m: float) -> None:
        self._predict(t_s)
        H = np.hstack([np.eye(2), np.zeros((2, 2))])
        S = H @ self._P @ H.T + sigma_m ** 2 * np.eye(2)
        K = self._P @ H.T @ np.linalg.inv(S)
        x = np.array(self._x)
        self._x = tuple((x + K @ (p - dr - x[:2])).tolist())
        A = np.eye(4) - K @ H
        self._P = A @ self._P @ A.T + sigma_m ** 2 * K @ K.T  # Joseph form: stays symmetric PSD
        self.fixes_used += 1

    def push(self, ping: SonarPing) -> tuple[np.ndarray, float]:
        """Dead-reckon to ``ping``; return its (north, east) (m) and σ per axis (m).

        Pings with a non-finite or non-increasing time do not move the estimate.
        """
        pn, pe, sigma = self.push_floats(ping)
        return np.array((pn, pe)), sigma

    def push_floats(self, ping: SonarPing) -> tuple[float, float, float]:
        """:meth:`push` with the position as two Python floats: (north, east, σ), m."""
        t = float(ping.t_s)
        if not math.isfinite(t) or (self._last is not None and not t > self._last[0]):
            return (*self._position(), self.sigma())
        speed = ping.speed_m_s if math.isfinite(ping.speed_m_s) else (self._last[1] if self._last else 0.0)
        yaw = ping.heading_rad if math.isfinite(ping.heading_rad) else (self._last[2] if self._last else 0.0)
        dr0 = self._dr
        if self._last is not None:
            t0, v0, yaw0 = self._last
            mid = yaw0 + 0.5 * math.remainder(yaw - yaw0, 2.0 * math.pi)
            step = 0.5 * (v0 + speed) * (t - t0)
            dn, de = self._dr
            self._dr = (dn + step * math.cos(mid), de + step * math.sin(mid))
        t_prev = self._last[0] if self._last is not None else t
        self._last = (t, speed, yaw)
        if self._pending:  # (most pings: no fix waiting)
            keep = []
            for tf, p, sig in sorted(self._pending, key=lambda f: f[0]):
                if tf > t:
                    keep.append((tf, p, sig))
                    continue
                a = 0.0 if t <= t_prev else min(max((tf - t_prev) / (t - t_prev), 0.0), 1.0)
                d0, d1 = np.array(dr0), np.array(self._dr)
                self._update(max(tf, self._t_kf) if math.isfinite(self._t_kf) else tf, d0 + a * (d1 - d0), p, sig)
            self._pending = keep
        self._predict(t)
        return (*self._position(), self.sigma())

    def _position(self) -> tuple[float, float]:
        """(north, east) now (m): the dead reckoning plus the estimated offset."""
        return self._dr[0] + self._x[0], self._dr[1] + self._x[1]

    def sigma(self) -> float:
        """σ per axis of the current position (m); NaN before the first fix."""
        if not self.fixes_used:
            return math.nan
        P = self._P
        return math.sqrt(max(0.5 * (P.item(0, 0) + P.item(1, 1)), 0.0))
