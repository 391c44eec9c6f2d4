r"""DVL velocity in the DVL head frame (lever arm, mounting rotation), bottom or water track.

::

    bottom track:  h(x) = R_db (R_nbᵀ v_n + ω̂_b × l_b),   R_db = R_bdᵀ, R_bd from ``rotation_bd_rpy_rad``
    water track:   h(x) = R_db (R_nbᵀ (v_n − c_n) + ω̂_b × l_b)

(Groves 2013 §16.3.4 / Brokloff 1994). With ``ω̂ = ω_m − b_g``: ∂(ω̂ × l)/∂δb_g = [l]×.
Jacobians: ``R_db R_nbᵀ`` (δv), ``R_db R_nbᵀ [v_n − c]×`` (δθ), ``R_db [l]×`` (δb_g), and for
water track ``−R_db R_nbᵀ[:, :2]`` (δc).

Scale factor and misalignment (:class:`DvlCalibration`): a real head reports
``v_m ≈ (1 + s) R_z(ψ)ᵀ v`` (sound-speed scale error ``s``, a yaw misalignment ``ψ`` left
by the installation survey; 0.1–1 % and tenths of a degree, sim/sensors.py). Neither is
observable from the DVL and the IMU over straight legs; absolute fixes see both: the
DVL's own track between two fixes, ``D = Σ R_nd v_m Δt``, against the fixes' displacement
``Δp`` gives ``Δp − D ≈ −s D + ψ (e_z × D)`` (horizontal, linear in (s, ψ); the track-to-fix
calibration of Kinsey & Whitcomb, IEEE JOE 31(2), 2006), and so does the vehicle's own
hydrodynamics when its hull does not sideslip ("Straight legs" below: ψ only). A Kalman
filter with prior σ (``scale_sigma``, ``misalignment_sigma_rad``) accumulates both; the
measurement is corrected with the current estimate, so with neither (GNSS at the surface
only, a vehicle that may crab) the correction stays at the prior's zero — "estimated where
observable".

Through turns the IMU sees them in principle: the DVL's error ``−s v + ψ e_z × v`` turns
with the velocity, so across a reversal at 1.5 m/s a 0.4° misalignment is a 21 mm/s jump
of the DVL against the free-inertial velocity. With the tactical IMU of dvl_outage that
does not pay: the aided filter's free-inertial velocity wanders ±30 mm/s over a lawnmower
turn (60–70 s with its transients), and lines fitted to it on the straights either side of
5 reversals (seed 1) missed the jump by ~80 mm/s RMS — a turn says less than the prior.
What the scale and misalignment cost there (counterfactual runs of the simulator): of the
1.8–2.4 m the filter carried into the outage at minute 29 (seeds 1–3) before the straight
legs below, 0.4° of misalignment made ~1.9 m (across the eastward cross legs) and 0.3 % of
scale ~0.8 m; the beam biases, the IMU's errors and the current 0.15–0.3 m each. With the
straight legs the estimate is 0.32–0.34° ± 0.04° by then and the error 0.10–0.58 m (seeds 1–10).

Straight legs (:class:`StraightLegs`, ``hull_sideslip = "none"``): a vehicle with no lateral
thrust (a torpedo AUV) does not sideslip through the water on a straight — at steady state
nothing pushes it sideways, so its hull points along its water-relative velocity (the angle
between heading and course is the current's, not the hull's). Its DVL's lateral velocity
there, in the heading-aligned level frame, is then the head's misalignment and the current::

    l̄ = −ψ ū + (−sin h̄, cos h̄) · c_ne          (ū the mean forward speed, h̄ the heading)

so reciprocal legs (the current's part changes sign, the misalignment's does not) observe ψ
without any fix — dvl_outage: 0.4° of misalignment was ~1.9 m of the 1.8–2.4 m the filter
carried into the outage. The current ``c_ne`` is a nuisance state of this estimator
(a random walk; the filter's own current estimate is not used, it is fitted to the DVL the
misalignment is in). Each leg is cut into segments of at most ``max_s`` (turn transients
left out: ``settle_s`` after the yaw rate falls), each a scalar measurement whose σ is the
segment's own scatter plus ``hull_sway_sigma_m_s`` (what a real hull's sway wanders
by over a minute: waves, control). A vehicle that does crab on a straight (an ROV with lateral
thrusters, a tethered one) must say ``"free"``: a constant crab would be taken for
misalignment. The filter applies the new estimate from then on; what its earlier part of
the track since the last fix was corrected with too little is a known error, carried in the
published covariance (:meth:`DvlCalibration.position_cov_ne`), not moved.
"""
from __future__ import annotations

import math
from collections import deque
from typing import NamedTuple

import numpy as np
from adaptnav.kernels import unguarded

