r"""External AHRS attitude (ArduSub ATTITUDE): ``h(x) = (φ, θ, ψ)`` ZYX, angles wrapped.

Used when logs carry ATTITUDE but no usable IMU rate (real ArduSub telemetry: IMU at
2 Hz, ATTITUDE at 20 Hz). ``H_att = M⁻¹`` (:func:`adaptnav.fusion.aiding.common.euler_jacobian`).
"""
from __future__ import annotations

import math

import numpy as np

from ..state import ATT, ATT_YAW, N_ERR, POS_NE, VEL, X_POS_NE, X_Q, X_VEL
from ..config import AttitudeConfig
from .common import ALL_ANGULAR, AidContext, AidSource, Measurement, dcm, euler_jacobian, euler_of


def predict(x) -> np.ndarray:
    return euler_of(dcm(x))


def jacobian(x) -> np.ndarray:
    H = np.zeros((3, N_ERR))
    H[:, ATT] = euler_jacobian(dcm(x))
    return H


def euler_rows(x) -> tuple:
    """``(roll, pitch, yaw, M⁻¹)``: :func:`predict` and the attitude block of :func:`jacobian`
    (M⁻¹ as nested tuples) from one attitude — the same operations on the same floats (the
    elements of common.dcm, the angles and the Jacobian of common.euler_of /
    euler_jacobian, numpy's trigonometry) without building R twice nor computing pitch and
    yaw twice (ATTITUDE comes at 10–50 Hz: its measurement was 40 % of its cost)."""
    w, a, b, c = x[X_Q].tolist()
    r00 = 1 - 2 * (b * b + c * c)
    r10 = 2 * (a * b + w * c)
    r20 = 2 * (a * c - w * b)
    r21 = 2 * (b * c + w * a)
    r22 = 1 - 2 * (a * a + b * b)
    # np.clip(r20, -1, 1) without its overhead (NaN stays NaN)
    pitch = -np.arcsin(1.0 if r20 > 1.0 else (-1.0 if r20 < -1.0 else r20))
    roll = np.arctan2(r21, r22)
    yaw = np.arctan2(r10, r00)
    cy, sy, cp, tp = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.tan(pitch)
    return roll, pitch, yaw, ((cy / cp, sy / cp, 0.0), (-sy, cy, 0.0), (cy * tp, sy * tp, 1.0))


def measure(sample, x, sigma_roll_pitch_rad, sigma_yaw_rad) -> Measurement:
    roll, pitch, yaw, m_inv = euler_rows(x)
    H = np.zeros((3, N_ERR))
    H[:, ATT] = m_inv
    R = np.zeros((3, 3))
    R[0, 0] = R[1, 1] = sigma_roll_pitch_rad**2
    R[2, 2] = sigma_yaw_rad**2
    z = np.array([sample.roll_rad, sample.pitch_rad, sample.yaw_rad], dtype=float)
    return Measurement(z, H, R, np.array([roll, pitch, yaw]), ALL_ANGULAR[3])


def _measure(sample, ctx: AidContext) -> Measurement:
    return measure(sample, ctx.x, ctx.config.sigma_roll_pitch_rad, ctx.config.sigma_yaw_rad)


AID = AidSource("attitude", AttitudeConfig, _measure, without_imu=True)


def reference_yaw_covariance(x: np.ndarray, anchor_ne_m, sigma_rad: float) -> np.ndarray:
    r"""What the autopilot's heading frame adds to the covariance (18×18, m², rad²) when the
    filter's yaw is held to ATTITUDE: ``σ_b² s sᵀ`` with ``s = ∂δx/∂b``.

    ATTITUDE is the autopilot's EKF estimate, fused at 10–50 Hz: the filter's yaw follows it
    within its own σ (0.17–0.28° on the ArduSub logs) while the autopilot's yaw is off the
    truth by an error ``b`` that stays for minutes (ArduSub SITL: 0.6° rms, correlation
    0.7–0.9 after 60 s; a compass's residual deviation, heading-dependent, on a real vehicle).
    Nothing on board observes ``b``; fused as white noise at the stream's rate it vanished
    from the covariance (yaw NEES 70–95 on the SITL logs). The filter therefore navigates in
    the autopilot's frame, rotated by ``b`` about the vertical, and ``b`` is a *consider*
    parameter (Schmidt 1966; Groves 2013 §3.4.3), as the DVL's scale and misalignment are
    (:class:`adaptnav.fusion.aiding.dvl.DvlCalibration`): its effect on the error state is

    .. math:: δθ_D = 1,\quad δp_{NE} = J (\hat p − a),\quad δv_{NE} = J \hat v,
              \qquad J = \begin{pmatrix}0 & −1\\ 1 & 0\end{pmatrix}

    per unit of ``−b`` (``δx = x_true − x̂``, ``q_true = q(δθ) ⊗ q̂``): the dead-reckoned track
    since the last absolute fix ``a`` (``anchor_ne_m``) turns with the frame. Exact for a
    constant offset; a wandering one moves less than that.
    """
    d = np.asarray(x[X_POS_NE], float) - np.asarray(anchor_ne_m, float)
    v = x[X_VEL]
    s = np.zeros(N_ERR)
    s[POS_NE] = (-d[1], d[0])
    s[VEL.start:VEL.start + 2] = (-float(v[1]), float(v[0]))
    s[ATT_YAW] = 1.0
    return sigma_rad ** 2 * np.outer(s, s)


