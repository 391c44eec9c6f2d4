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
observable from the DVL and the IMU over straight legs; both are from absolute fixes: the
DVL's own track between two fixes, ``D = Σ R_nd v_m Δt``, against the fixes' displacement
``Δp`` gives ``Δp − D ≈ −s D + ψ (e_z × D)`` (horizontal, linear in (s, ψ); the track-to-fix
calibration of Kinsey & Whitcomb, IEEE JOE 31(2), 2006). A two-state Kalman filter with
prior σ (``scale_sigma``, ``misalignment_sigma_rad``) accumulates those pairs; the
measurement is corrected with the current estimate, so without fixes (GNSS at the surface
only) the correction stays at the prior's zero — "estimated where observable".

Through turns the IMU sees them in principle: the DVL's error ``−s v + ψ e_z × v`` turns
with the velocity, so across a reversal at 1.5 m/s a 0.4° misalignment is a 21 mm/s jump
of the DVL against the free-inertial velocity. With the tactical IMU of dvl_outage that
does not pay: the aided filter's free-inertial velocity wanders ±30 mm/s over a lawnmower
turn (60–70 s with its transients), and lines fitted to it on the straights either side of
5 reversals (seed 1) missed the jump by ~80 mm/s RMS — a turn says less than the prior.
What the scale and misalignment cost there (counterfactual runs of the simulator): of the
1.8–2.4 m the filter carries into the outage at minute 29 (seeds 1–3), 0.4° of misalignment
makes ~1.9 m (across the eastward cross legs) and 0.3 % of scale ~0.8 m; the beam biases,
the IMU's errors and the current 0.15–0.3 m each.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ..frames import euler_to_quat, quat_to_dcm
from ..config import DvlConfig
from ..state import ATT, BG, CUR, N_ERR, VEL, X_CUR, X_VEL
from .common import AidContext, AidSource, Measurement, dcm, make, skew