from ..frames import euler_to_quat, quat_to_dcm
from ..config import DvlConfig
from ..state import ACC_OMEGA, ATT, BG, CUR, N_ERR, VEL, X_CUR, X_VEL
from ..kalman import (CORE_ACC, CORE_SIZE, CORE_X, WORK_DVL_H, WORK_DVL_R, WORK_DVL_SMALL_H, WORK_DVL_Z, WORK_SIZE,
                      dvl_bottom_track_core)
from .common import NOT_ANGULAR, AidContext, AidSource, Measurement, dcm, make, skew

# bottom_track_into's kernel without its argument guard (adaptnav.kernels.unguarded): its callers'
# arrays are always their own C-contiguous float64 ones (below), its numbers Python floats
_bottom_track_core = unguarded(dvl_bottom_track_core)


class StraightSegment(NamedTuple):
    """A stretch of a straight leg: its mid time (s), mean forward and lateral DVL velocity in
    the heading-aligned level frame (m/s, uncorrected), the variance of that lateral mean
    ((m/s)²), the mean heading (rad) and the filter's current along it (m/s)."""

    t_s: float
    forward_m_s: float
    lateral_m_s: float
    lateral_var: float
    heading_rad: float
    current_along_m_s: float


class StraightLegs:
    """Cuts the DVL's bottom-track samples into :class:`StraightSegment` (module docstring).

    Parameters
    ----------
    max_yaw_rate_rad_s : a sample turning faster, by its heading ``rate_window_s`` earlier (not
        the gyro's rate: noisy per sample, and the vehicle's heading loop oscillates), is not on
        a straight
    max_heading_change_rad : a segment ends when the heading leaves its first value by more
    min_speed_m_s : slower samples say too little of the misalignment (ψ ū)
    settle_s : after a turn, the hull's skid decays before a segment starts
    min_s, max_s : segment length (a long leg gives several; the current may change)
    max_gap_s : a longer gap between samples ends the segment
    """

    def __init__(self, max_yaw_rate_rad_s: float = 0.01, max_heading_change_rad: float = math.radians(5.0),
                 min_speed_m_s: float = 0.5, settle_s: float = 10.0, min_s: float = 20.0, max_s: float = 60.0,
                 max_gap_s: float = 2.0, rate_window_s: float = 5.0):
        self.max_yaw_rate_rad_s = max_yaw_rate_rad_s
        self.rate_window_s = rate_window_s
        self._headings: deque[tuple[float, float]] = deque()
        self.max_heading_change_rad = max_heading_change_rad
        self.min_speed_m_s = min_speed_m_s
        self.settle_s, self.min_s, self.max_s, self.max_gap_s = settle_s, min_s, max_s, max_gap_s
        self._straight_since: float | None = None
        self._last_t: float | None = None
        self._sums: list[float] | None = None  # t0, t1, n, Σf, Σl, Σl², Σsin h, Σcos h, Σc∥
        self._h0 = 0.0

    def _close(self) -> StraightSegment | None:
        sums, self._sums = self._sums, None
        if sums is None:
            return None
        t0, t1, n, sf, sl, sl2, ss, sc, sca = sums
        if t1 - t0 < self.min_s or n < 3:
            return None
        mean_l = sl / n
        var = max(sl2 - n * mean_l * mean_l, 0.0) / (n - 1)
        # the scatter is partly the vehicle's own (control, waves), correlated over seconds:
        # one independent sample per 2 s, not per ping
        n_eff = max(min(n, (t1 - t0) / 2.0), 1.0)
        return StraightSegment(0.5 * (t0 + t1), sf / n, mean_l, var / n_eff, math.atan2(ss, sc), sca / n)

    def add(self, t_s: float, forward_m_s: float, lateral_m_s: float, heading_rad: float,
            current_along_m_s: float = 0.0) -> StraightSegment | None:
        """One bottom-track sample; a segment when this sample closes one."""
        gap = self._last_t is None or t_s - self._last_t > self.max_gap_s
        self._last_t = t_s
        hist = self._headings
        if gap:
            hist.clear()
        hist.append((t_s, heading_rad))
        while t_s - hist[0][0] > self.rate_window_s:
            hist.popleft()
        span = t_s - hist[0][0]
        rate = abs(math.remainder(heading_rad - hist[0][1], 2.0 * math.pi)) / span if span > 0 else 0.0
        straight = (span >= 0.5 * self.rate_window_s and rate <= self.max_yaw_rate_rad_s
                    and forward_m_s >= self.min_speed_m_s)
        if self._sums is not None and straight and not gap:
            dh = math.remainder(heading_rad - self._h0, 2.0 * math.pi)
            straight = abs(dh) <= self.max_heading_change_rad
        if not straight or gap:
            out = self._close()
            self._straight_since = t_s if straight else None
            return out
        if self._straight_since is None:
            self._straight_since = t_s
        if t_s - self._straight_since < self.settle_s:
            return None
        out = None
        if self._sums is not None and t_s - self._sums[0] >= self.max_s:
            out = self._close()
        if self._sums is None:
            self._sums = [t_s, t_s, 0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]
            self._h0 = heading_rad
        s = self._sums
        s[1] = t_s
        s[2] += 1
        s[3] += forward_m_s
        s[4] += lateral_m_s
        s[5] += lateral_m_s * lateral_m_s
        s[6] += math.sin(heading_rad)
        s[7] += math.cos(heading_rad)
        s[8] += current_along_m_s
        return out


