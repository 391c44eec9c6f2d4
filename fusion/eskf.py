r"""Error-state Kalman filter over strapdown INS with model-aided velocity (DESIGN.md "Fusion").

Nominal state, error state and injection: :mod:`adaptnav.fusion.state`; mechanisation and the
earth model: :mod:`adaptnav.fusion.strapdown`; covariance propagation, gated update and error
injection kernels: :mod:`adaptnav.fusion.kalman`; alignment: :mod:`adaptnav.fusion.alignment`;
the adaptive surge variance: :mod:`adaptnav.fusion.adaptive_noise`; measurement models: one module per
source in :mod:`adaptnav.fusion.aiding`. This module does, once for every source (as PX4 EKF2's
``estimator_aid_src_*``): chi-square gating of the normalised innovation, Joseph-form
update, error injection and covariance reset, one :class:`~fusion.status.AidStatus`
per attempt. Depth and heading on time in INS mode (the commonest samples after the IMU's)
take one compiled call for the innovation, update, injection and the state guard
(:meth:`Estimator._fast_scalar`) with their aid modules' own models: the same numbers; the
general path answers whatever else comes (gated, late, not finite, at a lever arm). So does
the DVL's bottom track with lock (:meth:`Estimator._fast_dvl`, three rows), which answers its
gated samples itself (:meth:`Estimator._after_fuse`, shared with the general path).

Model-aided INS after Hegrenaes & Hallingstad (IEEE JOE 2011): the learned motion
model's surge ``k_speed k_V f(rpm)`` (seed §2.1, :mod:`adaptnav.fusion.aiding.learned_velocity`)
is fused at a fixed rate together with sway/heave ≈ 0 pseudo-measurements, against the
water-relative velocity ``R_nbᵀ(v_n − c_n)``; the current ``c_n`` and ``k_speed`` are
states, observable while absolute fixes exist.

Timing. IMU samples (single or :class:`~fusion.samples.ImuBatch`) propagate the state.
A measurement whose time of validity lies within ``on_time_tolerance_s`` of the state
time is fused at once; an older one (up to ``max_delay_s``) is fused at its own time:
the estimator keeps a short history of its inputs with a snapshot of its numeric state
before each, restores the last snapshot before the measurement and re-runs the inputs
since then with the measurement inserted ("buffer IMU and re-propagate"). Older still:
rejected ``too_late``.

Robustness. The surge variance adapts upwards to the innovations (a change of water
makes the released model too tight, :mod:`adaptnav.fusion.adaptive_noise`); an
absolute position source is trusted again after gate rejections by inflating the position
covariance (as PX4 EKF2 resets to GNSS) — only on consistent evidence: several gated fixes
consistent with each other and with the last accepted fix at the vehicle's top speed
(:meth:`Estimator._fuse_position`), so that a spoofer cannot move the solution.

Modes. ``"none"`` until aligned (aids answered ``not_initialized``; the latest
position fix and depth become the initial position, :mod:`adaptnav.fusion.alignment`); ``"ins"`` after levelling from a
static accelerometer window and a heading aid. When attitude samples arrive and the IMU is
absent or too slow to integrate (real ArduSub telemetry at its default stream rates: RAW_IMU
at 2 Hz, ATTITUDE at 10–20 Hz), ``"ins"`` on a virtual IMU made of the attitude's increments
(``[filter.attitude_driven]``, :meth:`Estimator._attitude_step`): the vehicle's accelerations
are process noise, velocity comes from the motion model and a DVL, position from fixes; valid
only while a velocity over ground or a fix measures the motion. With that off, ``"ahrs"``:
attitude from the AHRS, depth from pressure, position a random walk pinned by fixes, never
valid. A fast IMU appearing later re-aligns either into ``"ins"`` on it.

Bad input never raises: non-finite samples, out-of-order or duplicate IMU timestamps
and IMU gaps are counted in :attr:`Estimator.rejected` and the filter keeps going.
"""
from __future__ import annotations

import bisect
import dataclasses
import math
from collections import Counter

import numpy as np

from adaptnav.kernels import unguarded

from . import imu_grades
from . import kalman
from . import strapdown as sd
from .aiding import AIDS, AidContext
from .aiding import attitude as aid_attitude
from .aiding import depth as aid_depth
from .aiding import dvl as aid_dvl
from .aiding import heading as aid_heading
from .aiding import learned_velocity as aid_lv
from .aiding import loop_closure as aid_loop
from .aiding.common import Measurement
from .adaptive_noise import SurgeVariance
from .alignment import Alignment, Start, initial_covariance
from .config import FilterConfig
from .frames import GRAVITY_M_S2, GeoOrigin, euler_to_quat, quat_conj, quat_from_rotvec, quat_mul, quat_to_dcm, \
    rotvec_from_quat
from .integrity import NisMonitor
from .motion_model import MotionParams, RpmSpeedTable
from .samples import (SENSORS, DepthSample, DvlSample, HeadingSample, ImuBatch, ImuSample, InertialVelocitySample,
                      is_finite)
from .state import (ACC_F, ACC_OMEGA, ACC_T, ATT, ATT_TILT, ATT_YAW, BA, BG, CUR, KS, N_ERR, POS, POS_D, POS_NE, SLOW,
                    VEL, X_BA, X_BG, X_CUR, X_DEPTH, X_KS, X_POS, X_POS_NE, X_Q, X_SLOW, X_VEL, NavState, initial_nominal)
from .status import AidStatus, rejected

# Both from the sensor table and the aid registry: an aid-role kind without an aid
# source yet, truth and context kinds are ignored; the aid sources fuse theirs.
IGNORED_KINDS = frozenset(s.kind for s in SENSORS
                          if s.role in ("truth", "context") or (s.role == "aid" and s.kind not in AIDS))
AID_KINDS = frozenset(AIDS)
# Velocity random walk assumed across an IMU gap or in AHRS-only mode (m/s per √s): an
# AUV's speed changes by ~0.5 m/s within seconds when nothing measures it.
_BLIND_VEL_RW_M_S_RTHZ = 0.3
# aids that measure the motion (velocity over ground or position): an attitude-driven strapdown
# without any of them for a while has only the motion model's velocity — a measurement only
# where that model is calibrated (attitude_driven.model_measures_motion), or once fixes or a
# DVL have calibrated its scale in this run (attitude_driven.calibrated_sigma_k_speed)
_MOTION_AIDS = frozenset(("dvl", "visual_motion", "usbl", "gnss", "range", "loop_closure"))
# Attitude random walk without a gyro (AHRS-only mode), rad/√s.
_BLIND_ATT_RW_RAD_RTHZ = 0.3
# A state moving faster than this is broken (no vehicle the filter serves comes near it).
_MAX_SPEED_M_S = 1000.0
# Aid fusions after a recovery (:meth:`Estimator._recover`) before the solution may be
# valid again: a few seconds of learned velocity, depth and heading.
_FUSIONS_TO_CONVERGE = 10
# late-measurement history: a snapshot of the state before each aid sample and before an IMU
# run at most this long after the previous snapshot (a late sample re-runs ≤ this of IMU more)
_HIST_SNAPSHOT_PERIOD_S = 0.25
# Roll/pitch random walk across an IMU gap (AUVs stay near level), rad/√s.
_BLIND_LEVEL_RW_RAD_RTHZ = 0.03


# north, east of the velocity: in the nominal state, in the error state
_X_VEL_NE = slice(X_VEL.start, X_VEL.start + 2)
_VEL_NE = slice(VEL.start, VEL.start + 2)


def _finite(sample) -> bool:
    """Every number the estimator will use is finite (a USBL fix without a vertical σ
    needs no depth: underwater-GPS receivers report none)."""
    if sample.KIND == "usbl" and not math.isfinite(sample.sigma_v_m):
        return all(math.isfinite(v) for v in (sample.t_s, sample.lat_rad, sample.lon_rad, sample.sigma_h_m))
    return is_finite(sample)


def _all_finite(values: list) -> bool:
    """Every one of the floats finite (the state's 19 with every published state and ping): a
    finite sum has no inf or NaN in it, a third of the test per element; else (an overflow
    perhaps) each one."""
    return math.isfinite(sum(values)) or all(map(math.isfinite, values))


# the horizontal position's entries of a covariance (18×18) as index pairs: north-north,
# north-east, east-north, east-east
_NN = (POS_NE.start, POS_NE.start)
_NE = (POS_NE.start, POS_NE.start + 1)
_EN = (POS_NE.start + 1, POS_NE.start)
_EE = (POS_NE.start + 1, POS_NE.start + 1)


def _sigma_h_m(P: np.ndarray) -> float:
    """Horizontal position σ (m) of a covariance (18×18): the larger of north and east."""
    return math.sqrt(max(float(P[_NN]), float(P[_EE]), 0.0))


def _at_lever(meas: Measurement, x: np.ndarray, arm_b_m: np.ndarray) -> Measurement:
    """A position measurement of the IMU moved to a point ``arm_b_m`` (body, from the IMU).

    ``h ← h + (R_nb l)_j`` for each row measuring position axis j; with the global
    attitude error ``R = Exp(δθ) R̂``: ``∂(R l)/∂δθ = −[R̂ l]×`` (Groves 2013 §14.3.2).
    """
    r = aid_lv.dcm(x) @ arm_b_m
    rx = np.array([[0.0, -r[2], r[1]], [r[2], 0.0, -r[0]], [-r[1], r[0], 0.0]])
    H = meas.H.copy()
    h = meas.h.copy()
    for i in range(H.shape[0]):
        j = int(np.argmax(np.abs(H[i, POS])))
        if H[i, POS][j] == 1.0:
            h[i] += r[j]
            H[i, ATT] -= rx[j]
    return meas._replace(H=H, h=h)


def _rest_window_quiet(window: list, max_acc_std_m_s2: float, max_gyro_rad_s: float) -> bool:
    """The stationary-detection window (``Estimator._st`` as floats: t0, n, Σf (3), Σf² (3), max
    |ω|) was quiet: 3 samples or more, every axis's specific-force σ ``√max(Σf²/n − (Σf/n)², 0)``
    (m/s²) within ``max_acc_std_m_s2`` and the largest rate within ``max_gyro_rad_s``.

    Python floats, the arithmetic numpy did on the (3,) slices under ``np.errstate`` (~50 µs a
    window with the context manager and the small arrays; a window every data second): an
    overflow is inf and inf − inf NaN here too, and a NaN axis (absurd samples) is not quiet,
    as the NaN its maximum was."""
    _, n, f0, f1, f2, ff0, ff1, ff2, gyro_max = window
    if not (n >= 3 and gyro_max <= max_gyro_rad_s):
        return False
    m0, m1, m2 = f0 / n, f1 / n, f2 / n
    for var in (ff0 / n - m0 * m0, ff1 / n - m1 * m1, ff2 / n - m2 * m2):
        if not math.sqrt(max(var, 0.0)) <= max_acc_std_m_s2:  # (max(NaN, 0.0) is NaN)
            return False
    return True


# a DVL fused this recently (or during the vertical run) measured the run's horizontal drift
_DVL_MEASURES_DRIFT_S = 2.0


class _Snapshot:
    __slots__ = ("core", "rpm", "next_lv_t", "mode", "reset_counter", "lv_r_hat", "fix_evidence", "inertial_n",
                 "motion_params", "t_release", "reject_since", "t_reset", "yaw_fix_rad", "clones", "pos_unknown",
                 "anchor_ne", "yaw_frame", "attitude_driven", "t_motion_aid", "vertical_run", "t_dvl_fused", "t_fix_fused")


