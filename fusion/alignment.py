r"""Initial alignment: levelling from the accelerometers at rest, heading from an aid.

At rest the specific force is ``f_b = −R_nbᵀ g_n``, so (Groves 2013 §14.2.1)::

    roll = atan2(−f_y, −f_z),   pitch = atan2(f_x, √(f_y² + f_z²))

averaged over the last ``n_samples`` IMU samples of an unbroken run (no gap larger
than ``imu_gap_s``) whose spread is below ``max_acc_std_m_s2`` (otherwise the vehicle
is not at rest and the window keeps sliding). Heading cannot be observed by a tactical
IMU's gyros (earth rate ≪ gyro noise), so it comes from the first heading/attitude aid.

:class:`Alignment` is what the estimator holds before it starts: the samples that came
before alignment (heading, DVL, position fix, depth) and the state an INS or AHRS-only
start begins from (:class:`Start`); the estimator only applies it.
"""
from __future__ import annotations

import math
import statistics
from collections import deque
from typing import NamedTuple

import numpy as np

from . import imu_grades
from . import strapdown as sd
from .aiding import AIDS
from .aiding import depth as aid_depth
from .aiding.common import dcm
from .config import FilterConfig
from .frames import GeoOrigin, euler_to_quat, quat_from_rotvec, quat_mul, wrap_angle
from .imu_grades import ImuFigures, ResolvedImu
from .state import (ACC_SIZE, ATT_TILT, ATT_YAW, BA, BG, CUR, KS, N_ERR, POS_D, POS_NE, VEL, X_Q,
                    initial_nominal)

# an IMU stream's rate is judged on the median of its latest intervals: robust to a dropped
# sample or a burst, quick to see a stream change
IMU_RATE_WINDOW = 20


def imu_too_slow(recent_intervals_s, min_rate_hz: float) -> bool:
    """Is a stream with these latest sample intervals (s; at most :data:`IMU_RATE_WINDOW`) too
    slow to integrate? (None yet: yes.) One rule for the estimator and the log readers that
    withhold such a stream; called per IMU sample by a reader (``statistics.median`` of 20
    floats: a few µs, numpy's several times that)."""
    # 10 % of slack: a stream right at the threshold, with jitter, is not judged sample by
    # sample one way and the other (the reader withholding some, the estimator then seeing gaps)
    return not recent_intervals_s or statistics.median(recent_intervals_s) > 1.1 / min_rate_hz


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


def initial_covariance(config: FilterConfig, imu: ImuFigures, sigma_pos_h_m: float,
                       sigma_depth_m: float) -> np.ndarray:
    """The error-state covariance (18×18) a filter starts from: horizontal and vertical
    position σ (m) as given, the rest from ``config.initial`` and the IMU's bias σs."""
    c = config
    d = np.zeros(N_ERR)
    d[POS_NE] = sigma_pos_h_m ** 2
    d[POS_D] = sigma_depth_m ** 2
    d[VEL] = c.initial.sigma_vel_m_s ** 2
    d[ATT_TILT] = c.initial.sigma_att_rad ** 2
    d[ATT_YAW] = c.initial.sigma_yaw_rad ** 2
    d[BA] = imu.acc_bias_sigma_m_s2 ** 2
    d[BG] = imu.gyro_bias_sigma_rad_s ** 2
    d[CUR] = c.initial.sigma_current_m_s ** 2
    d[KS] = c.initial.sigma_k_speed ** 2
    return np.diag(d)


class Start(NamedTuple):
    """The state a filter starts from: nominal ``x`` (19,) and covariance ``P`` (18, 18) at
    ``t_s``; for an INS start also the IMU model decided at rest and the latitude of the
    earth model (``None``: flat, non-rotating; :func:`adaptnav.fusion.strapdown.set_earth`)."""

    t_s: float
    x: np.ndarray
    P: np.ndarray
    imu_model: ResolvedImu | None = None
    earth_lat_rad: float | None = None