class DvlCalibration:
    """Scale factor ``s`` and yaw misalignment ``ψ`` of the DVL head (module docstring).

    State ``(s, ψ, c_N, c_E)``: the current ``c`` is the straight legs' nuisance (a random
    walk, ``current_rw_m_s_rthz``), untouched by fix pairs.

    Parameters
    ----------
    scale_sigma : prior 1-σ of ``s`` (–)
    misalignment_sigma_rad : prior 1-σ of ``ψ`` (rad)
    max_gap_fraction : a fix-to-fix interval with more of its time without DVL is not used
    min_track_m : intervals with a shorter DVL track carry too little information
    straight_legs : cut the DVL's samples into straight-leg segments and estimate ψ from them
        (a hull that does not sideslip, ``hull_sideslip = "none"``); None: fixes only
    hull_sway_sigma_m_s : 1-σ of the hull's own mean sway over a segment (m/s)
    current_sigma_m_s, current_rw_m_s_rthz : the current's prior σ and random walk (a tidal
        current turning over 6 h changes by a few mm/s per leg)
    along_current_sigma_m_s : 1-σ of the filter's along-heading current on a segment
    """

    _BRIDGE_S = 2.0  # drop-outs up to this long are bridged by the trapezoid
    _GATE = 16.0     # a segment 4 σ off its prediction (a turn the rate test missed, fish) is not used

    def __init__(self, scale_sigma: float, misalignment_sigma_rad: float,
                 max_gap_fraction: float = 0.2, min_track_m: float = 20.0,
                 straight_legs: StraightLegs | None = None, hull_sway_sigma_m_s: float = 0.003,
                 current_sigma_m_s: float = 0.5, current_rw_m_s_rthz: float = 2.0e-4,
                 along_current_sigma_m_s: float = 0.01):
        self.theta = np.zeros(4)  # (s, ψ, c_N, c_E)
        self.P = np.diag([scale_sigma**2, misalignment_sigma_rad**2, current_sigma_m_s**2, current_sigma_m_s**2])
        self.max_gap_fraction = max_gap_fraction
        self.min_track_m = min_track_m
        self.straight_legs = straight_legs if misalignment_sigma_rad > 0 else None
        self.hull_sway_sigma_m_s = hull_sway_sigma_m_s
        self.current_rw_m_s_rthz = current_rw_m_s_rthz
        self.along_current_sigma_m_s = along_current_sigma_m_s
        self.pairs_used = 0
        self.segments_used = 0
        self.segments_rejected = 0
        self._t_theta: float | None = None  # time of the last straight-leg update (current walk)
        self._fix: tuple[float, np.ndarray, float] | None = None  # (t, NE, σ)
        # Σ R_nd v_m Δt since the last fix (n frame, N/E, m) and Σ H(d) θ̂ at the time (the
        # correction the filter applied): Python floats, added to per DVL sample (the same
        # IEEE additions as the (2,) arrays they were, without numpy's per-call cost)
        self._track_n = self._track_e = 0.0
        self._applied_n = self._applied_e = 0.0
        self._covered_s = 0.0
        self._last_t: float | None = None
        self._last_vel_ne: tuple[float, float] | None = None  # the last sample's N/E velocity (m/s)
        self._cov_ne_memo: tuple | None = None  # (track N, track E, P, position_cov_ne's floats, its array)

    def report(self) -> dict:
        """Estimate and 1-σ: scale (–), yaw misalignment (deg), fix pairs and straight-leg
        segments used, and whether anything but the prior is known (``"estimated"``;
        ``"prior"``: neither a fix pair nor a straight leg informed it, so the DVL navigated
        uncalibrated and the published covariance carries the prior's σ)."""
        sd = np.sqrt(np.diag(self.P))
        return {"scale_factor_error": float(self.theta[0]), "scale_sigma": float(sd[0]),
                "misalignment_deg": float(np.degrees(self.theta[1])),
                "misalignment_sigma_deg": float(np.degrees(sd[1])), "pairs_used": self.pairs_used,
                "straight_segments_used": self.segments_used,
                "straight_segments_rejected": self.segments_rejected,
                "status": "estimated" if self.pairs_used or self.segments_used else "prior"}

    def position_cov_ne(self, copy: bool = True) -> np.ndarray:
        """(2, 2) m²: what the scale and misalignment still unknown (their σ, ``P``) make of the
        DVL's track since the last fix, ``H P Hᵀ`` with ``H = ∂(Δp − D)/∂(s, ψ)``, plus ``k kᵀ``
        for the known part ``k = H θ̂ − Σ H(d) θ̂_then`` (the earlier track corrected with an
        older estimate).

        The filter fuses the corrected DVL as if (s, ψ) were exact, so its position covariance
        misses this correlated error (0.3 % and 0.4° leave ±1–2 m along and across a 345 m leg
        of dvl_outage, where the filter said σ 0.3–0.6 m: NEES north 15–20 on its own); the
        published covariance adds it (a *consider* covariance: Schmidt 1966; Groves 2013 §3.4.3).
        Zero before the first fix (the track is counted from a fix). ``copy=False``: the array
        kept (read-only).
        """
        if self._fix is None:
            return np.zeros((2, 2)) if copy else _ZERO22
        memo = self._cov_ne_memo_now()
        cov = memo[4]
        if cov is None:  # the array made when asked for (the published states and pings want the floats)
            cov = np.array(memo[3]).reshape(2, 2)
            cov.setflags(write=False)
            self._cov_ne_memo = memo[:4] + (cov,)
        return cov.copy() if copy else cov

    def position_cov_ne_values(self) -> tuple[float, float, float, float]:
        """:meth:`position_cov_ne` as Python floats, row by row (``c_nn, c_ne, c_en, c_ee``): for
        the callers that add it to every published state and side-scan ping — four scalar
        additions cost a third of a 2 × 2 slice's in-place add (~6 µs of an output epoch in a
        replay)."""
        if self._fix is None:
            return _ZERO4
        return self._cov_ne_memo_now()[3]

    def _cov_ne_memo_now(self) -> tuple:
        """The memo of :meth:`position_cov_ne` for the current track and ``P``: ``(d0, d1, P,
        cov as four floats, cov (2, 2) read-only or None until asked for)``."""
        d0, d1 = self._track_n, self._track_e
        # asked with every published state and side-scan ping, changed by DVL samples and fixes
        # only: kept with what it was computed from (P is replaced, never changed in place; the
        # reference kept means a new P cannot take its identity)
        memo = self._cov_ne_memo
        P = self.P
        if memo is None or memo[0] != d0 or memo[1] != d1 or memo[2] is not P:
            # H = [[−d0, −d1], [−d1, d0]]; H θ̂ and H P Hᵀ written out on floats (the track changes
            # with every DVL sample, so the memo misses every other epoch: numpy's 2 × 2 products
            # and arrays were ~6 µs of it; the same sums, to the last bits)
            (p00, p01), (p10, p11) = P[:2, :2].tolist()
            s, psi = self.theta.tolist()[:2]
            k0 = -d0 * s - d1 * psi - self._applied_n
            k1 = -d1 * s + d0 * psi - self._applied_e
            a00, a01 = -d0 * p00 - d1 * p10, -d0 * p01 - d1 * p11  # H P
            a10, a11 = -d1 * p00 + d0 * p10, -d1 * p01 + d0 * p11
            values = (-a00 * d0 - a01 * d1 + k0 * k0, -a00 * d1 + a01 * d0 + k0 * k1,
                      -a10 * d0 - a11 * d1 + k1 * k0, -a10 * d1 + a11 * d0 + k1 * k1)
            memo = self._cov_ne_memo = (d0, d1, P, values, None)
        return memo

    def correct(self, vel_d_m_s) -> tuple[float, float, float]:
        """The measured head velocity with the estimated scale and misalignment removed
        (floats: :func:`measure` takes them as the measurement)."""
        theta = self.theta
        return correct_velocity(vel_d_m_s, float(theta[0]), float(theta[1]))

    def on_dvl(self, t_s: float, vel_n_m_s) -> None:
        """A DVL sample at ``t_s``: its *uncorrected* velocity rotated to n (None: no lock).

        The track integrates the trapezoid between consecutive samples with lock, across
        short drop-outs (≤ ``_BRIDGE_S``); longer gaps count against the interval's coverage.
        """
        if vel_n_m_s is None or self._fix is None or (self._last_t is not None and t_s <= self._last_t):
            return  # no lock, before the first fix, or re-fused history (late measurements)
        v0, v1 = float(vel_n_m_s[0]), float(vel_n_m_s[1])
        if self._last_t is not None:
            dt = t_s - self._last_t
            if dt <= self._BRIDGE_S:
                l0, l1 = self._last_vel_ne
                self._add_track(0.5 * (l0 + v0) * dt, 0.5 * (l1 + v1) * dt)
                self._covered_s += dt
        self._last_t = t_s
        self._last_vel_ne = (v0, v1)

    def _add_track(self, d0: float, d1: float) -> None:
        """``d`` (m, N/E) onto the track, and what the current estimate corrected of it."""
        self._track_n += d0
        self._track_e += d1
        theta = self.theta
        s, psi = float(theta[0]), float(theta[1])
        self._applied_n += -s * d0 - psi * d1
        self._applied_e += -s * d1 + psi * d0

    def on_straight(self, t_s: float, forward_m_s: float, lateral_m_s: float, heading_rad: float,
                    current_along_m_s: float = 0.0) -> None:
        """A bottom-track sample in the heading-aligned level frame (uncorrected), with the
        filter's current along the heading; updates ``ψ`` and the current when it closes a
        straight-leg segment.

        Two scalar rows per segment: the lateral mean (above), and the filter's along-heading
        current ``(cos h̄, sin h̄)·c = c∥`` (σ ``along_current_sigma_m_s``). The second pins the
        current's component that the lateral rows barely see: on a lawnmower the vehicle
        heads a few degrees into a cross current (−3° and −177° on dvl_outage's north-south
        legs), so the along-leg current enters both legs' lateral rows with the same sign, as
        ψ does (0.05 c_N against 1.5 ψ: a current prior of 0.5 m/s would leave ψ at ±1°). The
        filter's along-track current is the DVL's speed against the motion model's — the
        misalignment does not enter it (to first order it is across the track).
        """
        if self.straight_legs is None:
            return
        seg = self.straight_legs.add(t_s, forward_m_s, lateral_m_s, heading_rad, current_along_m_s)
        if seg is None:
            return
        P = self.P.copy()
        if self._t_theta is not None and seg.t_s > self._t_theta:
            P[2:, 2:] += np.eye(2) * self.current_rw_m_s_rthz**2 * (seg.t_s - self._t_theta)
        self._t_theta = seg.t_s
        P_walked = P
        ch, sh = math.cos(seg.heading_rad), math.sin(seg.heading_rad)
        theta = self.theta
        H = np.array([0.0, 0.0, ch, sh])  # the filter's along-heading current
        K = P @ H / (float(H @ P @ H) + self.along_current_sigma_m_s**2)
        theta = theta + K * (seg.current_along_m_s - float(H @ theta))
        P = P - np.outer(K, H @ P)
        H = np.array([0.0, -seg.forward_m_s, -sh, ch])  # the lateral mean
        y = seg.lateral_m_s - float(H @ theta)
        S = float(H @ P @ H) + seg.lateral_var + self.hull_sway_sigma_m_s**2
        if y * y / S > self._GATE:
            self.segments_rejected += 1
            self.P = P_walked  # the segment says nothing, but the current walked meanwhile
            return
        K = P @ H / S
        self.theta = theta + K * y
        P = P - np.outer(K, H @ P)
        self.P = 0.5 * (P + P.T)
        self.segments_used += 1

    def on_fix(self, t_s: float, ne_m: np.ndarray, sigma_m: float) -> None:
        """An absolute horizontal fix: closes the interval since the previous one."""
        ne = np.asarray(ne_m, dtype=float)
        if self._fix is not None and t_s <= self._fix[0]:
            return
        bridged = self._last_t is not None and 0.0 <= t_s - self._last_t <= self._BRIDGE_S
        if bridged:  # carry the track from the last sample up to the fix's time
            l0, l1 = self._last_vel_ne
            dt = t_s - self._last_t
            self._add_track(l0 * dt, l1 * dt)
            self._covered_s += t_s - self._last_t
        if self._fix is not None:
            t0, ne0, s0 = self._fix
            span = t_s - t0
            D = np.array([self._track_n, self._track_e])
            if (span > 0 and self._covered_s >= (1.0 - self.max_gap_fraction) * span
                    and np.hypot(*D) >= self.min_track_m):
                H = np.zeros((2, 4))
                H[:, :2] = [[-D[0], -D[1]], [-D[1], D[0]]]
                y = (ne - ne0) - D - H @ self.theta
                R = np.eye(2) * (sigma_m**2 + s0**2)
                S = H @ self.P @ H.T + R
                K = self.P @ H.T @ np.linalg.inv(S)
                if float(y @ np.linalg.solve(S, y)) < 25.0:  # a wild fix says nothing about the DVL
                    self.theta = self.theta + K @ y
                    self.P = (np.eye(4) - K @ H) @ self.P
                    self.P = 0.5 * (self.P + self.P.T)
                    self.pairs_used += 1
        self._fix = (t_s, ne, sigma_m)
        self._track_n = self._track_e = 0.0
        self._applied_n = self._applied_e = 0.0
        self._covered_s = 0.0
        if bridged:  # the next interval starts at the fix
            self._last_t = t_s


