r"""Online calibrator: a sliding window of motion steps, re-calibrated by EM every K steps.

Data → steps. Samples are binned on a grid of ``step_s`` seconds that starts at the first
position fix (USBL/GNSS), the pose that anchors the filter. The controls of step k → k+1
are the means over ``[t_k, t_{k+1})`` of the surge speed ``v = f(rpm)``
(:class:`adaptnav.fusion.motion_model.RpmSpeedTable`) and of the yaw rate (IMU ``ω_z`` in body FRD,
i.e. about down = the NED yaw rate for small roll/pitch; or heading differences when no
IMU is seen). Observations at time t attach to pose ``round((t − t_0)/step_s)``:
position fixes, headings, beacon ranges, side-scan landmark sightings
(:mod:`adaptnav.calibration.sensors`). A pose is closed when data time passes its bin.

Forward filter. A running particle filter (the same filter, step by step) carries the pose
cloud; the cloud at each pose is kept for the last ``window_steps`` so that a window can
start from the filter's distribution at its first pose.

Calibration. Every ``period_steps`` closed steps, ``em_iterations`` of EM
(:mod:`adaptnav.calibration.em`) run over the last ``window_steps`` steps, warm started from the
current parameters, with exponential forgetting: step τ of a window ending at k has weight
``λ^{k−1−τ}`` in the M-step, so a change of the water is followed within ~1/(1−λ) steps.

Sea current. Positions are ground-referenced while (V, S) are water-relative, so the
window's model carries a horizontal current (:mod:`adaptnav.fusion.motion_model`), estimated by the
M-step with k_V (:func:`adaptnav.calibration.mstep.fit_means`), warm-started from the last accepted
value and released with the parameters (:attr:`Release.current_n_m_s`). Before EM, k_V and the
current are warm-started by the closed-form fit of the window's fixes against dead reckoning
(:mod:`adaptnav.calibration.fix_regression`, an ECME step): the smoother alone barely shows a
cross-track current because the sway prior is tight, so EM would follow it far too slowly.
In a window without two fixes, where k_V's only information is the side-scan pairs'
displacements (:mod:`adaptnav.calibration.sidescan`), the fit's k_V is also the one released:
it is their observed-data maximum, while EM's smoother sees them only through a landmark map
frozen with the whole uncertainty of the earlier pose, and its M-step k_V is the start plus
Monte Carlo noise (landmark survey: consecutive releases scattered ±3-4 % around the fit).

Step length. :class:`MotionParams` are defined for the model's reference step
``model_step_s`` (1 s); the window's steps are ``step_s`` long, so the filter and EM run with
``rescale_step(params, model_step_s, step_s)`` (variances × model_step_s/step_s) and the
released parameters are converted back (× step_s/model_step_s)
(:func:`adaptnav.fusion.motion_model.rescale_step`).

Observability of σ_Vv. With USBL fixes (σ 2 m, one a minute) the only information on the
surge noise is the fix-to-fix residual: 60 s of white surge noise σ_V = σ_Vv·v adds
``60 σ_V²`` to the ``2·σ_fix² = 8 m²`` variance of a fix difference — 0.3 m² at σ_Vv = 0.05,
3 m² at 0.15 (v = 1.5 m/s). Ten fixes (10 min) pin σ_Vv² down to about ±160 % (Fisher), and
EM creeps from a small σ_Vv (its rate is the observed fraction of that variance). The IMU
is the informative source: the navigation filter hands the calibrator its free-inertial
velocity and its integral (``InertialVelocitySample``, once a second) and the differences of its means
over consecutive model steps join the M-step's surge objective
(:mod:`adaptnav.calibration.inertial`; ``use_inertial``). Without them (a remote calibrator node,
the thesis) σ_Vv rests on the fixes as above.

Sanity gate before a release: the new parameters must be finite, within the configured
bounds, and the window log-likelihood with them (a fresh filter run) must not be worse than
with the current ones by more than ``ll_tolerance`` nats (the PF estimate is noisy). Every
attempt produces a :class:`Release` with ``accepted`` and the ``reason`` when refused.

The DVL as teacher (:mod:`adaptnav.calibration.dvl_teacher`). DVL samples with lock are
binned on the same grid as water-relative body velocities (the filter's current, carried by
its ``InertialVelocitySample``, removed). A window with at least ``min_dvl_steps`` steps
covered by the DVL is calibrated from those rows instead of the particle smoother (the
DVL observes the velocities the smoother would infer from fixes); fewer, and the window
is calibrated as before. Every release names the teacher of each term it changed
(:attr:`Release.teachers`: DVL, fixes, IMU, landmarks, heading).

Determinism: everything depends only on the samples observed and the ``rng``.
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, replace
from typing import ClassVar, Literal

import numpy as np

from adaptnav.fusion.motion_model import MotionParams, RpmSpeedTable, rescale_step
from adaptnav.fusion.samples import kinds
from adaptnav.calibration.em import EMOptions, run_em
from adaptnav.calibration.mstep import MStepOptions, surge_variances_from_increments
from adaptnav.calibration.particle_filter import filter_step, run_particle_filter
from adaptnav.calibration.inertial import InertialTrack, surge_increments
from adaptnav.calibration.resampling import systematic_resample
from adaptnav.calibration.sensors import (HeadingObservation, LandmarkAssociator, LandmarkSighting,
                                 PositionFix, RangeObservation, sighting_from_sonar)
from adaptnav.calibration.sidescan import body_sigmas_m


# Sample kinds (``KIND``) the calibrator has no use for (``calibrator_uses`` in the sensor
# table, :data:`adaptnav.fusion.samples.SENSORS`): senders skip them (they would only cost
# pickling across the process boundary) and :meth:`OnlineCalibrator.observe` ignores them.
# Depth aids the filter; the calibrator's model is horizontal and learns from position
# information, the DVL (calibration.dvl_teacher), IMU, RPM and headings.
UNUSED_KINDS = frozenset(kinds(calibrator_uses=False))


@dataclass(frozen=True)
class CalibratorConfig:
    """Online calibrator settings (typed_config-compatible)."""

    window_steps: int = 96        # 8 min of 5 s steps: ~8 USBL fixes at one per minute
    step_s: float = 5.0
    # reference step of MotionParams (s): the variances released are for this step
    model_step_s: float = 1.0
    period_steps: int = 12        # EM once a minute
    min_window_steps: int = 24
    em_iterations: int = 3
    n_particles: int = 500
    n_smoothed: int = 50
    n_mcmc: int = 2
    forgetting: float = 0.985     # λ per step: a ~5.5 min memory, follows a change within 10 min
    prior_tau: float = 1.0
    # centre of the log-variance prior: the current parameters (a step-size limit that
    # follows any change) or the initial ones (MAP-EM: unchanged terms stay put).
    # "initial" by default: with sparse fixes (USBL every 60 s) the variances are weakly
    # identified and a current-anchored prior lets them random-walk away (survey seed 1:
    # drift 0.52 % with "current" vs 0.36 % with "initial", 0.39 % with the static model)
    prior_anchor: Literal["current", "initial"] = "initial"
    max_condition: float = 30.0
    # k_V is held when the window's speeds pin it to no better than this (standard error,
    # calibration.mstep "Information on k_V"): a vehicle at rest says nothing about it
    max_k_v_sigma: float = 0.05
    fit_k_v: bool = True
    fit_b_w: bool = True
    fit_var_s: bool = True
    # σ_S² is held when the smoothed sway is mostly prior (calibration.mstep, missing information)
    max_missing_information_s: float = 0.5
    fit_current: bool = True      # estimate the sea current (USBL/GNSS are ground-referenced)
    fix_regression: bool = True   # warm-start k_V and the current from fixes vs dead reckoning
    # the filter's free-inertial velocity as surge-noise evidence (calibration.inertial)
    use_inertial: bool = True
    # IMU increments a window needs to update the surge variances on its own (no fixes)
    min_inertial_rows: int = 120
    # poses with absolute position information (fixes, ranges, landmarks) a window needs:
    # without them k_V and the current are not observable and EM would only wander
    min_position_poses: int = 3
    # bounds of the sanity gate
    max_variance: float = 25.0
    min_variance: float = 1e-12
    k_v_min: float = 0.5
    k_v_max: float = 1.5
    b_w_max_rad_s: float = 0.1
    max_current_m_s: float = 3.0
    ll_tolerance: float = 5.0
    # sensors without their own σ; priors
    heading_sigma_deg: float = 0.5
    init_pos_sigma_m: float = 3.0
    init_yaw_sigma_deg: float = 5.0
    # NED origin (degrees); NaN: the first fix becomes the origin
    origin_lat_deg: float = math.nan
    origin_lon_deg: float = math.nan
    landmark_sigma_along_m: float = 1.0
    landmark_sigma_across_m: float = 0.5
    # relative uncertainty of the speed used to bring an off-grid fix to the pose time
    lag_speed_sigma: float = 0.2
    # the DVL as teacher (calibration.dvl_teacher): steps with at least min_dvl_samples DVL
    # samples with lock count; a window with min_dvl_steps of them learns from the DVL
    use_dvl: bool = True
    min_dvl_steps: int = 24
    min_dvl_samples: int = 3
    # side-scan pairs (calibration.sidescan) are kept this many steps for the (k_V, current)
    # fit, beyond the EM window: the two sightings of an object on reciprocal 500 m legs are
    # up to 12 min apart and the filter's link comes back ~80 s after the later one
    landmark_memory_steps: int = 192
    # with side-scan pairs in the closed-form (k_V, current) fit (calibration.fix_regression),
    # k_V is a random walk of this rate, 1/√s (the filter's k_speed_rw_rthz without a DVL): old
    # rows weigh by what the walk allows since, not by the forgetting λ, and the k_V fitted is
    # the one at the window's end. 0: one k_V under the forgetting
    k_v_walk_rthz: float = 1.5e-3

    def validate(self) -> None:
        if self.window_steps < 2 or self.period_steps < 1 or self.min_window_steps < 2:
            raise ValueError("window_steps, min_window_steps ≥ 2 and period_steps ≥ 1 required")
        if not self.step_s > 0 or not self.model_step_s > 0:
            raise ValueError("step_s and model_step_s must be > 0")
        if not 0.0 < self.forgetting <= 1.0:
            raise ValueError("forgetting must be in (0, 1]")
        if not self.k_v_walk_rthz >= 0.0:
            raise ValueError("k_v_walk_rthz must be ≥ 0")
        if self.n_particles < 10 or self.n_smoothed < 1 or self.em_iterations < 1:
            raise ValueError("n_particles ≥ 10, n_smoothed ≥ 1, em_iterations ≥ 1 required")

    def __post_init__(self) -> None:
        self.validate()

    def em_options(self) -> EMOptions:
        return EMOptions(n_particles=self.n_particles, n_smoothed=self.n_smoothed,
                         max_iterations=self.em_iterations, n_mcmc=self.n_mcmc,
                         mstep=MStepOptions(max_condition=self.max_condition, prior_tau=self.prior_tau,
                                            fit_k_v=self.fit_k_v, fit_b_w=self.fit_b_w,
                                            fit_var_s=self.fit_var_s, fit_current=self.fit_current,
                                            max_missing_information_s=self.max_missing_information_s,
                                            max_k_v_sigma=self.max_k_v_sigma))


@dataclass(frozen=True)
class Release:
    """One calibration attempt: the parameters (for the model step ``model_step_s``), the
    window log-likelihood with them, whether they were released and why not, the EM
    iterations run, and the estimated sea current (north, east; m/s). A message like the
    samples (``KIND``; codec: :mod:`adaptnav.service.transport.release`)."""

    KIND: ClassVar[str] = "calibration_release"
    t_s: float
    params: MotionParams
    log_likelihood: float
    accepted: bool
    reason: str
    iterations: int
    current_n_m_s: tuple[float, float] = (0.0, 0.0)
    # which teacher informed the release: "DVL", "fixes", "IMU", "landmarks", "heading"
    teachers: tuple[str, ...] = ()
    # "DVL" when k_V itself was measured by the DVL (calibration.dvl_teacher): the filter then
    # takes k_V as the speed scale instead of keeping its own k_speed·k_V (Estimator.set_motion_params)
    k_v_teacher: str = ""


def gate_reason(params: MotionParams, config: CalibratorConfig) -> str:
    """Empty string if ``params`` are within bounds, else why not."""
    for name in MotionParams.VARIANCE_NAMES:
        val = getattr(params, name)
        if not (config.min_variance <= val <= config.max_variance):
            return f"{name}={val:.3g} outside [{config.min_variance:g}, {config.max_variance:g}]"
    if not config.k_v_min <= params.k_v <= config.k_v_max:
        return f"k_v={params.k_v:.4g} outside [{config.k_v_min}, {config.k_v_max}]"
    if abs(params.b_w) > config.b_w_max_rad_s:
        return f"|b_w|={abs(params.b_w):.3g} > {config.b_w_max_rad_s}"
    return ""


def calibrate_window(params: MotionParams, v, w, dt, observations, init_cloud, config: CalibratorConfig,
                     rng: np.random.Generator, t_s: float = math.nan,
                     initial_params: MotionParams | None = None, current_n_m_s=None,
                     headings_rad=None, inertial: InertialTrack | None = None,
                     landmark_memory=None) -> Release:
    """EM over one window + the sanity gate; returns the :class:`Release` record.

    ``params`` (and ``initial_params``, the prior centre when ``config.prior_anchor ==
    "initial"``) are for the model step ``config.model_step_s``; the window's steps are
    ``dt = config.step_s`` long and EM runs with the rescaled variances. ``current_n_m_s``
    (2,) m/s warm-starts the current. With ``headings_rad`` (T+1,) at the poses and
    ``config.fix_regression``, k_V and the current are first fitted to the window's fixes
    (:func:`adaptnav.calibration.fix_regression.fix_regression`). With ``inertial`` (the filter's
    free-inertial velocity over the window; the window starts at ``t_s − T·step_s``) the
    IMU's surge increments join the M-step and the log-likelihood
    (:mod:`adaptnav.calibration.inertial`). ``landmark_memory`` = (surges (M,), headings
    (M+1,), observation lists (M+1,)) over the calibrator's longer memory ending at the
    window's last pose: its side-scan pairs join the fix regression
    (:func:`adaptnav.calibration.sidescan.landmark_rows`) and count as position information. The release carries model-step parameters; the gate
    compares with the window log-likelihood of the current ones.
    """
    T = len(v)
    lam = config.forgetting ** np.arange(T - 1, -1, -1, dtype=float)
    to_window = lambda p: rescale_step(p, config.model_step_s, config.step_s)  # noqa: E731
    to_model = lambda p: rescale_step(p, config.step_s, config.model_step_s)  # noqa: E731
    cur0 = (0.0, 0.0) if current_n_m_s is None else (float(current_n_m_s[0]), float(current_n_m_s[1]))
    use_imu = inertial is not None and config.use_inertial and len(inertial) and math.isfinite(t_s)

    def increments(cur):  # the IMU's surge rows for this window (calibration.inertial)
        return surge_increments(inertial, t_s - T * dt, dt, v, w, lam, config.model_step_s, cur) if use_imu else None

    n_pos = sum(1 for obs in observations
                if any(not isinstance(o, HeadingObservation) for o in (obs or ())))
    lm_rows = None
    if landmark_memory is not None:
        from adaptnav.calibration.sidescan import landmark_rows
        v_h, th_h, obs_h = landmark_memory
        lam_h = (np.ones(len(v_h)) if config.k_v_walk_rthz > 0  # the walk is the forgetting
                 else config.forgetting ** np.arange(len(v_h) - 1, -1, -1, dtype=float))
        lm_rows = landmark_rows(v_h, dt, th_h, obs_h, to_window(params), lam_h)
        n_pos += len(lm_rows[1]) // 2  # each pair: a displacement between two poses
    if n_pos < config.min_position_poses:
        why = (f"too little position information: {n_pos} pose(s) with fixes/ranges/landmarks "
               f"< {config.min_position_poses}")
        inc = increments(cur0)
        if inc is None or len(inc) < config.min_inertial_rows:
            return Release(t_s, params, math.nan, False, why, 0, cur0)
        return _inertial_only(params, inc, config, t_s, initial_params, cur0, why)
    win_params = to_window(params)
    start_params, start_cur = win_params, cur0
    k_from_pairs = False
    if headings_rad is not None and config.fix_regression:
        from adaptnav.calibration.fix_regression import fix_pairs, fix_regression
        k_fix, cur_fix, held_fix = fix_regression(v, dt, headings_rad, observations, win_params, params.k_v, cur0,
                                           lam, config.max_condition, config.max_k_v_sigma, lm_rows,
                                           config.k_v_walk_rthz ** 2 * dt)
        if config.k_v_min <= k_fix <= config.k_v_max and all(abs(x) <= config.max_current_m_s for x in cur_fix):
            start_params = replace(win_params, k_v=k_fix) if config.fit_k_v else win_params
            start_cur = cur_fix if config.fit_current else cur0
            # without two fixes the pairs' fit is k_V's observed-data maximum and is released as
            # it is (ECME, Liu & Rubin 1994; module docstring)
            k_from_pairs = (config.fit_k_v and "k_v" not in held_fix and lm_rows is not None
                            and len(lm_rows[1]) > 0 and len(fix_pairs(observations)) < 2)
    inc = increments(start_cur)
    try:
        anchor = to_window(initial_params) if config.prior_anchor == "initial" and initial_params is not None else None
        res = run_em(start_params, v, w, dt, observations, init_cloud, rng, config.em_options(),
                     step_weights=lam, prior_params=anchor, current_n_m_s=start_cur, surge_increments=inc)
        fitted = replace(res.params, k_v=start_params.k_v) if k_from_pairs else res.params
        new = to_model(fitted)
    except (ValueError, FloatingPointError) as e:  # MotionParams refuses non-finite values
        return Release(t_s, params, math.nan, False, f"EM failed: {e}", 0, cur0)
    cur = tuple(float(x) for x in res.current_n_m_s)
    reason = gate_reason(new, config)
    if not reason and not all(math.isfinite(x) and abs(x) <= config.max_current_m_s for x in cur):
        reason = f"current {cur} outside ±{config.max_current_m_s} m/s"
    if reason:
        return Release(t_s, new, math.nan, False, reason, res.iterations, cur)
    ll_old = res.log_likelihoods[0]
    try:
        from adaptnav.calibration.em import freeze_landmarks
        obs = freeze_landmarks(win_params, v, w, dt, observations, init_cloud, rng, config.n_particles, cur0)
        imu_ll = inc.log_likelihood if inc is not None else (lambda p: 0.0)
        if start_params is not win_params or start_cur is not cur0:  # EM started elsewhere: the reference
            ll_old = run_particle_filter(win_params, v, w, dt, obs, init_cloud, rng, config.n_particles,
                                         current_n_m_s=cur0).log_likelihood + imu_ll(win_params)
        ll_new = run_particle_filter(fitted, v, w, dt, obs, init_cloud, rng, config.n_particles,
                                     current_n_m_s=cur).log_likelihood + imu_ll(fitted)
    except FloatingPointError as e:
        return Release(t_s, new, -math.inf, False, f"filter failed with new parameters: {e}", res.iterations, cur)
    if not math.isfinite(ll_new):
        return Release(t_s, new, ll_new, False, "log-likelihood not finite", res.iterations, cur)
    note = ""
    if ll_new < ll_old - config.ll_tolerance and (start_params is not win_params or start_cur is not cur0):
        # EM's means (k_V and the current, from smoothed tracks whose sway prior is tight)
        # can fit the fixes worse than the closed-form fix regression EM started from: a
        # few mm/s of current are metres over a window. Try EM's variances with those means.
        alt = replace(res.params, k_v=start_params.k_v)
        try:
            ll_alt = run_particle_filter(alt, v, w, dt, obs, init_cloud, rng, config.n_particles,
                                         current_n_m_s=start_cur).log_likelihood + imu_ll(alt)
        except FloatingPointError:
            ll_alt = -math.inf
        if ll_alt >= ll_old - config.ll_tolerance:
            note = f"; means from the fix regression (EM's: log-likelihood {ll_new:.2f})"
            new, cur, ll_new = to_model(alt), tuple(float(x) for x in start_cur), ll_alt
    if ll_new < ll_old - config.ll_tolerance:
        return Release(t_s, new, ll_new, False,
                       f"log-likelihood worse: {ll_new:.2f} < {ll_old:.2f} - {config.ll_tolerance}", res.iterations,
                       cur)
    held = "".join(f"; {n}" for n in res.notes)  # what was held and why (calibration.mstep)
    seen = [o for obs in observations for o in (obs or ())]
    teachers = tuple(t for t, used in (("fixes", any(isinstance(o, PositionFix) for o in seen)),
                                       ("landmarks", any(isinstance(o, (LandmarkSighting, RangeObservation))
                                                         for o in seen) or bool(lm_rows is not None
                                                                                and len(lm_rows[1]))),
                                       ("IMU", inc is not None)) if used)
    return Release(t_s, new, ll_new, True, "ok" + held + note + f"; taught by {', '.join(teachers)}",
                   res.iterations, cur, teachers)


def _inertial_only(params, inc, config: CalibratorConfig, t_s, initial_params, cur, why) -> Release:
    """Without position information k_V and the current are not observable, but the surge
    noise still is, from the IMU (:func:`adaptnav.calibration.mstep.surge_variances_from_increments`):
    release new surge variances if their likelihood is not worse, everything else kept."""
    win = rescale_step(params, config.model_step_s, config.step_s)
    anchor = (rescale_step(initial_params, config.model_step_s, config.step_s)
              if config.prior_anchor == "initial" and initial_params is not None else None)
    res = surge_variances_from_increments(win, inc, config.em_options().mstep, anchor)
    new = rescale_step(res.params, config.step_s, config.model_step_s)
    reason = gate_reason(new, config)
    if reason:
        return Release(t_s, new, math.nan, False, reason, 1, cur)
    ll_old, ll_new = inc.log_likelihood(win), inc.log_likelihood(res.params)
    if ll_new < ll_old - config.ll_tolerance:
        return Release(t_s, new, ll_new, False, f"log-likelihood worse: {ll_new:.2f} < {ll_old:.2f} - "
                       f"{config.ll_tolerance} (IMU only)", 1, cur)
    return Release(t_s, new, ll_new, True, f"ok; surge variances from the IMU only ({why}); taught by IMU", 1, cur,
                   ("IMU",))


def calibrate_from_dvl(params: MotionParams, v, w, dt, dvl_rows, config: CalibratorConfig, t_s: float,
                       initial_params: MotionParams | None, current_n_m_s, headings_rad=None) -> Release:
    """One window taught by the DVL (:mod:`adaptnav.calibration.dvl_teacher`) + the release rule.

    ``dvl_rows`` (T, 3) the steps' water-relative surge, sway, heave (NaN without DVL);
    ``headings_rad`` (T+1,) observed headings at the poses (NaN where none) for b_W.
    """
    from adaptnav.calibration.dvl_teacher import teach

    T = len(v)
    lam = config.forgetting ** np.arange(T - 1, -1, -1, dtype=float)
    win = rescale_step(params, config.model_step_s, config.step_s)
    anchor = (rescale_step(initial_params, config.model_step_s, config.step_s)
              if config.prior_anchor == "initial" and initial_params is not None else None)
    rate = None
    if headings_rad is not None:
        h = np.asarray(headings_rad, dtype=float)
        rate = ((np.diff(h) + math.pi) % (2 * math.pi) - math.pi) / dt
    rows = np.asarray(dvl_rows, dtype=float)
    res = teach(win, v, w, rows[:, 0], rows[:, 1], rows[:, 2], lam, config.em_options().mstep, anchor, rate)
    cur = (float(current_n_m_s[0]), float(current_n_m_s[1]))
    try:
        new = rescale_step(res.params, config.step_s, config.model_step_s)
    except ValueError as e:
        return Release(t_s, params, math.nan, False, f"DVL teacher failed: {e}", 1, cur)
    reason = gate_reason(new, config)
    if reason:
        return Release(t_s, new, math.nan, False, reason + " (DVL teacher)", 1, cur)
    if not res.ll_new >= res.ll_old - config.ll_tolerance:
        return Release(t_s, new, res.ll_new, False, f"log-likelihood worse: {res.ll_new:.2f} < {res.ll_old:.2f} - "
                       f"{config.ll_tolerance} (DVL teacher)", 1, cur)
    by = {}
    for term, teacher in res.teachers.items():
        by.setdefault(teacher, []).append(term)
    taught = "; ".join(f"{', '.join(terms)} from the {teacher}" for teacher, terms in by.items())
    held = "".join(f"; {n}" for n in res.notes)
    teachers = tuple(dict.fromkeys("DVL" if t == "DVL" else "heading" for t in res.teachers.values()))
    return Release(t_s, new, res.ll_new, True, f"ok; {res.rows} DVL steps: {taught}{held}", 1, cur, teachers,
                   res.teachers.get("k_v", ""))


@dataclass
class _Bin:
    """Running sums of the controls inside one step."""

    speed_sum: float = 0.0
    speed_n: int = 0
    yaw_rate_sum: float = 0.0
    yaw_rate_n: int = 0


class OnlineCalibrator:
    """Feed samples with :meth:`observe`, collect releases with :meth:`poll`."""

    def __init__(self, config: CalibratorConfig, params0: MotionParams, rpm_table: RpmSpeedTable,
                 rng: np.random.Generator, dvl_mount=None):
        """``dvl_mount``: (lever arm (3,) m, mounting roll/pitch/yaw (3,) rad) of the DVL head,
        the filter's ``[filter.dvl]``; None: at the origin, aligned."""
        self.config = config
        self.params = params0  # for the model step (config.model_step_s)
        self.params0 = params0
        self.current_n_m_s = (0.0, 0.0)  # sea current (north, east), m/s
        self._win_params = rescale_step(params0, config.model_step_s, config.step_s)  # for step_s steps
        self.rpm_table = rpm_table
        self.rng = rng
        self.rejected: dict[str, int] = {}
        self._pending: list[Release] = []
        self._origin = None
        if math.isfinite(config.origin_lat_deg) and math.isfinite(config.origin_lon_deg):
            from adaptnav.fusion.frames import GeoOrigin
            self._origin = GeoOrigin(math.radians(config.origin_lat_deg), math.radians(config.origin_lon_deg))
        self._t0: float | None = None
        self._last_t = -math.inf
        self._bins: dict[int, _Bin] = {}
        self._obs: dict[int, list] = {}
        self._heading_at: dict[int, tuple] = {}
        self._last_heading: tuple[float, float] | None = None  # (t, yaw)
        self._last_speed = 0.0
        self._last_yaw_rate = 0.0
        self._rpm_cache: tuple[float, float] = (math.nan, math.nan)  # (rpm, speed)
        self._closed = -1  # index of the last closed pose
        self._poses = None
        self._log_w = None
        maxlen = config.window_steps + 1
        self._v: deque = deque(maxlen=config.window_steps)
        self._w: deque = deque(maxlen=config.window_steps)
        self._win_obs: deque = deque(maxlen=maxlen)
        self._clouds: deque = deque(maxlen=maxlen)
        self._since_em = 0
        self._assoc = LandmarkAssociator()
        self._pre_fix: list = []  # observations before the grid exists
        # side-scan (calibration.sidescan): the object front end, created on the first ping
        self.sonar = None
        from adaptnav.sonar.dead_reckoning import AnchoredDeadReckoning
        self.sonar_nav = AnchoredDeadReckoning()  # ping positions (the image's row spacing), tied to fixes
        from adaptnav.calibration.sidescan import LinkIds
        self._link_ids = LinkIds()
        # the memory of side-scan pairs: (pose k, surge of step k−1 → k, heading at k) per closed
        # pose, and the linked sightings by pose (config.landmark_memory_steps)
        self._lm_poses: deque = deque(maxlen=config.landmark_memory_steps + 1)
        self._lm_obs: dict[int, list] = {}
        self._lag_s = 0.0  # poses stay open this long (data s) for late sightings
        self._next_close_t = -math.inf  # data time at which the next pose closes (_advance)
        # free-inertial samples (t, ∫v_n, ∫v_e, yaw, reset) over the window
        self._inertial_buf: deque = deque()
        # the DVL teacher: water-relative body velocity per step (calibration.dvl_teacher)
        from adaptnav.calibration.dvl_teacher import DvlBin, DvlWaterVelocity

        self.dvl_water = DvlWaterVelocity(*dvl_mount) if dvl_mount is not None else DvlWaterVelocity()
        self._dvl_bin = DvlBin  # (a new bin per step: the import statement there cost ~1 µs)
        self._dvl_bins: dict = {}
        self._dvl_rows: deque = deque(maxlen=config.window_steps)
        self._filter_current = (0.0, 0.0)  # the filter's current estimate (from its inertial samples)
        self._dvl_correction = (0.0, 0.0)  # the filter's DVL scale factor error and misalignment (rad)
        self._correct_dvl = None  # adaptnav.fusion.aiding.dvl.correct_velocity, once a correction is known
        self._taught_by_dvl = False  # the latest accepted release came from the DVL teacher
        self._dvl_steps_new = 0  # steps with DVL rows since the latest accepted DVL-taught release

    # ---------------------------------------------------------------- input
    def _reject(self, why: str) -> None:
        self.rejected[why] = self.rejected.get(why, 0) + 1

    def observe(self, sample) -> None:
        """Take one sample (any kind; unusable kinds are ignored, bad ones counted)."""
        if getattr(sample, "KIND", None) in UNUSED_KINDS:
            return
        kind = type(sample).__name__
        if kind == "InertialVelocitySample":
            return self._inertial(sample)
        if kind == "ObjectBatch":  # back from the filter with its links (not new data: no stepping)
            return self._links(sample)
        if kind == "ImuBatch":
            t = np.asarray(sample.t_s, dtype=float)
            wz = np.asarray(sample.omega_b_rad_s, dtype=float)[:, 2]
            # any NaN/inf makes a sum non-finite: one cheap test for the usual all-finite
            # batch (a few samples, ~14 per second), the element-wise mask otherwise; the yaw
            # rates' sum is the one their bin adds (ndarray.sum is np.add.reduce), the times'
            # only tested (a Python sum of the list: 1 µs less than a reduction; an overflow
            # to inf takes the mask, which finds every value finite)
            wz_sum = float(np.add.reduce(wz)) if t.size else math.nan
            if not (t.size and math.isfinite(sum(t.tolist()) + wz_sum)):
                ok = np.isfinite(t) & np.isfinite(wz)
                if not np.all(ok):
                    self._reject("non-finite imu")
                t, wz = t[ok], wz[ok]
                if t.size == 0:
                    return
                wz_sum = float(np.add.reduce(wz))
            if self._t0 is None:
                self._last_yaw_rate = float(wz[-1])
            elif (k0 := math.floor((t[0] - self._t0) / self.config.step_s)) == \
                    math.floor((t[-1] - self._t0) / self.config.step_s) and k0 >= max(self._closed, 0):
                # the usual batch (a few samples between two other samples): one bin
                b = self._bins.get(k0)
                if b is None:  # (not setdefault: its default was built for every batch)
                    b = self._bins[k0] = _Bin()
                b.yaw_rate_sum += wz_sum
                b.yaw_rate_n += int(wz.size)
                self._last_yaw_rate = float(wz[-1])
            else:  # vectorised binning: replay feeds thousands of IMU samples per batch
                k = np.floor((t - self._t0) / self.config.step_s).astype(np.int64)
                late = k < max(self._closed, 0)
                if np.any(late):
                    self.rejected["late yaw_rate"] = self.rejected.get("late yaw_rate", 0) + int(late.sum())
                for kk in np.unique(k[~late]):
                    sel = k == kk
                    b = self._bins.setdefault(int(kk), _Bin())
                    b.yaw_rate_sum += float(wz[sel].sum())
                    b.yaw_rate_n += int(sel.sum())
                self._last_yaw_rate = float(wz[-1])
            self._advance(float(t[-1]))
            return
        t = getattr(sample, "t_s", None)
        if t is None or not isinstance(t, (int, float)) or not math.isfinite(t):
            self._reject("bad timestamp")
            return
        t = float(t)
        try:
            if kind == "RpmSample":
                if sample.rpm != self._rpm_cache[0]:  # RPM repeats (integer PWM): one PCHIP call per value
                    self._rpm_cache = (sample.rpm, float(self.rpm_table.speed(sample.rpm)))
                self._add(t, "speed", self._rpm_cache[1], finite=sample.rpm)
            elif kind in ("HeadingSample", "AttitudeSample"):
                self._heading(t, float(sample.yaw_rad))
            elif kind == "SonarPing":  # (the kinds by how often they come: a ping per RPM sample)
                self._sonar(sample)
            elif kind == "DvlSample":
                self._dvl(t, sample)
            elif kind == "ImuSample":
                self._add(t, "yaw_rate", float(sample.omega_b_rad_s[2]))
            elif kind in ("UsblSample", "GnssSample"):
                self._fix(t, sample)
            elif kind == "RangeSample":
                vals = [sample.range_m, sample.sigma_m, *sample.beacon_pos_n_m]
                if not all(math.isfinite(x) for x in vals) or sample.sigma_m <= 0:
                    return self._reject("bad range")
                ob = RangeObservation(np.asarray(sample.beacon_pos_n_m[:2], float)[None], np.array([sample.range_m]),
                                      float(sample.sigma_m))
                self._add_obs(t, ob)
            elif hasattr(sample, "ground_range_m") and hasattr(sample, "side"):
                tid = self._assoc.assign(sample)
                ob = sighting_from_sonar(sample, tid, self.config.landmark_sigma_along_m,
                                         self.config.landmark_sigma_across_m)
                self._add_obs(t, ob)
        except (ValueError, TypeError) as e:
            self._reject(f"{kind}: {e}")
        self._advance(t)

    def _sonar(self, ping):
        """Side-scan ping → the object front end owned here (:mod:`adaptnav.calibration.sidescan`):
        a completed block's sightings leave by :meth:`poll` as an :class:`ObjectBatch` for the
        filter, which associates them across legs and returns the batch with its links
        (:meth:`_links`). The front end's dead reckoning (ping speed and heading, tied to the
        fixes) only spaces the image's rows; positions are the filter's."""
        if self.sonar is None:
            from adaptnav.calibration.sidescan import CalibratorSonar

            self.sonar = CalibratorSonar(self.sonar_nav)
        batch = self.sonar.push(ping)
        if batch is not None:
            self._pending.append(batch)

    def _links(self, batch) -> None:
        """The filter's cross-leg pairs (``batch.links``, one tuple per loop closure) →
        :class:`LandmarkSighting` s sharing a track id at the poses of their two sightings,
        also poses already closed (the window keeps their observations for EM; the running
        filter does not use landmarks). Along-track offsets from the pose are the model's
        speed × time (not the ping's speed over ground)."""
        if self._t0 is None:
            return
        c = self.config
        speed = self.params.k_v * self._last_speed
        for closure in batch.links:
            group = self._link_ids.new_group()
            for a, b in closure:
                tid, new_a, new_b = self._link_ids.pair(a, b)
                for o, new in ((a, new_a), (b, new_b)):
                    if not new:
                        continue
                    k = round((o.t_s - self._t0) / c.step_s)
                    d = speed * (o.t_s - (self._t0 + k * c.step_s))
                    s_al, s_ac = body_sigmas_m(o)
                    side = 1.0 if o.side == "starboard" else -1.0
                    ob = LandmarkSighting(tid, d, side * o.ground_range_m,
                                          math.hypot(s_al, c.lag_speed_sigma * abs(d)), s_ac, group)
                    oldest = self._lm_poses[0][0] if self._lm_poses else self._closed + 1
                    if k < oldest:
                        self._reject("landmark link older than the landmark memory")
                        continue
                    self._lm_obs.setdefault(k, []).append(ob)
                    if k > self._closed:  # and in the EM window's observations (its landmark map)
                        self._obs.setdefault(k, []).append(ob)
                    elif 0 <= self._closed - k < len(self._win_obs):
                        self._win_obs[len(self._win_obs) - 1 - (self._closed - k)].append(ob)

    def _inertial(self, sample) -> None:
        """Buffer the filter's free-inertial velocity (no stepping: it is a filter output at
        the nav epoch, which may trail the latest sensor time)."""
        t, yaw = float(sample.t_s), float(sample.yaw_rad)
        pn, pe = float(sample.pos_n_m[0]), float(sample.pos_n_m[1])
        if not all(math.isfinite(x) for x in (t, yaw, pn, pe)):
            return self._reject("non-finite inertial_velocity")
        buf = self._inertial_buf
        if buf and t <= buf[-1][0]:
            return self._reject("out-of-order inertial_velocity")
        buf.append((t, pn, pe, yaw, int(sample.reset_counter)))
        cur = getattr(sample, "current_n_m_s", None)
        if cur is not None and math.isfinite(cur[0]) and math.isfinite(cur[1]):
            self._filter_current = (float(cur[0]), float(cur[1]))
        cal = getattr(sample, "dvl_scale_misalignment", None)
        # (a scale error of −50 % or worse is no DVL's: correcting by it would divide by ~0)
        if cal is not None and math.isfinite(cal[0]) and math.isfinite(cal[1]) and cal[0] > -0.5:
            self._dvl_correction = (float(cal[0]), float(cal[1]))
        keep_s = (self.config.window_steps + 2) * self.config.step_s + self._lag_s
        while buf and buf[0][0] < t - keep_s:
            buf.popleft()

    def _dvl(self, t, sample):
        """A DVL sample with lock → water-relative body velocity, binned on the step grid."""
        if not (self.config.use_dvl and sample.valid) or self._t0 is None:
            return
        vel = sample.vel_d_m_s
        if not all(map(math.isfinite, vel)):
            return self._reject("non-finite dvl")
        if self._dvl_correction != (0.0, 0.0):  # the head's scale and misalignment, as the filter knows them
            correct = self._correct_dvl
            if correct is None:  # (imported once: the import statement per sample cost 1.2 µs)
                from adaptnav.fusion.aiding.dvl import correct_velocity as correct

                self._correct_dvl = correct
            vel = correct(vel, *self._dvl_correction)
        k = math.floor((t - self._t0) / self.config.step_s)
        if k < max(self._closed, 0):
            return self._reject("late dvl")
        yaw = self._last_heading[1] if self._last_heading is not None else 0.0
        x, y, z = self.dvl_water.body(vel, bool(getattr(sample, "water_track", False)), yaw,
                                      self._last_yaw_rate, self._filter_current)
        b = self._dvl_bins.get(k)
        if b is None:
            b = self._dvl_bins[k] = self._dvl_bin()
        b.add(x, y, z)

    def _add(self, t, what, value, finite=0.0):
        if not (math.isfinite(value) and math.isfinite(finite)):
            return self._reject(f"non-finite {what}")
        if self._t0 is None:
            if what == "speed":
                self._last_speed = value
            else:
                self._last_yaw_rate = value
            return
        k = math.floor((t - self._t0) / self.config.step_s)
        if k < max(self._closed, 0):
            return self._reject(f"late {what}")
        b = self._bins.get(k)
        if b is None:
            b = self._bins[k] = _Bin()
        if what == "speed":
            b.speed_sum += value
            b.speed_n += 1
        else:
            b.yaw_rate_sum += value
            b.yaw_rate_n += 1
        if what == "speed":
            self._last_speed = value
        else:
            self._last_yaw_rate = value

    def _heading(self, t, yaw):
        if not self._take_heading(t, yaw):
            return
        at = self._pose_lag(t)
        if at is None:
            return
        k, lag = at
        best = self._heading_at.get(k)
        if best is not None and abs(best[0]) <= abs(lag):
            return  # one heading per pose: the nearest (headings at 1 Hz are not independent)
        # brought to the pose time with the latest yaw rate
        ob = HeadingObservation(yaw - self._last_yaw_rate * lag, math.radians(self.config.heading_sigma_deg))
        if best is not None:
            self._obs[k].remove(best[1])
        self._heading_at[k] = (lag, ob)
        self._obs.setdefault(k, []).append(ob)

    def _fix(self, t, sample):
        vals = (sample.lat_rad, sample.lon_rad, sample.sigma_h_m)
        if not all(math.isfinite(x) for x in vals) or sample.sigma_h_m <= 0:
            return self._reject("bad position fix")
        if self._origin is None:
            from adaptnav.fusion.frames import GeoOrigin
            self._origin = GeoOrigin(float(sample.lat_rad), float(sample.lon_rad))
        ned = self._origin.to_ned(sample.lat_rad, sample.lon_rad)
        fix = PositionFix((float(ned[0]), float(ned[1])), float(sample.sigma_h_m))
        if self._t0 is None:
            self._start(t, fix)
        self._add_obs(t, fix)
        self.sonar_nav.fix(t, fix.pos_n_m, fix.sigma_m)  # ties the sonar's ping positions

    def _take_heading(self, t, yaw) -> bool:
        """The heading rate and the latest heading from a heading sample; False (counted) when
        the heading is not finite."""
        if not math.isfinite(yaw):
            self._reject("non-finite heading")
            return False
        if self._last_heading is not None and t > self._last_heading[0]:
            dyaw = (yaw - self._last_heading[1] + math.pi) % (2 * math.pi) - math.pi
            self._heading_rate = dyaw / (t - self._last_heading[0])
        self._last_heading = (t, yaw)
        return True

    def _pose_lag(self, t) -> tuple[int, float] | None:
        """The pose ``k`` nearest ``t`` and ``t − t_k``; None before the grid exists, or (counted)
        when that pose is closed."""
        if self._t0 is None:
            return None
        k = round((t - self._t0) / self.config.step_s)
        if k <= self._closed:
            self._reject("late observation")
            return None
        return k, t - (self._t0 + k * self.config.step_s)

    def _add_obs(self, t, ob):
        """An observation (not a heading: :meth:`_heading`) at the pose nearest ``t``."""
        at = self._pose_lag(t)
        if at is None:
            return
        # bring the observation to the pose time t_k with the latest controls (a fix taken
        # 2 s off the grid at 1.5 m/s is 3 m off — more than a USBL σ)
        k, lag = at
        yaw = self._last_heading[1] if self._last_heading is not None else None
        if isinstance(ob, PositionFix) and lag != 0.0 and yaw is not None:
            d = self._last_speed * lag
            ob = PositionFix((ob.pos_n_m[0] - d * math.cos(yaw), ob.pos_n_m[1] - d * math.sin(yaw)),
                             math.hypot(ob.sigma_m, self.config.lag_speed_sigma * abs(d)))
        elif isinstance(ob, RangeObservation) and lag != 0.0:
            ob = RangeObservation(ob.landmarks_m, ob.ranges_m,
                                  math.hypot(ob.sigma_m, self._last_speed * abs(lag)))
        self._obs.setdefault(k, []).append(ob)

    def _start(self, t, fix: PositionFix):
        c, n = self.config, self.config.n_particles
        self._t0 = t
        xy = np.asarray(fix.pos_n_m) + max(c.init_pos_sigma_m, fix.sigma_m) * self.rng.standard_normal((n, 2))
        if self._last_heading is not None:
            yaw = self._last_heading[1] + math.radians(c.init_yaw_sigma_deg) * self.rng.standard_normal(n)
        else:
            yaw = self.rng.uniform(-math.pi, math.pi, n)
        self._poses = np.column_stack([xy, yaw])
        self._log_w = np.full(n, -math.log(n))

    # ------------------------------------------------------------- stepping
    def _advance(self, t):
        if t < self._last_t:
            self._reject("out-of-order timestamp")
        elif t > self._last_t:
            self._last_t = t
        if self._t0 is None or self._last_t < self._next_close_t:
            return  # no pose closes before then (_close_time): most samples
        newest = self._newest_closed(self._last_t)
        while self._closed < newest:
            self._close_pose(self._closed + 1)
        self._next_close_t = self._close_time(self._closed + 1)

    def _newest_closed(self, t_s: float) -> int:
        """The newest pose that is closed at data time ``t_s``."""
        return math.floor((t_s - self._lag_s - self._t0) / self.config.step_s - 0.5)

    def _close_time(self, k: int) -> float:
        """The earliest data time at which pose ``k`` is closed (:meth:`_newest_closed` ≥ k): each
        step of that is monotone in the time, so every earlier time leaves it open and
        :meth:`_advance` need not compute it (−inf, when not found within 64 ulps of its
        estimate: computed at every sample)."""
        t = self._t0 + self._lag_s + (k + 0.5) * self.config.step_s  # within a few ulps of it
        if not math.isfinite(t):
            return -math.inf
        for _ in range(64):
            if self._newest_closed(t) < k:
                t = math.nextafter(t, math.inf)
                continue
            earlier = math.nextafter(t, -math.inf)
            if self._newest_closed(earlier) < k:
                return t
            t = earlier
        return -math.inf

    def _controls(self, k):
        b = self._bins.pop(k, None)
        v = b.speed_sum / b.speed_n if b and b.speed_n else self._last_speed
        if b and b.yaw_rate_n:
            w = b.yaw_rate_sum / b.yaw_rate_n
        else:
            w = getattr(self, "_heading_rate", 0.0)
        return v, w

    def _close_pose(self, k):
        c = self.config
        obs = self._obs.pop(k, [])
        self._heading_at.pop(k, None)
        fwd_obs = [o for o in obs if not isinstance(o, LandmarkSighting)]
        if k == 0:
            g = np.zeros(self._poses.shape[0])
            for o in fwd_obs:
                g += o.log_likelihood(self._poses)
            self._log_w = self._log_w + g
            self._log_w -= np.logaddexp.reduce(self._log_w)
        else:
            v, w = self._controls(k - 1)
            self._v.append(v)
            self._w.append(w)
            dvl_bin = self._dvl_bins.pop(k - 1, None)
            row = dvl_bin.mean(self.config.min_dvl_samples) if dvl_bin is not None else None
            self._dvl_rows.append(np.full(3, np.nan) if row is None else row)
            self._dvl_steps_new += row is not None
            try:
                self._poses, self._log_w, _ = filter_step(self._win_params, self._poses, self._log_w, v, w, c.step_s,
                                                          fwd_obs, self.rng, current_n_m_s=self.current_n_m_s)
            except FloatingPointError:
                # no particle explains this step's observations (e.g. a wild fix): move
                # without them rather than stop calibrating; counted
                self._reject("observations impossible under every particle (dropped)")
                self._poses, self._log_w, _ = filter_step(self._win_params, self._poses, self._log_w, v, w, c.step_s,
                                                          [], self.rng, current_n_m_s=self.current_n_m_s)
            self._since_em += 1
        self._closed = k
        self._win_obs.append(obs)
        cloud = self._poses[systematic_resample(np.exp(self._log_w), self.rng, c.n_particles)]
        self._clouds.append(cloud)
        # the heading observed at the pose where there is one: the cloud's lags in a turn (its
        # yaw-rate control is the latest heading rate; 8-13° at the ends of a 5 s-step turn),
        # which made the dead-reckoned turn 3-4 % longer than the truth
        seen = [o.yaw_rad for o in obs if isinstance(o, HeadingObservation)]
        heading = seen[0] if seen else math.atan2(float(np.mean(np.sin(cloud[:, 2]))),
                                                  float(np.mean(np.cos(cloud[:, 2]))))
        self._lm_poses.append((k, self._v[-1] if k > 0 and self._v else math.nan, heading))
        if self._lm_obs and min(self._lm_obs) < self._lm_poses[0][0]:
            self._lm_obs = {kk: o for kk, o in self._lm_obs.items() if kk >= self._lm_poses[0][0]}
        n_steps = len(self._v)
        if self._since_em >= c.period_steps and n_steps >= c.min_window_steps:
            self._since_em = 0
            self._calibrate(self._t0 + k * c.step_s)

    def _calibrate(self, t_s):
        v = np.array(self._v)
        w = np.array(self._w)
        T = v.size
        obs = list(self._win_obs)[-(T + 1):]
        clouds = list(self._clouds)[-(T + 1):]
        init = clouds[0]
        from adaptnav.calibration.fix_regression import circular_mean_headings
        inertial = None
        if len(self._inertial_buf) >= 3:
            a = np.array(self._inertial_buf)
            inertial = InertialTrack(a[:, 0], a[:, 1:3], a[:, 3], a[:, 4])
        dvl_rows = np.array(list(self._dvl_rows)[-T:]) if self._dvl_rows else np.empty((0, 3))
        dvl_window = (self.config.use_dvl and len(dvl_rows) == T
                      and int(np.sum(np.isfinite(dvl_rows[:, 0]))) >= self.config.min_dvl_steps)
        if dvl_window and self._taught_by_dvl and self._dvl_steps_new == 0:
            # the DVL lost lock after the latest DVL-taught release: this window holds the same
            # rows minus the newest, so a fit from it is only noisier (dvl_outage seed 2: the
            # releases from 87 down to 27 DVL steps moved k_V 0.951 -> 0.956, truth 0.945)
            rel = Release(t_s, self.params, math.nan, False,
                          "held: no DVL step since the latest DVL-taught release (lock lost); "
                          "the model it taught is kept", 0, self.current_n_m_s)
        elif dvl_window:
            observed = np.full(T + 1, np.nan)
            for i, pose_obs in enumerate(obs):
                for o in pose_obs or ():
                    if isinstance(o, HeadingObservation):
                        observed[i] = o.yaw_rad
            rel = calibrate_from_dvl(self.params, v, w, self.config.step_s, dvl_rows, self.config, t_s,
                                     self.params0, self._filter_current, observed)
        elif self._taught_by_dvl and sum(1 for o in obs if any(not isinstance(x, HeadingObservation)
                                                                for x in (o or ()))) < self.config.min_position_poses:
            # the DVL is out (a trench, too steep): the model it taught minutes ago is the
            # better evidence; the IMU alone (calibration.inertial) sees only velocity changes
            rel = Release(t_s, self.params, math.nan, False,
                          "held: the DVL-taught model is kept while the DVL is out and no fixes inform the window",
                          0, self.current_n_m_s)
        else:
            rel = calibrate_window(self.params, v, w, self.config.step_s, obs, init, self.config, self.rng, t_s,
                                   initial_params=self.params0, current_n_m_s=self.current_n_m_s,
                                   headings_rad=circular_mean_headings(clouds), inertial=inertial,
                                   landmark_memory=self._landmark_memory())
        if rel.accepted:
            self._taught_by_dvl = "DVL" in rel.teachers
            self._dvl_steps_new = 0
            self.params = rel.params
            self.current_n_m_s = rel.current_n_m_s
            self._win_params = rescale_step(rel.params, self.config.model_step_s, self.config.step_s)
        self._pending.append(rel)

    def _landmark_memory(self):
        """(surges, headings, observation lists) over the landmark memory, or None without pairs."""
        poses = list(self._lm_poses)
        if len(poses) < 2 or not any(poses[0][0] <= k for k in self._lm_obs):
            return None
        return (np.array([p[1] for p in poses[1:]]), np.array([p[2] for p in poses]),
                [self._lm_obs.get(p[0], []) for p in poses])

    def pings_to_block(self) -> int | None:
        """Side-scan pings still needed before the object front end completes its next block
        (and runs the detector); None before the first ping."""
        return None if self.sonar is None else self.sonar.front_end.pings_to_block()

    def side_scan_report(self) -> dict | None:
        """What the object front end made of the side-scan pings (None before the first):
        ``pings`` taken, ``resampled`` (another range or sample count put on the stream's
        first), ``rejected`` by reason (pings: ``bad geometry``, ``out of order``,
        ``non-finite`` navigation; objects: ``turning``, seen while the vehicle turned),
        ``blocks`` run and ``sightings`` found."""
        if self.sonar is None:
            return None
        fe = self.sonar.front_end
        return {"pings": int(fe.pings_taken), "resampled": int(fe.resampled), "rejected": dict(fe.rejected),
                "blocks": int(fe.blocks), "sightings": int(fe.sightings)}

    def finish(self) -> None:
        """The data ended: what is still held for completion leaves by :meth:`poll` — the
        side-scan's last, incomplete block of pings (:meth:`CalibratorSonar.finish`)."""
        if self.sonar is not None:
            batch = self.sonar.finish()
            if batch is not None:
                self._pending.append(batch)

    def poll(self) -> list:
        """Releases (accepted or refused) computed since the last call, and the side-scan's
        :class:`~adaptnav.calibration.sidescan.ObjectBatch` es (for the filter), oldest first."""
        out, self._pending = self._pending, []
        return out