class Alignment:
    """What the estimator gathers before it starts, and the state it starts from.

    Before alignment every aid sample is kept here (:meth:`observe`): the latest heading
    (or the autopilot's attitude once its yaw has settled), the latest bottom-locked DVL
    sample (a moving start), the latest position fix and depth (the initial position);
    IMU samples fill the levelling window (:meth:`add_imu`). :meth:`ins_start` gives the
    INS start once the window is at rest and a heading is known; :meth:`ahrs_start` the
    AHRS-only start when no usable IMU comes. A restart's persisted position
    (:attr:`saved_pos`) is the initial position when no fix came.

    Parameters
    ----------
    config : FilterConfig
    origin : GeoOrigin
        Mission origin (fixes are geodetic).
    R_db : numpy.ndarray
        (3, 3) DVL head → body rotation of the DVL aid's setup (a moving start's velocity).
    """

    def __init__(self, config: FilterConfig, origin: GeoOrigin, R_db: np.ndarray):
        self.config = config
        self.origin = origin
        self._R_db = R_db
        self.aligner = self._new_aligner()
        self._imu_dt_s: deque = deque(maxlen=IMU_RATE_WINDOW)  # recent IMU intervals before INS mode
        self.yaw_rad: float | None = None
        self._att_yaw: deque = deque()  # (t_s, yaw) of recent attitude samples
        self._t_first_att = math.nan
        self._t_att: deque = deque(maxlen=21)  # times of the latest attitude samples
        self._dvl = None  # latest bottom-locked DVL sample (velocity seed)
        self._fix: tuple[np.ndarray, float] | None = None  # (NE m, σ m)
        # that fix is a radio fix taken before any depth: void once the depth says under water
        self._fix_gnss = False
        self._depth_m: float | None = None
        # (t_s, (north, east) m, σ m) of that fix: where later fixes must be reachable from
        self.first_fix: tuple[float, tuple[float, float], float] | None = None
        # the last position of an earlier run (Estimator.restore_slow_states): (t_s, pos_n (3),
        # var (3), time known to have passed since, s)
        self.saved_pos: tuple[float, np.ndarray, np.ndarray, float] | None = None
        # whether the latest initial_position() came from a fix or a saved state (else the
        # origin, a guess of initial.sigma_pos_m)
        self.position_known = False

    def _new_aligner(self) -> Aligner:
        a = self.config.alignment
        return Aligner(a.n_samples, a.max_acc_std_m_s2, self.config.imu_gap_s)

    def restart_levelling(self) -> None:
        """An empty levelling window (the filter starts over from scratch)."""
        self.aligner = self._new_aligner()

    def add_imu(self, t_s: np.ndarray, f_b_m_s2: np.ndarray, w_b_rad_s: np.ndarray,
                t_imu_last_s: float) -> None:
        """Clean IMU samples (N,), (N, 3), (N, 3) into the levelling window; ``t_imu_last_s``
        the previous sample's time (the interval says whether the IMU is fast enough)."""
        dt = np.diff(np.concatenate(([t_imu_last_s], t_s)))
        self._imu_dt_s.extend(dt[np.isfinite(dt) & (dt > 0)][-IMU_RATE_WINDOW:].tolist())
        self.aligner.add(t_s, f_b_m_s2, w_b_rad_s)

    def imu_fast_enough(self) -> bool:
        """Is the IMU stream fast enough to integrate (``alignment.min_imu_rate_hz``)?"""
        return not imu_too_slow(self._imu_dt_s, self.config.alignment.min_imu_rate_hz)

    def carry_over(self, yaw_rad: float, depth_m: float,
                   position: tuple[np.ndarray, float] | None = None) -> None:
        """Heading and depth of the AHRS (or attitude-driven) mode for the INS alignment that
        replaces it; ``position``: its horizontal position (NE, m) and σ (m), when it had one."""
        self.yaw_rad = yaw_rad
        self._depth_m = depth_m
        if position is not None:
            self._fix, self._fix_gnss = (np.asarray(position[0], dtype=float), float(position[1])), False

    def attitude_rate_hz(self) -> float:
        """The latest attitude samples' rate (Hz, from their median interval; nan: fewer than two)."""
        dt = np.diff(np.asarray(self._t_att))
        dt = dt[dt > 0]
        return 1.0 / float(np.median(dt)) if dt.size else math.nan

    def _settled_yaw(self, t_s: float, yaw_rad: float) -> float | None:
        """The autopilot's yaw once it has stayed within ``yaw_settle_tol_rad`` for
        ``yaw_settle_s`` (ArduSub sends 0, its DCM yaw, 0 again, then the EKF's), else None."""
        a = self.config.alignment
        hist = self._att_yaw
        hist.append((t_s, yaw_rad))
        while len(hist) > 2 and hist[1][0] <= t_s - a.yaw_settle_s:
            hist.popleft()
        if t_s - hist[0][0] < a.yaw_settle_s - 1e-9:
            return None
        if max(abs(float(wrap_angle(y - yaw_rad))) for _, y in hist) > a.yaw_settle_tol_rad:
            return None
        return yaw_rad

    def observe(self, sample, t_imu_last_s: float) -> str:
        """Keep an aid sample that came before alignment (finite, of an aid kind).

        Returns what the estimator must do besides answering ``not_initialized``:
        ``"ahrs"`` start in AHRS mode now (attitude samples and no usable IMU for
        ``alignment.ahrs_after_s``; ``t_imu_last_s`` the latest IMU sample's time),
        ``"surface_only"`` reject (a radio fix under water), ``"fix"`` a fix became the
        initial position (:attr:`first_fix`), ``"fix_void"`` the initial fix is void (a radio
        fix before the first depth, which says under water), else ``""``.
        """
        cfg = self.config
        kind = sample.KIND
        if kind == "heading":
            self.yaw_rad = sample.yaw_rad
        elif kind == "attitude":
            self.yaw_rad = self._settled_yaw(sample.t_s, sample.yaw_rad)
            if math.isnan(self._t_first_att):
                self._t_first_att = sample.t_s
            self._t_att.append(float(sample.t_s))
            # no IMU, or one too slow to integrate (ArduSub telemetry: 2 Hz), for a while
            # (an ATTITUDE may come just before the first IMU sample): AHRS mode
            slow_imu = sample.t_s - t_imu_last_s > cfg.imu_gap_s or not self.imu_fast_enough()
            if slow_imu and sample.t_s - self._t_first_att >= cfg.alignment.ahrs_after_s:
                return "ahrs"
        elif kind == "dvl":
            bottom = sample.valid and not getattr(sample, "water_track", False)
            self._dvl = sample if bottom else self._dvl
        elif kind == "gnss" and self._depth_m is not None and self._depth_m >= cfg.gnss.max_depth_m:
            # a radio fix below the surface is no position (a simulator keeps its fix under
            # water): as after alignment (aiding.gnss), it does not seed the position either
            return "surface_only"
        elif AIDS[kind].absolute_position:
            ned = self.origin.to_ned(sample.lat_rad, sample.lon_rad)
            self._fix = (ned[:2], sample.sigma_h_m)
            self._fix_gnss = kind == "gnss" and self._depth_m is None
            self.first_fix = (float(sample.t_s), (float(ned[0]), float(ned[1])), float(sample.sigma_h_m))
            return "fix"
        elif kind == "depth":
            self._depth_m = float(aid_depth.pressure_to_depth(
                sample.pressure_pa, cfg.depth.water_density_kg_m3, cfg.depth.atmospheric_pressure_pa))
            if self._fix_gnss and self._depth_m >= cfg.gnss.max_depth_m:
                self._fix, self._fix_gnss = None, False  # came before the first depth
                self.first_fix = None
                return "fix_void"
        return ""

    def initial_position(self, t_s: float) -> tuple[np.ndarray, float, float]:
        """Initial position (3, m) and its horizontal and vertical σ (m) at state time ``t_s``:
        the latest fix; else the position an earlier run persisted (a restart), its σ grown by
        what the vehicle can have moved since — ``position_reset_max_speed_m_s`` × elapsed
        time taken as the 3σ bound, elapsed the longer of the data clock's and
        ``pos_min_elapsed_s`` — (only on the same clock, data time not gone back, and within
        1 h); else the origin (σ ``initial.sigma_pos_m``). Depth from the latest pressure."""
        pos = np.zeros(3)
        sigma_h = self.config.initial.sigma_pos_m
        sigma_d = self.config.initial.sigma_pos_m
        saved = self.saved_pos
        self.position_known = True
        if self._fix is not None:
            pos[:2], sigma_h = self._fix
        elif saved is not None and 0.0 <= t_s - saved[0] and max(t_s - saved[0], saved[3]) <= 3600.0:
            moved = self.config.position_reset_max_speed_m_s * max(t_s - saved[0], saved[3]) / 3.0
            pos[:] = saved[1]
            sigma_h = math.sqrt(float(max(saved[2][0], saved[2][1])) + moved**2)
            sigma_d = math.sqrt(float(saved[2][2]) + moved**2)
        else:
            self.position_known = False
        if self._depth_m is not None:
            pos[2], sigma_d = self._depth_m, self.config.depth.sigma_m
        return pos, sigma_h, sigma_d

    def ahrs_start(self, sample, imu_model: ResolvedImu) -> Start:
        """No usable IMU: attitude from the AHRS ``sample``, depth from pressure, position
        from :meth:`initial_position`, at rest; the covariance with ``imu_model``'s biases."""
        pos, sigma_h, sigma_d = self.initial_position(sample.t_s)
        q = euler_to_quat(sample.roll_rad, sample.pitch_rad, sample.yaw_rad)
        x = initial_nominal(pos, (0.0, 0.0, 0.0), q)
        return Start(float(sample.t_s), x, initial_covariance(self.config, imu_model.figures, sigma_h, sigma_d))

    def ins_start(self, imu_source: str = "") -> Start | None:
        """The INS start once the levelling window is at rest and a heading is known, else None.

        Levelled from the window, heading from the aid; the IMU model is the configured
        grade's or decided from the window and who measured it (``imu.grade = "auto"``,
        ``imu_source``: :attr:`adaptnav.fusion.samples.ImuSample.source`); velocity zero or, a
        moving start, the DVL's if its latest sample is at most 1 s old. The attitude is
        turned from the local plumb line into the origin's tangent axes when the earth
        model is on (:func:`adaptnav.fusion.strapdown.plumb_line_rotvec`).
        """
        level = self.aligner.level()
        if level is None or self.yaw_rad is None:
            return None
        if self._t_att and not self.imu_fast_enough():
            return None  # the attitude will drive the strapdown (observe → "ahrs")
        roll, pitch = level
        t_s = self.aligner.t_last_s
        # the IMU model: the configured grade's, or decided from the data at rest (auto)
        imu_model = imu_grades.resolve(self.config.imu, *self.aligner.window(), source=imu_source)
        pos, sigma_h, sigma_d = self.initial_position(t_s)
        q = euler_to_quat(roll, pitch, self.yaw_rad)
        vel = np.zeros(3)
        dvl = self._dvl
        if dvl is not None and t_s - dvl.t_s <= 1.0:
            # a moving start: the DVL's velocity, not zero (no later aid removes that error)
            v_b = self._R_db.T @ np.asarray(dvl.vel_d_m_s, dtype=float)
            vel = dcm(initial_nominal(q_nb=q)) @ v_b
        x = initial_nominal(pos, vel, q)
        P = initial_covariance(self.config, imu_model.figures, sigma_h, sigma_d)
        if dvl is not None and np.any(vel):
            P[VEL, VEL] = np.eye(3) * self.config.dvl.sigma_m_s ** 2 * 4.0
        lat = self.origin.lat_rad if imu_model.earth_rotation else None
        earth = np.zeros(ACC_SIZE)
        sd.set_earth(earth, lat)
        # levelled on the local plumb line: in the tangent plane of the origin that leans by p/R
        x[X_Q] = quat_mul(quat_from_rotvec(sd.plumb_line_rotvec(earth, pos)), x[X_Q])
        return Start(float(t_s), x, P, imu_model, lat)