_ZERO4 = (0.0, 0.0, 0.0, 0.0)
_ZERO22 = np.zeros((2, 2))
_ZERO22.setflags(write=False)


def correct_velocity(vel_d_m_s, scale_factor_error: float, misalignment_rad: float) -> tuple[float, float, float]:
    """A head velocity with a scale factor error and yaw misalignment removed:
    ``R_z(ψ) v_m / (1 + s)`` (floats: the calibrator corrects every DVL sample with it)."""
    x, y, z = (float(v) for v in vel_d_m_s)
    k = 1.0 / (1.0 + scale_factor_error)
    c, s = math.cos(misalignment_rad) * k, math.sin(misalignment_rad) * k
    return (c * x - s * y, s * x + c * y, z * k)


def rotation_db(rotation_bd_rpy_rad) -> np.ndarray:
    """``R_db`` (3×3) from the mounting roll/pitch/yaw of the DVL head in the body."""
    return quat_to_dcm(euler_to_quat(*rotation_bd_rpy_rad)).T


def predict(x, omega_b_rad_s, lever_arm_b_m, R_db) -> np.ndarray:
    v_b = dcm(x).T @ x[X_VEL] + np.cross(omega_b_rad_s, lever_arm_b_m)
    return R_db @ v_b


def jacobian(x, lever_arm_b_m, R_db) -> np.ndarray:
    R = dcm(x)
    H = np.zeros((3, N_ERR))
    H[:, VEL] = R_db @ R.T
    H[:, ATT] = R_db @ R.T @ skew(x[X_VEL])
    H[:, BG] = R_db @ skew(lever_arm_b_m)
    return H


