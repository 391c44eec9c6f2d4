r"""Expectation–Maximisation for the motion parameters over one window (seed §3.3).

Iteration k (Bishop 2006, §9.4; seed §3.1–3.3):

1. E-step with θ_k: particle filter (:mod:`adaptnav.calibration.particle_filter`) → window
   log-likelihood ``ℓ(θ_k)`` (the PF estimate) and M smoothed trajectories by FFBSi
   (:mod:`adaptnav.calibration.smoother`, MCMC backward kernel by default, exact on request).
2. M-step (:mod:`adaptnav.calibration.mstep`): θ_{k+1} = argmax of the expected complete-data
   log-likelihood, Newton-CG on log-variances, closed-form k_V, b_W.
3. Stop when ``|ℓ(θ_k) − ℓ(θ_{k−1})| < ll_tol · (1 + |ℓ|)`` *and* every parameter moved by
   less than ``param_rtol`` (relative), or after ``max_iterations``.

Side-scan landmark sightings (:class:`adaptnav.calibration.sensors.LandmarkSighting`) are handled
by a FastSLAM forward pass with θ_k that builds the landmark map, which is then frozen for
that iteration's filter + smoother (see :mod:`adaptnav.calibration.sensors`); the map is rebuilt at
every iteration because a map built with wrong parameters (e.g. k_V) is distorted by them.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from adaptnav.fusion.motion_model import MotionParams
from adaptnav.calibration.mstep import MStepOptions, m_step
from adaptnav.calibration.particle_filter import run_particle_filter
from adaptnav.calibration.sensors import FixedLandmarkObservation, LandmarkSighting
from adaptnav.calibration.smoother import ffbsi_exact, ffbsi_mcmc


@dataclass(frozen=True)
class EMOptions:
    n_particles: int = 1000
    n_smoothed: int = 100
    max_iterations: int = 5
    ll_tol: float = 1e-3
    param_rtol: float = 0.02
    smoother: str = "mcmc"  # "mcmc" | "exact"
    n_mcmc: int = 2
    mstep: MStepOptions = MStepOptions()


@dataclass
class EMResult:
    params: MotionParams
    log_likelihoods: list[float]  # ℓ(θ_k) for each E-step, k = 0..iterations-1
    iterations: int
    converged: bool
    held: tuple[str, ...] = ()
    notes: list[str] = field(default_factory=list)
    filter_result: object = None  # the last E-step's FilterResult
    current_n_m_s: tuple[float, float] = (0.0, 0.0)  # sea current (north, east), m/s


def freeze_landmarks(params, v, w, dt, observations, init_poses, rng, n_particles, current_n_m_s=None):
    """Replace :class:`LandmarkSighting` by :class:`FixedLandmarkObservation` using maps
    built by a FastSLAM forward pass; other observations are kept.

    No sighting is scored against a map it helped to build (the information would be
    counted twice): every re-observation is frozen against the map of the sightings
    *before* it, as the FastSLAM pass had it then (mean and covariance over the particles,
    the spread of the earlier poses included: :attr:`ParticleLandmarkMap.before`) — the
    sequential decomposition ``p(y_1) p(y_2 | y_1) …`` of the landmark's likelihood. A
    first sighting has no earlier map and says nothing about the motion (its position is
    free): it is dropped, as are landmarks sighted once in the window.
    """
    counts: dict[int, int] = {}
    for obs in observations:
        for o in (obs or ()):
            if isinstance(o, LandmarkSighting):
                counts[o.track_id] = counts.get(o.track_id, 0) + 1
    if not counts:
        return observations
    observations = [[o for o in (obs or ()) if not (isinstance(o, LandmarkSighting) and counts[o.track_id] < 2)]
                    for obs in observations]
    if not any(isinstance(o, LandmarkSighting) for obs in observations for o in obs):
        return observations
    fr = run_particle_filter(params, v, w, dt, observations, init_poses, rng, n_particles,
                             map_landmarks=True, current_n_m_s=current_n_m_s)
    before = fr.landmark_map.before
    out = []
    for obs in observations:
        out.append([FixedLandmarkObservation(o, *before[id(o)]) if isinstance(o, LandmarkSighting) else o
                    for o in (obs or ()) if not isinstance(o, LandmarkSighting) or id(o) in before])
    return out


def _max_rel_change(a: MotionParams, b: MotionParams) -> float:
    da, db = a.to_dict(), b.to_dict()
    out = 0.0
    for key in da:
        if key.startswith("var_"):  # compare standard deviations
            x, y = math.sqrt(da[key]), math.sqrt(db[key])
            out = max(out, abs(x - y) / max(abs(x), 1e-12))
        elif key == "b_w":
            out = max(out, abs(da[key] - db[key]) / 0.01)  # 0.01 rad/s as the scale
        else:
            out = max(out, abs(da[key] - db[key]) / max(abs(da[key]), 1e-12))
    return out


def run_em(params0: MotionParams, v_m_s, w_rad_s, dt_s, observations, init_poses,
           rng: np.random.Generator, options: EMOptions = EMOptions(), step_weights=None,
           prior_params: MotionParams | None = None, current_n_m_s=None,
           surge_increments=None) -> EMResult:
    """EM over one window; arguments as :func:`adaptnav.calibration.particle_filter.run_particle_filter`.

    ``step_weights`` (T,) are forgetting weights passed to the M-step; ``prior_params``
    the centre of its log-variance prior (default: the current iterate). ``current_n_m_s``
    (2,) m/s is the sea current to start from (default zero); re-estimated by the M-step
    when ``options.mstep.fit_current``, returned in :attr:`EMResult.current_n_m_s`.
    ``surge_increments`` (:mod:`adaptnav.calibration.inertial`) go to every M-step, and their
    composite log-likelihood is part of ℓ.
    """
    raw_observations = observations
    has_landmarks = any(isinstance(o, LandmarkSighting) for obs in observations for o in (obs or ()))
    smooth = ffbsi_exact if options.smoother == "exact" else ffbsi_mcmc
    params = params0
    current = (0.0, 0.0) if current_n_m_s is None else (float(current_n_m_s[0]), float(current_n_m_s[1]))
    lls: list[float] = []
    converged = False
    held: tuple[str, ...] = ()
    notes: list[str] = []
    fr = None
    for it in range(options.max_iterations):
        if has_landmarks or it == 0:  # the map follows the parameters (it is built with them)
            observations = freeze_landmarks(params, v_m_s, w_rad_s, dt_s, raw_observations, init_poses, rng,
                                            options.n_particles, current)
        fr = run_particle_filter(params, v_m_s, w_rad_s, dt_s, observations, init_poses, rng,
                                 options.n_particles, current_n_m_s=current)
        lls.append(fr.log_likelihood + (surge_increments.log_likelihood(params) if surge_increments is not None
                                        else 0.0))
        if it > 0 and abs(lls[-1] - lls[-2]) < options.ll_tol * (1.0 + abs(lls[-1])) and moved < options.param_rtol:
            converged = True
            break
        kwargs = {"n_mcmc": options.n_mcmc} if smooth is ffbsi_mcmc else {}
        kwargs["turn_about_mean"] = options.mstep.turn_about_mean  # same branch as the M-step
        traj = smooth(fr, params, v_m_s, w_rad_s, dt_s, options.n_smoothed, rng, current_n_m_s=current, **kwargs)
        ms = m_step(traj, v_m_s, w_rad_s, dt_s, params, step_weights, options.mstep, prior_params, current,
                    surge_increments)
        held, notes = ms.held, ms.notes
        # current: 0.01 m/s as the scale of a relevant change
        moved = max(_max_rel_change(params, ms.params),
                    max(abs(a - b) for a, b in zip(current, ms.current_n_m_s)) / 0.01)
        params, current = ms.params, ms.current_n_m_s
    return EMResult(params, lls, len(lls), converged, held, notes, fr, current)
