r"""IMU grade profiles (noise, bias, bias random walk per class) and the ``auto`` choice.

Conventions as :mod:`adaptnav.fusion.config` (continuous-time densities, Groves 2013 §14.2.6).
Figures are the class's datasheet values, rounded towards the pessimistic side; each
can be overridden one by one in ``[filter.imu]``.

- ``consumer`` — the MEMS parts in autopilots. Every flight controller ArduSub/ArduPilot runs on
  carries them (Pixhawk 1: InvenSense MPU-6000; Pixhawk 4: ICM-20689, BMI055; Pixhawk 6C/6X:
  ICM-42688-P, BMI055/BMI088; Cube Orange: ICM-20948, ICM-20649, ICM-20602; Blue Robotics
  Navigator: ICM-20602). Datasheet white-noise densities, gyro / accelerometer (checked
  2026-11-24 against the datasheets' text as published):
  MPU-6000 (PS-MPU-6000A-00 rev 3.4, §6.1/6.2) rate noise spectral density 0.005 °/s/√Hz at
  10 Hz, accelerometer 400 µg/√Hz at 10 Hz; initial zero-rate tolerance ±20 °/s, zero-g
  ±50 mg (X, Y) and ±80 mg (Z); ICM-20602 (DS-000176 rev 1.0) 4 mdps/√Hz, 100 µg/√Hz;
  ICM-42688-P (DS-000347 v1.7) 2.8 mdps/√Hz, 70 µg/√Hz — the quietest of them,
  4.9e-5 rad/s/√Hz (:data:`MEMS_GYRO_DENSITY_FLOOR`); Bosch BMI088 gyro 0.014 °/s/√Hz (Bosch
  Sensortec's support, the BMG160 gyro it contains; its accelerometer's density was not
  found in a source we could read). None of these datasheets states an in-run bias
  instability. On a vehicle, through
  an autopilot's decimated MAVLink stream, the white noise is far larger: ArduPilot's EKF3
  defaults (EK3_ACC_P_NSE, EK3_GYRO_P_NSE) are used. An autopilot trims the
  gyro offset at boot; what remains over a dive is tens to hundreds of °/h (0.1 °/s taken),
  accelerometer offsets after calibration ~10 mg; in-run instability ~10 °/h, 0.1 mg (the
  class's order of magnitude, not a datasheet figure) — but the gyro's bias also moves with
  temperature over a dive, so its random walk is EKF3's (EK3_GBIAS_P_NSE), not the instability's.
- ``tactical`` — MEMS tactical IMUs: Analog Devices ADIS16495 (ARW 0.12 °/√h, in-run bias
  0.8 °/h, VRW 0.008 m/s/√h; not re-checked), Safran STIM300 (datasheet rev 9, 10 g
  accelerometers: ARW 0.15 °/√h, bias instability 0.5 °/h, VRW 0.06 m/s/√h, accelerometer
  bias instability 0.05 mg); bias 1-σ 2 °/h, 0.5 mg.
- ``navigation`` — fibre-optic gyro INS of the iXblue PHINS / Honeywell HG9900 class:
  gyro bias < 0.01 °/h, ARW ≈ 0.0025 °/√h; accelerometer bias ≈ 50 µg, noise ≈ 15 µg/√Hz.
  These see the earth rate (15 °/h): mechanised with earth rate, Coriolis and normal
  gravity by default (:mod:`adaptnav.fusion.strapdown`).

Quantisation (``RAW_IMU`` / ``SCALED_IMU*``: int16 in 1 mg and 1 mrad/s) adds white noise of
variance ``q²/12`` per sample, i.e. density ``q √(Δt/12)`` at sample interval Δt
(Widrow & Kollár, *Quantization Noise*, 2008, ch. 4). It is detected from the data (every
sample on the 1 mg / 1 mrad/s grid ⇒ an autopilot's integer IMU message ⇒ ``consumer``).

``auto`` decides from who measured the samples (:attr:`adaptnav.fusion.samples.ImuSample.source`,
set by the reader: the MAVLink converter marks the autopilot's own IMU messages) and from the
noise measured in the alignment window (at rest or cruising: :func:`white_sigma`):

1. samples on the RAW_IMU grid, or the autopilot's own IMU (``source = "autopilot"``: RAW_IMU /
   SCALED_IMU*, a DataFlash log's IMU, or HIGHRES_IMU from the flight controller's component
   on its boot clock — a UNIX-stamped one, or one from a "generic autopilot", is a vehicle
   computer's IMU of its own) ⇒
   ``consumer``, whatever the noise measured: the part is a MEMS (above), and what the stream
   shows of its noise is not the part's — ArduPilot low-pass filters gyro and accelerometer
   before it streams them (INS_GYRO_FILTER / INS_ACCEL_FILTER, 20 Hz by default), and its
   simulator's IMU is near noise-free (ArduSub SITL's HIGHRES_IMU at rest: 5.9e-6 rad/s/√Hz,
   eight times below the quietest MEMS part, which the noise rule would call tactical);
2. a measured gyro noise below any physical gyro's (:data:`PHYSICAL_GYRO_DENSITY_MIN`, a
   sixth of the best navigation-grade ARW cited below) is no measurement of a sensor — a
   simulator's or a re-sampled stream's — and promotes nothing ⇒ ``consumer`` (the class
   whose larger process noise cannot make the filter overconfident);
3. otherwise the measured gyro density picks the class (above
   :data:`CONSUMER_GYRO_DENSITY_MIN` ⇒ consumer, below :data:`NAVIGATION_GYRO_DENSITY_MAX` ⇒
   navigation, else tactical): a dedicated IMU (``source = "dedicated"``, e.g. a companion's
   FOG driver) or one of unknown origin.

For a consumer IMU chosen by ``auto`` the white-noise densities used are never below what was
measured (vibration of an armed vehicle is noise to the filter). :attr:`ResolvedImu.why` says
which rule decided.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .frames import GRAVITY_M_S2

DEG = math.pi / 180.0
HOUR = 3600.0
MG = 1e-3 * GRAVITY_M_S2
UG = 1e-6 * GRAVITY_M_S2

GRADES = ("consumer", "tactical", "navigation")
# RAW_IMU / SCALED_IMU* resolution (ArduPilot: mg and mrad/s in int16)
RAW_IMU_ACC_LSB_M_S2 = MG
RAW_IMU_GYRO_LSB_RAD_S = 1e-3
# class boundaries on the measured gyro white-noise density (rad/s/√Hz): between the
# consumer (≥ 7e-5) and tactical (≤ 4.4e-5) datasheet figures, and between tactical and
# navigation (≤ 1e-6)
CONSUMER_GYRO_DENSITY_MIN = 7.0e-5
NAVIGATION_GYRO_DENSITY_MAX = 5.0e-6
# the quietest MEMS gyro in an autopilot (ICM-42688-P, 0.0028 °/s/√Hz): an autopilot's stream
# measured below it is filtered or simulated, not a better part
MEMS_GYRO_DENSITY_FLOOR = 0.0028 * DEG
# no physical gyro is quieter: a sixth of the navigation class's best ARW (Honeywell HG9900
# ≤ 0.002 °/√h = 5.8e-7 rad/s/√Hz); a stream measured below it carries no sensor noise
PHYSICAL_GYRO_DENSITY_MIN = 1.0e-7


@dataclass(frozen=True)
class ImuFigures:
    """One class's figures (units as :class:`adaptnav.fusion.config.ImuConfig`)."""

    acc_noise_m_s2_rthz: float
    gyro_noise_rad_s_rthz: float
    acc_bias_sigma_m_s2: float
    gyro_bias_sigma_rad_s: float
    acc_bias_rw_m_s3_rthz: float
    gyro_bias_rw_rad_s2_rthz: float