def measure_water_track(vel_d_m_s, x, omega_b_rad_s, lever_arm_b_m, R_db, sigma_m_s) -> Measurement:
    """Water-track velocity (relative to the water: over ground minus the current)."""
    lever = np.asarray(lever_arm_b_m, dtype=float)
    R = dcm(x)
    rel = x[X_VEL].copy()
    rel[:2] -= x[X_CUR]
    A = R_db @ R.T
    H = np.zeros((3, N_ERR))
    H[:, VEL] = A
    H[:, ATT] = A @ skew(rel)
    H[:, BG] = R_db @ skew(lever)
    H[:, CUR] = -A[:, :2]
    h = A @ rel + R_db @ np.cross(np.asarray(omega_b_rad_s, dtype=float), lever)
    return make(vel_d_m_s, H, np.eye(3) * sigma_m_s**2, h)


def measure(sample, x, omega_b_rad_s, lever_arm_b_m, R_db, sigma_m_s, vel_d_m_s=None, *,
            R_nb=None, lever_block=None) -> Measurement | None:
    """``None`` when the DVL reports no bottom lock. ``vel_d_m_s`` replaces the sample's
    velocity (the calibrated one, :meth:`DvlCalibration.correct`). ``R_nb`` (``dcm(x)``) and
    ``lever_block`` (``R_db [l]×``, :func:`lever_block`) when the caller has them: the same
    numbers, computed once (a DVL sample every 0.2 s; :class:`DvlSetup` keeps the block)."""
    if not sample.valid:
        return None
    if sample.sigma_m_s > sigma_m_s:  # the sensor says it is worse than configured (NaN: not said)
        sigma_m_s = sample.sigma_m_s
    lever = np.asarray(lever_arm_b_m, dtype=float)
    # jacobian() and predict() from one R_nb, with the same operations on the same floats
    # (R_db R_nbᵀ once; ω × l written out as np.cross computes it: a product difference per
    # component — np.cross on two 3-vectors costs more than the rest of this function)
    R = dcm(x) if R_nb is None else R_nb
    vel = x[X_VEL]
    A = R_db @ R.T
    H = np.zeros((3, N_ERR))
    H[:, VEL] = A
    H[:, ATT] = A @ skew(vel.tolist())  # (skew of floats: the same matrix, without numpy scalars)
    H[:, BG] = lever_block_of(lever, R_db) if lever_block is None else lever_block
    o0, o1, o2 = np.asarray(omega_b_rad_s, dtype=float).tolist()
    l0, l1, l2 = lever.tolist()
    v_b = R.T @ vel + np.array([o1 * l2 - o2 * l1, o2 * l0 - o0 * l2, o0 * l1 - o1 * l0])
    z = sample.vel_d_m_s if vel_d_m_s is None else vel_d_m_s
    # make()'s conversions written out (z the only one not already a float array of its shape)
    return Measurement(np.array(z, dtype=float), H, _EYE3 * sigma_m_s**2, R_db @ v_b, NOT_ANGULAR[3])