class Estimator:
    """The navigation filter. Feed it samples in replay order with :meth:`process`.

    Parameters
    ----------
    config : FilterConfig
    motion_params : MotionParams
        The learned motion model in use (replaced by :meth:`set_motion_params`).
    rpm_table : RpmSpeedTable
        Static RPM → surge speed lookup ``u = f(n)``.
    origin : GeoOrigin
        Mission origin of the local NED frame (GNSS/USBL are geodetic).
    """

    def __init__(self, config: FilterConfig, motion_params: MotionParams,
                 rpm_table: RpmSpeedTable, origin: GeoOrigin):
        self.config = config
        self.motion_params = motion_params
        self.rpm_table = rpm_table
        self.origin = origin
        self.rejected: Counter = Counter()
        # one contiguous array holds all numeric state (views below): a snapshot for
        # late-measurement re-fusion is then a single copy
        self._core = np.zeros(kalman.CORE_SIZE)
        self._x = self._core[kalman.CORE_X]
        self._P = self._core[kalman.CORE_P].reshape(N_ERR, N_ERR)
        self._acc = self._core[kalman.CORE_ACC]
        self._clock = self._core[kalman.CORE_CLOCK]
        self._x[:] = initial_nominal()
        self._clock[:] = -math.inf
        sd.set_earth(self._acc, None)
        # the IMU error model: the configured grade, or decided at alignment (``auto``)
        self.imu_model = imu_grades.resolve(config.imu, np.empty((0, 3)), np.empty((0, 3)), math.nan)
        self._imu_source = ""  # ImuSample.source of the latest IMU sample
        # past horizontal positions for leg-to-leg loop closures (aiding.loop_closure)
        self._clones = aid_loop.CloneBank(config.loop_closure.clone_period_s, config.loop_closure.clone_horizon_s,
                                          self._core)
        self._gate = {m: config.gate_threshold(m) for m in (1, 2, 3)}
        self._mode = "none"  # "none" | "ins" | "ahrs"
        # INS mode driven by the attitude's increments (no usable IMU, [filter.attitude_driven]):
        # the previous attitude sample (t_s, q_nb) and the latest fusion of a velocity aid or fix
        self._attitude_driven = False
        self._att_prev: tuple[float, np.ndarray] | None = None
        self._t_real_imu = -math.inf  # the latest real IMU sample's time beside it
        self._t_motion_aid = -math.inf
        self._motion_aids = _MOTION_AIDS | ({"learned_velocity"} if config.attitude_driven.model_measures_motion
                                            else set())
        self._reset_counter = 0
        self._t_imu_last = -math.inf
        # (t_s, surge, sway, commanded surge, commanded sway, slow surge, slow sway) m/s: see _take_rpm
        self._rpm: tuple[float, ...] | None = None
        self._rpm_raw = math.nan  # latest RPM (rev/min), for stationary detection
        self._next_lv_t = math.nan
        self._lv_period = 1.0 / config.learned_velocity.rate_hz
        self._lv_phase_s = float(config.learned_velocity.phase_s)
        # per aid kind: (its config section, what its setup() made of it), once
        self._aid_cfg = {kind: (getattr(config, kind), aid.setup(getattr(config, kind)) if aid.setup else None)
                         for kind, aid in AIDS.items()}
        # the DVL's scale/misalignment estimate (None when not configured): its aid owns it
        self.dvl_calibration: aid_dvl.DvlCalibration | None = self._aid_cfg["dvl"][1].calibration
        # what comes before the start (heading, fix, depth, levelling window) and the start
        self._alignment = Alignment(config, origin, self._aid_cfg["dvl"][1].R_db)
        # the scratch of the compiled calls beside the core (kalman.WORK_*): the process noise, the
        # latest update's correction and outputs, the depth's and heading's rows, the DVL's model;
        # the arrays below are views of it (the kernels of the commonest samples take it whole)
        self._work = np.zeros(kalman.WORK_SIZE)
        self._qdiag = self._work[kalman.WORK_QDIAG:kalman.WORK_QDIAG + N_ERR]
        self._qdiag[:] = self._process_noise()  # (set again at the start, with what the alignment saw)
        # reference points: lever arms are given from the vehicle reference point; the filter
        # navigates the IMU, so each becomes an arm from the IMU (None: at the IMU)
        l_imu = np.asarray(config.imu.lever_arm_b_m, dtype=float)
        if np.any(l_imu):
            dvl_cfg, dvl_setup = self._aid_cfg["dvl"]
            self._aid_cfg["dvl"] = (dvl_cfg, dvl_setup.with_lever(dvl_setup.lever_b - l_imu))
        self._arm = {kind: np.asarray(getattr(config, kind).lever_arm_b_m, dtype=float) - l_imu
                     for kind in ("gnss", "usbl", "depth")}
        self._arm = {k: a for k, a in self._arm.items() if np.any(a)}
        out_arm = np.asarray(config.output_point_b_m, dtype=float) - l_imu
        self._out_arm = out_arm if np.any(out_arm) else None
        # the considered terms' settings (_add_considered, horizontal_nav, a fix under the autopilot's heading)
        self._reference_yaw_sigma_rad = config.attitude.reference_yaw_sigma_rad
        self._density_sigma_kg_m3 = (config.depth.density_sigma_kg_m3, config.depth.water_density_kg_m3)
        self._t_dvl_lock = -math.inf  # latest bottom-track sample with lock (k_speed random walk)
        self._dx = self._work[kalman.WORK_DX:kalman.WORK_DX + N_ERR]
        self._sdiag = self._work[kalman.WORK_SDIAG:kalman.WORK_SDIAG + 3]
        # the compiled path of the commonest aids (:meth:`_fast_scalar`, :meth:`_fast_dvl`): per
        # sample type, where its aid is enabled and measured at the IMU (a lever arm: the general
        # path; the DVL's arm is in its own model); the depth's Jacobian row is constant, the
        # heading's attitude part is filled in per sample
        self._fast = {t: f for t, kind, f in ((DepthSample, "depth", self._fast_depth),
                                              (HeadingSample, "heading", self._fast_heading),
                                              (DvlSample, "dvl", self._fast_dvl))
                      if getattr(config, kind).enabled and kind not in self._arm}
        self._fast[ImuBatch] = self._fast[ImuSample] = self._fast_imu
        # a scalar's (y, S, nis), the DVL's innovation (:meth:`_fast_scalar`, :meth:`_fast_dvl`)
        self._fast_out = self._work[kalman.WORK_OUT:kalman.WORK_OUT + 3]
        self._work[kalman.WORK_H_DEPTH:kalman.WORK_H_DEPTH + N_ERR] = aid_depth.jacobian(None)[0]
        self._work[kalman.WORK_H_HEADING + ATT.start + 2] = 1.0
        # the DVL's model in the scratch as a Measurement of views (:meth:`_fast_dvl`: what a
        # velocity reset after a long rejection reads) and its installation packed for its kernel
        self._dvl_meas = aid_dvl.work_measurement(self._work)
        # the compiled calls of the hot paths without their guard (adaptnav.kernels.unguarded,
        # looked up when the estimator is made): each takes only the estimator's own arrays,
        # allocated once C-contiguous float64 (the core, the scratch _work and their views, the
        # learned velocity's kit, a snapshot's copy of the core), and numbers of its types
        self._fuse_scalar_core = unguarded(kalman.fuse_scalar_core)
        self._fuse_heading_core = unguarded(kalman.fuse_heading_core)
        self._fuse_vector_core = unguarded(kalman.fuse_vector_core)
        self._propagated_covariance = unguarded(kalman.propagated_covariance)  # (_P, _acc, _qdiag)
        self._lv_epoch = unguarded(kalman.lv_epoch)
        self._core_positive_definite = unguarded(kalman.core_positive_definite)  # (a _Snapshot's core)
        self._dvl_consts = aid_dvl.packed_setup(self._aid_cfg["dvl"][1])
        # the stationary window's length for the IMU path's kernel (-1: no rest detection)
        self._rest_window_s = config.stationary.window_s if config.stationary.enabled else -1.0
        # rehearse_epoch's scratch: a core to propagate, one IMU sample (no allocation per call)
        self._rehearsal_core = np.zeros(kalman.CORE_SIZE)
        self._rehearsal_t = np.zeros(1)
        self._rehearsal_f = np.zeros((1, 3))
        self._rehearsal_w = np.zeros((1, 3))
        self._rehearsal_inertial = np.zeros(6)
        self._rehearsal_rest = np.zeros(9)
        # input history for late measurements: entries (kind, payload, the state before it or
        # None: see _record) and their state times
        self._hist_t: list[float] = []
        self._hist: list[tuple[str, object, _Snapshot | None]] = []
        self._t_hist_snap = -math.inf  # state time of the history's latest snapshot
        # False: whoever feeds the filter guarantees that no sample comes later than the
        # filter's time (a source in time order: a simulation), so no history is kept — the
        # inputs and snapshots of the state before them, a twentieth of a replay's process for
        # nothing. A late sample all the same is rejected as too late (nothing to re-fuse it in).
        self.keep_history = True  # (a property: sets _history_on)
        self._replaying = False
        self._restored = False  # slow states restored: an alignment keeps them
        self._speed_cache: dict[float, float] = {}
        self._surge = SurgeVariance(config.learned_velocity)  # the adaptive surge variance
        # the learned velocity's compiled epoch (_lv_fast): its parameters and scratch (motion
        # params, config section, their packed numbers, the scratch array), made on first use;
        # _lv_compiled False: the general path always (tests compare the two)
        self._lv_kit: tuple | None = None
        self._lv_compiled = True
        self._heading_source: aid_attitude.HeadingSource | None = None  # ATTITUDE next to a FOG
        # the depth sensor's own noise (the σ it is fused with)
        self.depth_noise = aid_depth.DepthNoise(config.depth)
        self._yaw_fix_rad = 0.0  # Σ heading corrections of updates and resets (with a HeadingSource)
        self._t_release = -math.inf  # state time of the latest calibrator release applied
        # position-reset evidence: "last_fix" → (t, (n, e), σ) of the last fused fix; per
        # source, the recent gated fixes (tuples: snapshots share them)
        self._fix_evidence: dict[str, tuple] = {}
        self.position_resets: list[tuple[float, str, float]] = []  # (t_s, source, size m)
        # the vehicle starts at the origin, within initial.sigma_pos_m (a configured origin, a
        # launch point, a fix near the start); False: the origin is a place it passes later (a
        # replay's origin from a fix long after the data starts) — until a fix places it the
        # position is unknown, and that fix places it whatever it says (_seed_position)
        self.origin_is_start = True
        # (t_s, north, east m): how far each first fix moved the position it placed
        self.position_seeds: list[tuple[float, float, float]] = []
        # the horizontal position has no information yet (started at the origin, no fix, no
        # restored state): the first fix places it (_seed_position)
        self._pos_unknown = False
        # the horizontal position the dead-reckoned track is counted from (the start, then
        # each fused absolute fix) and whether ATTITUDE holds the yaw (the autopilot's heading
        # frame, a consider parameter of the published covariance: _add_considered)
        self._anchor_ne = (0.0, 0.0)
        self._yaw_frame = False
        # velocity/attitude resets: when each aid's current run of rejections began
        self._reject_since: dict[str, float] = {}
        self._t_reset = -math.inf  # state time of the latest velocity/attitude reset
        self.resets: Counter = Counter()  # by what was reset and why ("attitude", "velocity", ...)
        self._nis = NisMonitor(config.integrity.nis_window, config.integrity.nis_quantile)
        # stationary detection over IMU windows: [t0, n, Σf (3), Σf² (3), max |ω|]
        self._st = np.array([math.nan, 0.0] + [0.0] * 7)
        self._depth_win: list[float] = []  # [t0, depth0, t, depth] of the current window
        self._vertical_run: tuple | None = None  # aid_depth.vertical_run_step's (_keep_depth)
        self._t_dvl_fused = -math.inf
        self._t_fix_fused = -math.inf  # the last absolute position fix fused (data time, s)
        self.zero_velocity_updates = 0
        # free-inertial velocity: the strapdown's velocity increments summed without the
        # aiding corrections — what the IMU alone says about velocity *changes* (the
        # calibrator's surge-noise evidence; the corrected velocity is pulled towards the
        # very motion model being calibrated)
        # (north, east, down: its integral (m), exact step means for the calibrator, then the
        # velocity (m/s); advanced in the propagation's kernel, kalman.ins_run)
        self._inertial_n = np.zeros(6)
        self.late_fused = 0  # measurements fused at their own (past) time of validity
        # guard (:meth:`process`): last good state (snapshot, IMU time) and its time
        self._good: tuple[_Snapshot, float] | None = None
        self._good_t = -math.inf
        self._good_candidate: tuple[_Snapshot, float, float] | None = None  # (settle): snapshot, IMU time, its time
        self._recovering = False  # after a recovery: invalid until aids have fused again
        self._fused_since_recovery = 0

    # ------------------------------------------------------------------ public API
    @property
    def keep_history(self) -> bool:
        return self._keep_history

    @keep_history.setter
    def keep_history(self, keep: bool) -> None:
        self._keep_history = keep
        # what _record tests with every input besides the mode (the config's bound is fixed)
        self._history_on = bool(keep) and self.config.max_delay_s > 0

    @property
    def initialized(self) -> bool:
        return self._mode != "none"

    def _cov_now(self) -> np.ndarray:
        """The covariance at the state time, a new array: the pending step propagated
        (:func:`~adaptnav.fusion.kalman.propagated_covariance`), or, with none pending (the
        commonest case when asked: the IMU sample before flushed it), the copy that kernel
        returns then, without the call."""
        if not self._acc.item(ACC_T) <= 0.0:
            return self._propagated_covariance(self._P, self._acc, self._qdiag)
        return self._P.copy()

    def nav_state(self) -> NavState:
        """The current state; the covariance includes the not yet flushed propagation."""
        x = self._x
        ins = self._mode == "ins"
        cov = self._cov_now() if ins else self._P.copy()
        reasons = self.invalid_reasons(self._add_considered(cov))
        if ins and not reasons and not _all_finite(x.tolist()):
            reasons = ["non_finite"]
        x = x.copy()  # one copy; the state's vectors are views of it
        pos, vel = x[X_POS], x[X_VEL]
        if self._out_arm is not None:
            # reported at the output point: p + R l, v + R (ω̂ × l), P ← J P Jᵀ (J[POS, ATT] = −[R l]×)
            R = aid_lv.dcm(x)
            r = R @ self._out_arm
            pos += r
            vel += R @ np.cross(self._acc[ACC_OMEGA], self._out_arm)
            J = np.eye(N_ERR)
            J[POS, ATT] = -np.array([[0.0, -r[2], r[1]], [r[2], 0.0, -r[0]], [-r[1], r[0], 0.0]])
            cov = J @ cov @ J.T
        # (positional: NavState's field order)
        return NavState(self._clock.item(0), pos, vel, x[X_Q], x[X_BA], x[X_BG], x[X_CUR], x.item(X_KS), cov,
                        ins and not reasons, self._reset_counter, tuple(reasons))

    def rehearse_epoch(self, dt_s: float) -> NavState | None:
        """Rehearse an output epoch's IMU sample ``dt_s`` after the state time; nothing of the
        filter changes. The compiled call that sample takes (:func:`~adaptnav.fusion.kalman.ins_run`:
        the sample check, the propagation, the state guard) runs on scratch copies of the core,
        the free-inertial integral and the rest window, with the latest specific force and
        rate; the published state (:meth:`nav_state`, which only reads) is computed of the
        filter itself and returned. None outside INS mode or for a ``dt_s`` not in (0, 1] s.

        Why: live, the epoch's sample comes after the daemon slept an IMU period, and finds
        the interpreter's and the filter's code and data gone from the caches; run a
        millisecond before it (:class:`adaptnav.service.runtime.rehearsal.EpochRehearsal`),
        this leaves them there."""
        if self._mode != "ins" or not 0.0 < dt_s <= 1.0:
            return None
        scratch = self._rehearsal_core
        scratch[:] = self._core
        t = self._rehearsal_t
        t[0] = float(self._clock[0]) + dt_s
        f, w = self._rehearsal_f, self._rehearsal_w
        f[0] = self._acc[ACC_F]
        w[0] = self._acc[ACC_OMEGA]
        # the epoch sample's own compiled call (Estimator._fast_imu's), on scratch copies of
        # everything it writes; no learned-velocity epoch (∞)
        self._rehearsal_inertial[:] = self._inertial_n
        self._rehearsal_rest[:] = self._st
        kalman.ins_run(t, f, w, 0, scratch, self._qdiag, self.config.covariance_step_s, math.inf,
                       self._rehearsal_inertial, self.config.imu_gap_s, self._rehearsal_rest,
                       self.config.stationary.window_s if self.config.stationary.enabled else -1.0, _MAX_SPEED_M_S)
        return self.nav_state()

    def horizontal_nav(self) -> tuple | None:
        """What a side-scan ping records of the current state
        (:meth:`adaptnav.service.loop_closures.SideScanEstimator._ping`): ``None`` when
        :meth:`nav_state` would not be valid, else ``(t, pos NE, vel NE, yaw, cov POS_NE,
        cov VEL_NE)`` — the same numbers, without building the whole state (the ping's
        record was a tenth of the replaying process with side-scan). Where the published
        state needs more than these blocks (an output lever arm, the autopilot's heading
        frame), it is :meth:`nav_state` itself. Python floats (the vectors as tuples, the
        blocks as nested ones): what the record keeps, at a fraction of the arrays' cost."""
        if self._mode != "ins":
            return None
        if self._out_arm is not None or (self._yaw_frame and self._reference_yaw_sigma_rad > 0.0):
            ns = self.nav_state()
            if not ns.valid:
                return None
            return (ns.t_s, tuple(ns.pos_n_m[:2].tolist()), tuple(ns.vel_n_m_s[:2].tolist()), ns.euler_rad()[2],
                    ns.cov[POS_NE, POS_NE].tolist(), ns.cov[_VEL_NE, _VEL_NE].tolist())
        # _cov_now's numbers, read in place when no step is pending (no copy)
        cov = self._P if self._acc[ACC_T] <= 0.0 else self._propagated_covariance(self._P, self._acc, self._qdiag)
        (c00, c01), (c10, c11) = cov[POS_NE, POS_NE].tolist()
        if self.dvl_calibration is not None:  # _add_considered's terms of these blocks (the same additions)
            a00, a01, a10, a11 = self.dvl_calibration.position_cov_ne_values()
            c00, c01, c10, c11 = c00 + a00, c01 + a01, c10 + a10, c11 + a11
        xs = self._x.tolist()
        # (_sigma_h_m of these numbers)
        if self.invalid_reasons(math.sqrt(max(c00, c11, 0.0))) or not _all_finite(xs):
            return None
        n, e, q = X_POS_NE.start, _X_VEL_NE.start, X_Q.start
        # quat_to_euler's yaw of the same floats (the same arithmetic, without its roll and pitch)
        w, x, y, z = xs[q:q + 4]
        yaw = math.atan2(2.0 * (x * y + w * z), 1.0 - 2.0 * (y * y + z * z))
        if yaw >= math.pi:
            yaw -= 2.0 * math.pi
        return (float(self._clock[0]), (xs[n], xs[n + 1]), (xs[e], xs[e + 1]), yaw,
                [[c00, c01], [c10, c11]], cov[_VEL_NE, _VEL_NE].tolist())

    def _add_considered(self, cov: np.ndarray) -> float:
        """The published covariance (in place) gains what the filter treats as known but is
        not (*consider* parameters): the DVL's scale and misalignment on its track since the
        last fix (:meth:`DvlCalibration.position_cov_ne`), the autopilot's heading frame while
        ATTITUDE holds the yaw (:func:`~adaptnav.fusion.aiding.attitude.reference_yaw_covariance`,
        ``attitude.reference_yaw_sigma_rad``), and the water density the depth is
        converted with, a depth scale ``(d σ_ρ/ρ)²`` (``depth.density_sigma_kg_m3``;
        unobservable at constant depth: dvl_outage, 1025 → 1008 kg/m³ at minute 20, left the
        depth 0.34 m off at a published σ of 0.01 m, NEES 1700 from that term alone).

        Returns :func:`_sigma_h_m` of the result (what :meth:`nav_state` tests), of the
        block's floats at hand when the DVL's terms were the last to touch it."""
        cal = self.dvl_calibration
        sigma_h = None
        if cal is not None:
            # four float additions on the block read as Python floats (the IEEE additions numpy's
            # in-place ones of each entry made), written back: every epoch
            a00, a01, a10, a11 = cal.position_cov_ne_values()
            c00, c11 = cov.item(_NN) + a00, cov.item(_EE) + a11
            cov[_NN] = c00
            cov[_NE] = cov.item(_NE) + a01
            cov[_EN] = cov.item(_EN) + a10
            cov[_EE] = c11
            sigma_h = math.sqrt(max(c00, c11, 0.0))  # (_sigma_h_m of the entries just written)
        sigma_b = self._reference_yaw_sigma_rad
        if self._yaw_frame and sigma_b > 0.0:
            cov += aid_attitude.reference_yaw_covariance(self._x, self._anchor_ne, sigma_b)
            sigma_h = None  # (the block changed)
        sigma_rho, rho = self._density_sigma_kg_m3
        if sigma_rho > 0.0:  # (POS_D only: not the horizontal block)
            cov[POS_D, POS_D] += (float(self._x[X_DEPTH]) * sigma_rho / rho) ** 2
        return _sigma_h_m(cov) if sigma_h is None else sigma_h

    def integrity_report(self) -> dict:
        """The integrity monitor's window per aid (:meth:`adaptnav.fusion.integrity.NisMonitor.report`):
        attempts, mean NIS per degree of freedom, its bound, failing (then ``nis:<source>`` is
        among :meth:`invalid_reasons`)."""
        return self._nis.report()

    def invalid_reasons(self, sigma_h_m: float | None = None) -> list[str]:
        """Why the solution is not valid now (empty: valid), see ``[filter.integrity]``.

        ``not_initialized`` / ``ahrs_only`` (no dead reckoning), ``position_unknown`` (the
        origin is not where the vehicle started, :attr:`origin_is_start`, and no fix has placed
        it yet), ``no_motion_measurement``
        (the attitude drives the strapdown and neither a velocity over ground nor a fix has been
        fused for ``attitude_driven.motion_aid_max_age_s``), ``sigma_h`` (horizontal σ
        above the bound), ``converging`` (a velocity/attitude reset less than
        ``after_reset_s`` ago), ``recovering`` (after a non-finite state, until aids fused
        again), ``nis:<source>`` (that aid's recent innovations say the covariance is too
        small).
        """
        mode = self._mode
        if mode == "none":
            return ["not_initialized"]
        if mode == "ahrs":
            return ["ahrs_only"]
        if self._pos_unknown and not self.origin_is_start:
            return ["position_unknown"]
        t_s = self._clock.item(0)  # (a Python float: the same differences, without numpy's scalars)
        config = self.config
        if self._attitude_driven and t_s - self._t_motion_aid > config.attitude_driven.motion_aid_max_age_s:
            return ["no_motion_measurement"]
        if sigma_h_m is None:
            sigma_h_m = _sigma_h_m(self._cov_now())
        out = []
        if not sigma_h_m <= config.valid_max_sigma_h_m:
            out.append("sigma_h")
        if t_s - self._t_reset < config.integrity.after_reset_s:
            out.append("converging")
        if self._recovering:
            out.append("recovering")
        failing = self._nis.failing()
        if failing:  # (rarely: no comprehension to run for none, every epoch)
            out += [f"nis:{s}" for s in failing]
        return out

    def inertial_velocity(self) -> InertialVelocitySample | None:
        """The free-inertial velocity at the state time (INS mode only, else ``None``).

        Its value drifts (it is never corrected) but its changes over seconds are the
        IMU's, attitude-compensated with the filter's attitude and bias estimates; an IMU
        gap (coasting, no increments) bumps ``reset_counter``.
        """
        if self._mode != "ins" or self._attitude_driven:  # (a virtual IMU measures no motion)
            return None
        yaw = aid_heading.predict(self._x)[0]
        c = self._x[X_CUR]
        cal = self.dvl_calibration
        dvl_cal = (float(cal.theta[0]), float(cal.theta[1])) if cal is not None else (0.0, 0.0)
        pos_n, vel_n = self._inertial_n[0:3].tolist(), self._inertial_n[3:6].tolist()
        return InertialVelocitySample(float(self._clock[0]), tuple(vel_n), tuple(pos_n), float(yaw),
                                      int(self._reset_counter), (float(c[0]), float(c[1]), 0.0), dvl_cal)

    def clone_position(self) -> bool:
        """Keep the current horizontal position as a clone for later loop closures
        (:mod:`adaptnav.fusion.aiding.loop_closure`), at most every
        ``loop_closure.clone_period_s``; the side-scan user calls this as data arrive
        (clones cost a kernel call per covariance step, so only a user of loop closures pays).
        Returns True when a clone was made."""
        if self._mode != "ins" or not self.config.loop_closure.enabled:
            return False
        t = float(self._clock[0])
        if self._clones.t_s and t - self._clones.t_s[-1] < self._clones.period_s:
            return False
        self._clones.flush(self._core, self._qdiag)
        return self._clones.maybe_clone(t, self._x[X_POS_NE], self._P)

    def relative_position_covariance(self, t_a_s: float, t_b_s: float) -> np.ndarray | None:
        """Covariance (2×2, m²) of the horizontal position error difference between the
        clones nearest ``t_a_s`` and ``t_b_s``: what a loop closure's gate needs (the errors of
        two epochs are correlated, most of all during an outage); None without both clones."""
        a, b = self._clones.nearest(t_a_s), self._clones.nearest(t_b_s)
        if a is None or b is None:
            return None
        return self._clones.relative_cov(a, b)

    def relative_position_covariances(self, t_a_s: np.ndarray, t_b_s: float) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`relative_position_covariance` of every time in ``t_a_s`` with ``t_b_s`` at
        once: covariances (K, 2, 2; zero where not known) and known (K,) — what the side-scan
        association's gate asks of every stored sighting for each batch (one call each was a
        third of the association an hour in)."""
        cl = self._clones
        a = cl.nearest_many(t_a_s)
        b = cl.nearest(t_b_s)
        known = a >= 0 if b is not None else np.zeros(a.shape, bool)
        cov = np.zeros((a.size, 2, 2))
        if np.any(known):
            cov[known] = cl.relative_covs(a[known], b)
        return cov, known

    def fuse_loop_closure(self, t_a_s: float, t_b_s: float, offset_n_m, cov) -> AidStatus:
        """Fuse a leg-to-leg loop closure: ``offset_n_m ≈ e(t_a) − e(t_b)`` (the navigation's
        horizontal error at the earlier leg minus at the later one; m) with covariance ``cov``
        (2×2, m²), between the clones nearest ``t_a_s`` and ``t_b_s``
        (:meth:`clone_position`). Gated like every aid; the status has source
        ``"loop_closure"`` (``too_late`` when no clone is near one of the times)."""
        src = "loop_closure"
        offset = np.asarray(offset_n_m, dtype=float).reshape(-1)
        obs = tuple(float(v) for v in offset[:2])
        if self._mode != "ins":
            return rejected(t_b_s, src, "not_initialized", obs)
        if not self.config.loop_closure.enabled:
            return rejected(t_b_s, src, "disabled", obs)
        if not (offset.size == 2 and aid_loop.is_valid(offset, cov) and math.isfinite(t_a_s)
                and math.isfinite(t_b_s) and t_a_s < t_b_s):
            self.rejected["non_finite"] += 1
            return rejected(t_b_s if math.isfinite(t_b_s) else math.nan, src, "invalid", obs)
        payload = (float(self._clock[0]), float(t_a_s), float(t_b_s), offset.copy(),
                   np.asarray(cov, dtype=float).reshape(2, 2).copy())
        self._record("loop_closure", payload)
        return self._loop_closure(*payload)

    def _loop_closure(self, t_now: float, t_a_s: float, t_b_s: float, offset, cov) -> AidStatus:
        src = "loop_closure"
        a, b = self._clones.nearest(t_a_s), self._clones.nearest(t_b_s)
        if a is None or b is None or a == b:
            return rejected(t_b_s, src, "too_late", tuple(offset.tolist()))
        self._clones.flush(self._core, self._qdiag)
        K, y, S, nis = self._clones.closure_update(a, b, offset, cov)
        gate = self._gate[2]
        fused = bool(nis <= gate)
        if fused:
            dx = K @ y
            P = self._P - K @ S @ K.T
            self._P[:, :] = 0.5 * (P + P.T)
            self._clones.apply(a, b, K)
            kalman.inject_error(self._x, dx, self._P)
            if self._heading_source is not None:
                self._yaw_fix_rad += self._yaw_of(dx)
            self._clones.transform(aid_loop.reset_jacobian(dx))
        return AidStatus(float(t_b_s), src, tuple(offset.tolist()), tuple(y.tolist()), tuple(np.diag(S).tolist()),
                         float(nis) / gate, fused, "" if fused else "gate")

    def set_motion_params(self, params: MotionParams, adopt_k_v: bool = False) -> None:
        """Apply a calibrator release; ``k_speed · k_V`` is kept continuous — unless
        ``adopt_k_v``: the release's k_V was measured by the DVL (calibration.dvl_teacher, a
        least-squares fit of DVL surge on the RPM speed over the window), and ``k_speed`` goes
        back to 1 so the speed scale is the release's. Kept continuous, a DVL-taught k_V never
        reached the velocity the filter predicts: the product stayed the filter's own slow
        (``dvl.k_speed_rw_rthz``) estimate (dvl_outage seed 2: 0.969 into the outage, the
        release 0.954, truth 0.949 × the DVL's scale error).

        The release is part of the input history: a late measurement older than it is
        re-fused before it and the release re-applied after, as it came. For
        ``learned_velocity.adaptive_suspend_after_release_s`` after it, the released surge
        variance is used as it is (:meth:`_learned_velocity`).
        """
        self._record("params", (float(self._clock[0]), params, adopt_k_v))
        self._apply_motion_params(params, adopt_k_v)

    def _apply_motion_params(self, params: MotionParams, adopt_k_v: bool = False) -> None:
        ratio = (1.0 / self._x[X_KS]) if adopt_k_v else self.motion_params.k_v / params.k_v
        self._x[X_KS] *= ratio
        self._P[KS, :] *= ratio
        self._P[:, KS] *= ratio
        self._clones.scale_rows(KS, ratio)
        self.motion_params = params
        self._t_release = float(self._clock[0])

    def slow_states(self) -> dict:
        """Biases, current and ``k_speed`` with their variances (for persistence); in INS
        mode also the position with its variances and state time (``pos_n_m``,
        ``var_pos_n_m2``, ``pos_t_s``): a restart seeds from it (:meth:`restore_slow_states`).
        Empty before the filter has aligned, unless some were restored: the defaults, with no
        variance yet, are no state to keep (a restart refused them as "not usable")."""
        if self._mode == "none" and not self._restored:
            return {}
        d = np.diag(self._P)
        out = {
            "bias_acc_b_m_s2": self._x[X_BA].tolist(), "var_bias_acc": d[BA].tolist(),
            "bias_gyro_b_rad_s": self._x[X_BG].tolist(), "var_bias_gyro": d[BG].tolist(),
            "current_n_m_s": self._x[X_CUR].tolist(), "var_current": d[CUR].tolist(),
            "k_speed": float(self._x[X_KS]), "var_k_speed": float(d[KS][0]),
        }
        if self._mode == "ins":
            P = kalman.propagated_covariance(self._P, self._acc, self._qdiag)
            out.update(pos_n_m=self._x[X_POS].tolist(), var_pos_n_m2=np.diag(P)[POS].tolist(),
                       pos_t_s=float(self._clock[0]))
        return out

    def restore_slow_states(self, d: dict) -> None:
        """Inverse of :meth:`slow_states` (also before initialisation: kept through it).

        The restored states replace the filter's, uncorrelated with everything: with the
        clones too, if any (their rows of the clones' map zeroed after the flush, as in
        :meth:`_reset_attitude`)."""
        kalman.flush_core(self._core, self._qdiag)
        self._clones.zero_rows(SLOW)
        for name, xs, block, var in (("bias_acc_b_m_s2", X_BA, BA, "var_bias_acc"),
                                     ("bias_gyro_b_rad_s", X_BG, BG, "var_bias_gyro"),
                                     ("current_n_m_s", X_CUR, CUR, "var_current")):
            value = np.asarray(d[name], dtype=float)
            variance = np.asarray(d[var], dtype=float)
            if not (np.all(np.isfinite(value)) and np.all(variance > 0)):
                raise ValueError(f"restore_slow_states: bad {name}")
            self._x[xs] = value
            self._P[block, :] = 0.0
            self._P[:, block] = 0.0
            self._P[block, block] = np.diag(variance)
        k, vk = float(d["k_speed"]), float(d["var_k_speed"])
        if not (math.isfinite(k) and k > 0 and vk > 0):
            raise ValueError("restore_slow_states: bad k_speed")
        self._x[X_KS] = k
        self._P[KS, :] = 0.0
        self._P[:, KS] = 0.0
        self._P[KS, KS] = vk
        self._restored = True
        self._alignment.saved_pos = None
        if d.get("pos_n_m") is not None:
            t, pos, var = float(d["pos_t_s"]), np.asarray(d["pos_n_m"], float), np.asarray(d["var_pos_n_m2"], float)
            if not (math.isfinite(t) and pos.shape == (3,) and var.shape == (3,)
                    and np.all(np.isfinite(pos)) and np.all(var > 0) and np.all(np.isfinite(var))):
                raise ValueError("restore_slow_states: bad position")
            # the caller may know more time passed than the data clock says (an autopilot
            # rebooted meanwhile restarts its boot clock): the σ grows with the longer
            passed = float(d.get("pos_min_elapsed_s") or 0.0)
            self._alignment.saved_pos = (t, pos, var, passed if math.isfinite(passed) and passed > 0 else 0.0)

    def process(self, sample) -> list[AidStatus]:
        """Consume one sample (any type of :mod:`adaptnav.fusion.samples`, or an ImuBatch).

        Guarded: a state or covariance that became non-finite or lost positive variances
        (an absurd input the door let through, a numerical failure) is replaced by the last
        good state with an inflated covariance (:meth:`_recover`), counted in
        ``rejected["filter_recovered"]``; the solution is invalid until it has converged again.
        """
        kind = sample.KIND
        if kind in IGNORED_KINDS:
            return []
        if kind == "rpm" and _finite(sample):
            # changes no number of the state (the guard's verdict is the previous sample's)
            self._record("sample", sample)
            self._take_rpm(sample)
            return []
        if self._good_candidate is not None:
            self.settle()
        fast = self._fast.get(type(sample)) if self._mode == "ins" else None
        done = fast(sample) if fast is not None else None
        if done is not None:
            out, ok = done
        else:
            try:
                out = self._process(sample)
            except np.linalg.LinAlgError:
                out = []
            ok = self._mode == "none" or self._state_ok()
        if self._mode != "none":
            if not ok:
                self._recover()
            if self._clock.item(0) >= self._good_t + 1.0:  # (a Python float's comparison)
                self._keep_good()
        return out

    def settle(self) -> None:
        """Finish what the last :meth:`process` left that none of its outputs depends on;
        the runner calls it once the item's nav state is out (live: published), and
        :meth:`process` first if nobody did, so the filter is the same either way.

        That is the check of the state kept as the last good one (:meth:`_keep_good`, once
        per data second): a Cholesky of its covariance (compiled,
        :func:`~adaptnav.fusion.kalman.core_positive_definite`), some 50 µs with numpy's on a
        live sample (caches cold) that was on the way to the nav state."""
        candidate = self._good_candidate
        if candidate is None:
            return
        self._good_candidate = None
        snap, t_imu_last, t_s = candidate
        if not self._core_positive_definite(snap.core):
            return  # not positive definite: not a state to come back to (the next sample tries again)
        self._good = (snap, t_imu_last)
        self._good_t = t_s

    def _state_ok(self) -> bool:
        """Nominal state and covariance finite, every variance positive, speed physical."""
        return bool(kalman.core_ok(self._core, _MAX_SPEED_M_S))

    def _keep_good(self) -> None:
        """Take the current state as the candidate for the last good one (once per data
        second); :meth:`settle` keeps it if its covariance is positive definite."""
        self._good_candidate = (self._snapshot(), self._t_imu_last, float(self._clock[0]))

    def _recover(self) -> None:
        """Back to the last good state, its covariance inflated by the initial σs (plus a
        velocity random walk over the time lost), ``reset_counter`` bumped, history dropped."""
        self.rejected["filter_recovered"] += 1
        self._clones.clear()
        t_now = self._good_t
        for t in (self._clock[0], self._t_imu_last):
            if math.isfinite(t) and t > t_now:
                t_now = float(t)
        self._hist_t.clear()
        self._hist.clear()
        if self._good is None:  # nothing good yet: align again from scratch
            self._mode = "none"
            self._attitude_driven = False
            self._x[:] = initial_nominal()
            self._P[:, :] = initial_covariance(self.config, self.imu_model.figures, self.config.initial.sigma_pos_m,
                                               self.config.initial.sigma_pos_m)
            self._acc[:] = 0.0
            self._alignment.restart_levelling()
            self._t_imu_last = -math.inf
            self._reset_counter += 1
            return
        snap, t_imu_last = self._good
        rc = self._reset_counter
        self._restore(snap)
        self._reset_counter = rc + 1
        dt = max(t_now - self._good_t, 0.0)
        c = self.config.initial
        d = np.zeros(N_ERR)
        d[POS] = c.sigma_pos_m ** 2 + (_BLIND_VEL_RW_M_S_RTHZ ** 2) * dt ** 3 / 3.0
        d[VEL] = c.sigma_vel_m_s ** 2 + (_BLIND_VEL_RW_M_S_RTHZ ** 2) * dt
        d[ATT_TILT] = c.sigma_att_rad ** 2
        d[ATT_YAW] = c.sigma_yaw_rad ** 2
        self._P[:, :] += np.diag(d)
        self._acc[:] = 0.0
        self._clock[:] = t_now
        self._t_imu_last = max(t_imu_last, t_now)
        self._advance_lv_epoch(t_now)
        self._recovering = True
        self._fused_since_recovery = 0

    def shift_time(self, delta_s: float) -> None:
        """Re-base every time the filter holds by ``delta_s`` (a confirmed clock jump of the
        input, :class:`adaptnav.fusion.plausibility.Door`): the state continues at the new
        time as if no time had passed; late-measurement history is dropped."""
        if not math.isfinite(delta_s) or delta_s == 0.0:
            return
        self.settle()
        if np.isfinite(self._clock[0]):
            self._clock[:] += delta_s
        for name in ("_t_imu_last", "_next_lv_t", "_t_release", "_good_t", "_t_dvl_fused", "_t_fix_fused"):
            setattr(self, name, getattr(self, name) + delta_s)
        self._alignment.aligner.t_last_s += delta_s
        self._clones.shift_time(delta_s)
        if self._rpm is not None:
            self._rpm = (self._rpm[0] + delta_s, *self._rpm[1:])  # (t, surge, sway, commanded ...)
        self._hist_t.clear()
        self._hist.clear()
        self._good = None  # its time base is gone
        self._reset_counter += 1

    def _process(self, sample) -> list[AidStatus]:
        kind = sample.KIND
        if kind in IGNORED_KINDS:
            return []
        if kind in ("imu", "imu_batch"):
            self._imu_source = sample.source  # who measured it: the auto IMU grade's prior
        if kind == "imu_batch":
            return self._imu(np.asarray(sample.t_s, dtype=float),
                             np.asarray(sample.specific_force_b_m_s2, dtype=float).reshape(-1, 3),
                             np.asarray(sample.omega_b_rad_s, dtype=float).reshape(-1, 3))
        if kind == "imu":
            return self._imu(np.array([sample.t_s], dtype=float),
                             np.array([sample.specific_force_b_m_s2], dtype=float),
                             np.array([sample.omega_b_rad_s], dtype=float))
        if not _finite(sample):
            self.rejected["non_finite"] += 1
            return [rejected(sample.t_s if math.isfinite(sample.t_s) else math.nan, kind,
                             "non_finite")]
        if kind == "rpm":
            self._record("sample", sample)
            self._take_rpm(sample)
            return []
        if kind not in AID_KINDS:
            return []
        if self._mode == "none":
            return self._before_init(sample)
        t_now = self._clock[0]
        if self._mode == "ins" and sample.t_s < t_now - self.config.on_time_tolerance_s:
            if sample.t_s < t_now - self.config.max_delay_s:
                self.rejected["too_late"] += 1
                return [rejected(sample.t_s, kind, "too_late")]
            return self._fuse_late(sample)
        if kind == "attitude" and self._attitude_driven:
            out = self._attitude_step(sample)  # (recorded as an IMU input: a re-run repeats it)
            self._record("sample", sample)
            return out + self._aid(sample)
        self._record("sample", sample)
        return self._aid(sample)

    # ------------------------------------------------------------------ internals
    def _fast_depth(self, sample) -> tuple[list[AidStatus], bool] | None:
        """A depth on time in INS mode (:meth:`_fast_scalar`): what :meth:`_aid` does with it."""
        t_s, pressure_pa = sample.t_s, sample.pressure_pa
        if not self._fast_taken(sample, pressure_pa):
            return None
        c = self.config.depth
        d = aid_depth.depth_m(pressure_pa, c.water_density_kg_m3, c.atmospheric_pressure_pa)
        var = self.depth_noise.variance_m2(t_s, d)
        self._keep_depth(t_s, d)
        return self._fast_scalar(sample, d, self._x.item(X_DEPTH), kalman.WORK_H_DEPTH, var, False)

    def _fast_heading(self, sample) -> tuple[list[AidStatus], bool] | None:
        """A heading on time in INS mode (:meth:`_fast_scalar`): what :meth:`_aid` does with it."""
        yaw_rad = sample.yaw_rad
        if not self._fast_taken(sample, yaw_rad):
            return None
        # h(x̂) and the row's attitude part (heading.yaw_row's) computed in the kernel
        done = self._fast_scalar(sample, float(yaw_rad), None, kalman.WORK_H_HEADING,
                                 self.config.heading.sigma_rad**2, True)
        if done[0] and done[0][0].fused and "heading" in self._reject_since:
            self._rejected_too_long(done[0][0], self.config.reset.attitude_after_s)  # the rejection run ends
        return done  # (not fused: _aid has kept its count)

    def _fast_dvl(self, sample) -> tuple[list[AidStatus], bool] | None:
        """A bottom-track DVL sample with lock on time in INS mode: :meth:`_aid`'s steps with the
        aid's own model (:func:`~adaptnav.fusion.aiding.dvl._measure`, calibration included),
        (:func:`~adaptnav.fusion.aiding.dvl.bottom_track_into`: into the scratch ``_work``),
        then the innovation, update, injection and state guard in one compiled call
        (:func:`~adaptnav.fusion.kalman.fuse_vector_core`) and :meth:`_after_fuse`. Unlike the
        scalar aids a sample not fused is not handed back (measuring it again would count it
        twice in the calibration's straight legs): :meth:`_after_fuse` answers it here, as
        :meth:`_aid` would. Water track, no lock, a velocity not a tuple of three finite floats
        (what :func:`~adaptnav.fusion.samples.is_finite` checks of a DVL sample), late: the
        general path."""
        vel = sample.vel_d_m_s
        if (not sample.valid or sample.water_track or type(vel) is not tuple or len(vel) != 3
                or not (math.isfinite(vel[0]) and math.isfinite(vel[1]) and math.isfinite(vel[2]))
                or not self._fast_taken(sample, 0.0)):
            return None
        aid = AIDS["dvl"]
        config, setup = self._aid_cfg["dvl"]
        self._dvl_lock(sample.t_s)
        # the aid's model (dvl._measure's bottom track) without its context and checks, done above,
        # into the scratch, where self._dvl_meas's arrays are
        aid_dvl.bottom_track_into(sample, self._core, self._work, self._dvl_consts, config, setup)
        meas, y, sdiag = self._dvl_meas, self._fast_out, self._sdiag
        try:
            nis, fused, ok = self._fuse_vector_core(self._core, self._work, meas.z, meas.h, meas.H, meas.R,
                                                         self._gate[3], True, _MAX_SPEED_M_S)
            status = self._attempt(sample.t_s, "dvl", tuple(meas.z.tolist()), tuple(y.tolist()),
                                   tuple(sdiag.tolist()), nis, fused)
            out = self._after_fuse(sample, aid, config, setup, meas, status)
        except np.linalg.LinAlgError:
            return [], self._state_ok()
        # a reset after a long rejection changed the state since the guard
        return out, ok if fused else self._state_ok()

    def _fast_taken(self, sample, value: float) -> bool:
        """The sample's time and ``value`` finite and on time: then recorded for re-fusion, as
        :meth:`_process` does, and it takes the compiled path; else :meth:`_process` answers it
        (a rejection, or a late sample fused at its own time)."""
        t_s = sample.t_s
        if not (math.isfinite(t_s) and math.isfinite(value)) or \
                t_s < self._clock.item(0) - self.config.on_time_tolerance_s:
            return False
        if self._history_on:  # (in INS mode: _record's other test)
            self._record("sample", sample)
        return True

    def _fast_scalar(self, sample, z: float, h: float | None, row: int, var: float,
                     angular: bool) -> tuple[list[AidStatus], bool]:
        """Update, injection and the state guard of a scalar aid in one compiled call
        (:func:`~adaptnav.fusion.kalman.fuse_scalar_core`; ~20 µs of Python per sample before,
        the commonest samples after the IMU's), with the measurement ``z``, ``h`` = h(x̂), the
        row ``H`` (at ``row`` in the scratch ``_work``) and variance ``var`` of the aid's own
        model; ``h`` None: a heading, whose ``h`` and the attitude part of ``H`` the kernel
        computes from the state
        (:func:`~adaptnav.fusion.kalman.fuse_heading_core`). Returns ``([status], state ok)``.
        Not fused (gated, or a number not finite): :meth:`_aid` answers the sample instead —
        the flush is done (a no-op again), the gate gives the same verdict on the same numbers,
        and the reset after a long rejection and the non-finite count stay in one place."""
        if h is None:
            fused, ok = self._fuse_heading_core(self._core, self._work, z, var, self._gate[1], True, _MAX_SPEED_M_S)
        else:
            fused, ok = self._fuse_scalar_core(self._core, self._work, z, h, row, var, angular, self._gate[1], True,
                                               _MAX_SPEED_M_S)
        if not fused:
            try:
                return self._aid(sample), self._state_ok()
            except np.linalg.LinAlgError:
                return [], self._state_ok()
        y, s, nis = self._fast_out.tolist()
        return [self._attempt(sample.t_s, sample.KIND, (z,), (y,), (s,), nis, True)], ok

    def _position_variance_ne(self) -> tuple[float, float]:
        """The north and east position variances now (m²)."""
        kalman.flush_core(self._core, self._qdiag)
        return float(self._P[0, 0]), float(self._P[1, 1])

    def _floor_position_variance(self, sigma_m: float, prior_ne: tuple[float, float]) -> None:
        """North and east position variances raised to at least ``sigma_m²`` (an inflation:
        independent noise added to the position, the estimate unchanged) — the error of a
        fix that the next ones share (``gnss.correlated_fraction``, ``usbl.correlated_fraction``)
        — but never above ``prior_ne``, the variances before the fix: a poor fix after good
        ones shares their error too and takes nothing away (a Water Linked UGPS reporting
        11 m between fixes of 1.6 m on one spot had raised the σ to 5.6 m)."""
        kalman.flush_core(self._core, self._qdiag)
        for i in (0, 1):
            floor = min(sigma_m * sigma_m, prior_ne[i])
            if self._P[i, i] < floor:
                self._P[i, i] = floor

    def _keep_depth(self, t_s: float, depth_m: float) -> None:
        """The current stationary-detection window's first and latest depth (``_depth_win``),
        and the vertical run: its horizontal drift, unmeasured without a DVL, grows the
        position covariance (``learned_velocity.vertical_drift_sigma_per_m``; an inflation of
        the north/east variances, as a position reset's — the estimate moves only when a fix
        comes, and then as far as the drift may have taken it)."""
        win = self._depth_win
        if win:  # (always four entries then; the list is this window's own: written in place)
            win[2] = t_s
            win[3] = depth_m
        else:
            self._depth_win = [t_s, depth_m, t_s, depth_m]
        k = self.config.learned_velocity.vertical_drift_sigma_per_m
        if k <= 0.0:  # off (the default: an AUV's dives are its motion model's)
            return
        # the run on the filter's depth (the sensor's noise, 0.1 m per sample on ArduSub's
        # simulator, would start runs at a steady depth)
        self._vertical_run, grown_m2 = aid_depth.vertical_run_step(self._vertical_run, t_s, float(self._x[X_DEPTH]))
        if grown_m2 > 0.0 and not (self._t_dvl_fused >= self._vertical_run[0]
                                   or t_s - self._t_dvl_fused <= _DVL_MEASURES_DRIFT_S):
            self._P[0, 0] += k * k * grown_m2
            self._P[1, 1] += k * k * grown_m2

    def _take_rpm(self, sample) -> None:
        """Latest thrust: ``_rpm = (t, surge, sway, commanded surge, commanded sway, slow surge,
        slow sway)`` m/s.

        The speeds follow the commanded ones with the vehicle's first-order response
        (``learned_velocity.response_time_s``; the command held constant between samples):
        a vehicle does not stop the instant its thrusters do. The slow ones follow them with
        ``learned_velocity.transient_time_s`` (the bound of an unknown response: the learned
        velocity's variance takes the gap, :meth:`_lv_measure`).
        """
        cfg = self.config.learned_velocity
        r_y = float(sample.sway_rpm)
        sway = 0.0
        if r_y != 0.0:
            sway = math.copysign(self._speed(abs(r_y)), r_y) * cfg.sway_speed_scale
        # astern as ahead, mirrored (the table starts at 0 RPM: astern thrust was speed 0, and
        # an ROV backing at 0.5 m/s was "stopped" — gated, then reset onto 0)
        rpm = float(sample.rpm)
        surge = math.copysign(self._speed(abs(rpm)), rpm) if rpm < 0.0 else self._speed(rpm)
        prev = self._rpm
        if cfg.response_time_s > 0 and prev is not None and sample.t_s > prev[0]:
            a = 1.0 - math.exp(-(sample.t_s - prev[0]) / cfg.response_time_s)
            now = (prev[1] + a * (prev[3] - prev[1]), prev[2] + a * (prev[4] - prev[2]))
        else:
            now = (surge, sway)
        if cfg.transient_time_s > 0 and prev is not None and sample.t_s > prev[0]:
            b = 1.0 - math.exp(-(sample.t_s - prev[0]) / cfg.transient_time_s)
            slow = (prev[5] + b * (prev[3] - prev[5]), prev[6] + b * (prev[4] - prev[6]))
        else:
            slow = (surge, sway)
        self._rpm = (sample.t_s, *now, surge, sway, *slow)
        self._rpm_raw = max(abs(float(sample.rpm)), abs(r_y))

    def _speed(self, rpm: float) -> float:
        """``f(rpm)`` memoised: commanded RPMs repeat and the PCHIP call is slow."""
        u = self._speed_cache.get(rpm)
        if u is None:
            if len(self._speed_cache) > 4096:
                self._speed_cache.clear()
            u = self._speed_cache[rpm] = float(self.rpm_table.speed(rpm))
        return u

    def _process_noise(self) -> np.ndarray:
        c = self.config
        imu = self.imu_model.figures
        q = np.zeros(N_ERR)
        q[POS] = c.process.pos_noise_m_rthz ** 2
        q[VEL] = imu.acc_noise_m_s2_rthz ** 2
        q[ATT] = imu.gyro_noise_rad_s_rthz ** 2
        q[BA] = imu.acc_bias_rw_m_s3_rthz ** 2
        if self._tilt_held_by_autopilot():
            # the autopilot's tilt wanders and ATTITUDE holds ours on it (AttitudeConfig)
            q[BA.start:BA.start + 2] += (GRAVITY_M_S2 * c.attitude.reference_tilt_rw_rad_rthz) ** 2
        q[BG] = imu.gyro_bias_rw_rad_s2_rthz ** 2
        q[CUR] = c.process.current_rw_m_s_rthz ** 2
        q[KS] = c.process.k_speed_rw_rthz ** 2
        return q

    def _tilt_held_by_autopilot(self) -> bool:
        """A consumer IMU with the autopilot's ATTITUDE seen at the alignment: the filter's
        roll and pitch follow the autopilot's (built on the same MEMS, wandering by tenths of a
        degree)."""
        return (self.config.attitude.enabled and self.config.attitude.reference_tilt_rw_rad_rthz > 0
                and self.imu_model.grade == "consumer" and math.isfinite(self._alignment.attitude_rate_hz()))

    def _snapshot(self) -> _Snapshot:
        s = _Snapshot()
        s.core = self._core.copy()
        s.rpm = self._rpm
        s.next_lv_t = self._next_lv_t
        s.mode = self._mode
        s.reset_counter = self._reset_counter
        s.lv_r_hat = self._surge.r_hat_m2_s2
        s.fix_evidence = self._fix_evidence
        s.inertial_n = self._inertial_n.copy()
        s.motion_params = self.motion_params
        s.t_release = self._t_release
        s.reject_since = dict(self._reject_since)
        s.t_reset = self._t_reset
        s.yaw_fix_rad = self._yaw_fix_rad
        s.pos_unknown = self._pos_unknown
        s.anchor_ne = self._anchor_ne
        s.yaw_frame = self._yaw_frame
        s.attitude_driven = self._attitude_driven
        s.t_motion_aid = self._t_motion_aid
        s.vertical_run = self._vertical_run
        # the rest detector's hold-offs: a re-run must see the fixes and DVL fused before it
        # as they were, not one fused after the late sample's time
        s.t_dvl_fused = self._t_dvl_fused
        s.t_fix_fused = self._t_fix_fused
        s.clones = self._clones.copy() if self._clones.active else None
        return s

    def _restore(self, s: _Snapshot) -> None:
        self._core[:] = s.core
        self._rpm = s.rpm
        self._next_lv_t = s.next_lv_t
        self._mode = s.mode
        self._reset_counter = s.reset_counter
        self._surge.r_hat_m2_s2 = s.lv_r_hat
        self._fix_evidence = s.fix_evidence
        self._inertial_n[:] = s.inertial_n
        self.motion_params = s.motion_params
        self._t_release = s.t_release
        self._reject_since = dict(s.reject_since)
        self._t_reset = s.t_reset
        self._yaw_fix_rad = s.yaw_fix_rad
        self._pos_unknown = s.pos_unknown
        self._anchor_ne = s.anchor_ne
        self._yaw_frame = s.yaw_frame
        self._attitude_driven = s.attitude_driven
        self._t_motion_aid = s.t_motion_aid
        self._vertical_run = s.vertical_run
        self._t_dvl_fused = s.t_dvl_fused
        self._t_fix_fused = s.t_fix_fused
        if s.clones is not None:
            self._clones = s.clones.copy()
        elif self._clones.active:
            self._clones.clear()

    def _record(self, kind: str, payload, trim: bool = True) -> None:
        """Remember an input for late-measurement re-fusion, with the state before it when
        it is not an IMU run or the last snapshot is :data:`_HIST_SNAPSHOT_PERIOD_S` old: a
        late sample re-runs the inputs from the snapshot before its time (a copy of the
        state per IMU sample was a quarter of the live IMU path's work)."""
        if self._mode != "ins" or not self._history_on:
            return
        t = float(self._clock[0])
        snap = None
        if kind != "imu" or t - self._t_hist_snap >= _HIST_SNAPSHOT_PERIOD_S or not self._hist:
            snap = self._snapshot()
            self._t_hist_snap = t
        self._hist_t.append(t)
        self._hist.append((kind, payload, snap))
        if trim:
            self._trim_history(t)

    def _trim_history(self, t: float) -> None:
        """The history's inputs older than needed at state time ``t`` dropped."""
        # kept from 0.5 s beyond max_delay_s: more than a snapshot period, so a sample late by
        # up to max_delay_s finds a snapshot before its time; trimmed a second at a time (not
        # a bisect and a delete per input)
        horizon = t - self.config.max_delay_s - 0.5
        if self._hist_t[0] < horizon - 1.0 and len(self._hist_t) > 64:
            k = bisect.bisect_left(self._hist_t, horizon)
            del self._hist_t[:k]
            del self._hist[:k]

    def _fuse_late(self, sample) -> list[AidStatus]:
        k = bisect.bisect_right(self._hist_t, sample.t_s) - 1
        while k >= 0 and self._hist[k][2] is None:  # back to the snapshot before it
            k -= 1
        if k < 0:
            self.rejected["too_late"] += 1
            return [rejected(sample.t_s, sample.KIND, "too_late")]
        replay = self._hist[k:]
        del self._hist_t[k:]
        del self._hist[k:]
        self._restore(replay[0][2])
        self._t_hist_snap = -math.inf  # the re-run inputs are recorded afresh
        self._replaying = True
        out: list[AidStatus] = []
        inserted = False
        try:
            for kind, payload, _ in replay:
                if not inserted:
                    if kind == "imu":
                        t, f, w = payload
                        j = int(np.searchsorted(t, sample.t_s, side="right"))
                        if j < len(t):
                            self._imu_run(t[:j], f[:j], w[:j])
                            self._record("sample", sample)
                            out = self._aid(sample)
                            inserted = True
                            self._imu_run(t[j:], f[j:], w[j:])
                            continue
                    else:
                        t_entry = payload[0] if kind in ("gap", "params", "zupt", "loop_closure") else payload.t_s
                        if t_entry > sample.t_s:
                            self._record("sample", sample)
                            out = self._aid(sample)
                            inserted = True
                if kind == "imu":
                    self._imu_run(*payload)
                elif kind == "gap":
                    self._record("gap", payload)
                    self._imu_gap(*payload)
                elif kind == "loop_closure":
                    self._record("loop_closure", payload)  # (a later late measurement replays it again)
                    self._loop_closure(*payload)
                elif kind == "params":
                    self._record("params", payload)
                    self._apply_motion_params(payload[1], payload[2])
                elif kind == "zupt":
                    self._record("zupt", payload)
                    self._zero_velocity(*payload)
                else:
                    self._record("sample", payload)
                    if payload.KIND == "rpm":
                        self._take_rpm(payload)
                    else:
                        self._aid(payload)
            if not inserted:
                self._record("sample", sample)
                out = self._aid(sample)
        finally:
            self._replaying = False
        for st in out:
            self._monitor(st.source, st.test_ratio, len(st.innovation), st.reason)
        self.late_fused += 1
        return out

    def _before_init(self, sample) -> list[AidStatus]:
        """An aid sample before the start: kept by the alignment, answered ``not_initialized``
        (the alignment may start the filter: AHRS-only now, or as an INS)."""
        event = self._alignment.observe(sample, self._t_imu_last)
        if event == "ahrs":
            ad = self.config.attitude_driven
            if ad.enabled and self._alignment.attitude_rate_hz() * ad.max_step_s >= 2.0:
                self._start_attitude_driven(sample)  # (sparser attitude: every step a gap, AHRS)
            else:
                self._start(self._alignment.ahrs_start(sample, self.imu_model), "ahrs")
            return self._aid(sample)
        if event == "surface_only":
            return [rejected(sample.t_s, sample.KIND, "surface_only")]
        if event == "fix":  # the initial position: where later fixes must be reachable from
            self._fix_evidence = {"last_fix": self._alignment.first_fix}
        elif event == "fix_void":
            self._fix_evidence = {}
        return [rejected(sample.t_s, sample.KIND, "not_initialized")] + self._try_align()

    def _try_align(self) -> list[AidStatus]:
        """Start as an INS when the alignment can (levelled at rest, heading known)."""
        start = self._alignment.ins_start(self._imu_source)
        if start is None:
            return []
        self._begin_ins(start)
        return []

    def _begin_ins(self, start: Start) -> None:
        self.imu_model = start.imu_model
        self._qdiag[:] = self._process_noise()
        self._acc[:] = 0.0
        sd.set_earth(self._acc, start.earth_lat_rad)
        self._start(start, "ins")
        self._attitude_driven = False
        self._clones.clear()  # a new alignment: earlier epochs' errors are not this filter's
        # the first update epoch k period + phase after the start (LearnedVelocityConfig.phase_s)
        phase = self._lv_phase_s
        self._next_lv_t = math.floor((self._clock[0] - phase) / self._lv_period + 1.0) * self._lv_period + phase

    def _start_attitude_driven(self, sample) -> None:
        """No usable IMU but attitude samples: INS mode on a virtual IMU made of the attitude's
        increments (:meth:`_attitude_step`), at rest, attitude the sample's, position the
        alignment's initial one (:meth:`Alignment.ahrs_start`)."""
        model = imu_grades.attitude_driven(self.config.attitude_driven, self._alignment.attitude_rate_hz())
        start = self._alignment.ahrs_start(sample, model)
        self._begin_ins(start._replace(imu_model=model))
        self._attitude_driven = True
        self._att_prev = (float(sample.t_s), start.x[X_Q].copy())
        self._t_real_imu = self._t_imu_last

    def _attitude_step(self, sample) -> list[AidStatus]:
        """The virtual IMU's sample at an attitude sample's time: the body-frame rotation since
        the previous attitude sample as a rate, and gravity seen in the body frame (halfway
        through the step, the filter's own attitude: the vehicle's accelerations are process
        noise, and a tilt between the filter and the autopilot makes none)."""
        t = float(sample.t_s)
        q = euler_to_quat(sample.roll_rad, sample.pitch_rad, sample.yaw_rad)
        t_prev, q_prev = self._att_prev
        self._att_prev = (t, q)
        if not (t > t_prev and t > self._clock[0]):
            return []
        w = rotvec_from_quat(quat_mul(quat_conj(q_prev), q)) / (t - t_prev)
        q_mid = quat_mul(self._x[X_Q], quat_from_rotvec(0.5 * (t - self._clock[0]) * w))
        f = quat_to_dcm(q_mid).T @ np.array([0.0, 0.0, -GRAVITY_M_S2])
        return self._imu(np.array([t]), f[None, :], w[None, :], virtual=True)

    def _start(self, start: Start, mode: str) -> None:
        """Take the alignment's start; restored slow states (a restart) are kept through it."""
        keep = (self._x[X_SLOW].copy(), self._P[SLOW, SLOW].copy()) if self._restored else None
        self._x[:] = start.x
        self._P[:, :] = start.P
        if keep is not None:
            self._x[X_SLOW], self._P[SLOW, SLOW] = keep
        self._clock[:] = start.t_s
        self._mode = mode
        self._reset_counter += 1
        self._pos_unknown = not self._alignment.position_known
        self._anchor_ne = (float(self._x[0]), float(self._x[1]))
        self._yaw_frame = False

    def _imu(self, t: np.ndarray, f: np.ndarray, w: np.ndarray, virtual: bool = False) -> list[AidStatus]:
        """Validate IMU samples (vectorised), then align or propagate them (``virtual``: the
        attitude-driven strapdown's own sample, :meth:`_attitude_step`)."""
        if self._attitude_driven and not virtual:
            return self._imu_beside_attitude(t, f, w)
        # the attitude's increments are exact over any interval: a longer one is only a longer step
        gap_s = self.config.attitude_driven.max_step_s if virtual else self.config.imu_gap_s
        if self._mode == "ins" and sd.imu_clean(t, f, w, self._clock[0], gap_s):
            out = self._imu_run(t, f, w)
            if self.config.stationary.enabled and not virtual:
                out += self._stationary(t, f, w)
            return out
        finite = np.isfinite(t) & np.isfinite(f).all(axis=1) & np.isfinite(w).all(axis=1)
        if not finite.all():
            self.rejected["non_finite"] += int((~finite).sum())
            t, f, w = t[finite], f[finite], w[finite]
        if t.size == 0:
            return []
        t_last = self._clock[0] if self._mode == "ins" else self._t_imu_last
        prev = np.maximum.accumulate(np.concatenate(([t_last], t)))[:-1]
        keep = t > prev
        if not keep.all():
            self.rejected["duplicate"] += int((t == prev).sum())
            self.rejected["out_of_order"] += int((t < prev).sum())
            t, f, w = t[keep], f[keep], w[keep]
            if t.size == 0:
                return []
        if self._mode != "ins":
            self._alignment.add_imu(t, f, w, self._t_imu_last)
            self._t_imu_last = float(t[-1])
            was_ahrs = self._mode == "ahrs"
            if was_ahrs:
                self.rejected["ahrs_mode"] += int(t.size)
                if self._alignment.aligner.level() is not None and self._alignment.imu_fast_enough():
                    # a usable IMU rate appeared: re-align as an INS, keeping the AHRS
                    # heading and the depth
                    self._alignment.carry_over(aid_heading.predict(self._x)[0], float(self._x[X_DEPTH]))
                    self._mode = "none"
            if self._mode == "none":
                return self._try_align()
            return []
        dt = np.diff(np.concatenate(([t_last], t)))
        gaps = np.nonzero(dt > gap_s)[0]
        out: list[AidStatus] = []
        start = 0
        for g in gaps:
            out += self._imu_run(t[start:g], f[start:g], w[start:g])
            self.rejected["imu_gap"] += 1
            payload = (float(t[g]), f[g].copy(), w[g].copy())
            self._record("gap", payload)
            self._imu_gap(*payload)
            start = g + 1
        out += self._imu_run(t[start:], f[start:], w[start:])
        self._t_imu_last = float(self._clock[0])
        if self.config.stationary.enabled and not virtual:
            out += self._stationary(t, f, w)
        return out

    def _imu_beside_attitude(self, t: np.ndarray, f: np.ndarray, w: np.ndarray) -> list[AidStatus]:
        """A real IMU sample while the attitude drives the strapdown: into the levelling
        window only; once it levels (a rate fast enough to integrate, as for the AHRS mode) the
        filter re-aligns as an INS on it, keeping heading, depth and the horizontal position."""
        finite = np.isfinite(t) & np.isfinite(f).all(axis=1) & np.isfinite(w).all(axis=1)
        t, f, w = t[finite], f[finite], w[finite]
        keep = t > self._t_real_imu  # (the virtual samples' times are not this stream's)
        t, f, w = t[keep], f[keep], w[keep]
        self.rejected["attitude_driven"] += int(t.size)
        if t.size == 0:
            return []
        self._alignment.add_imu(t, f, w, self._t_real_imu)
        self._t_real_imu = float(t[-1])
        if self._alignment.aligner.level() is None or not self._alignment.imu_fast_enough():
            return []
        cov = kalman.propagated_covariance(self._P, self._acc, self._qdiag)
        self._alignment.carry_over(aid_heading.predict(self._x)[0], float(self._x[X_DEPTH]),
                                   (self._x[X_POS_NE].copy(), _sigma_h_m(cov)))
        self._mode = "none"
        self._attitude_driven = False
        self._hist_t.clear()  # a new filter: nothing before it is re-run into it
        self._hist.clear()
        return self._try_align()

    def _stationary(self, t, f, w) -> list[AidStatus]:
        """Accumulate IMU windows; a window at rest (IMU quiet, thrusters idle, depth
        steady) gives one zero-velocity update at its end."""
        st = self._st
        if t.size == 0 or self._mode != "ins":
            return []
        if not math.isfinite(st[0]):
            st[0] = float(t[0])
        sd.accumulate_rest_window(st, f, w)
        t_end = float(t[-1])
        if t_end - st[0] < self.config.stationary.window_s:
            return []
        return self._rest_window_end(t_end)

    def _rest_window_end(self, t_end: float) -> list[AidStatus]:
        """The stationary-detection window ends at ``t_end``: a zero-velocity update when the
        vehicle was at rest over it; the next window starts."""
        c = self.config.stationary
        st = self._st
        quiet = _rest_window_quiet(st.tolist(), c.max_acc_std_m_s2, c.max_gyro_rad_s)
        st[:] = [math.nan, 0.0] + [0.0] * 7
        dw = self._depth_win
        depth_steady = len(dw) < 4 or (dw[2] - dw[0] > 0 and abs(dw[3] - dw[1]) <= c.max_depth_rate_m_s * max(dw[2] - dw[0], c.window_s))
        self._depth_win = dw[2:] * 2 if len(dw) == 4 else []
        idle = math.isfinite(self._rpm_raw) and abs(self._rpm_raw) <= c.max_rpm
        recent_dvl = t_end - self._t_dvl_fused < c.window_s
        # a floating vehicle drifts with the water, thrusters idle or not: where fixes come,
        # they say whether it moves (a rest update there had the surface drift learnt as none,
        # and the dive carried no current at a σ of 0.01 m/s)
        recent_fix = t_end - self._t_fix_fused < c.fix_holdoff_s
        dry = self._x[X_DEPTH] < c.max_depth_m
        if not (quiet and depth_steady and idle and dry and not recent_dvl and not recent_fix):
            return []
        payload = (t_end,)
        self._record("zupt", payload)
        return [self._zero_velocity(*payload)]

    def _zero_velocity(self, t_s: float) -> AidStatus:
        """Zero-velocity update (the vehicle is at rest in the navigation frame)."""
        sigma = self.config.stationary.sigma_m_s
        H = np.zeros((3, N_ERR))
        H[:, VEL] = np.eye(3)
        meas = Measurement(np.zeros(3), H, np.eye(3) * sigma ** 2, self._x[X_VEL].copy(), np.zeros(3, bool))
        self.zero_velocity_updates += 1
        return self._fuse(meas, t_s, "zero_velocity")

    def _imu_run(self, t, f, w) -> list[AidStatus]:
        if t.size == 0:
            return []
        self._record("imu", (t, f, w))
        return self._imu_pieces(t, f, w, 0)[0]

    def _imu_pieces(self, t, f, w, stop: int, lv_due: bool = False) -> tuple[list[AidStatus], bool]:
        """Propagate a run of clean samples from ``stop`` a piece at a time
        (:func:`~adaptnav.fusion.kalman.ins_run`), fusing the learned velocity at each of its
        epochs; ``lv_due``: the piece before (:meth:`_fast_imu`'s) reached one. Returns the
        statuses and whether the state guard must run again: True when something was fused
        or the last piece's own guard failed."""
        out: list[AidStatus] = []
        n = t.size
        fused_any = False
        ok = True
        while True:
            if lv_due:
                status = self._learned_velocity()
                if status is not None:
                    out.append(status)
                self._advance_lv_epoch(self._clock[0])
                fused_any = True
            if stop >= n:
                break
            stop, lv_due, _, ok = kalman.ins_run(t, f, w, stop, self._core, self._qdiag, self.config.covariance_step_s,
                                                 self._next_lv_t, self._inertial_n, 0.0, self._st, -1.0,
                                                 _MAX_SPEED_M_S)
        return ([] if self._replaying else out), fused_any or not ok

    def _fast_imu(self, batch) -> tuple[list[AidStatus], bool] | None:
        """An IMU run (an :class:`ImuBatch`, or one :class:`ImuSample`: live, the epoch's own
        sample) in INS mode whose samples are clean (finite, after the state time, no gap):
        :meth:`_imu`'s steps — the propagation to the learned velocity's epochs, the
        free-inertial bookkeeping, the stationary window, the state guard — with the check,
        the first piece and the window in one compiled call
        (:func:`~adaptnav.fusion.kalman.ins_run`). Not clean, or the attitude drives the
        strapdown: the general path (nothing changed)."""
        if self._attitude_driven:
            return None
        if batch.KIND == "imu":  # (as _process makes them)
            t = np.array([batch.t_s], dtype=float)
            f = np.array([batch.specific_force_b_m_s2], dtype=float)
            w = np.array([batch.omega_b_rad_s], dtype=float)
        else:
            t = np.asarray(batch.t_s, dtype=float)
            f = np.asarray(batch.specific_force_b_m_s2, dtype=float).reshape(-1, 3)
            w = np.asarray(batch.omega_b_rad_s, dtype=float).reshape(-1, 3)
            if t.size == 0:
                return None
        history = self._history_on
        if history:
            # recorded for re-fusion with the state before it, untrimmed, before the kernel's
            # check (imu_clean's, in the call that propagates: no call of its own); a run not
            # clean is taken out again (and the snapshot time it set), as if never recorded
            t_hist_snap = self._t_hist_snap
            self._record("imu", (t, f, w), trim=False)
        stop, lv_due, window_done, ok = kalman.ins_run(t, f, w, 0, self._core, self._qdiag,
                                                       self.config.covariance_step_s, self._next_lv_t,
                                                       self._inertial_n, self.config.imu_gap_s, self._st,
                                                       self._rest_window_s, _MAX_SPEED_M_S)
        if stop < 0:
            if history:
                del self._hist_t[-1], self._hist[-1]
                self._t_hist_snap = t_hist_snap
            return None
        if history:
            self._trim_history(self._hist_t[-1])
        self._imu_source = batch.source
        out, ask = self._imu_pieces(t, f, w, stop, lv_due) if (lv_due or stop < t.size) else ([], not ok)
        if window_done:
            rest = self._rest_window_end(float(t[-1]))
            if rest:
                out += rest
                ask = True
        return out, (self._state_ok() if ask else True)

    def _advance_lv_epoch(self, t_s: float) -> None:
        """Move the next learned-velocity epoch past ``t_s`` in one step (a loop of
        periods would run for ever after a far-future stamp)."""
        if self._next_lv_t <= t_s:
            self._next_lv_t += (math.floor((t_s - self._next_lv_t) / self._lv_period) + 1.0) * self._lv_period
            if self._next_lv_t <= t_s:  # rounding
                self._next_lv_t += self._lv_period

    def _imu_gap(self, t_s: float, f_b, w_b) -> None:
        """An IMU gap: coast at constant velocity, inflate the covariance, restart at t_s."""
        self._clones.flush(self._core, self._qdiag)
        dt = t_s - self._clock[0]
        self._x[X_POS] += self._x[X_VEL] * dt
        Phi = np.eye(N_ERR)
        Phi[POS, VEL] = np.eye(3) * dt
        q = _BLIND_VEL_RW_M_S_RTHZ ** 2
        Q = np.zeros((N_ERR, N_ERR))
        Q[POS, POS] = np.eye(3) * q * dt ** 3 / 3.0
        Q[POS, VEL] = Q[VEL, POS] = np.eye(3) * q * dt ** 2 / 2.0
        Q[VEL, VEL] = np.eye(3) * q * dt
        # no gyro across the gap: the vehicle may have turned (yaw) and, less, pitched/rolled
        Q[ATT, ATT] = np.diag([_BLIND_LEVEL_RW_RAD_RTHZ ** 2, _BLIND_LEVEL_RW_RAD_RTHZ ** 2,
                               _BLIND_ATT_RW_RAD_RTHZ ** 2]) * dt
        self._P[:, :] = Phi @ self._P @ Phi.T + Q
        self._clones.transform(Phi)
        self._acc[ACC_OMEGA] = np.asarray(w_b) - self._x[X_BG]
        self._acc[ACC_F] = np.asarray(f_b) - self._x[X_BA]
        self._clock[:] = t_s
        self._reset_counter += 1
        self._advance_lv_epoch(t_s)

    def _ahrs_time_update(self, t_s: float) -> None:
        dt = t_s - self._clock[0]
        if dt > 0:
            q = _BLIND_VEL_RW_M_S_RTHZ ** 2
            self._P[POS, POS] += np.eye(3) * q * dt
            # no gyro: the attitude may turn at vehicle rates, so the AHRS leads
            self._P[ATT, ATT] += np.eye(3) * _BLIND_ATT_RW_RAD_RTHZ ** 2 * dt
            self._clock[:] = t_s

    def _learned_velocity(self) -> AidStatus | None:
        cfg = self.config.learned_velocity
        if not cfg.enabled or self._rpm is None:
            return None
        t = float(self._clock[0])
        self._set_k_speed_walk(self._t_dvl_lock > -math.inf)
        if t - self._rpm[0] > cfg.rpm_hold_s:
            return rejected(t, "learned_velocity", "stale")
        if self._lv_compiled and self._mode == "ins" and not self._attitude_driven:
            status = self._lv_fast(t, cfg)  # the common case, compiled
            if status.fused and "learned_velocity" not in self._reject_since:
                return status  # (_rejected_too_long's answer: no run of rejections to end)
            meas = None
        else:
            meas = self._lv_measure(t, adapt=True)
            status = self._fuse(meas, t, "learned_velocity")
        if self._rejected_too_long(status, self.config.reset.velocity_after_s):
            if meas is None:  # the compiled path's measurement, still in its scratch (not fused)
                buf = self._lv_kit[3]
                meas = aid_lv.make(buf[kalman.LV_Z].copy(), buf[kalman.LV_JAC].copy(), buf[kalman.LV_R].copy(),
                                   buf[kalman.LV_H].copy())
            # the learned velocity is in doubt: its surge variance takes the rejected
            # innovation (re-admitted, not gated again) and k_speed its initial σ again
            self._surge.doubt(meas)
            self._doubt_k_speed()
            self._reset_velocity(meas, status)
            # measured again: the innovation before the reset is what the reset removed
            status = self._fuse(self._lv_measure(t, adapt=False), t, "learned_velocity")
        return status

    def _lv_fast(self, t: float, cfg) -> AidStatus:
        """:meth:`_lv_measure` (adapted) and :meth:`_fuse` in INS mode in one compiled call
        (:func:`~adaptnav.fusion.kalman.lv_epoch`: the aid's model
        :func:`~adaptnav.fusion.aiding.learned_velocity.measure` with the additions below, the
        surge variance's adaptation :meth:`SurgeVariance.adapt`, the update), then the status
        (:meth:`_attempt`). Why: the epoch was ~110 µs in a replay, mostly Python steps (a numpy
        model, its Measurement, the adaptation's h P hᵀ, the additions' copies); ~30 µs now, most
        of it the covariance flush and update the old path also paid. The measurement stays in
        the scratch for a reset after a long rejection (:meth:`_learned_velocity`)."""
        kit = self._lv_kit
        params = self.motion_params
        if kit is None or kit[0] is not params or kit[1] is not cfg:
            kit = self._lv_kit = (params, cfg, aid_lv.kernel_params(params, cfg), np.zeros(kalman.LV_BUF_SIZE))
        r = self._rpm
        surge = self._surge
        r_hat = surge.r_hat_m2_s2
        out = self._lv_epoch(self._core, self._qdiag, kit[2], kit[3], self._dx, r[1], r[2], r[5], r[6],
                             0.0 if r_hat is None else r_hat, r_hat is not None, t - self._t_release,
                             self._gate[3], True)
        if out[12]:
            surge.r_hat_m2_s2 = out[11]
        return self._attempt(t, "learned_velocity", out[2:5], out[5:8], out[8:11], out[0], out[1])

    def _lv_measure(self, t: float, adapt: bool) -> Measurement:
        """The learned-velocity measurement now, its surge variance adapted
        (:class:`~adaptnav.fusion.adaptive_noise.SurgeVariance`; ``adapt``: the estimate is
        updated with this epoch's innovation)."""
        cfg = self.config.learned_velocity
        R_nb = aid_lv.dcm(self._x)
        yaw_rate = float(R_nb[2] @ self._acc[ACC_OMEGA])
        surge = self._rpm[1]
        # a coast (the thrust fell, the hull slows on drag alone): its speed between the
        # command's and the slow lag's (LearnedVelocityConfig.coast_mean_fraction)
        coast = cfg.transient_time_s > 0 and abs(self._rpm[5]) > abs(surge)
        if coast:
            surge += cfg.coast_mean_fraction * (self._rpm[5] - surge)
        meas = aid_lv.measure(self._x, surge, yaw_rate, self.motion_params,
                              cfg.sigma_heave_m_s, cfg.variance_scale, self._rpm[2], R_nb=R_nb)
        P = None
        if adapt and self._surge.enabled:
            # the prior covariance, propagated in place: the update (_fuse) starts from it and
            # would flush it itself; propagated into a copy here, it was computed twice
            kalman.flush_core(self._core, self._qdiag)
            P = self._P
        extra = None  # (surge, sway) variance the model leaves unknown on this vehicle
        if cfg.transient_time_s > 0:
            # a thrust change settling in a vehicle of unknown response: the speed is anywhere
            # between the model's now and the model's through the slow lag (1σ = a multiple of
            # the gap, transient_sigma_per_gap; coast_sigma_per_gap in a coast)
            scale = abs(float(self._x[X_KS])) * self.motion_params.k_v
            g_surge = cfg.coast_sigma_per_gap if coast else cfg.transient_sigma_per_gap
            extra = ((scale * g_surge * (self._rpm[1] - self._rpm[5])) ** 2,
                     (scale * cfg.transient_sigma_per_gap * (self._rpm[2] - self._rpm[6])) ** 2)
            if extra == (0.0, 0.0):
                extra = None
        if cfg.skid_sigma_s > 0:
            # a turning vehicle of unknown skid: sway β u w with β ~ N(0, σ_β²), its σ at most
            # skid_max_fraction of the speed (LearnedVelocityConfig.skid_sigma_s)
            # u the speed the vehicle may still have: in a pivot right after a lane the thrust
            # says 0 while the hull coasts on and turns under its own velocity (the slow lag's
            # speed; the model's once the thrust change has settled); coasting, it turns under
            # the velocity it keeps: a sideslip of any angle (coast_skid_max_fraction)
            u = max(abs(self._rpm[1]), abs(self._rpm[5])) if cfg.transient_time_s > 0 else self._rpm[1]
            cap = cfg.coast_skid_max_fraction if coast else cfg.skid_max_fraction
            skid = (abs(float(self._x[X_KS])) * self.motion_params.k_v * u
                    * min(cfg.skid_sigma_s * abs(yaw_rate), cap)) ** 2
            if skid > 0.0:
                extra = (extra[0], extra[1] + skid) if extra else (0.0, skid)
        meas = self._surge.adapt(meas, P, t - self._t_release, extra_var=extra[0] if extra else 0.0)
        # a vehicle that may heave on vertical thrusters: heave ≈ 0 ± (c v_d)
        # (LearnedVelocityConfig.heave_sigma_per_vertical_speed; 0: 0.0, the same floats)
        heave = (cfg.heave_sigma_per_vertical_speed * float(self._x[X_VEL][2])) ** 2
        if extra is not None or heave > 0.0:
            R = meas.R.copy()
            if extra is not None:
                R[0, 0] += extra[0]
                R[1, 1] += extra[1]
            R[2, 2] += heave
            meas = meas._replace(R=R)
        return meas

    def _doubt_k_speed(self) -> None:
        """``k_speed`` back to its initial σ (the RPM → speed scale is in doubt).

        An inflation, not a replacement: ``k ← k + w`` with ``w`` independent of everything and
        ``Var w`` the variance added, so ``Cov(k + w, ·) = Cov(k, ·)`` — its covariances with the
        other states and with the clones stay as they are (nothing to do to the clones' map)."""
        kalman.flush_core(self._core, self._qdiag)
        k = KS.start
        self._P[k, k] += max(0.0, self.config.initial.sigma_k_speed ** 2 - float(self._P[k, k]))

    def _aid(self, sample) -> list[AidStatus]:
        kind = sample.KIND
        aid = AIDS[kind]
        if self._mode == "ahrs":
            # no dead reckoning: attitude, depth and absolute fixes only (position is a
            # random walk between fixes and never reported valid)
            if not aid.without_imu:
                return [rejected(sample.t_s, kind, "no_imu")]
            self._ahrs_time_update(sample.t_s)
        config, setup = self._aid_cfg[kind]
        if not config.enabled:
            return [rejected(sample.t_s, kind, "disabled")]
        if kind == "attitude" and self._mode == "ins" and self.imu_model.grade == "navigation" \
                and config.with_navigation_grade != "fuse":
            return [self._ins_class_heading(sample, config)]
        if kind == "dvl" and sample.valid and not getattr(sample, "water_track", False):
            self._dvl_lock(sample.t_s)
        meas = aid.measure(sample, AidContext(self._x, self._acc[ACC_OMEGA], self.origin, config, setup))
        if meas is None or isinstance(meas, str):
            return [rejected(sample.t_s, kind, meas or aid.none_reason)]
        if kind == "depth":
            meas = self.depth_noise.adapt(meas, sample.t_s)
        if kind in self._arm:
            meas = _at_lever(meas, self._x, self._arm[kind])
        if aid.absolute_position:
            # a source whose fixes share their error says so in its config (gnss. and
            # usbl.correlated_fraction): the fixes that follow do not average it away
            shared = getattr(config, "correlated_fraction", 0.0)
            prior_ne = self._position_variance_ne() if shared > 0.0 else None
            status = self._fuse_position(meas, sample.t_s, kind)
            if status.fused:
                self._t_fix_fused = sample.t_s
                if prior_ne is not None:
                    self._floor_position_variance(shared * float(sample.sigma_h_m), prior_ne)
            if self.dvl_calibration is not None and status.fused:  # a fix closes a DVL track interval
                self.dvl_calibration.on_fix(sample.t_s, self.origin.to_ned(sample.lat_rad, sample.lon_rad)[:2],
                                            sample.sigma_h_m)
            return [status]
        if kind == "depth" and self._mode == "ins":
            self._keep_depth(sample.t_s, float(meas.z[0]))
        return self._after_fuse(sample, aid, config, setup, meas, self._fuse(meas, sample.t_s, kind))

    def _after_fuse(self, sample, aid, config, setup, meas: Measurement, status: AidStatus) -> list[AidStatus]:
        """What follows an attempt to fuse ``meas`` of ``sample`` (:meth:`_aid`, and the DVL's
        compiled path :meth:`_fast_dvl`): a reset after a long rejection, then the attempt again."""
        kind = sample.KIND
        if kind == "dvl" and status.fused:
            self._t_dvl_fused = sample.t_s
        if self._mode == "ins":
            c = self.config.reset
            reset = False
            if kind in ("attitude", "heading") and self._rejected_too_long(status, c.attitude_after_s):
                self._reset_attitude(sample, meas, status)
                reset = True
            elif kind == "dvl" and self._rejected_too_long(status, c.velocity_after_s):
                self._reset_velocity(meas, status)
                reset = True
            if reset:
                # measured again: the innovation before the reset is what the reset removed
                meas = aid.measure(sample, AidContext(self._x, self._acc[ACC_OMEGA], self.origin, config, setup))
                if isinstance(meas, Measurement):
                    status = self._fuse(meas, sample.t_s, kind)
        if kind == "attitude" and status.fused:
            self._yaw_frame = True  # the yaw now follows the autopilot's (also after a reset onto it)
        return [status]

    def heading_source_report(self) -> dict | None:
        """What the ATTITUDE heading was judged to be next to a navigation-grade INS
        (``with_navigation_grade = "learn"``): ``{"class": "ins" | "compass" | "undecided",
        "variability_deg": …, "time_offset_s": …}`` (its 1-σ variability against the gyro, and
        how late its time stamps are against the IMU's); None when not judged."""
        src = self._heading_source
        if src is None:
            return None
        t = float(self._clock[0])
        var = src.var_rad2
        judged = t - src.t_first_s >= src.config.learn_min_s and math.isfinite(var)
        kind = ("ins" if src.r_rad2(t) is not None else "compass") if judged else "undecided"
        return {"class": kind, "variability_deg": math.degrees(math.sqrt(var)) if math.isfinite(var) else None,
                "time_offset_s": -src.lag_s}

    def _ins_class_heading(self, sample, config) -> AidStatus:
        """ATTITUDE next to a navigation-grade INS: its heading fused only when it is an
        INS's (``with_navigation_grade = "learn"``, :class:`~adaptnav.fusion.aiding.attitude.HeadingSource`),
        with the variance learned, while the filter's heading is less certain than it."""
        if config.with_navigation_grade == "seed":
            return rejected(sample.t_s, "attitude", "navigation_grade_ins")  # the heading seed only
        if self._heading_source is None:
            # without an origin yet: latitude 0 (the earth rate's vertical part then shows as a
            # drift of the source against the gyro: judged a compass, the safe side)
            lat = self.origin.lat_rad if self.origin is not None else 0.0
            self._heading_source = aid_attitude.HeadingSource(config, lat)
        src = self._heading_source
        if not self._replaying:
            src.observe(sample.t_s, sample.yaw_rad, aid_heading.predict(self._x)[0] - self._yaw_fix_rad)
        r = src.r_rad2(sample.t_s)
        if r is None:
            return rejected(sample.t_s, "attitude", "navigation_grade_ins")  # not an INS's heading
        sample = dataclasses.replace(sample, yaw_rad=src.heading_rad(sample.yaw_rad))
        meas = aid_heading.measure(sample, self._x, math.sqrt(r))
        h = meas.H[0]
        if float(h @ kalman.propagated_covariance(self._P, self._acc, self._qdiag) @ h) <= r:
            return rejected(sample.t_s, "attitude", "heading_known_better")
        status = self._fuse(meas, sample.t_s, "attitude")
        if self._rejected_too_long(status, self.config.reset.attitude_after_s):
            self._reset_attitude(sample, meas, status)
            status = self._fuse(aid_heading.measure(sample, self._x, math.sqrt(r)), sample.t_s, "attitude")
        return status

    def _yaw_of(self, dx: np.ndarray) -> float:
        """The heading change (rad) of the error-state correction ``dx`` (the heading row of
        the attitude Jacobian, :func:`adaptnav.fusion.aiding.heading.measure`)."""
        _, pitch, yaw = aid_attitude.predict(self._x)
        t = math.tan(pitch)
        return float(math.cos(yaw) * t * dx[ATT][0] + math.sin(yaw) * t * dx[ATT][1] + dx[ATT][2])

    def _rejected_too_long(self, status: AidStatus, after_s: float) -> bool:
        """This aid has been gated continuously for ``after_s`` (the run restarts after a reset)."""
        src = status.source
        if status.fused or status.reason != "gate":
            self._reject_since.pop(src, None)
            return False
        # in state time: across an IMU gap the state is stale, and the gap has its own reset
        t_now = float(self._clock[0])
        t0 = self._reject_since.setdefault(src, t_now)
        if t_now - t0 < after_s:
            return False
        self._reject_since.pop(src, None)
        return True

    def _after_reset(self, what: str, source: str, t_s: float) -> None:
        self._reset_counter += 1
        self.resets[f"{what}:{source}"] += 1
        self._t_reset = float(self._clock[0])
        self._nis.clear()

    def _reset_attitude(self, sample, meas: Measurement, status: AidStatus) -> None:
        """Attitude (heading: yaw only) to the aid's; its covariance to the aid's, uncorrelated.

        Uncorrelated with the clones too: the attitude error is replaced by one independent of
        every past epoch, so ``Cov(δθ, d_i) = 0`` — the attitude rows of the clones' pending
        map are zeroed after the flush (they kept the old cross-covariance, and the next loop
        closure corrected the new attitude by it). A heading-only reset keeps the tilt but zeroes
        its correlations as ``P`` does: the joint covariance must stay one matrix, positive
        semi-definite (the attitude block and the rest, each a principal block of it)."""
        kalman.flush_core(self._core, self._qdiag)
        self._clones.zero_rows(ATT)
        roll, pitch, yaw = aid_attitude.predict(self._x)
        if meas.z.size == 3:  # the whole attitude (a heading-only measurement keeps the tilt)
            roll, pitch = sample.roll_rad, sample.pitch_rad
            var = np.diag(meas.R)
        else:
            var = np.array([*np.diag(self._P)[ATT_TILT], meas.R[0, 0]])
        self._yaw_fix_rad += math.remainder(sample.yaw_rad - yaw, 2.0 * math.pi)
        self._x[X_Q] = euler_to_quat(roll, pitch, sample.yaw_rad)
        self._P[ATT, :] = 0.0
        self._P[:, ATT] = 0.0
        self._P[ATT, ATT] = np.diag(var)
        self._after_reset("attitude", status.source, status.t_s)

    def _reset_velocity(self, meas: Measurement, status: AidStatus) -> None:
        """Velocity to what the aid says (the innovation solved through H's velocity block),
        its error independent of everything else: of the clones too (their pending map's
        velocity rows zeroed after the flush, as in :meth:`_reset_attitude`)."""
        kalman.flush_core(self._core, self._qdiag)
        self._clones.zero_rows(VEL)
        Hv = meas.H[:, VEL]
        dv, *_ = np.linalg.lstsq(Hv, meas.innovation(), rcond=None)
        self._x[X_VEL] += dv
        Hv_pinv = np.linalg.pinv(Hv)
        self._P[VEL, :] = 0.0
        self._P[:, VEL] = 0.0
        self._P[VEL, VEL] = Hv_pinv @ meas.R @ Hv_pinv.T + np.eye(3) * 1e-6
        self._after_reset("velocity", status.source, status.t_s)

    def _dvl_lock(self, t_s: float) -> None:
        """A bottom-track sample with lock: a DVL vehicle, k_speed walks slowly from now on
        (the walk written only when it is not already the DVL's: ~2 µs of every sample)."""
        self._t_dvl_lock = float(t_s)
        if self._qdiag[KS.start] != self.config.dvl.k_speed_rw_rthz ** 2:
            self._set_k_speed_walk(True)

    def _set_k_speed_walk(self, dvl_lock: bool) -> None:
        """k_speed's random walk: slow once the DVL has had lock (``dvl.k_speed_rw_rthz``)."""
        rw = self.config.dvl.k_speed_rw_rthz if dvl_lock else self.config.process.k_speed_rw_rthz
        self._qdiag[KS] = rw ** 2

    def _fuse_position(self, meas: Measurement, t_s: float, source: str) -> AidStatus:
        """Fuse an absolute position; reset onto gated fixes only on consistent evidence.

        A gated fix joins the evidence of its source. A reset needs
        ``position_reset_after_rejections`` gated fixes that are mutually consistent and
        each within reach of the last accepted fix, both at
        ``position_reset_max_speed_m_s`` (+ 3σ): a spoofer repeating a fix 1 km away is
        consistent with itself but not with where the vehicle can have gone. A fused fix
        clears the evidence. The reset inflates the position covariance by the
        innovation's outer product (plus R), so the fix pulls the state and the
        velocity-related states follow; it is recorded in :attr:`position_resets` as
        ``(t_s, source, size_m)``.
        """
        if not self._pos_unknown:
            self._fold_heading_frame()
        status = self._seed_position(meas, t_s, source) if self._pos_unknown else self._fuse(meas, t_s, source)
        ne = (float(meas.z[0]), float(meas.z[1]))
        sigma = math.sqrt(max(float(meas.R[0, 0]), float(meas.R[1, 1])))
        if status.fused:
            self._fix_evidence = {"last_fix": (float(t_s), ne, sigma)}
            self._anchor_ne = (float(self._x[0]), float(self._x[1]))
            return status
        if status.reason != "gate":
            return status
        cfg = self.config
        fixes = tuple(f for f in self._fix_evidence.get(source, ())
                      if t_s - f[0] <= cfg.position_reset_window_s)[-31:] + ((float(t_s), ne, sigma),)
        self._fix_evidence = {**self._fix_evidence, source: fixes}
        if len(self._consistent_fixes(fixes)) < cfg.position_reset_after_rejections:
            return status
        y = meas.innovation()
        idx = np.arange(y.size)  # position rows: POS is the first block
        # an inflation (independent noise added to the position error): its covariances with
        # the other states and with the clones are unchanged (as _doubt_k_speed)
        self._P[np.ix_(idx, idx)] += np.outer(y, y) + meas.R
        self._reset_counter += 1
        self.rejected["position_reset"] += 1
        self.position_resets.append((float(t_s), source, float(np.hypot(y[0], y[1]))))
        self._fix_evidence = {k: v for k, v in self._fix_evidence.items() if k != source}
        return self._fuse(meas, t_s, source)

    def _fold_heading_frame(self) -> None:
        """Before an absolute fix: the track the autopilot's heading frame has turned since the
        last fix (:func:`~adaptnav.fusion.aiding.attitude.reference_yaw_covariance`, its position
        block) becomes position uncertainty of the state, and the track is counted again from
        here. The fix is then gated and fused against what the published covariance says
        (against the internal one, a correct fix 1.8° × 450 m off after a long track on the
        autopilot's heading was refused or pulled the position only part of the way). Added as
        independent noise: its covariances with the other states and with the clones are
        unchanged (as :meth:`_doubt_k_speed`), and no later ATTITUDE can explain it away."""
        sigma_b = self._reference_yaw_sigma_rad
        if not (self._yaw_frame and sigma_b > 0.0 and self._mode == "ins"):
            return
        kalman.flush_core(self._core, self._qdiag)
        self._P[POS_NE, POS_NE] += aid_attitude.reference_yaw_covariance(self._x, self._anchor_ne, sigma_b)[POS_NE, POS_NE]
        self._anchor_ne = (float(self._x[0]), float(self._x[1]))

    def _seed_position(self, meas: Measurement, t_s: float, source: str) -> AidStatus:
        """The first fix when the horizontal position has no information (the start took the
        origin, ``initial.sigma_pos_m``) and the fix is within the gate of that: the position
        becomes the fix's, its covariance the fix's, uncorrelated — as if the fix had come
        before the start. Fused as an update
        instead, the arbitrary start would keep a weight σ_fix²/(σ_fix² + σ_0²) (2.5 % for a
        1.6 m fix) — and an origin taken from this very fix (a replay's) counts it twice,
        pulling the position back by that share of the motion since the start (0.1–0.2 m on
        the navigation-grade AUV class, tests/service/test_auv_navgrade.py)."""
        kalman.flush_core(self._core, self._qdiag)
        y = meas.innovation()
        S = meas.H @ self._P @ meas.H.T + meas.R  # reported as for an update
        nis = float(y @ np.linalg.solve(S, y))
        if self.origin_is_start and not nis <= self._gate[y.size]:
            # beyond what the start allows (a launch point known within σ_0, a spoofed or wild
            # first fix): gated like any fix, a reset only on consistent evidence. A start that
            # is not the origin allows anything: a fix 60 s into the log, 90 m from where the
            # vehicle started, was gated and the whole track stayed 90 m off
            return self._fuse(meas, t_s, source)
        self.position_seeds.append((float(t_s), float(y[0]), float(y[1])))
        self._x[X_POS_NE] += y[:2]
        self._P[POS_NE, :] = 0.0
        self._P[:, POS_NE] = 0.0
        self._P[POS_NE, POS_NE] = meas.R[:2, :2]
        self._pos_unknown = False
        if self._clones.active:
            self._clones.clear()  # their positions were relative to the arbitrary start
        self._reset_counter += 1  # a jump the autopilot must not take for motion
        return AidStatus(float(t_s), source, tuple(meas.z.tolist()), tuple(y.tolist()), tuple(np.diag(S).tolist()),
                         nis / self._gate[y.size], True, "")

    def _consistent_fixes(self, fixes: tuple) -> list:
        """The newest fix and the older ones consistent with it and with each other (greedy,
        newest first), all within reach of the last accepted fix."""
        v = self.config.position_reset_max_speed_m_s
        last = self._fix_evidence.get("last_fix")

        def reach(a, b) -> bool:
            d = math.hypot(a[1][0] - b[1][0], a[1][1] - b[1][1])
            return d <= v * abs(a[0] - b[0]) + 3.0 * math.hypot(a[2], b[2])

        chosen: list = []
        for f in reversed(fixes):
            if last is not None and not reach(f, last):
                continue
            if all(reach(f, g) for g in chosen):
                chosen.append(f)
        return chosen

    def _fuse(self, meas: Measurement, t_s: float, source: str) -> AidStatus:
        y = meas.innovation()
        m = y.size
        sdiag = self._sdiag[:m]
        # a non-finite y, H or R gives a NaN NIS, which the gate rejects before P is touched;
        # the clones' cross-covariances follow the flush and the update in the kernel
        nis, fused = kalman.fuse_core(self._core, self._qdiag, y, meas.H, meas.R, self._gate[m],
                                      self._dx, sdiag, self._mode == "ins")
        return self._attempt(t_s, source, tuple(meas.z.tolist()), tuple(y.tolist()), tuple(sdiag.tolist()),
                             nis, fused)

    def _attempt(self, t_s: float, source: str, z: tuple, y: tuple, s_diag: tuple, nis: float,
                 fused: bool) -> AidStatus:
        """The status of an update attempt (``z``, ``y``, diag S as tuples of floats; ``nis``
        and ``fused`` as :func:`~adaptnav.fusion.kalman.gated_update` returns them) and what
        follows from it (after :meth:`_fuse`, and the compiled path :meth:`_fast_scalar`)."""
        m = len(y)
        if fused:
            if source in self._motion_aids or (
                    source == "learned_velocity" and self._attitude_driven
                    and self._P[KS.start, KS.start] <= self.config.attitude_driven.calibrated_sigma_k_speed ** 2):
                self._t_motion_aid = float(t_s)
            if self._heading_source is not None:
                self._yaw_fix_rad += self._yaw_of(self._dx)
            reason = ""
            if self._recovering:
                self._fused_since_recovery += 1
                self._recovering = self._fused_since_recovery < _FUSIONS_TO_CONVERGE
        elif math.isfinite(nis):
            reason = "gate"
        else:
            self.rejected["non_finite"] += 1
            reason = "non_finite"
        test_ratio = float(nis) / self._gate[m]
        status = AidStatus(float(t_s), source, z, y, s_diag, test_ratio, bool(fused), reason)
        if not self._replaying:
            self._monitor(source, test_ratio, m, reason)
        return status

    def _monitor(self, source: str, test_ratio: float, m: int, reason: str) -> None:
        """Feed an attempt's NIS (its status's ``test_ratio`` × the gate of its ``m`` rows) to the
        integrity monitor (INS mode; fused or gated). The status's fields as arguments: the
        attempt has them at hand (~93k attempts per data hour)."""
        if self._mode == "ins" and reason in ("", "gate"):
            self._nis.add(source, test_ratio * self._gate[m], m)
