r"""The velocity motion model that adaptnav learns (DESIGN.md "Motion model", errata).

Pose ``(x, y, θ)``: x north, y east (m), θ yaw from north towards east (rad) — the
horizontal part of the local NED frame. Reported controls per step: surge speed
``v = f(rpm)`` from the static RPM lookup (m/s) and yaw rate ``w`` (rad/s), step ``δt`` (s).

True velocities (seed §2.1, after Eliazar & Parr 2004 / Yap & Shelton 2008, with the
mean terms of DESIGN.md and the lateral term of the errata)::

    V ~ N(k_V v (1 − κ w²),  v² σ_Vv² + w² σ_Vw² + σ_V1²)        surge, m/s
    W ~ N(w + b_W, v² σ_Wv² + w² σ_Ww² + σ_W1²)       yaw rate, rad/s
    S ~ N(0, σ_S²)                                    sway (starboard), m/s

The turn speed loss ``κ`` (s²/rad², ``turn_speed_loss``; beyond the seed): a vehicle in a
turn slows down — the sway it takes on and the yaw rate add drag through the coupling terms
``(m + X_vr) v r`` and ``X_rr r²`` of the surge equation (Fossen 2011, "Handbook of Marine
Craft Hydrodynamics and Motion Control"; Prestero 2001 for the REMUS-100 coefficients; the
simulator's :class:`adaptnav.sim.vehicle.Fossen3Dof` has them),
so a single speed scale learned over straight legs *and* turns is too slow on the legs and
too fast in the turns. ``κ = 0`` is the seed's model. Likewise a turning vehicle skids: its
sway has the mean ``β v w`` (``sway_per_turn``; the REMUS-100 of the simulator: β ≈ −0.25 s,
0.04 m/s at 1.5 m/s and 0.1 rad/s, 93 % of its sway), not 0 — the filter's sway row and the
DVL teacher use it, with ``s₀ V`` (``sway_per_surge``), the crab on the straight the DVL it
was taught by reports (a DVL head misaligned by 0.4° reads a sway of 0.7 % of the surge): a
model that agrees with its teacher leaves the filter's current estimate alone, while a
disagreement fixed in the body would be put into the current along each leg and carried,
wrong, through a DVL outage. The sampling and transition density here keep ``S ~ N(0, σ_S²)``.

Pose update with constant body velocity (V, S) and yaw rate W over δt — exact
integration (the seed's printed arc update is garbled; this is the errata's form plus
the sway term)::

    θ' = θ + W δt
    [x' − x, y' − y]ᵀ = c · R(φ) [V, S]ᵀ,  φ = θ + W δt / 2,  c = 2 sin(W δt/2) / W

``R(φ)`` is the 2-D rotation; ``c → δt`` as ``|W| → 0`` (computed with ``np.sinc``, so
the straight-line limit is exact and smooth). Expanding gives the errata's
``x' = x − V/W sin θ + V/W sin(θ + W δt)``.

Sea current. (V, S) are water-relative; a horizontal current ``u_c = (u_n, u_e)`` (m/s, NED)
adds ``u_c δt`` to the ground displacement (optional ``current_n_m_s`` argument of
:func:`propagate`, :func:`sample_poses`, :func:`invert_step`, :func:`step_errors`,
:func:`transition_logpdf`; default zero, the water-relative model above). Positions
(USBL, GNSS) are ground-referenced, so a calibrator that ignores the current sees it as
surge and sway noise.

Step length. The variances are defined for the *reference step* of the model (1 s: the
simulator's ``motion.step_s`` and the filter's 1 Hz learned-velocity aid). A model run at a
longer step uses :func:`rescale_step` (white-noise averaging).

Transition density. The map (V, S, W) → (x', y', θ') is invertible:
``Ŵ = wrap(θ' − θ)/δt``, ``[V̂, Ŝ] = R(−φ) d / c``, with Jacobian ``|∂(x',y',θ')/∂(V,S,W)| =
c² δt``, so ``log p(x' | x) = log N(V̂) + log N(Ŝ) + log N(Ŵ) − log(c² δt)``.

The seed's per-step errors for the M-step are ``ε_V = V̂ − v``, ``ε_W = Ŵ − w``,
``ε_S = Ŝ`` (:func:`step_errors`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace

import numpy as np
from scipy.interpolate import PchipInterpolator

LOG_2PI = math.log(2.0 * math.pi)


@dataclass(frozen=True)
class MotionParams:
    """Parameters of the velocity motion model.

    Variances (units): ``var_vv`` σ_Vv² (–, surge noise per unit surge speed²),
    ``var_vw`` σ_Vw² (m²/rad², surge noise per unit yaw rate²), ``var_v1`` σ_V1² (m²/s²),
    ``var_wv`` σ_Wv² (rad²/m², yaw-rate noise per unit surge²), ``var_ww`` σ_Ww² (–),
    ``var_w1`` σ_W1² (rad²/s²), ``var_s`` σ_S² (m²/s², sway). Means: ``k_v`` speed
    scale (–), ``b_w`` yaw-rate bias (rad/s), ``heave_per_surge`` (–) the body heave per
    unit surge while holding depth, ``tan α`` of the angle of attack (a heavy or trimmed
    vehicle flies nose-up; learned from the DVL, calibration/dvl_teacher.py);
    ``turn_speed_loss`` κ (s²/rad², ≥ 0): the surge's mean is ``k_V v (1 − κ w²)``, the speed
    a turn at yaw rate ``w`` costs (learned from the DVL; 0 = none); ``sway_per_turn`` β (s):
    the sway's mean is ``β v w``, the sideslip of a turning vehicle (learned from the DVL;
    used by the filter's learned-velocity aid; 0 = none, the seed's ``S ~ N(0, σ_S²)``);
    ``sway_per_surge`` s₀ (–): a mean sway ``s₀ V`` on the straight, the crab the DVL that
    teaches the model sees (its head's yaw misalignment, tan 0.4° = 0.007, or a fin trim).

    The seed's results name σ_Dd ≡ σ_Vv and σ_Tr ≡ σ_Ww (:attr:`sigma_dd`,
    :attr:`sigma_tr`).
    """

    var_vv: float = 0.05**2
    var_vw: float = 0.01**2
    var_v1: float = 0.01**2
    var_wv: float = 0.001**2
    var_ww: float = 0.05**2
    var_w1: float = 0.001**2
    var_s: float = 0.01**2
    k_v: float = 1.0
    b_w: float = 0.0
    heave_per_surge: float = 0.0
    turn_speed_loss: float = 0.0
    sway_per_turn: float = 0.0
    sway_per_surge: float = 0.0

    VARIANCE_NAMES = ("var_vv", "var_vw", "var_v1", "var_wv", "var_ww", "var_w1", "var_s")

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if not math.isfinite(value):
                raise ValueError(f"MotionParams.{f.name} must be finite, got {value}")
        for name in self.VARIANCE_NAMES:
            if getattr(self, name) <= 0.0:
                raise ValueError(f"MotionParams.{name} must be > 0, got {getattr(self, name)}")
        if self.k_v <= 0.0:
            raise ValueError(f"MotionParams.k_v must be > 0, got {self.k_v}")
        if self.turn_speed_loss < 0.0:
            raise ValueError(f"MotionParams.turn_speed_loss must be ≥ 0, got {self.turn_speed_loss}")

    @property
    def sigma_dd(self) -> float:
        """σ_Dd ≡ σ_Vv (the seed's drift-per-distance term)."""
        return math.sqrt(self.var_vv)

    @property
    def sigma_tr(self) -> float:
        """σ_Tr ≡ σ_Ww (the seed's turn-per-rotation term)."""
        return math.sqrt(self.var_ww)

    def to_dict(self) -> dict[str, float]:
        return {f.name: float(getattr(self, f.name)) for f in fields(self)}

    @classmethod
    def from_dict(cls, data: dict[str, float]) -> "MotionParams":
        names = {f.name for f in fields(cls)}
        unknown = set(data) - names
        if unknown:
            raise ValueError(f"MotionParams: unknown key(s) {sorted(unknown)}")
        return cls(**{k: float(v) for k, v in data.items()})

    def with_sigmas(self, sigma_dd: float | None = None, sigma_tr: float | None = None) -> "MotionParams":
        """Copy with σ_Dd and/or σ_Tr replaced (standard deviations, not variances)."""
        changes = {}
        if sigma_dd is not None:
            changes["var_vv"] = sigma_dd**2
        if sigma_tr is not None:
            changes["var_ww"] = sigma_tr**2
        return replace(self, **changes)


def velocity_means(params: MotionParams, v, w):
    """Means of (V, W) given reported surge ``v`` (m/s) and yaw rate ``w`` (rad/s)."""
    v = np.asarray(v, dtype=float)
    w = np.asarray(w, dtype=float)
    if params.turn_speed_loss == 0.0:  # the seed's model, the same floats
        return params.k_v * v, w + params.b_w
    return params.k_v * v * (1.0 - params.turn_speed_loss * w * w), w + params.b_w


def velocity_variances(params: MotionParams, v, w):
    """Variances of (V, W, S) given reported ``v``, ``w``; broadcasts over arrays."""
    v2 = np.square(np.asarray(v, dtype=float))
    w2 = np.square(np.asarray(w, dtype=float))
    var_V = v2 * params.var_vv + w2 * params.var_vw + params.var_v1
    var_W = v2 * params.var_wv + w2 * params.var_ww + params.var_w1
    var_S = np.full(np.broadcast(v2, w2).shape, params.var_s)
    return var_V, var_W, var_S


def sample_velocities(params: MotionParams, v, w, rng: np.random.Generator, size=None):
    """Draw true (V, W, S) for reported ``v``, ``w``; ``size`` particles (or broadcast shape)."""
    mean_V, mean_W = velocity_means(params, v, w)
    var_V, var_W, var_S = velocity_variances(params, v, w)
    shape = size if size is not None else np.broadcast(mean_V, mean_W).shape
    V = mean_V + np.sqrt(var_V) * rng.standard_normal(shape)
    W = mean_W + np.sqrt(var_W) * rng.standard_normal(shape)
    S = np.sqrt(var_S) * rng.standard_normal(shape)
    return V, W, S


def _chord(W, dt):
    """``c = 2 sin(W δt / 2) / W`` with the exact limit ``δt`` at W = 0."""
    return dt * np.sinc(np.asarray(W) * dt / (2.0 * np.pi))


def rescale_step(params: MotionParams, from_step_s: float, to_step_s: float) -> MotionParams:
    """The same water expressed for a model step of ``to_step_s`` instead of ``from_step_s``.

    Assumption (white-noise averaging): the true velocities are drawn independently every
    ``from_step_s`` seconds (the simulator's ``motion.step_s``; a 1 Hz velocity aid sees
    the same). A step of ``to_step_s = n · from_step_s`` moves with the *mean* of n such
    draws, whose variance is 1/n of one draw's, so every variance is multiplied by
    ``from_step_s / to_step_s``. The means (``k_v``, ``b_w``, ``turn_speed_loss``) do not change.

    Parameters
    ----------
    params : parameters valid for a step of ``from_step_s`` (s)
    from_step_s, to_step_s : step lengths (s), > 0

    Returns
    -------
    MotionParams with the variances scaled by ``from_step_s / to_step_s``.
    """
    if not (from_step_s > 0 and to_step_s > 0 and math.isfinite(from_step_s) and math.isfinite(to_step_s)):
        raise ValueError(f"rescale_step: steps must be finite and > 0, got {from_step_s}, {to_step_s}")
    f = from_step_s / to_step_s
    if f == 1.0:
        return params
    return replace(params, **{name: getattr(params, name) * f for name in MotionParams.VARIANCE_NAMES})


def _current(current_n_m_s):
    """(u_n, u_e) as two arrays (m/s); ``None`` means no current."""
    if current_n_m_s is None:
        return 0.0, 0.0
    c = np.asarray(current_n_m_s, dtype=float)
    return c[..., 0], c[..., 1]


def propagate(pose, V, W, S, dt, current_n_m_s=None):
    """Exact pose update for body velocity (V, S) and yaw rate W over ``dt``.

    Parameters
    ----------
    pose : (..., 3) array of (x_m, y_m, theta_rad)
    V, W, S : arrays broadcastable to ``pose[..., 0]`` (m/s, rad/s, m/s)
    dt : float or array (s)
    current_n_m_s : optional (2,) horizontal current (north, east) in m/s; adds
        ``current · dt`` to the displacement

    Returns
    -------
    (..., 3) array, the new poses (θ not wrapped; wrap where angles are compared).
    """
    pose = np.asarray(pose, dtype=float)
    theta = pose[..., 2]
    phi = theta + 0.5 * W * dt
    c = _chord(W, dt)
    cos_phi, sin_phi = np.cos(phi), np.sin(phi)
    out = np.empty(np.broadcast(pose[..., 0], V, W, S).shape + (3,))
    un, ue = _current(current_n_m_s)
    out[..., 0] = pose[..., 0] + c * (cos_phi * V - sin_phi * S) + un * dt
    out[..., 1] = pose[..., 1] + c * (sin_phi * V + cos_phi * S) + ue * dt
    out[..., 2] = theta + W * dt
    return out


def sample_poses(params: MotionParams, poses, v, w, dt, rng: np.random.Generator, current_n_m_s=None):
    """Propagate many particles one step with velocities drawn from the model.

    ``poses`` is (N, 3); returns the (N, 3) new poses. ``current_n_m_s`` as :func:`propagate`.
    """
    poses = np.asarray(poses, dtype=float)
    V, W, S = sample_velocities(params, v, w, rng, size=poses.shape[0])
    return propagate(poses, V, W, S, dt, current_n_m_s)


def invert_step(pose0, pose1, dt, current_n_m_s=None, turn_ref_rad=None):
    """Velocities (V̂, Ŵ, Ŝ) that carry ``pose0`` to ``pose1`` in ``dt``; broadcasts.

    The water-relative (V̂, Ŝ) after removing ``current_n_m_s · dt`` (optional (2,), m/s)
    from the displacement. Also returns ``c`` (the chord factor) for the Jacobian of the
    transition density.

    The heading change is known modulo 2π; by default the branch in (−π, π] is taken.
    ``turn_ref_rad`` (optional, broadcastable, rad) takes the branch nearest to it instead,
    e.g. the expected turn ``(w + b_W) δt``: when turns per step can exceed π (large
    ``w δt`` or σ_Ww), the branch about 0 inverts such a step to the opposite turn and a
    flipped surge (V̂ ≈ −V), which inflates the learned surge variance.
    """
    pose0 = np.asarray(pose0, dtype=float)
    pose1 = np.asarray(pose1, dtype=float)
    ref = 0.0 if turn_ref_rad is None else np.asarray(turn_ref_rad, dtype=float)
    dtheta = (pose1[..., 2] - pose0[..., 2] - ref + np.pi) % (2.0 * np.pi) - np.pi + ref
    W = dtheta / dt
    phi = pose0[..., 2] + 0.5 * dtheta
    c = _chord(W, dt)
    un, ue = _current(current_n_m_s)
    dx = pose1[..., 0] - pose0[..., 0] - un * dt
    dy = pose1[..., 1] - pose0[..., 1] - ue * dt
    cos_phi, sin_phi = np.cos(phi), np.sin(phi)
    V = (cos_phi * dx + sin_phi * dy) / c
    S = (-sin_phi * dx + cos_phi * dy) / c
    return V, W, S, c


def step_errors(pose0, pose1, v, w, dt, current_n_m_s=None):
    """The M-step's per-step errors ``(ε_V, ε_W, ε_S) = (V̂ − v, Ŵ − w, Ŝ)`` (current removed)."""
    V, W, S, _ = invert_step(pose0, pose1, dt, current_n_m_s)
    return V - np.asarray(v, dtype=float), W - np.asarray(w, dtype=float), S


def transition_logpdf(params: MotionParams, pose0, pose1, v, w, dt, current_n_m_s=None):
    """``log p(pose1 | pose0, v, w)`` in (x, y, θ) coordinates; broadcasts.

    Includes the Jacobian ``log(c² δt)`` of the change of variables, so densities of
    different pose pairs are comparable (the backward smoother needs that). The current
    (optional (2,), m/s) shifts the displacement and leaves the Jacobian unchanged.
    """
    V, W, S, c = invert_step(pose0, pose1, dt, current_n_m_s)
    mean_V, mean_W = velocity_means(params, v, w)
    var_V, var_W, var_S = velocity_variances(params, v, w)
    ll = -0.5 * ((V - mean_V) ** 2 / var_V + np.log(var_V) + LOG_2PI)
    ll += -0.5 * ((W - mean_W) ** 2 / var_W + np.log(var_W) + LOG_2PI)
    ll += -0.5 * (S**2 / var_S + np.log(var_S) + LOG_2PI)
    return ll - np.log(c * c * dt)


@dataclass(frozen=True)
class RpmSpeedTable:
    """Static lookup ``u = f(n)``: propeller RPM → water-relative surge speed (m/s).

    Monotone piecewise-cubic (PCHIP) interpolation of a measured table; clamped to the
    table's end values outside its range (an extrapolated thrust curve is a guess).
    """

    rpm: tuple[float, ...] = (0.0, 300.0, 600.0, 900.0, 1200.0, 1500.0)
    speed_m_s: tuple[float, ...] = (0.0, 0.35, 0.75, 1.12, 1.50, 1.85)

    def __post_init__(self) -> None:
        rpm = np.asarray(self.rpm, dtype=float)
        speed = np.asarray(self.speed_m_s, dtype=float)
        if rpm.ndim != 1 or rpm.shape != speed.shape or rpm.size < 2:
            raise ValueError("RpmSpeedTable: rpm and speed_m_s must be equal-length lists of ≥ 2 values")
        if not (np.all(np.isfinite(rpm)) and np.all(np.isfinite(speed))):
            raise ValueError("RpmSpeedTable: values must be finite")
        if np.any(np.diff(rpm) <= 0):
            raise ValueError("RpmSpeedTable: rpm must be strictly increasing")
        if np.any(np.diff(speed) < 0):
            raise ValueError("RpmSpeedTable: speed_m_s must be non-decreasing in rpm")
        object.__setattr__(self, "_interp", PchipInterpolator(rpm, speed, extrapolate=False))

    def speed(self, rpm):
        """Surge speed (m/s) for ``rpm``; scalar in → float out, array in → array out."""
        r = np.clip(np.asarray(rpm, dtype=float), self.rpm[0], self.rpm[-1])
        out = self._interp(r)  # type: ignore[attr-defined]
        return float(out) if np.ndim(out) == 0 else out

    def rpm_for_speed(self, speed_m_s):
        """Inverse lookup (the simulator commands a speed and reports the RPM)."""
        grid = np.linspace(self.rpm[0], self.rpm[-1], 2001)
        return np.interp(speed_m_s, self.speed(grid), grid)