_EYE3 = np.eye(3)
_EYE3.setflags(write=False)


def lever_block_of(lever_arm_b_m, R_db) -> np.ndarray:
    """``R_db [l]×`` (3, 3): the Jacobian's gyro-bias block, constant for an installation."""
    return R_db @ skew(np.asarray(lever_arm_b_m, dtype=float))


class DvlSetup(NamedTuple):
    """What the estimator keeps for its DVL: lever arm ``l_b`` (3,) m, ``R_db`` (3, 3), the
    scale/misalignment estimate (None when ``scale_sigma`` and ``misalignment_sigma_rad``
    are 0) and ``R_db [l]×`` of that arm (:func:`lever_block_of`; :meth:`with_lever` keeps
    the two together)."""

    lever_b: np.ndarray
    R_db: np.ndarray
    calibration: DvlCalibration | None
    lever_block: np.ndarray | None = None

    def with_lever(self, lever_b: np.ndarray) -> "DvlSetup":
        """The setup at another lever arm (the filter navigates the IMU, not the reference point)."""
        return self._replace(lever_b=lever_b, lever_block=lever_block_of(lever_b, self.R_db))


def _setup(config: DvlConfig) -> DvlSetup:
    cal = None
    if config.scale_sigma > 0 or config.misalignment_sigma_rad > 0:
        # "auto" not resolved by a service (a library user): the default vehicle, a torpedo AUV
        legs = StraightLegs() if config.hull_sideslip in ("none", "auto") else None
        cal = DvlCalibration(config.scale_sigma, config.misalignment_sigma_rad, straight_legs=legs,
                             hull_sway_sigma_m_s=config.hull_sway_sigma_m_s)
    return DvlSetup(np.asarray(config.lever_arm_b_m, dtype=float), rotation_db(config.rotation_bd_rpy_rad),
                    cal).with_lever(np.asarray(config.lever_arm_b_m, dtype=float))


