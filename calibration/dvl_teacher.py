r"""The DVL as teacher: the motion model learned from water-relative velocities while the DVL has lock.

Why. Position fixes see the motion model only through its integral (a USBL fix a minute,
σ 2 m) and the IMU only through velocity *changes*. A DVL with bottom lock measures the
velocity over ground several times a second to mm/s; minus the sea current it is the very
quantity the model predicts, the water-relative velocity. So while the DVL has lock the
calibrator learns k_V, the surge and sway variances and the flow angle directly from it,
and when the DVL drops out (too high over a trench, too steep, soft mud) the filter carries
the vehicle on a model taught minutes ago, in the water it is in.

Rows. Per calibrator step ``k`` (``step_s`` long, the window's grid) the DVL samples in
``[t_k, t_{k+1})`` with lock give the mean body velocity relative to the water::

    u_b = R_bd v_d − ω × l_b − (R_z(ψ)ᵀ c_n, 0)        (bottom track; c_n the filter's current)
    u_b = R_bd v_d − ω × l_b                            (water track: already relative to the water)

with ``R_bd``, ``l_b`` the DVL mounting (the filter's ``[filter.dvl]``), ``ω ≈ (0, 0, ω_z)``
the latest yaw rate and ψ the latest heading (roll and pitch leave the horizontal current
almost unchanged). Its components are the step's surge ``V̂_k``, sway ``Ŝ_k`` and heave
``Ĥ_k``; the controls ``(v_k, w_k)`` are the window's. A step needs
``min_samples`` samples to count.

M-step (window-step variances, like EM; the same rules as :mod:`adaptnav.calibration.mstep`),
each row weighted by the forgetting ``λ_k``:

- ``k_V`` and the turn speed loss ``κ``: weighted least squares ``V̂ = k_V v (1 − κ w²) + e``
  (linear in ``k_V`` and ``k_V κ``), weights ``λ/σ_V²(v, w)``. A vehicle slows in turns (the
  sway–yaw coupling drag of the surge equation, :class:`adaptnav.sim.vehicle.Fossen3Dof`); with
  one scale for legs and turns the model is too slow on the legs, and along a leg the filter
  puts the difference between the DVL and the model into its current estimate — which the
  vehicle then carries, wrong, through a DVL outage (dvl_outage: the current at the outage's
  start was off by 2–5 mm/s along the legs, 3–6 m of the error at its end). ``κ`` is held when
  the window's turns do not inform it; ``k_V`` is held when its standard error exceeds
  ``max_k_v_sigma`` (speeds that do not inform it);
- surge variances: the Newton-CG log-variance fit of ``(V̂ − k_V v)²`` on ``(v², w², 1)``
  with the identifiability test (columns the controls do not separate are held) and the
  prior of the M-step;
- sway: ``Ŝ = s₀ V̂ + β v w + e`` (weighted least squares, held when the turns do not inform
  β): the skid of a turning vehicle β and the crab on the straight s₀ the DVL reports (its
  head's yaw misalignment; the model agrees with its teacher, so the filter's current does
  not take the difference along each leg), then ``σ_S² = Σλ (Ŝ − s₀ V̂ − β v w)² / Σλ``
  (without them the skid in the turns made σ_S several times the vehicle's sway noise);
- flow angle ``heave_per_surge = tan α = Σλ V̂ Ĥ / Σλ V̂²`` (body heave per unit of the
  *measured* surge: a heavy or trimmed vehicle flies nose-up by α to hold depth), what the
  filter's flow-angle row ``v_b,z − tan α · v_b,x = 0`` uses (it carries no speed);
- ``b_W`` is not in the DVL's rows: it comes from the heading (compass) against the IMU yaw
  rate, ``b_W = Σλ (Δψ_k/Δ − w_k) / Σλ`` over the window's headings, when given.

The release rule is the calibrator's (:func:`adaptnav.calibration.online.calibrate_window`):
the sanity gate on bounds, the held terms with their reasons, and the rows' Gaussian
log-likelihood with the new parameters not worse than with the current ones.

What the rows do not see: the DVL's own scale factor (0.1–1 %) goes into k_V unless the
filter has calibrated it (:class:`adaptnav.fusion.aiding.dvl.DvlCalibration`); an error in the
filter's current goes into k_V along the legs (opposite on reciprocal legs, so it averages
out over a lawnmower) and into the sway. Pure math: no clock, no I/O.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from adaptnav.fusion.frames import euler_to_quat, quat_to_dcm
from adaptnav.fusion.motion_model import MotionParams, velocity_means
from adaptnav.calibration.mstep import (V_PRIORITY, V_TERMS, MStepOptions, _fit_log_variances,
                                        identifiable_terms, k_v_informed, least_squares_sigmas)


class DvlWaterVelocity:
    """DVL samples → body velocity relative to the water (module docstring, "Rows").

    Parameters
    ----------
    lever_arm_b_m : (3,) DVL head position in the body frame, m
    rotation_bd_rpy_rad : (3,) mounting roll, pitch, yaw of the head in the body (R_bd), rad
    """

    def __init__(self, lever_arm_b_m=(0.0, 0.0, 0.0), rotation_bd_rpy_rad=(0.0, 0.0, 0.0)):
        self.lever_b = np.asarray(lever_arm_b_m, dtype=float)
        self.R_bd = quat_to_dcm(euler_to_quat(*rotation_bd_rpy_rad))
        # per DVL sample (:meth:`body`): the lever arm as Python floats, and whether the
        # head is mounted unrotated (R_bd v is then v itself)
        self._lever_xy = (float(self.lever_b[0]), float(self.lever_b[1]))
        self._unrotated = bool(np.array_equal(self.R_bd, np.eye(3)))

    def body(self, vel_d_m_s, water_track: bool, yaw_rad: float, yaw_rate_rad_s: float,
             current_ne_m_s) -> tuple[float, float, float]:
        """Surge, sway, heave relative to the water (m/s), as three Python floats (an array's item
        arithmetic and the 3 × 3 product cost ~3 µs of the calibrator's ~5 per DVL sample).
        An unrotated head's finite velocity is taken as it is: ``R_bd v`` with ``R_bd = I`` is
        ``v``, but for the sign of a zero component (a sum of them in a bin is the same)."""
        x, y, z = vel_d_m_s
        x, y, z = float(x), float(y), float(z)
        if not (self._unrotated and math.isfinite(x + y + z)):  # (a non-finite one: I v has NaNs)
            x, y, z = (self.R_bd @ np.array((x, y, z))).tolist()
        lx, ly = self._lever_xy
        x += yaw_rate_rad_s * ly   # − (ω × l) with ω = (0, 0, ω_z)
        y -= yaw_rate_rad_s * lx
        if not water_track:
            cn, ce = float(current_ne_m_s[0]), float(current_ne_m_s[1])
            c, s = math.cos(yaw_rad), math.sin(yaw_rad)
            x -= c * cn + s * ce
            y -= -s * cn + c * ce
        return x, y, z


class DvlBin:
    """Running sums of the water-relative body velocity inside one step (Python floats: three
    additions per DVL sample, which an array's in-place sum took ~1 µs for)."""

    __slots__ = ("_sum", "n")

    def __init__(self) -> None:
        self._sum = (0.0, 0.0, 0.0)
        self.n = 0

    @property
    def sum_m_s(self) -> np.ndarray:
        """(3,) the sum of the velocities added, m/s."""
        return np.array(self._sum)

    def add(self, x: float, y: float, z: float) -> None:
        """One water-relative body velocity ``(x, y, z)`` (m/s, Python floats: :meth:`DvlWaterVelocity.body`'s)."""
        sx, sy, sz = self._sum
        self._sum = (sx + x, sy + y, sz + z)
        self.n += 1

    def mean(self, min_samples: int) -> np.ndarray | None:
        return self.sum_m_s / self.n if self.n >= min_samples else None


@dataclass(frozen=True)
class TeacherResult:
    """Parameters (window-step units), notes (held terms and why), teachers per term,
    and the rows' log-likelihood with the current and the new parameters."""

    params: MotionParams
    notes: list[str]
    teachers: dict[str, str]
    ll_old: float
    ll_new: float
    rows: int


def _surge_design(v, w) -> np.ndarray:
    return np.column_stack([v**2, w**2, np.ones_like(v)])


def rows_log_likelihood(params: MotionParams, v, w, V, S, lam) -> float:
    """Gaussian log-likelihood of the surge and sway rows (window-step variances)."""
    s_v = _surge_design(v, w) @ np.array([params.var_vv, params.var_vw, params.var_v1])
    r = V - velocity_means(params, v, w)[0]
    r_s = S - params.sway_per_surge * V - params.sway_per_turn * v * w
    return -0.5 * float(np.sum(lam * (np.log(2 * math.pi * s_v) + r * r / s_v
                                      + np.log(2 * math.pi * params.var_s) + r_s * r_s / params.var_s)))


def teach(params: MotionParams, v, w, V, S, H, lam, options: MStepOptions = MStepOptions(),
          prior_params: MotionParams | None = None, heading_rate_rad_s=None,
          min_heave_speed_m_s: float = 0.3, fit_turn_loss: bool = True,
          max_turn_loss_sigma_s2: float = 1.0, max_sway_per_turn_sigma_s: float = 0.05,
          max_sway_per_surge_sigma: float = 0.01) -> TeacherResult:
    """The DVL M-step of the module docstring.

    Parameters
    ----------
    params : MotionParams, current, for the window step
    v, w : (T,) controls (m/s, rad/s); V, S, H : (T,) the DVL rows (NaN: no DVL that step)
    lam : (T,) forgetting weights
    options : the M-step options (identifiability, prior, fit flags, k_V information)
    prior_params : centre of the log-variance prior (window step); default ``params``
    heading_rate_rad_s : (T,) observed yaw rates from headings (NaN where unknown), for b_W
    fit_turn_loss : fit the turn terms when the window's turns inform them: the speed loss κ
        with k_V (standard error ≤ ``max_turn_loss_sigma_s2``, s²/rad²: 1 s² is 1 % of the
        speed at 0.1 rad/s) and the skid β with the crab s₀ (≤ ``max_sway_per_turn_sigma_s``,
        s: 0.05 s is 7.5 mm/s at 1.5 m/s and 0.1 rad/s; ≤ ``max_sway_per_surge_sigma``);
        otherwise they are held and the rest fitted with them
    """
    v, w, V, S, H, lam = (np.asarray(a, dtype=float) for a in (v, w, V, S, H, lam))
    ok = np.isfinite(V) & np.isfinite(S) & np.isfinite(H)
    v, w, V, S, H, lam = v[ok], w[ok], V[ok], S[ok], H[ok], lam[ok]
    hr = None if heading_rate_rad_s is None else np.asarray(heading_rate_rad_s, dtype=float)[ok]
    notes: list[str] = []
    teachers: dict[str, str] = {}
    new = params
    design = _surge_design(v, w)
    s_v = design @ np.array([params.var_vv, params.var_vw, params.var_v1])
    # k_V (and the turn speed loss κ): weighted least squares through the origin
    if options.fit_k_v:
        omega = lam / s_v
        kappa = params.turn_speed_loss
        if fit_turn_loss:
            design_t = np.column_stack([v, -v * w * w]) * np.sqrt(omega)[:, None]
            sig_t = least_squares_sigmas(design_t)
            coef = np.linalg.lstsq(design_t, np.sqrt(omega) * V, rcond=None)[0]
            sig_kappa = sig_t[1] / coef[0] if coef[0] > 0 else math.inf
            if sig_t[0] <= options.max_k_v_sigma and sig_kappa <= max_turn_loss_sigma_s2:
                # a turn cannot speed the vehicle up: a negative estimate is noise about 0
                kappa = max(float(coef[1] / coef[0]), 0.0)
                new = replace(new, turn_speed_loss=kappa)
                teachers["turn_speed_loss"] = "DVL"
            else:
                notes.append(f"held turn_speed_loss (the window's turns do not inform it: σ {sig_kappa:.3g} s² > "
                             f"{max_turn_loss_sigma_s2})")
        u = v * (1.0 - kappa * w * w)   # the model's speed per unit k_V
        informed, sig = k_v_informed((np.sqrt(omega) * u)[:, None], [0], options.max_k_v_sigma)
        if informed:
            new = replace(new, k_v=float(np.sum(omega * u * V) / np.sum(omega * u * u)))
            teachers["k_v"] = "DVL"
        else:
            notes.append(f"held k_v (the window's speeds do not inform it: σ {sig:.3g} > {options.max_k_v_sigma})")
    # surge variances
    kept, _ = identifiable_terms(design * np.sqrt(lam)[:, None], V_PRIORITY, options.max_condition)
    kept = [k for k in kept if V_TERMS[k] not in options.hold_terms]
    alpha = np.log([params.var_vv, params.var_vw, params.var_v1])
    pp = params if prior_params is None else prior_params
    center = np.log([pp.var_vv, pp.var_vw, pp.var_v1])
    resid_sq = (V - velocity_means(new, v, w)[0]) ** 2
    a = _fit_log_variances(design, lam, resid_sq, 1, alpha, kept, options.prior_tau, center)
    ev = np.maximum(np.exp(a), options.var_floor)
    for k, name in enumerate(V_TERMS):
        if k in kept:
            new = replace(new, **{name: float(ev[k])})
            teachers[name] = "DVL"
        else:
            reason = "configured" if name in options.hold_terms else "the controls do not separate it"
            notes.append(f"held {name} ({reason})")
    # sway and flow angle
    if options.fit_var_s:
        beta, s0 = params.sway_per_turn, params.sway_per_surge
        if fit_turn_loss:
            x = v * w
            X = np.column_stack([V, x]) * np.sqrt(lam)[:, None]
            var_s_now = float(np.sum(lam * (S - s0 * V - beta * x) ** 2) / np.sum(lam))
            sig = least_squares_sigmas(X) * math.sqrt(var_s_now)
            coef = np.linalg.lstsq(X, np.sqrt(lam) * S, rcond=None)[0]
            if sig[1] <= max_sway_per_turn_sigma_s and sig[0] <= max_sway_per_surge_sigma:
                s0, beta = float(coef[0]), float(coef[1])
                new = replace(new, sway_per_turn=beta, sway_per_surge=s0)
                teachers["sway_per_turn"] = teachers["sway_per_surge"] = "DVL"
            else:
                notes.append(f"held sway_per_turn, sway_per_surge (the window's turns do not inform β: σ {sig[1]:.3g} s > "
                             f"{max_sway_per_turn_sigma_s})")
        r_s = S - s0 * V - beta * v * w
        new = replace(new, var_s=float(max(np.sum(lam * r_s * r_s) / np.sum(lam), options.var_floor)))
        teachers["var_s"] = "DVL"
    moving = (v >= min_heave_speed_m_s) & (V >= min_heave_speed_m_s)
    if np.sum(lam[moving]) > 0:
        Vm = V[moving]
        new = replace(new, heave_per_surge=float(np.sum(lam[moving] * Vm * H[moving]) / np.sum(lam[moving] * Vm * Vm)))
        teachers["heave_per_surge"] = "DVL"
    else:
        notes.append("held heave_per_surge (no step under way)")
    # b_W from the headings against the IMU yaw rate
    if options.fit_b_w and hr is not None and np.any(np.isfinite(hr)):
        good = np.isfinite(hr)
        new = replace(new, b_w=float(np.sum(lam[good] * (hr[good] - w[good])) / np.sum(lam[good])))
        teachers["b_w"] = "heading vs IMU"
    return TeacherResult(new, notes, teachers, rows_log_likelihood(params, v, w, V, S, lam),
                         rows_log_likelihood(new, v, w, V, S, lam), int(v.size))