def rotation_z(psi_rad: float) -> np.ndarray:
    c, s = np.cos(psi_rad), np.sin(psi_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


class DvlCalibration:
    """Scale factor ``s`` and yaw misalignment ``ψ`` of the DVL head (module docstring).

    Parameters
    ----------
    scale_sigma : prior 1-σ of ``s`` (–)
    misalignment_sigma_rad : prior 1-σ of ``ψ`` (rad)
    max_gap_fraction : a fix-to-fix interval with more of its time without DVL is not used
    min_track_m : intervals with a shorter DVL track carry too little information
    """

    _BRIDGE_S = 2.0  # drop-outs up to this long are bridged by the trapezoid

    def __init__(self, scale_sigma: float, misalignment_sigma_rad: float,
                 max_gap_fraction: float = 0.2, min_track_m: float = 20.0):
        self.theta = np.zeros(2)  # (s, ψ)
        self.P = np.diag([scale_sigma**2, misalignment_sigma_rad**2])
        self.max_gap_fraction = max_gap_fraction
        self.min_track_m = min_track_m
        self.pairs_used = 0
        self._fix: tuple[float, np.ndarray, float] | None = None  # (t, NE, σ)
        self._track = np.zeros(2)     # Σ R_nd v_m Δt since the last fix (n frame, N/E)
        self._covered_s = 0.0
        self._last_t: float | None = None
        self._last_vel_n: np.ndarray | None = None
        self._cov_ne_memo: tuple | None = None  # ((track N, track E, P), position_cov_ne)

    def report(self) -> dict:
        """Estimate and 1-σ: scale (–), yaw misalignment (deg), fix pairs used, and whether
        anything but the prior is known (``"estimated"``; ``"prior"``: no fix pair closed a DVL
        track, so the DVL navigated uncalibrated and the published covariance carries the
        prior's σ)."""
        sd = np.sqrt(np.diag(self.P))
        return {"scale_factor_error": float(self.theta[0]), "scale_sigma": float(sd[0]),
                "misalignment_deg": float(np.degrees(self.theta[1])),
                "misalignment_sigma_deg": float(np.degrees(sd[1])), "pairs_used": self.pairs_used,
                "status": "estimated" if self.pairs_used else "prior"}

    def position_cov_ne(self) -> np.ndarray:
        """(2, 2) m²: what the scale and misalignment still unknown (their σ, ``P``) make of the
        DVL's track since the last fix, ``H P Hᵀ`` with ``H = ∂(Δp − D)/∂(s, ψ)``.

        The filter fuses the corrected DVL as if (s, ψ) were exact, so its position covariance
        misses this correlated error (0.3 % and 0.4° leave ±1–2 m along and across a 345 m leg
        of dvl_outage, where the filter said σ 0.3–0.6 m: NEES north 15–20 on its own); the
        published covariance adds it (a *consider* covariance: Schmidt 1966; Groves 2013 §3.4.3).
        Zero before the first fix (the track is counted from a fix).
        """
        if self._fix is None:
            return np.zeros((2, 2))
        D = self._track
        # asked with every published state and side-scan ping, changed by DVL samples and fixes
        # only: kept with what it was computed from (P is replaced, never changed in place; the
        # reference kept means a new P cannot take its identity)
        key = (float(D[0]), float(D[1]), self.P)
        memo = self._cov_ne_memo
        if memo is None or memo[0][0] != key[0] or memo[0][1] != key[1] or memo[0][2] is not key[2]:
            H = np.array([[-D[0], -D[1]], [-D[1], D[0]]])
            memo = self._cov_ne_memo = (key, H @ self.P @ H.T)
        return memo[1].copy()

    def correct(self, vel_d_m_s) -> np.ndarray:
        """The measured head velocity with the estimated scale and misalignment removed."""
        return rotation_z(self.theta[1]) @ np.asarray(vel_d_m_s, dtype=float) / (1.0 + self.theta[0])

    def on_dvl(self, t_s: float, vel_n_m_s: np.ndarray | None) -> None:
        """A DVL sample at ``t_s``: its *uncorrected* velocity rotated to n (None: no lock).

        The track integrates the trapezoid between consecutive samples with lock, across
        short drop-outs (≤ ``_BRIDGE_S``); longer gaps count against the interval's coverage.
        """
        if vel_n_m_s is None or self._fix is None or (self._last_t is not None and t_s <= self._last_t):
            return  # no lock, before the first fix, or re-fused history (late measurements)
        v = np.asarray(vel_n_m_s, dtype=float)
        if self._last_t is not None:
            dt = t_s - self._last_t
            if dt <= self._BRIDGE_S:
                self._track += 0.5 * (self._last_vel_n[:2] + v[:2]) * dt
                self._covered_s += dt
        self._last_t = t_s
        self._last_vel_n = v

    def on_fix(self, t_s: float, ne_m: np.ndarray, sigma_m: float) -> None:
        """An absolute horizontal fix: closes the interval since the previous one."""
        ne = np.asarray(ne_m, dtype=float)
        if self._fix is not None and t_s <= self._fix[0]:
            return
        bridged = self._last_t is not None and 0.0 <= t_s - self._last_t <= self._BRIDGE_S
        if bridged:  # carry the track from the last sample up to the fix's time
            self._track += self._last_vel_n[:2] * (t_s - self._last_t)
            self._covered_s += t_s - self._last_t
        if self._fix is not None:
            t0, ne0, s0 = self._fix
            span = t_s - t0
            D = self._track
            if (span > 0 and self._covered_s >= (1.0 - self.max_gap_fraction) * span
                    and np.hypot(*D) >= self.min_track_m):
                H = np.array([[-D[0], -D[1]], [-D[1], D[0]]])
                y = (ne - ne0) - D - H @ self.theta
                R = np.eye(2) * (sigma_m**2 + s0**2)
                S = H @ self.P @ H.T + R
                K = self.P @ H.T @ np.linalg.inv(S)
                if float(y @ np.linalg.solve(S, y)) < 25.0:  # a wild fix says nothing about the DVL
                    self.theta = self.theta + K @ y
                    self.P = (np.eye(2) - K @ H) @ self.P
                    self.P = 0.5 * (self.P + self.P.T)
                    self.pairs_used += 1
        self._fix = (t_s, ne, sigma_m)
        self._track = np.zeros(2)
        self._covered_s = 0.0
        if bridged:  # the next interval starts at the fix
            self._last_t = t_s


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


def measure(sample, x, omega_b_rad_s, lever_arm_b_m, R_db, sigma_m_s, vel_d_m_s=None) -> Measurement | None:
    """``None`` when the DVL reports no bottom lock. ``vel_d_m_s`` replaces the sample's
    velocity (the calibrated one, :meth:`DvlCalibration.correct`)."""
    if not sample.valid:
        return None
    if sample.sigma_m_s > sigma_m_s:  # the sensor says it is worse than configured (NaN: not said)
        sigma_m_s = sample.sigma_m_s
    lever = np.asarray(lever_arm_b_m, dtype=float)
    # jacobian() and predict() from one R_nb, with the same operations on the same floats
    # (R_db R_nbᵀ once; ω × l written out as np.cross computes it: a product difference per
    # component — np.cross on two 3-vectors costs more than the rest of this function)
    R = dcm(x)
    vel = x[X_VEL]
    A = R_db @ R.T
    H = np.zeros((3, N_ERR))
    H[:, VEL] = A
    H[:, ATT] = A @ skew(vel)
    H[:, BG] = R_db @ skew(lever)
    o0, o1, o2 = np.asarray(omega_b_rad_s, dtype=float).tolist()
    l0, l1, l2 = lever.tolist()
    v_b = R.T @ vel + np.array([o1 * l2 - o2 * l1, o2 * l0 - o0 * l2, o0 * l1 - o1 * l0])
    z = sample.vel_d_m_s if vel_d_m_s is None else vel_d_m_s
    return make(z, H, np.eye(3) * sigma_m_s**2, R_db @ v_b)


class DvlSetup(NamedTuple):
    """What the estimator keeps for its DVL: lever arm ``l_b`` (3,) m, ``R_db`` (3, 3) and
    the scale/misalignment estimate (None when ``scale_sigma`` and
    ``misalignment_sigma_rad`` are 0)."""

    lever_b: np.ndarray
    R_db: np.ndarray
    calibration: DvlCalibration | None


def _setup(config: DvlConfig) -> DvlSetup:
    cal = None
    if config.scale_sigma > 0 or config.misalignment_sigma_rad > 0:
        cal = DvlCalibration(config.scale_sigma, config.misalignment_sigma_rad)
    return DvlSetup(np.asarray(config.lever_arm_b_m, dtype=float), rotation_db(config.rotation_bd_rpy_rad), cal)


def _measure(sample, ctx: AidContext) -> Measurement | str:
    """Bottom or water track, corrected with the calibrated scale and misalignment; a
    rejection reason when there is nothing to fuse."""
    c = ctx.config
    lever_b, R_db, cal = ctx.setup
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
    z = None
    if cal is not None:
        cal.on_dvl(sample.t_s, dcm(ctx.x) @ (R_db.T @ vel_d))
        z = cal.correct(vel_d)
    meas = measure(sample, ctx.x, ctx.omega_b_rad_s, lever_b, R_db, c.sigma_m_s, z)
    if meas is None or c.lever_arm_sigma_m <= 0.0:
        return meas
    return meas._replace(R=meas.R + lever_arm_doubt(ctx.omega_b_rad_s, c.lever_arm_sigma_m, R_db))


def lever_arm_doubt(omega_b_rad_s, lever_arm_sigma_m: float, R_db: np.ndarray) -> np.ndarray:
    """Covariance (3, 3), (m/s)², the lever arm's own error adds to a DVL velocity: an error
    ``δl`` (1-σ ``lever_arm_sigma_m`` per axis) of the configured arm is a velocity error
    ``ω × δl`` in the head's frame, ``σ² R_db [ω]× [ω]×ᵀ R_dbᵀ``.  Zero on a straight leg; in a
    turn at 0.1 rad/s a 0.5 m arm nobody configured is 5 cm/s of sway, which a DVL fused at its
    straight-leg σ puts into the heading (tests/service/test_auv_navgrade.py: a navigation-grade
    AUV whose DVL sits 0.5 m ahead of the IMU, the log saying nothing of it: lawnmower heading
    0.2–0.3° off after its turns)."""
    W = skew(np.asarray(omega_b_rad_s, dtype=float))
    A = R_db @ W
    return lever_arm_sigma_m**2 * (A @ A.T)


AID = AidSource("dvl", DvlConfig, _measure, setup=_setup)