def _measure(sample, ctx: AidContext) -> Measurement | str:
    """Bottom or water track, corrected with the calibrated scale and misalignment; a
    rejection reason when there is nothing to fuse. The estimator's general path and its
    compiled one (:meth:`adaptnav.fusion.eskf.Estimator._fast_dvl`) both measure with this."""
    c = ctx.config
    lever_b, R_db, cal, block = ctx.setup
    if not sample.valid:
        if cal is not None:
            cal.on_dvl(sample.t_s, None)
        return "invalid"
    vel_d = np.asarray(sample.vel_d_m_s, dtype=float)
    if getattr(sample, "water_track", False):
        if not c.water_track:
            return "water_track_off"
        z = cal.correct(vel_d) if cal is not None else vel_d
        return measure_water_track(z, ctx.x, ctx.omega_b_rad_s, lever_b, R_db, c.water_track_sigma_m_s)
    return bottom_track(sample, ctx.x, ctx.omega_b_rad_s, c, ctx.setup)


def bottom_track(sample, x, omega_b_rad_s, config: DvlConfig, setup: DvlSetup) -> Measurement:
    """A bottom-track sample with lock: the calibration fed (:meth:`DvlCalibration.on_dvl`,
    :meth:`DvlCalibration.on_straight`) and the measurement of :func:`measure`, corrected
    (:meth:`DvlCalibration.correct`), with the lever arm's doubt (:func:`lever_arm_doubt`).

    The numbers come from one compiled call (:func:`adaptnav.fusion.kalman.dvl_bottom_track_core`:
    the same sums, without BLAS's fused multiply-adds, so the last bits may differ from
    :func:`measure`'s): the numpy glue it replaces was ~40 µs per sample, 2/3 of the DVL's
    cost in a replay (a sample every 0.2 s). The estimator's general path measures with this,
    its compiled one with :func:`bottom_track_into` (into its own arrays; the same kernel, also
    here: the kernel a replay's warm-up sees, so the rare general path never compiles one just
    in time), on a core array of ``x`` and ``ω̂_b`` and a scratch of this call's own."""
    core = np.zeros(CORE_SIZE)
    core[CORE_X] = x
    core[CORE_ACC][ACC_OMEGA] = omega_b_rad_s
    work = np.zeros(WORK_SIZE)
    bottom_track_into(sample, core, work, packed_setup(setup), config, setup)
    return work_measurement(work)


def _model_inputs(sample, config: DvlConfig, cal: DvlCalibration | None) -> tuple:
    """What the bottom-track kernels take besides the state: the head's velocity, the σ (the
    sensor's when it says it is worse than configured; NaN: not said), and the calibration's
    estimate (None without one) with its scale and misalignment (0 without)."""
    sigma_m_s = config.sigma_m_s
    if sample.sigma_m_s > sigma_m_s:
        sigma_m_s = sample.sigma_m_s
    v0, v1, v2 = sample.vel_d_m_s
    theta = None
    s_err = psi = 0.0
    if cal is not None:
        theta = cal.theta
        s_err, psi = theta.tolist()[:2]
    return v0, v1, v2, sigma_m_s, theta, s_err, psi


