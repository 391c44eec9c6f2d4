"""Configuration of the navigation filter (one typed tree, built with :mod:`adaptnav.fusion.typed_config`).

Every number the ESKF uses lives here with its unit in its name. Build it from TOML with
``typed_config.load_toml(FilterConfig, text, overrides)`` (unknown keys are an error) or
take the defaults ``FilterConfig()``.

Noise conventions (continuous-time power spectral densities, as in Groves 2013, §14.2.6):

- ``imu.acc_noise_m_s2_rthz`` velocity random walk density (m/s²/√Hz) → Q_vel = σ² per s,
- ``imu.gyro_noise_rad_s_rthz`` angle random walk density (rad/s/√Hz) → Q_att = σ² per s,
- ``imu.acc_bias_rw_m_s3_rthz`` / ``imu.gyro_bias_rw_rad_s2_rthz`` bias random walk densities,
- ``imu.acc_bias_sigma_m_s2`` / ``imu.gyro_bias_sigma_rad_s`` initial (turn-on + instability)
  1-σ of the biases; bias instability is folded into these and into the random walk.

The IMU figures come from ``imu.grade`` (:mod:`adaptnav.fusion.imu_grades`: datasheet
classes ``consumer`` / ``tactical`` / ``navigation``, or ``auto`` from the data); a figure
set here overrides its class's.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

from scipy import special

from .integrity import chi2_quantile
from .plausibility import PlausibilityConfig


@dataclass(frozen=True)
class ImuConfig:
    """IMU error model: a grade's datasheet figures, each overridable (None: the grade's)."""

    grade: Literal["auto", "consumer", "tactical", "navigation"] = "auto"
    acc_noise_m_s2_rthz: float | None = None
    gyro_noise_rad_s_rthz: float | None = None
    acc_bias_sigma_m_s2: float | None = None
    gyro_bias_sigma_rad_s: float | None = None
    acc_bias_rw_m_s3_rthz: float | None = None
    gyro_bias_rw_rad_s2_rthz: float | None = None
    # "raw_imu": samples quantised to 1 mg / 1 mrad/s (adds q²/12 per sample); "auto": detected
    quantization: Literal["auto", "none", "raw_imu"] = "auto"
    # earth rate, Coriolis and normal gravity in the mechanisation ("auto": navigation grade)
    earth_rotation: Literal["auto", "on", "off"] = "auto"
    # body-frame position of the IMU relative to the vehicle reference point (m): the point
    # the filter navigates; every other lever arm is relative to the same reference point
    lever_arm_b_m: tuple[float, float, float] = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class ProcessConfig:
    current_rw_m_s_rthz: float = 1.0e-4        # sea current random walk, (m/s)/√s
    # RPM speed-scale random walk, 1/√s: large enough to follow a change of water
    # (k_V −10 %) within minutes while absolute fixes exist
    k_speed_rw_rthz: float = 1.5e-3
    pos_noise_m_rthz: float = 1.0e-4           # keeps P[POS] from going singular


@dataclass(frozen=True)
class InitialConfig:
    sigma_pos_m: float = 10.0
    sigma_vel_m_s: float = 1.0
    sigma_att_rad: float = 0.02
    sigma_yaw_rad: float = 0.05
    sigma_current_m_s: float = 0.3
    sigma_k_speed: float = 0.1


@dataclass(frozen=True)
class LearnedVelocityConfig:
    enabled: bool = True
    # fused at a fixed rate, not per IMU sample; 1 Hz matches the motion model's step
    # (its variances are per step: faster fusion would count the same error twice)
    rate_hz: float = 1.0
    # the updates at t = k / rate_hz + phase_s (s): half the service's default output period
    # (outputs.nav_rate_hz 10 Hz), so that none falls on an output epoch. One there ran on
    # the way to that epoch's published state: ~0.2 ms of a live nav state's latency, in
    # one epoch in 16 (issue 17); between epochs it runs with the samples held for the next
    phase_s: float = 0.05
    rpm_hold_s: float = 1.0                    # latest RpmSample is used this long
    sigma_heave_m_s: float = 0.05              # heave ≈ 0 pseudo-measurement
    variance_scale: float = 1.0                # inflation of the motion model's variances
    # lateral speed per lateral-thrust RPM relative to the surge table (vehicles with
    # lateral thrusters: RpmSample.sway_rpm)
    sway_speed_scale: float = 1.0
    # the vehicle's speed follows a thrust change with this first-order time constant (s)
    # (mass over linear drag); 0: at once
    response_time_s: float = 0.0
    # a vehicle whose response to thrust is not known (the uncalibrated motion prior): while a
    # thrust change settles, its speed lies anywhere between the command's and the command's
    # through a first-order lag of this time constant (s), and the surge and sway variances take
    # that gap, (g k_speed k_V (u − u_slow))², so a coasting stop or a spin-up is not read as a
    # speed-scale error. 0: off (a calibrated vehicle: response_time_s models it)
    transient_time_s: float = 0.0
    # g: the gap's 1-σ multiple. A coast is not a first-order lag (quadratic drag leaves a slow
    # tail) and the gap is a scale of the error, not its bound: at 1 each 1 Hz update of a coast
    # still moved the position back 0.4–0.6 m through k_speed's covariance with it (ArduSub stop-
    # and-go drives, docs/vehicle.md "Drives of other shapes": worst log 4.87 % at 1, 4.34 % at 2, 4.15 % at 3)
    transient_sigma_per_gap: float = 3.0
    # ... except while the thrust falls (a coast: the slow lag's speed above the command's). A
    # hull under thrust reaches its new speed fast (thrust ≫ drag at low speed: ArduSub SITL's
    # BlueROV2 in ~0.3 s), one coasting slows on drag alone, v₀/(1 + t/τ) for quadratic drag, a
    # tail that stays well above the command: SITL 0.09 / 0.05 / 0.03 m/s at 1.5 / 3.5 / 5.5 s
    # after a 0.53 m/s lane, the slow lag (2 s) 0.25 / 0.09 / 0.03. Read as "0 ± 3 gaps" each
    # 1 Hz update of the tail had an innovation of one sign, which k_speed's covariance with the
    # position turned into the position moving back 1–2.3 m at every stop. In a coast the speed
    # is taken at coast_mean_fraction of the way from the command to the slow lag, 1σ
    # coast_sigma_per_gap gaps (the 17 ArduSub SITL logs, docs/vehicle.md "Stops and the autopilot's
    # tilt": stops tlog 4.41 → 1.84 %)
    coast_mean_fraction: float = 0.5
    coast_sigma_per_gap: float = 1.0
    # a vehicle whose skid in a turn is not known (the uncalibrated motion prior): the sway
    # of a turning vehicle, β u w (MotionParams.sway_per_turn), with β unknown, σ_β (s): the
    # sway variance takes (σ_β k_speed k_V u w)², u the surge speed the vehicle may have (the
    # model's, or the slow lag's while a thrust change settles: a pivot right after a lane turns
    # a hull still coasting) and w the gyro's yaw rate. 0: off (a calibrated vehicle:
    # sway_per_turn models it)
    skid_sigma_s: float = 0.0
    # ... at most this fraction of that speed (the tangent of the sideslip angle's σ,
    # 0.2 ≈ 11°): a skid saturates (sway drag grows with the square of the sway: ArduSub's
    # BlueROV2 skids 8° at 4°/s and 13° at both 8 and 12°/s), and a pivot at a high yaw rate
    # with the speed coasting down does not skid faster than it moves
    skid_max_fraction: float = 0.2
    # ... and in a coast (the thrust fell below the slow lag's speed, see coast_mean_fraction):
    # a hull coasting through a pivot turns under the velocity it keeps, its sideslip is
    # anything (ArduSub SITL after a 0.8 m/s lane: course held within 7° while the hull yawed
    # 116°, sway 0.09 m/s at 0.15 m/s), so the bound is the speed itself
    coast_skid_max_fraction: float = 1.0
    # a vehicle that may change depth on vertical thrusters (an ROV) rather than by pitching (an
    # AUV) — not known under the uncalibrated motion prior: the heave variance takes
    # (this × v_d)², v_d the filter's vertical speed (the depth sensor's). ArduSub's BlueROV2
    # descends at 0.35 m/s level: "heave 0 ± 0.05" held the filter's v_d at half of that and
    # its innovations (0.2-0.3 m/s) failed the integrity test for 25 % of the submerged time
    # (brisk drive). 0: off (heave ≈ 0 ± sigma_heave_m_s)
    heave_sigma_per_vertical_speed: float = 0.0
    # a vehicle that may change depth on vertical thrusters (an ROV) — the horizontal drift of a
    # vertical run that no aid measured (no DVL fused during it): the position covariance grows
    # by (this × the run's depth change)² north and east (fusion/aiding/depth.py
    # vertical_run_step). Nothing in the motion model says where such a vehicle goes while it
    # dives or climbs; ArduSub's simulated BlueROV2 Heavy drifts 0.36 m per metre of depth
    # (2.2 m in a 6 m dive), its IMU followed about 70 % of that, and the 0.5 m left were outside
    # the 99 % ellipse (3–5 % of the valid submerged epochs of its tlogs). An AUV dives by
    # pitching, on its propeller: the model holds. 0: off (motion.uncalibrated_* raises it)
    vertical_drift_sigma_per_m: float = 0.0
    # innovation-based adaptive surge variance (Mehra 1972): R̂ = E[y²] − H P Hᵀ over this
    # window (s); the model's σ_V² is scaled up (never down) to R̂. 0 disables.
    adaptive_window_s: float = 120.0
    adaptive_max_scale: float = 25.0
    # after a calibrator release the released surge variance is used as it is for this
    # long (s): it replaces the innovation estimate, which is noisy and only ever scales
    # up (survey, 8 seeds: drift since the last fix 0.07 points lower on average); a
    # calibrator that stops releasing hands the surge variance back to it. 0: always adaptive.
    adaptive_suspend_after_release_s: float = 600.0


@dataclass(frozen=True)
class DvlConfig:
    enabled: bool = True
    # per-axis 1-σ the DVL is fused with at its rate: white noise (a few mm/s per ping) plus
    # the white-noise equivalent of its long-term errors (scale, misalignment, beam biases:
    # 0.2–0.5 % of speed, correlated over minutes, which fusion at 5 Hz would average away).
    # Survey with the simulated 600 kHz DVL (seed 1): NEES mean 118 with the beam noise alone
    # (7 mm/s), 13 with 0.03 (95 % band 2.7–19); drift since the last fix 0.09 % either way
    sigma_m_s: float = 0.03
    lever_arm_b_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    # 1-σ per axis of that lever arm (m): the velocity error ω × δl it leaves in turns is added
    # to the DVL's covariance (fusion/aiding/dvl.py lever_arm_doubt). The default is an arm
    # nobody measured (a DVL head within about half a metre of the IMU on a small AUV or ROV);
    # a surveyed installation: its survey's accuracy (≈ 0.01)
    lever_arm_sigma_m: float = 0.5
    rotation_bd_rpy_rad: tuple[float, float, float] = (0.0, 0.0, 0.0)  # R_bd maps d → b
    # scale factor and yaw misalignment, calibrated from fixes vs the DVL's own track
    # (fusion/aiding/dvl.py DvlCalibration): prior 1-σ; 0 for both: no calibration
    scale_sigma: float = 0.005
    misalignment_sigma_rad: float = 0.01
    # does the hull sideslip through the water on a straight leg? "none" (a torpedo AUV, no
    # lateral thrust): the DVL's lateral velocity on straights is its misalignment plus the
    # current, and reciprocal legs give the misalignment without fixes (DvlCalibration,
    # StraightLegs); "free" (an ROV with lateral thrusters, a tethered vehicle: a steady crab
    # would be taken for misalignment); "auto": free when the thrust is an autopilot's
    # (ArduSub's vectored ROVs), else none
    hull_sideslip: Literal["auto", "none", "free"] = "auto"
    # 1-σ of such a hull's mean sway over a straight-leg segment (≤ 1 min): waves, control (m/s)
    hull_sway_sigma_m_s: float = 0.003
    water_track: bool = True                   # fuse water-track velocities (relative to the water)
    water_track_sigma_m_s: float = 0.03
    # k_speed random walk (1/√s) on a vehicle whose DVL has had bottom lock, instead of
    # process.k_speed_rw_rthz: its calibrator re-learns k_V from the DVL (calibration.dvl_teacher),
    # and a fast k_speed absorbs the along-track current within each leg and wanders through a
    # DVL outage (dvl_outage seed 1, learned: error at the end of the outage 14.1 m with
    # 1.5e-3, 4.4 m with 1e-4)
    k_speed_rw_rthz: float = 1.0e-4


@dataclass(frozen=True)
class DepthConfig:
    enabled: bool = True
    sigma_m: float = 0.05
    water_density_kg_m3: float = 1025.0
    # 1-σ of that density (kg/m³): without a CTD aboard the water may be anything from sea
    # (1020–1030) to brackish or fresh (1000). Its error is a depth *scale*, unobservable at
    # constant depth and the same at every sample: the filter does not estimate it, the
    # published covariance carries it ((depth · σ_ρ/ρ)², Estimator._add_considered). 0: known.
    density_sigma_kg_m3: float = 0.0
    atmospheric_pressure_pa: float = 101325.0
    # the depth noise σ used is the sensor's own, measured from the depth signal's
    # high-frequency residual (fusion/aiding/depth.py DepthNoise: why this and not the
    # innovations, why 0.5 m), never below sigma_m and never above this bound (m); a sensor
    # noisier than the bound fails the integrity test (nis:depth). 0: sigma_m as configured
    adaptive_max_sigma_m: float = 0.5
    # body-frame (FRD) position of the sensor relative to the vehicle reference point (m);
    # the filter navigates the IMU (filter.imu.lever_arm_b_m) and models this aid here
    lever_arm_b_m: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def validate(self) -> None:
        if not 0.0 <= self.adaptive_max_sigma_m <= 10.0:
            raise ValueError("depth: adaptive_max_sigma_m must be within [0, 10] m (0: off)")


@dataclass(frozen=True)
class HeadingConfig:
    enabled: bool = True
    sigma_rad: float = math.radians(0.5)


@dataclass(frozen=True)
class AttitudeConfig:
    enabled: bool = True
    sigma_roll_pitch_rad: float = math.radians(0.5)
    sigma_yaw_rad: float = math.radians(2.0)
    # with a navigation-grade IMU: "learn" — what the ATTITUDE heading is worth is learned
    # from its variability against the gyro (fusion/aiding/attitude.py HeadingSource): an
    # INS-class heading (the vehicle's own PHINS/SPRINT: 0.01–0.1° sec L) is fused, a magnetic
    # one (a consumer AHRS: degrees off, correlated over minutes, which fused as white noise
    # would pull the INS onto its error) only seeds the heading and the DVL-aided FOG finds
    # north from the earth rate. "seed": never fused after the seed; "fuse": fused with
    # sigma_yaw_rad as with every other grade
    with_navigation_grade: Literal["learn", "seed", "fuse"] = "learn"
    # "learn": time constant (s) of the source's variability estimate against the gyro, and
    # the data (s) it needs before any decision
    learn_window_s: float = 60.0
    learn_min_s: float = 20.0
    # a source varying less than this (1-σ, rad) against a navigation-grade gyro is an INS's
    # heading: a PHINS varies by milli-degrees (its noise; its error drifts over the Schuler
    # period), a magnetic heading by ≥ 0.1° (noise, tilt compensation with the vehicle's
    # motion, the thrusters' fields)
    ins_max_variability_rad: float = math.radians(0.05)
    # the absolute heading accuracy assumed for an INS-class source (1-σ at the equator, rad;
    # × sec L): a constant offset does not show against the gyro. PHINS: 0.01° sec L with DVL
    # aiding, 0.05° sec L without
    ins_sigma_yaw_rad: float = math.radians(0.05)
    # the absolute accuracy of the autopilot's own heading (1-σ, rad), an error that stays for
    # minutes (a compass's residual deviation, its EKF's yaw): ATTITUDE fused at 10–50 Hz holds
    # the filter's yaw within ~0.2° of the autopilot's, so the filter navigates in the
    # autopilot's heading frame and the published covariance carries that frame's offset as a
    # consider parameter (fusion/aiding/attitude.py reference_yaw_covariance). ArduSub SITL: 0.6° rms with
    # correlation 0.7–0.9 after a minute (tests/fusion/test_attitude_reference.py); 0: off
    reference_yaw_sigma_rad: float = math.radians(2.0)
    # the autopilot's roll and pitch wander too (its EKF's tilt, 1 mg of accelerometer bias is
    # 0.06°): ArduSub SITL's ATTITUDE against SIM_STATE is 0.05–0.2° off, for minutes, and
    # moves by 0.1–0.15° within 10–30 s of a manoeuvre. Fused at 10–50 Hz, ATTITUDE holds the
    # filter's tilt on it, so g × that offset is an acceleration the strapdown integrates
    # (0.02–0.04 m/s²; velocity 0.15 m/s off by the end of a stop's coast) which only the
    # accelerometer bias can absorb: with a consumer IMU and ATTITUDE at the alignment, the
    # horizontal accelerometer biases' random walk takes (g × this)² beside the part's own
    # (rad/√s; 1e-4: 0.05° a minute). 0: off
    reference_tilt_rw_rad_rthz: float = 1.0e-4

    def validate(self) -> None:
        if not (0.0 <= self.reference_yaw_sigma_rad < 0.5):
            raise ValueError("attitude: reference_yaw_sigma_rad must be within [0, 0.5) rad")
        if not (0.0 <= self.reference_tilt_rw_rad_rthz < 0.01):
            raise ValueError("attitude: reference_tilt_rw_rad_rthz must be within [0, 0.01) rad/√s")
        if not (0.0 < self.learn_window_s <= 3600.0 and 0.0 <= self.learn_min_s <= 3600.0):
            raise ValueError("attitude: learn_window_s must be within (0, 3600] s and learn_min_s within [0, 3600] s")
        if not (0.0 < self.ins_max_variability_rad < 0.1 and 0.0 < self.ins_sigma_yaw_rad < 0.1):
            raise ValueError("attitude: ins_max_variability_rad and ins_sigma_yaw_rad must be within (0, 0.1) rad")


@dataclass(frozen=True)
class GnssConfig:
    enabled: bool = True
    max_depth_m: float = 0.5                   # surface-only: estimated depth below this
    # the part of a fix's σ that averaging does not remove: a receiver's error is correlated
    # over minutes (multipath, atmosphere; a consumer u-blox's short-term noise is a fraction of
    # its CEP), so fixes at 5 Hz for a minute are not 300 independent ones (σ_fix/17). After a
    # fused fix the horizontal position variance is at least (this × σ_fix)² (never above the
    # variance before the fix): what the vehicle takes under water is the receiver's error at
    # the dive. 1: a fix's σ is what a minute of them leaves — a consumer receiver's
    # short-term noise (~0.3 m) beside its metres of CEP (docs/vehicle.md, stop 31).
    # 0: every fix independent
    correlated_fraction: float = 1.0
    # body-frame (FRD) position of the antenna relative to the vehicle reference point (m);
    # the filter navigates the IMU (filter.imu.lever_arm_b_m) and models this aid here
    lever_arm_b_m: tuple[float, float, float] = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class UsblConfig:
    enabled: bool = True
    # as gnss.correlated_fraction: the part of a fix's σ that the next fixes share (a
    # transducer's residual misalignment, the sound-speed profile, multipath — the same for
    # every fix of a leg), so an underwater GPS at 1–2 Hz is not 100 independent fixes a
    # minute. After a fused fix the horizontal position variance is at least
    # (this × σ_fix)². 0: every fix independent
    correlated_fraction: float = 0.5
    # body-frame (FRD) position of the transponder relative to the vehicle reference point (m);
    # the filter navigates the IMU (filter.imu.lever_arm_b_m) and models this aid here
    lever_arm_b_m: tuple[float, float, float] = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class VisualMotionConfig:
    # off: displacement between consecutive windows of one swath restates the dead-reckoned
    # speed (shared pings, along-track spacing from the speed) — it is not a measurement.
    # Side-scan's independent information is in revisits: filter.loop_closure.
    enabled: bool = False


@dataclass(frozen=True)
class LoopClosureConfig:
    """Side-scan leg-to-leg loop closures (fusion/aiding/loop_closure.py, stochastic clones)."""

    enabled: bool = True
    clone_period_s: float = 5.0                # a horizontal-position clone at most this often
    clone_horizon_s: float = 900.0             # clones older than this are dropped (two legs)

    def validate(self) -> None:
        if not (0.1 <= self.clone_period_s <= 600.0 and self.clone_period_s < self.clone_horizon_s <= 86400.0):
            raise ValueError("loop_closure: clone_period_s must be within [0.1, 600] s and below "
                             "clone_horizon_s (≤ 86400 s)")


@dataclass(frozen=True)
class RangeConfig:
    """Acoustic ranges to known beacons (:mod:`adaptnav.fusion.aiding.range`); opt-in."""

    enabled: bool = False
    sigma_scale: float = 1.0                   # × the sample's own sigma_m
    min_range_m: float = 1.0                   # closer: line of sight undefined, not fused


@dataclass(frozen=True)
class AlignmentConfig:
    n_samples: int = 100                       # static IMU samples averaged for levelling
    max_acc_std_m_s2: float = 0.5              # more spread than this: not at rest, keep waiting
    # the autopilot's yaw seeds the heading only once it has settled: attitude samples over
    # this long (s) whose yaw stays within yaw_settle_tol_rad (ArduSub sends 0, then its DCM
    # yaw, then 0 again while EKF3 starts, then the aligned yaw)
    yaw_settle_s: float = 2.0
    yaw_settle_tol_rad: float = 0.02
    # attitude samples but no IMU fast enough for this long (s): the attitude drives the
    # strapdown (AttitudeDrivenConfig), or AHRS-only mode
    ahrs_after_s: float = 2.0
    # an IMU stream slower than this (Hz, median of its recent intervals) is not integrated
    # while the autopilot's attitude is there: its samples are instants, not increments. At
    # 10 Hz the eight ArduSub SITL drives ended as close with the attitude driving the
    # strapdown (mean 2.11 % of distance, none outside the 99 % ellipse) as integrating the IMU
    # (2.16 %, arcs 5 % of valid epochs outside). The tlog reader withholds such a stream too
    # (service.transport.tlog_source): replay and the live daemon decide alike
    min_imu_rate_hz: float = 20.0


@dataclass(frozen=True)
class AttitudeDrivenConfig:
    """No IMU fast enough to integrate — an autopilot's telemetry as logged by default
    (ArduSub streams RAW_IMU at 2 Hz, ATTITUDE at 10–20 Hz) — but the autopilot's attitude:
    the strapdown runs on the attitude's own increments (a virtual IMU whose gyro is the
    rotation between consecutive ATTITUDE samples and whose accelerometer reads gravity
    alone, :func:`adaptnav.fusion.imu_grades.attitude_driven`), the vehicle's accelerations
    are velocity process noise, and velocity comes from the velocity aids (the learned
    motion model from thruster outputs, a DVL). ``enabled = false``: AHRS only (attitude and
    depth; never a valid position)."""

    enabled: bool = True
    # the vehicle's unmodelled acceleration as white noise: the velocity's random walk
    # between the velocity aids (an ROV's thrusters change its speed by ~0.3 m/s in a second; 0.2
    # left 1.7 % of the valid epochs outside their 99 % ellipse in the freedrive's circles with an
    # underwater GPS, and the freedrive with its profile ended 4.3 % off, not 2.6 %)
    acc_noise_m_s2_rthz: float = 0.3
    # the attitude increments' noise (the autopilot's attitude is smooth; its errors are
    # held by the attitude aid)
    gyro_noise_rad_s_rthz: float = 0.005
    # attitude samples further apart than this (s) are a gap (the filter coasts, reset_counter
    # moves); closer, the rotation between them is exact whatever the interval — a telemetry
    # radio drops ATTITUDE messages, and a gap at imu_gap_s (0.2 s) would tell the autopilot of
    # a reset at every second drop. An attitude stream slower than 2 / max_step_s (2 Hz) does
    # not drive the strapdown (AHRS only)
    max_step_s: float = 1.0
    # no measurement of the motion (a DVL or other velocity over ground, a position fix) fused
    # for this long (s): the track is the motion model's alone, whose scale nothing checks
    # without an accelerometer (reason ``no_motion_measurement``), kept but not valid
    motion_aid_max_age_s: float = 10.0
    # the learned velocity measures the motion too (a motion model calibrated for this vehicle:
    # the freedrive at ArduSub's default stream rates with its vehicle profile, 4.3 % of the
    # distance, every valid epoch inside its 99 % ellipse). Not for a model nobody calibrated
    # (service: motion.prior = uncalibrated sets it false): the embedded table's 1.10 m/s against
    # the SITL vehicle's 0.62 left 83 % of the valid epochs outside it, 44 m off
    model_measures_motion: bool = True
    # ... and so does a model whose speed scale fixes or a DVL have calibrated in this run:
    # k_speed's σ at or below this. The freedrive at default rates with an underwater GPS and the
    # defaults: through a 60 s outage of the fixes valid throughout (86 % before), none outside
    # its 99 % ellipse, 2.2 m at most; the same eight drives without fixes never reach it
    calibrated_sigma_k_speed: float = 0.03

    def validate(self) -> None:
        if not (self.acc_noise_m_s2_rthz > 0.0 and self.gyro_noise_rad_s_rthz > 0.0
                and 0.0 < self.motion_aid_max_age_s <= 600.0 and 0.0 < self.max_step_s <= 10.0
                and 0.0 <= self.calibrated_sigma_k_speed < 1.0):
            raise ValueError("attitude_driven: noises must be > 0, motion_aid_max_age_s within (0, 600] s, "
                             "max_step_s within (0, 10] s and calibrated_sigma_k_speed within [0, 1)")


@dataclass(frozen=True)
class ResetConfig:
    """States reset to an aid that has been rejected for too long (as PX4 EKF2 does)."""

    attitude_after_s: float = 5.0              # ATTITUDE / heading rejected this long: reset attitude
    velocity_after_s: float = 10.0             # DVL / learned velocity rejected this long: reset velocity


@dataclass(frozen=True)
class IntegrityConfig:
    """When ``valid`` is set (also the ODOMETRY quality sent to the autopilot), besides
    ``FilterConfig.valid_max_sigma_h_m``."""

    # windowed normalised-innovation test per aid: the sum of the last nis_window NIS
    # (fused and gated alike) against the χ² quantile nis_quantile of its degrees of freedom
    nis_window: int = 20
    nis_quantile: float = 0.9999
    # after a velocity/attitude reset the solution is invalid this long (s): converging
    after_reset_s: float = 10.0


@dataclass(frozen=True)
class StationaryConfig:
    """Zero-velocity updates while the vehicle is at rest (bench, deck, launch).

    Only out of the water (estimated depth below ``max_depth_m``): in water an idle vehicle
    drifts with the current, and the learned velocity (no thrust ⇒ no water-relative
    velocity) already holds it. A vehicle floating at the surface reads the same depth as one
    on deck, so where position fixes come (``fix_holdoff_s``) they judge whether it moves.
    """

    enabled: bool = True
    max_depth_m: float = 0.2
    window_s: float = 1.0                      # IMU window judged at once
    max_acc_std_m_s2: float = 0.05             # specific-force spread at rest (per axis)
    max_gyro_rad_s: float = 0.01               # |ω| at rest
    max_depth_rate_m_s: float = 0.03           # depth change over the window (when a depth aid exists)
    max_rpm: float = 1.0                       # thrusters idle (when RPM is known)
    sigma_m_s: float = 0.01                    # zero-velocity pseudo-measurement 1-σ
    fix_holdoff_s: float = 10.0                # no update within this long after a fused position fix


@dataclass(frozen=True)
class FilterConfig:
    """The whole filter configuration (see module docstring for units)."""

    imu: ImuConfig = field(default_factory=ImuConfig)
    process: ProcessConfig = field(default_factory=ProcessConfig)
    initial: InitialConfig = field(default_factory=InitialConfig)
    learned_velocity: LearnedVelocityConfig = field(default_factory=LearnedVelocityConfig)
    dvl: DvlConfig = field(default_factory=DvlConfig)
    depth: DepthConfig = field(default_factory=DepthConfig)
    heading: HeadingConfig = field(default_factory=HeadingConfig)
    attitude: AttitudeConfig = field(default_factory=AttitudeConfig)
    gnss: GnssConfig = field(default_factory=GnssConfig)
    usbl: UsblConfig = field(default_factory=UsblConfig)
    visual_motion: VisualMotionConfig = field(default_factory=VisualMotionConfig)
    range: RangeConfig = field(default_factory=RangeConfig)
    loop_closure: LoopClosureConfig = field(default_factory=LoopClosureConfig)
    alignment: AlignmentConfig = field(default_factory=AlignmentConfig)
    attitude_driven: AttitudeDrivenConfig = field(default_factory=AttitudeDrivenConfig)
    plausibility: PlausibilityConfig = field(default_factory=PlausibilityConfig)  # the door's bounds
    reset: ResetConfig = field(default_factory=ResetConfig)
    integrity: IntegrityConfig = field(default_factory=IntegrityConfig)
    stationary: StationaryConfig = field(default_factory=StationaryConfig)
    gate_sigma: float = 5.0                    # chi-square gate ≡ this many σ per DOF
    covariance_step_s: float = 0.1             # covariance propagated at this period
    max_delay_s: float = 1.0                   # late measurements up to this are re-fused
    on_time_tolerance_s: float = 0.02          # older than this: fused at its own time
    imu_gap_s: float = 0.2                     # IMU interval longer than this: gap (≤ 5 Hz is no INS)
    # horizontal 1-σ (m) above this: invalid. A consistent model-aided solution without
    # fixes grows mostly with the unknown sea current (initial σ 0.3 m/s: 180 m in 10 min),
    # not only with the surge (σ 5 %) and heading errors: survey at 1.5 m/s, no fixes after
    # the start, σ_h = 173 m at 10 min (NEES consistent; tests/service/test_valid_without_fixes.py).
    # 100 m made it invalid after 5.5 min; 200 m keeps it valid for > 10 min
    valid_max_sigma_h_m: float = 200.0
    # where the solution is reported (bus, CSV, ODOMETRY): body-frame position relative to
    # the vehicle reference point (m), e.g. the sonar; the IMU is what is navigated
    output_point_b_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    # a position source (GNSS/USBL) is trusted again after this many gated fixes that are
    # consistent with each other and with the last accepted fix at the vehicle's top speed
    # (+ 3σ), within the window: the filter, not the fixes, is then wrong (PX4 EKF2 resets
    # to the measurement likewise); a spoofer's fixes far from where the vehicle can be never are
    position_reset_after_rejections: int = 3
    position_reset_max_speed_m_s: float = 3.0    # over ground: an AUV's top speed + current
    position_reset_window_s: float = 600.0       # gated fixes older than this are no evidence

    def validate(self) -> None:
        if not 0.5 <= self.gate_sigma <= 50.0:  # nan rejected every aid, inf gated nothing
            raise ValueError(f"gate_sigma must be within [0.5, 50], got {self.gate_sigma!r}")
        if not 0.0 < self.valid_max_sigma_h_m:
            raise ValueError("valid_max_sigma_h_m must be > 0")
        if not 0 < self.covariance_step_s <= 1.0:
            raise ValueError("covariance_step_s must be in (0, 1] s")
        # bounded: the late-measurement history holds max_delay_s of inputs
        if not (0 <= self.max_delay_s <= 60.0 and 0 < self.imu_gap_s <= 60.0):
            raise ValueError("max_delay_s must be within [0, 60] s and imu_gap_s within (0, 60] s")
        if self.alignment.min_imu_rate_hz * self.imu_gap_s <= 1.0:
            # a stream at the slowest rate kept would be nothing but gaps: the filter never starts
            raise ValueError(f"alignment.min_imu_rate_hz ({self.alignment.min_imu_rate_hz:g} Hz) must be above "
                             f"1 / imu_gap_s ({1.0 / self.imu_gap_s:g} Hz)")
        if not 0 < self.learned_velocity.rate_hz <= 100.0:
            raise ValueError("learned_velocity.rate_hz must be within (0, 100] Hz")
        lv = self.learned_velocity
        if not 0.0 <= lv.phase_s < 1.0 / lv.rate_hz:
            raise ValueError(f"learned_velocity.phase_s must be within [0, 1 / rate_hz) = [0, {1.0 / lv.rate_hz:g}) s, "
                             f"got {lv.phase_s!r}")
        for name, aid in (("gnss", self.gnss), ("usbl", self.usbl)):
            if not 0.0 <= aid.correlated_fraction <= 1.0:
                raise ValueError(f"{name}.correlated_fraction must be within [0, 1]")
        lv = self.learned_velocity
        if not (lv.skid_sigma_s >= 0.0 and 0.0 < lv.skid_max_fraction <= 1.0
                and 0.0 < lv.coast_skid_max_fraction <= 1.0):
            raise ValueError("learned_velocity.skid_sigma_s must be ≥ 0, skid_max_fraction and "
                             "coast_skid_max_fraction within (0, 1]")
        if not self.learned_velocity.vertical_drift_sigma_per_m >= 0.0:
            raise ValueError("learned_velocity.vertical_drift_sigma_per_m must be ≥ 0")
        if not self.learned_velocity.heave_sigma_per_vertical_speed >= 0.0:
            raise ValueError("learned_velocity.heave_sigma_per_vertical_speed must be ≥ 0")
        if not (0.0 <= self.learned_velocity.coast_mean_fraction <= 1.0 and self.learned_velocity.coast_sigma_per_gap > 0.0):
            raise ValueError("learned_velocity.coast_mean_fraction must be within [0, 1] and coast_sigma_per_gap > 0")
        if self.position_reset_after_rejections < 1:
            raise ValueError("position_reset_after_rejections must be ≥ 1")
        if not (0 < self.position_reset_max_speed_m_s <= 100.0 and 0 < self.position_reset_window_s <= 86400.0):
            raise ValueError("position_reset_max_speed_m_s must be within (0, 100] m/s and "
                             "position_reset_window_s within (0, 86400] s")

    def gate_threshold(self, dof: int) -> float:
        """Chi-square gate for ``dof`` dimensions at the ``gate_sigma`` two-sided level."""
        # scipy.stats' norm.sf through the special function it calls (see chi2_quantile)
        return chi2_quantile(1.0 - 2.0 * float(special.ndtr(-self.gate_sigma)), dof)
