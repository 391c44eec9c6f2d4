"""Side-scan renderer: a :class:`~sim.seabed.Seabed` seen from a pose → :class:`SonarPing`.

For each side the ping samples slant ranges ``r_k = (k + ½) R / N``.  With the sonar at
height ``H`` over the flat seabed, sample ``k`` hits ground range ``g_k = sqrt(r_k² − H²)``
(``r_k < H``: water column, only noise), at ``p = pos + g_k u`` with ``u`` the unit
vector to that side (starboard ``(−sin ψ, cos ψ)`` in (n, e)).  Intensity:

    I_k = ρ(p) · max(cos i_k, 0) · B(δ_k) · S_k · L + n_k,

* ``cos i_k = (g s + H − z) / (r sqrt(1 + s²))``: incidence on the local slope
  ``s = dz/dg`` (Lambert-like; slopes facing the sonar are bright — the highlight);
* shadow: ``I_k = n_k`` when a nearer point occludes the ray, i.e.
  ``min_{j<k} (H − z_j)/g_j < (H − z_k)/g_k``;
* ``B(δ) = exp(−½ ((δ − δ₀)/σ_b)²)``: vertical beam pattern over the depression
  angle ``δ = atan2(H − z, g)``;
* ``S_k ~ Gamma(L, 1/L)``: speckle (L looks); ``L`` per ping: log-normal gain jitter
  plus, with probability ``line_probability``, a bright line — the horizontal-line
  noise of the seed (sec. 3.2);
* ``n_k``: exponential background noise.

Everything is vectorised over the samples: one ping is a handful of numpy calls.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import map_coordinates

from adaptnav.sim.seabed import Seabed
from adaptnav.sonar.ping import SonarPing


@dataclass(frozen=True)
class SidescanSettings:
    """Beam, speckle and noise settings of :class:`SidescanRenderer`."""

    beam_depression_rad: float = math.radians(15.0)
    beam_width_rad: float = math.radians(25.0)
    speckle_looks: float = 4.0
    noise_level: float = 0.02
    line_gain_sigma: float = 0.15
    line_probability: float = 0.02
    line_strength: float = 1.5


class SidescanRenderer:
    """Renders side-scan pings of a seabed.

    Parameters
    ----------
    seabed : Seabed
    range_m : float
        Slant range of the last sample (m).
    samples_per_side : int
    settings : SidescanSettings
    """

    def __init__(self, seabed: Seabed, range_m: float = 30.0, samples_per_side: int = 1024,
                 settings: SidescanSettings = SidescanSettings()) -> None:
        self.seabed = seabed
        self.range_m = float(range_m)
        self.samples_per_side = int(samples_per_side)
        self.settings = settings
        self._r = ((np.arange(self.samples_per_side) + 0.5) * self.range_m
                   / self.samples_per_side).astype(np.float64)

    def _sides(self, pos: np.ndarray, u: np.ndarray, altitude_m: float,
               rng: np.random.Generator, gain: float) -> np.ndarray:
        """Both sides at once: ``u`` (2, 2) unit vectors (port, starboard) → (2, N)."""
        st = self.settings
        r = self._r[None, :]
        h = altitude_m
        ground = np.broadcast_to(r > h, (2, r.size))
        g1 = np.sqrt(np.maximum(self._r * self._r - h * h, 0.0))
        g = np.broadcast_to(g1, (2, r.size))
        pn = pos[0] + g * u[:, 0:1]
        pe = pos[1] + g * u[:, 1:2]
        coords = np.stack([pn.ravel(), pe.ravel()]) / self.seabed.res_m
        refl = map_coordinates(self.seabed.reflectivity, coords, order=1, mode="constant",
                               cval=0.0).reshape(2, -1)
        z = map_coordinates(self.seabed.height_m, coords, order=1, mode="constant",
                            cval=0.0).reshape(2, -1)
        z = np.minimum(z, 0.95 * h)
        dz, dg = np.gradient(z, axis=1), np.gradient(g1)[None, :]
        slope = np.divide(dz, dg, out=np.zeros_like(z), where=dg > 1e-9)
        cos_inc = (g * slope + (h - z)) / (r * np.sqrt(1.0 + slope * slope))
        q = np.where(ground, (h - z) / np.maximum(g, 1e-6), np.inf)
        run_min = np.minimum.accumulate(q, axis=1)
        prev_min = np.concatenate([np.full((2, 1), np.inf), run_min[:, :-1]], axis=1)
        lit = ground & (prev_min >= q * (1.0 - 1e-6))
        depression = np.arctan2(h - z, np.maximum(g, 1e-6))
        beam = np.exp(-0.5 * ((depression - st.beam_depression_rad) / st.beam_width_rad) ** 2)
        speckle = rng.gamma(st.speckle_looks, 1.0 / st.speckle_looks, z.shape)
        echo = refl * np.maximum(cos_inc, 0.0) * beam * speckle * gain
        noise = rng.exponential(st.noise_level, z.shape)
        return np.where(lit, echo, 0.0) + noise

    def render(self, t_s: float, pos_n_m, yaw_rad: float, altitude_m: float,
               rng: np.random.Generator, speed_m_s: float = math.nan) -> SonarPing:
        """One ping at a pose.

        Parameters
        ----------
        t_s : float
        pos_n_m : (2,) or (3,) array
            Sonar position (north, east[, down]) in the seabed's frame (m).
        yaw_rad : float
            Heading (rad, from north towards east).
        altitude_m : float
            Height of the sonar above the flat seabed (m).
        rng : numpy.random.Generator
        speed_m_s : float
            Copied into the ping (NaN unknown).

        Returns
        -------
        SonarPing
        """
        st = self.settings
        pos = np.asarray(pos_n_m, dtype=float)
        c, s = math.cos(yaw_rad), math.sin(yaw_rad)
        stbd_u = np.array([-s, c])
        gain = math.exp(rng.normal(0.0, st.line_gain_sigma))
        line = rng.random() < st.line_probability
        port, stbd = self._sides(pos, np.stack([-stbd_u, stbd_u]), altitude_m, rng, gain)
        if line:
            stbd = stbd + st.line_strength
            port = port + st.line_strength
        depth = float(pos[2]) if pos.size > 2 else math.nan
        return SonarPing(t_s=float(t_s), port=port.astype(np.float32), starboard=stbd.astype(np.float32),
                         slant_range_m=self.range_m, altitude_m=float(altitude_m),
                         heading_rad=float(yaw_rad), pitch_rad=0.0, roll_rad=0.0,
                         sensor_depth_m=depth, speed_m_s=float(speed_m_s))

    def render_track(self, t_s, pos_n_m, yaw_rad, altitude_m, rng: np.random.Generator,
                     speed_m_s=None) -> list[SonarPing]:
        """Pings along a trajectory (arrays of length P; scalars broadcast)."""
        t = np.atleast_1d(np.asarray(t_s, float))
        pos = np.asarray(pos_n_m, float).reshape(t.size, -1)
        yaw = np.broadcast_to(np.asarray(yaw_rad, float), t.shape)
        alt = np.broadcast_to(np.asarray(altitude_m, float), t.shape)
        spd = np.broadcast_to(np.asarray(math.nan if speed_m_s is None else speed_m_s, float), t.shape)
        return [self.render(t[i], pos[i], yaw[i], alt[i], rng, spd[i]) for i in range(t.size)]