PROFILES: dict[str, ImuFigures] = {
    "consumer": ImuFigures(
        # ArduPilot EKF3's defaults for these parts on a vehicle, EK3_ACC_P_NSE = 0.35 m/s² and
        # EK3_GYRO_P_NSE = 0.015 rad/s per 10 ms prediction step (×√0.01 s → densities): ~9× and
        # ~17× the MPU-6000 datasheet's 400 µg/√Hz and 0.005 °/s/√Hz, for vibration of an
        # armed vehicle and the aliasing of a decimated sample stream (the datasheet figures
        # made the freedrive replay's velocity innovations fail the NIS test)
        acc_noise_m_s2_rthz=0.35 * math.sqrt(0.01),
        gyro_noise_rad_s_rthz=0.015 * math.sqrt(0.01),
        acc_bias_sigma_m_s2=10 * MG,
        gyro_bias_sigma_rad_s=0.1 * DEG,                   # 360 °/h after boot trimming
        acc_bias_rw_m_s3_rthz=0.1 * MG * math.sqrt(2.0 / 100.0),   # 0.1 mg over ~100 s
        # EKF3's EK3_GBIAS_P_NSE = 1e-3 rad/s² per 10 ms step (×√0.01 s): 1e-4 rad/s²/√Hz, ~1 mrad/s
        # (200 °/h) a minute. An autopilot's MEMS drifts with its temperature (a hull warming, a dive
        # into cold water), and ArduSub's SITL models it (SIM_DRIFT_SPEED 0.05 °/s per minute, a
        # 5 min ramp): its DataFlash log (float IMU; RAW_IMU's int mrad/s hides most of it) showed
        # the bias go 0.7 → 4.3 mrad/s in 4 min, which the former 10 °/h over 100 s (6.9e-6) could
        # not follow — the lag went into tilt and the current, 5.25 % of distance, now 1.80 %
        gyro_bias_rw_rad_s2_rthz=1.0e-3 * math.sqrt(0.01),
    ),
    "tactical": ImuFigures(                                # STIM300 / ADIS16495 class
        acc_noise_m_s2_rthz=0.0006,                        # ≈ 0.036 m/s/√h
        gyro_noise_rad_s_rthz=5.0e-5,                      # ≈ 0.17 °/√h
        acc_bias_sigma_m_s2=0.005,                         # ≈ 0.5 mg
        gyro_bias_sigma_rad_s=1.0e-5,                      # ≈ 2 °/h
        acc_bias_rw_m_s3_rthz=1.0e-5,
        gyro_bias_rw_rad_s2_rthz=1.0e-7,
    ),
    "navigation": ImuFigures(                              # PHINS / HG9900 class
        acc_noise_m_s2_rthz=15 * UG,
        gyro_noise_rad_s_rthz=0.0025 * DEG / math.sqrt(HOUR),
        acc_bias_sigma_m_s2=50 * UG,
        gyro_bias_sigma_rad_s=0.01 * DEG / HOUR,
        acc_bias_rw_m_s3_rthz=1.0e-6,
        gyro_bias_rw_rad_s2_rthz=1.0e-10,
    ),
}


