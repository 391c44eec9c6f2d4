"""AnchoredDeadReckoning's covariance prediction by np.dot into kept buffers against the
np.matmul steps it replaced (37da4aa): bit for bit over pings with fixes, speed gaps, repeated
and out-of-order times, and np.dot's 4 × 4 products the same as np.matmul's on this BLAS."""
from __future__ import annotations

import math

import numpy as np

from adaptnav.sonar.dead_reckoning import AnchoredDeadReckoning
from adaptnav.sonar.ping import SonarPing


class _MatmulPrediction(AnchoredDeadReckoning):
    """The prediction as it was: np.matmul, the diagonal by pairs of indices, max() of the times."""

    def _predict(self, t_s: float) -> None:
        if math.isfinite(self._t_kf) and t_s > self._t_kf:
            dt = t_s - self._t_kf
            o_n, o_e, d_n, d_e = self._x
            self._x = (o_n + d_n * dt, o_e + d_e * dt, d_n, d_e)
            F = self._F
            F[0, 2] = F[1, 3] = dt
            np.matmul(F, self._P, out=self._FP)
            P = self._P_out[0] if self._P is not self._P_out[0] else self._P_out[1]
            np.matmul(self._FP, self._F_T, out=P)
            q_o, q_d = self.q_offset * dt, self.q_drift * dt
            P[0, 0] += q_o
            P[1, 1] += q_o
            P[2, 2] += q_d
            P[3, 3] += q_d
            self._P = P
        self._t_kf = t_s if not math.isfinite(self._t_kf) else max(self._t_kf, t_s)


def _ping(t_s, speed_m_s, yaw_rad):
    z = np.zeros(16, np.float32)
    return SonarPing(t_s=t_s, port=z, starboard=z, slant_range_m=20.0, altitude_m=5.0, heading_rad=yaw_rad,
                     speed_m_s=speed_m_s)


def _events(n_pings: int, seed: int):
    """("fix", (t, pos, σ)) and ("ping", (t, speed, yaw)): irregular intervals with repeated times,
    speed gaps, turns, fixes late and early (one before the first ping), times out of order and NaN."""
    rng = np.random.default_rng(seed)
    steps = np.where(np.arange(n_pings) % 97 == 3, 0.0, rng.uniform(0.02, 0.4, n_pings))
    t_s = 100.0 + np.cumsum(steps)
    yaw_rad = np.remainder(0.3 + np.cumsum(rng.normal(0.0, 0.05, n_pings)) + math.pi, 2.0 * math.pi) - math.pi
    speed_m_s = np.where(np.arange(n_pings) % 37 == 5, np.nan, rng.uniform(0.5, 2.0, n_pings))
    events = [("fix", (99.0, rng.normal(0.0, 50.0, 2), 2.0))]
    for k in range(n_pings):
        if k % 53 == 10:
            events.append(("fix", (float(t_s[k]) - float(rng.uniform(-0.5, 3.0)), rng.normal(0.0, 50.0, 2),
                                   float(rng.uniform(0.5, 5.0)))))
        t_ping = t_s[k] - 1.0 if k % 401 == 7 else (math.nan if k % 503 == 9 else t_s[k])
        events.append(("ping", (float(t_ping), float(speed_m_s[k]), float(yaw_rad[k]))))
    return events


def test_prediction_by_dot_is_the_matmul_one_bit_for_bit():
    nav, ref = AnchoredDeadReckoning(), _MatmulPrediction()
    for k, (kind, args) in enumerate(_events(4000, 54)):
        if kind == "fix":
            nav.fix(*args)
            ref.fix(*args)
            continue
        got, want = nav.push_floats(_ping(*args)), ref.push_floats(_ping(*args))
        assert np.array(got).tobytes() == np.array(want).tobytes(), k
        assert nav._t_kf == ref._t_kf or (math.isnan(nav._t_kf) and math.isnan(ref._t_kf))
    assert nav.fixes_used == ref.fixes_used > 70
    assert nav._P.tobytes() == ref._P.tobytes()
    assert nav._x == ref._x


def test_dot_is_matmul_for_the_prediction_products():
    """What the prediction relies on: np.dot of C-contiguous 4 × 4 arrays, the second also
    as a transposed view, is np.matmul's dgemm, bit for bit (covariances of many magnitudes)."""
    rng = np.random.default_rng(3)
    F = np.eye(4)
    out_dot, out_matmul = np.empty((4, 4)), np.empty((4, 4))
    for _ in range(3000):
        F[0, 2] = F[1, 3] = float(rng.uniform(0.001, 2.0))
        A = rng.normal(size=(4, 4)) * 10.0 ** rng.uniform(-6, 6, (4, 4))
        P = A @ A.T
        np.dot(F, P, out=out_dot)
        np.matmul(F, P, out=out_matmul)
        assert out_dot.tobytes() == out_matmul.tobytes()
        FP = out_dot.copy()
        np.dot(FP, F.T, out=out_dot)
        np.matmul(FP, F.T, out=out_matmul)
        assert out_dot.tobytes() == out_matmul.tobytes()


def test_prediction_before_any_time_and_for_earlier_times():
    nav = AnchoredDeadReckoning()
    assert math.isnan(nav._t_kf)
    nav._predict(5.0)  # the first time: taken, nothing predicted
    assert nav._t_kf == 5.0 and nav._P is not nav._P_out[0] and nav._P is not nav._P_out[1]
    P0 = nav._P.copy()
    nav._predict(4.0)  # earlier: nothing
    nav._predict(math.nan)
    assert nav._t_kf == 5.0 and nav._P.tobytes() == P0.tobytes()
    nav._predict(5.5)
    assert nav._t_kf == 5.5 and nav._P is nav._P_out[0]
    nav._predict(6.0)
    assert nav._P is nav._P_out[1]
    nav._predict(6.5)
    assert nav._P is nav._P_out[0]