class HeadingSource:
    r"""What a heading source (the autopilot's ``ATTITUDE`` yaw) is worth next to a
    navigation-grade INS, learned from the data.

    An ``ATTITUDE`` may come from a compass-grade AHRS (a magnetic heading: 1–3° off, its
    error wandering with the vehicle's magnetic environment and its tilt compensation) or
    from the vehicle's own navigation-grade INS (PHINS / SPRINT class: 0.01–0.1° sec L, a
    gyrocompass whose error drifts over the Schuler and earth periods). Fused as white noise,
    a compass pulls a FOG's heading onto its offset; ignored, an INS's heading is thrown away
    while the filter's own gyrocompass needs minutes to converge (and wanders a few tenths of
    a degree meanwhile). Which one it is shows in the source's heading *relative to the
    gyro*: a navigation-grade gyro propagates the heading to milli-degrees over minutes, so

        d_k = ψ_src(t_k) − ψ_g(t_k),   ψ_g = ψ_INS − Σ δψ (the INS's heading without the corrections of any update)

    holds the source's own error minus a constant. (ψ_g is the strapdown's own propagation at
    the IMU rate; integrating the body rate between the source's samples instead aliases the
    vehicle's rate steps: 0.14° RMS at 10 Hz on a lawnmower.) Its variability over a window —
    an exponentially weighted variance, each sample of weight ``α = 1 − exp(−Δt/τ)``,
    ``τ = learn_window_s``, the past decaying by ``1 − α``, updated by West's weighted
    incremental algorithm (West 1979, CACM 22(9); ``W ← (1 − α) W + α``,
    ``m ← m + (α/W)(d − m)``, ``S ← (1 − α) S + α (d − m_prev)(d − m)``, ``v = S/W``), each
    deviation clipped at 3 ``ins_max_variability_rad`` (one glitch of a good source must not
    read as a compass for minutes) — less the part a time offset between the source's clock
    and the IMU's explains (``d ≈ e + β ψ̇`` in turns, ``β`` by the same weighted least squares
    on the gyro's heading rate, |β| ≤ 0.2 s, and the fused heading shifted by it: a PHINS
    heading stamped 50 ms off the FOG reads 0.26° off in a 5 °/s turn), is the source's
    short-term heading noise. An INS-class source varies by milli-degrees against the gyro
    (its heading *is* a gyro's); a magnetic heading by ≥ 0.1°. Once ``learn_min_s`` of data are in, a source with ``√v ≤ ins_max_variability_rad``
    is taken for an INS and fused with

        R = max(v, (ins_sigma_yaw_rad · sec L)²)

    — bounded below by the class's absolute accuracy, which no comparison with the gyro can
    show (a constant offset drops out of ``d``) — and only while the filter's own heading
    variance ``h P hᵀ`` exceeds ``R``: a source whose error is correlated over minutes can
    bring the heading variance down to its own error variance, not below (fused as white
    noise at 10 Hz it would claim a hundredfold more). A source that varies more is not
    fused (a compass next to a FOG: the heading seed only, as before). The decision follows
    the estimate: a source that starts to vary is dropped again.

    Parameters
    ----------
    config : AttitudeConfig
        ``learn_window_s``, ``learn_min_s``, ``ins_max_variability_rad``, ``ins_sigma_yaw_rad``.
    lat_rad : float
        Latitude of the mission origin (sec L of the class's accuracy).
    """

    _MIN_RATE_VAR = math.radians(0.5) ** 2  # (rad/s)²: below, no turns to see a time offset in
    _MAX_LAG_S = 0.2  # s: clock mappings are off by tens of ms; more would explain a compass away

    def __init__(self, config: AttitudeConfig, lat_rad: float):
        self.config = config
        self._r_floor = (config.ins_sigma_yaw_rad / max(math.cos(lat_rad), 0.05)) ** 2
        self._t = -math.inf        # the latest sample observed
        self._t_first = math.nan   # the first
        self._psi_g = math.nan     # the gyro heading there (rad)
        self.rate_rad_s = 0.0      # the gyro's heading rate over the latest interval
        self.mean_rad = 0.0        # EW mean of d
        self._m_rate = 0.0         # EW mean of the rate
        self._c = np.zeros(3)      # EW co-moments (rate·rate, rate·d, d·d), unnormalised ...
        self._weight = 0.0         # ... and the weight of the data in them

    @property
    def t_first_s(self) -> float:
        """The first sample observed (nan before)."""
        return self._t_first

    @property
    def lag_s(self) -> float:
        """``β`` of ``d ≈ e + β ψ̇``: the source's heading is ``ψ(t − δ)``, δ = −β, when its
        time and the IMU's are offset (two clocks mapped onto one); 0 until turns show it."""
        c_rr, c_rd, _ = self._c
        if self._weight <= 0 or c_rr / self._weight < self._MIN_RATE_VAR:
            return 0.0
        return min(max(c_rd / c_rr, -self._MAX_LAG_S), self._MAX_LAG_S)

    @property
    def var_rad2(self) -> float:
        """EW variance of ``d`` (rad²) less what a time offset explains (``lag_s``),
        normalised by the weight the data have so far (an average of the first minutes, not
        pulled towards the zero it started from)."""
        if self._weight <= 0:
            return math.inf
        c_rr, c_rd, c_dd = self._c
        b = self.lag_s
        return max(c_dd - 2.0 * b * c_rd + b * b * c_rr, 0.0) / self._weight

    def heading_rad(self, yaw_src_rad: float) -> float:
        """The source's heading at its own time stamp, the time offset removed."""
        return yaw_src_rad - self.lag_s * self.rate_rad_s

    def observe(self, t_s: float, yaw_src_rad: float, yaw_gyro_rad: float) -> None:
        """Take the source's heading at ``t_s`` against the gyro-propagated heading ψ_g (rad);
        samples not after the latest are ignored (a re-fusion of the past sees them again)."""
        if not (t_s > self._t and math.isfinite(yaw_src_rad) and math.isfinite(yaw_gyro_rad)):
            return
        if not math.isfinite(self._t_first):  # the first sample: nothing to compare yet
            self._t_first = t_s
            self.mean_rad = math.remainder(yaw_src_rad - yaw_gyro_rad, 2.0 * math.pi)
        else:
            dt = t_s - self._t
            self.rate_rad_s = math.remainder(yaw_gyro_rad - self._psi_g, 2.0 * math.pi) / dt
            d = self.mean_rad + math.remainder(yaw_src_rad - yaw_gyro_rad - self.mean_rad, 2.0 * math.pi)
            # West's weighted incremental co-moments (each sample weight a, the past decaying
            # by 1 − a): the first samples are averaged, not dominated by the first one
            a = 1.0 - math.exp(-dt / self.config.learn_window_s)
            self._weight = (1.0 - a) * self._weight + a
            self._c *= 1.0 - a
            # a deviation counts at most 3× the INS-class bound (Huber): one glitch of a
            # good source must not read as a compass for minutes; a compass's every sample
            # deviates, and its variance stays above the bound
            lim = 3.0 * self.config.ins_max_variability_rad
            if self._weight == a:  # the first difference: its own mean
                self._m_rate = self.rate_rad_s
            dr = self.rate_rad_s - self._m_rate
            b = self.lag_s  # clipped is what the time offset does not explain
            dd = b * dr + min(max(d - self.mean_rad - b * dr, -lim), lim)
            g = a / self._weight
            self.mean_rad += g * dd
            self._m_rate += g * dr
            self._c += a * np.array([dr * dr * (1.0 - g), dr * dd * (1.0 - g), dd * dd * (1.0 - g)])
        self._t, self._psi_g = t_s, yaw_gyro_rad

    def r_rad2(self, t_s: float) -> float | None:
        """The source's heading variance (rad²) if it is an INS-class heading worth fusing at
        ``t_s``, else None (not yet judged, or a compass)."""
        cfg = self.config
        if not (t_s - self._t_first >= cfg.learn_min_s and self.var_rad2 <= cfg.ins_max_variability_rad ** 2):
            return None
        return max(self.var_rad2, self._r_floor)