def _calibrate(sample, cal: DvlCalibration, theta: np.ndarray, aux) -> tuple | None:
    """The calibration fed with a bottom-track sample (``aux``: the kernel's six numbers); the
    velocity corrected anew when a straight-leg segment updated ``(s, ψ)`` (``theta`` the
    estimate the model was corrected with), else None."""
    vn, ve, forward, lateral, heading, current_along = aux
    cal.on_dvl(sample.t_s, (vn, ve))
    if cal.straight_legs is not None:
        # the lever arm's ω × l is left in: a segment's mean yaw rate is ≤ 5°/min
        # (StraightLegs), 0.7 mm/s at 0.5 m
        cal.on_straight(sample.t_s, forward, lateral, heading, current_along)
    z = cal.correct(sample.vel_d_m_s) if cal.theta is not theta else None  # a segment updated (s, ψ)
    # the published covariance's consider term of the new track, made here (the memo the
    # next output epoch reads): live, the ~100 bytecodes of its miss leave the epoch's path
    cal.position_cov_ne_values()
    return z


def bottom_track_into(sample, core: np.ndarray, work: np.ndarray, consts: np.ndarray, config: DvlConfig,
                      setup: DvlSetup) -> None:
    """:func:`bottom_track` of the state in the estimator's ``core`` array, its model written into
    the estimator's scratch ``work`` (``kalman.WORK_DVL_*``: :func:`work_measurement`'s views),
    with the installation ``consts`` (:func:`packed_setup` of ``setup``): the same numbers and
    the same calls of the calibration, by one compiled call of three arrays
    (:func:`adaptnav.fusion.kalman.dvl_bottom_track_core`) and no new array (the estimator's
    compiled DVL path, :meth:`adaptnav.fusion.eskf.Estimator._fast_dvl`).

    The kernel is called without its argument guard: ``core``, ``work`` and ``consts`` must be
    C-contiguous, writeable float64 arrays of ``kalman.CORE_SIZE``, ``kalman.WORK_SIZE`` and
    ``kalman.DVL_CONST_SIZE`` made by the caller (``np.zeros``, :func:`packed_setup`), never an
    array from outside (every caller's: the estimator's core and scratch, :func:`bottom_track`'s
    own)."""
    cal = setup.calibration
    v0, v1, v2, sigma_m_s, theta, s_err, psi = _model_inputs(sample, config, cal)
    aux = _bottom_track_core(core, consts, work, float(v0), float(v1), float(v2), s_err, psi,
                             float(sigma_m_s), float(config.lever_arm_sigma_m))
    z = sample.vel_d_m_s if cal is None else _calibrate(sample, cal, theta, aux)
    if z is not None:  # (as bottom_track's np.array of it)
        work[WORK_DVL_Z:WORK_DVL_Z + 3] = z


def work_measurement(work: np.ndarray) -> Measurement:
    """The :class:`Measurement` whose arrays are views of the estimator's scratch ``work``,
    where :func:`bottom_track_into` writes the model."""
    return Measurement(work[WORK_DVL_Z:WORK_DVL_Z + 3], work[WORK_DVL_H:WORK_DVL_H + 3 * N_ERR].reshape(3, N_ERR),
                       work[WORK_DVL_R:WORK_DVL_R + 9].reshape(3, 3), work[WORK_DVL_SMALL_H:WORK_DVL_SMALL_H + 3],
                       NOT_ANGULAR[3])


def packed_setup(setup: DvlSetup) -> np.ndarray:
    """``setup``'s lever arm, ``R_db`` and ``R_db [l]×`` in one array (``kalman.DVL_CONST_SIZE``),
    as :func:`bottom_track_into` hands them to its kernel."""
    block = lever_block_of(setup.lever_b, setup.R_db) if setup.lever_block is None else setup.lever_block
    return np.concatenate([np.asarray(setup.lever_b, dtype=float).ravel(), np.asarray(setup.R_db, dtype=float).ravel(),
                           np.asarray(block, dtype=float).ravel()])


def lever_arm_doubt(omega_b_rad_s, lever_arm_sigma_m: float, R_db: np.ndarray) -> np.ndarray:
    """Covariance (3, 3), (m/s)², the lever arm's own error adds to a DVL velocity: an error
    ``δl`` (1-σ ``lever_arm_sigma_m`` per axis) of the configured arm is a velocity error
    ``ω × δl`` in the head's frame, ``σ² R_db [ω]× [ω]×ᵀ R_dbᵀ``.  Zero on a straight leg; in a
    turn at 0.1 rad/s a 0.5 m arm nobody configured is 5 cm/s of sway, which a DVL fused at its
    straight-leg σ puts into the heading (tests/service/test_auv_navgrade.py: a navigation-grade
    AUV whose DVL sits 0.5 m ahead of the IMU, the log saying nothing of it: lawnmower heading
    0.2–0.3° off after its turns)."""
    W = skew(np.asarray(omega_b_rad_s, dtype=float).tolist())  # (skew of floats: the same matrix, cheaper)
    A = R_db @ W
    return lever_arm_sigma_m**2 * (A @ A.T)


AID = AidSource("dvl", DvlConfig, _measure, setup=_setup)
