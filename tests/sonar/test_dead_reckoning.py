"""AnchoredDeadReckoning's per-ping scalar steps against the textbook filter in numpy matrices.

The two agree to rounding, not bit for bit on every machine: numpy's ``F @ x`` may fuse a
multiply-add (one rounding of ``o + d dt`` where the scalar step rounds twice), as a BLAS built
for a CPU with FMA does. The tolerance (1e-12 relative, over 3000 pings) is far below anything
a wrong step would give — a missing ``dt`` or a swapped axis is off by metres."""
from __future__ import annotations

import math

import numpy as np

from adaptnav.sonar.dead_reckoning import AnchoredDeadReckoning
from adaptnav.sonar.ping import SonarPing


class _MatrixPrediction(AnchoredDeadReckoning):
    """The reference: the prediction as matrices, x ← F x and P ← F P Fᵀ + Q dt (as the class
    computed it before its scalar steps), the rest of the filter the class's own."""

    def _predict(self, t_s: float) -> None:
        if math.isfinite(self._t_kf) and t_s > self._t_kf:
            dt = t_s - self._t_kf
            F = np.eye(4)
            F[0, 2] = F[1, 3] = dt
            Q = np.diag([self.q_offset, self.q_offset, self.q_drift, self.q_drift])
            self._x = tuple((F @ np.array(self._x)).tolist())
            self._P = F @ self._P @ F.T + Q * dt
        self._t_kf = t_s if not math.isfinite(self._t_kf) else max(self._t_kf, t_s)


def _ping(t_s, speed_m_s, yaw_rad):
    z = np.zeros(16, np.float32)
    return SonarPing(t_s=t_s, port=z, starboard=z, slant_range_m=20.0, altitude_m=5.0, heading_rad=yaw_rad,
                     speed_m_s=speed_m_s)


def _close(a, b) -> bool:
    return bool(np.allclose(a, b, rtol=1e-12, atol=1e-9, equal_nan=True))


def test_dead_reckoning_prediction_is_the_matrix_one():
    # irregular ping intervals, speed gaps, turns, fixes late and early, out-of-order pings
    rng = np.random.default_rng(52)
    nav, ref = AnchoredDeadReckoning(), _MatrixPrediction()
    t, yaw = 100.0, 0.3
    for k in range(3000):
        t += float(rng.uniform(0.02, 0.4))
        yaw = math.remainder(yaw + float(rng.normal(0.0, 0.05)), 2.0 * math.pi)
        speed = math.nan if k % 37 == 5 else float(rng.uniform(0.5, 2.0))
        if k % 53 == 10:
            fix = (t - float(rng.uniform(-0.5, 3.0)), rng.normal(0.0, 50.0, 2), float(rng.uniform(0.5, 5.0)))
            nav.fix(*fix)
            ref.fix(*fix)
        ping = _ping(t - 1.0 if k % 401 == 7 else t, speed, yaw)
        (p, sigma), (p_ref, sigma_ref) = nav.push(ping), ref.push(ping)
        assert _close(p, p_ref), k
        assert _close(sigma, sigma_ref), k
    assert nav.fixes_used == ref.fixes_used > 50
    assert _close(nav._P, ref._P)


def test_dead_reckoning_state_matches_numpy_vectors():
    # the position: the dead reckoning plus the offset, as numpy adds the two 2-vectors
    nav = AnchoredDeadReckoning()
    nav.fix(0.5, [3.0, -2.0], 1.0)
    for k in range(40):
        p, _ = nav.push(_ping(0.25 * k, 1.3, 0.1 * k))
    assert p.tobytes() == (np.array(nav._dr) + np.array(nav._x[:2])).tobytes()