def on_raw_imu_grid(f_b_m_s2: np.ndarray, w_b_rad_s: np.ndarray) -> bool:
    """Every sample is an integer number of 1 mg and 1 mrad/s (an autopilot's int16 IMU message)."""
    f = np.asarray(f_b_m_s2, float) / RAW_IMU_ACC_LSB_M_S2
    w = np.asarray(w_b_rad_s, float) / RAW_IMU_GYRO_LSB_RAD_S
    if f.size == 0:
        return False
    return bool(np.all(np.abs(f - np.round(f)) < 1e-6) and np.all(np.abs(w - np.round(w)) < 1e-6))


def white_sigma(x: np.ndarray, robust: bool = False) -> float:
    """Largest per-axis 1-σ of the white noise in samples ``x`` (N, 3), from second differences
    (std(Δ²x)/√6): the vehicle's own motion — roll and pitch oscillating by a degree, turns,
    accelerations — changes smoothly from one sample to the next and drops out, so a vehicle
    that is cruising, not at rest, still shows its IMU's noise (a plain std would call a FOG on a
    rolling AUV a consumer part).  ``robust``: from the median absolute second difference
    (1.4826 median|Δ²x|/√6, the same σ for Gaussian noise) — a few steps of the turn rate in
    the window (a rudder kick, a thruster change) leave it alone, where they dominate the
    std: what the grade is decided on.  0 with fewer than 3 samples."""
    x = np.asarray(x, float).reshape(-1, 3)
    if len(x) < 3:
        return 0.0
    d2 = np.diff(x, n=2, axis=0)
    if robust:
        return float(np.max(1.4826 * np.median(np.abs(d2), axis=0))) / math.sqrt(6.0)
    return float(np.max(np.std(d2, axis=0))) / math.sqrt(6.0)


@dataclass(frozen=True)
class ResolvedImu:
    """What the estimator uses: the class, its figures (overrides applied), quantisation."""

    grade: str
    figures: ImuFigures
    quantized: bool
    measured_acc_density: float
    measured_gyro_density: float
    earth_rotation: bool
    source: str = ""   # ImuSample.source of the samples it was resolved from
    why: str = ""      # what decided the grade (configured, or the auto rule that applied)


def attitude_driven(cfg, attitude_rate_hz: float) -> ResolvedImu:
    """The virtual IMU of an attitude-driven strapdown (``[filter.attitude_driven]``,
    :class:`~adaptnav.fusion.config.AttitudeDrivenConfig`): its gyro is the rotation between
    consecutive attitude samples, its accelerometer gravity in the body frame — no biases
    (the increments have none: a tenth of a consumer MEMS's, held nearly constant), its
    accelerometer noise the vehicle's own unmodelled acceleration."""
    figures = ImuFigures(
        acc_noise_m_s2_rthz=cfg.acc_noise_m_s2_rthz,
        gyro_noise_rad_s_rthz=cfg.gyro_noise_rad_s_rthz,
        acc_bias_sigma_m_s2=1.0 * MG,
        gyro_bias_sigma_rad_s=0.01 * DEG,
        acc_bias_rw_m_s3_rthz=0.0,
        gyro_bias_rw_rad_s2_rthz=0.0,
    )
    why = (f"no IMU fast enough to integrate: the attitude's increments ({attitude_rate_hz:.1f} Hz) drive "
           "the strapdown, the vehicle's accelerations are process noise")
    return ResolvedImu("attitude", figures, False, math.nan, math.nan, False, "attitude", why)


def resolve(cfg, f_b_m_s2: np.ndarray, w_b_rad_s: np.ndarray, dt_s: float, source: str = "") -> ResolvedImu:
    """The IMU model from ``cfg`` (:class:`~adaptnav.fusion.config.ImuConfig`) and a window
    of samples (N, 3) taken ``dt_s`` apart (the alignment window); ``source``: who measured
    them (:attr:`adaptnav.fusion.samples.ImuSample.source`, ``""`` unknown)."""
    f = np.asarray(f_b_m_s2, float).reshape(-1, 3)
    w = np.asarray(w_b_rad_s, float).reshape(-1, 3)
    dt = dt_s if math.isfinite(dt_s) and dt_s > 0 else 0.01
    quantized = on_raw_imu_grid(f, w) if cfg.quantization == "auto" else cfg.quantization == "raw_imu"
    rt = math.sqrt(dt)
    acc_d = white_sigma(f) * rt
    gyro_d = white_sigma(w) * rt
    # the class from the gyro's noise alone, steps of the vehicle's turn rate aside (a FOG on an
    # AUV whose simulator steps its yaw rate every second, 0.25–4 mrad/s, measured a tactical
    # gyro's std in 4 of 5 alignment windows); the consumer floor below from all of it
    grade, why = auto_grade(cfg.grade, quantized, white_sigma(w, robust=True) * rt, source, len(w))
    base = PROFILES[grade]
    q_acc = RAW_IMU_ACC_LSB_M_S2 * math.sqrt(dt / 12.0) if quantized else 0.0
    q_gyro = RAW_IMU_GYRO_LSB_RAD_S * math.sqrt(dt / 12.0) if quantized else 0.0

    # an autopilot's MEMS on an armed vehicle: vibration and aliasing are noise to the filter
    measured_floor = cfg.grade == "auto" and grade == "consumer"

    def pick(name: str) -> float:
        v = getattr(cfg, name)
        return float(getattr(base, name)) if v is None else float(v)

    acc_noise = pick("acc_noise_m_s2_rthz")
    gyro_noise = pick("gyro_noise_rad_s_rthz")
    if cfg.acc_noise_m_s2_rthz is None:
        # measured at rest (includes vibration and quantisation) or the datasheet + quantisation
        acc_noise = max(math.hypot(acc_noise, q_acc), acc_d if measured_floor else 0.0)
    if cfg.gyro_noise_rad_s_rthz is None:
        gyro_noise = max(math.hypot(gyro_noise, q_gyro), gyro_d if measured_floor else 0.0)
    figures = ImuFigures(acc_noise, gyro_noise, pick("acc_bias_sigma_m_s2"), pick("gyro_bias_sigma_rad_s"),
                         pick("acc_bias_rw_m_s3_rthz"), pick("gyro_bias_rw_rad_s2_rthz"))
    earth = cfg.earth_rotation == "on" or (cfg.earth_rotation == "auto" and grade == "navigation")
    return ResolvedImu(grade, figures, quantized, acc_d, gyro_d, earth, source, why)


def auto_grade(configured: str, quantized: bool, gyro_density: float, source: str, n: int) -> tuple[str, str]:
    """``(grade, why)``: the configured grade, or ``auto``'s choice (module docstring, rules
    1–3) from the RAW_IMU grid, the measured gyro white-noise density (rad/s/√Hz), the
    samples' ``source`` and their number ``n``."""
    if configured != "auto":
        return configured, "configured"
    if n < 3:
        return "tactical", "nothing measured yet (before alignment)"
    if quantized:
        return "consumer", "on the RAW_IMU grid (1 mg, 1 mrad/s)"
    if source == "autopilot":
        quiet = gyro_density < MEMS_GYRO_DENSITY_FLOOR
        return "consumer", "the autopilot's own IMU (a flight controller's MEMS)" + (
            f"; its stream's gyro noise {gyro_density:.2g} rad/s/√Hz is below any MEMS part's: "
            "filtered or simulated" if quiet else "")
    if gyro_density < PHYSICAL_GYRO_DENSITY_MIN:
        return "consumer", f"gyro noise {gyro_density:.2g} rad/s/√Hz: below any physical gyro's, not promoted"
    measured = f"measured gyro noise {gyro_density:.2g} rad/s/√Hz"
    if gyro_density >= CONSUMER_GYRO_DENSITY_MIN:
        return "consumer", measured
    if gyro_density <= NAVIGATION_GYRO_DENSITY_MAX:
        return "navigation", measured
    return "tactical", measured
