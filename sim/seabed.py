"""Synthetic seabed for the side-scan simulator: sediment texture + shadow-casting objects.

The seabed is a flat plane (``z = 0``, heights positive upwards) over the local NED
rectangle ``[0, extent_n] × [0, extent_e]`` sampled every ``res_m``:

* **reflectivity** ``ρ(n, e) = exp(a₁ g₁ + a₂ g₂)`` normalised to mean 1, with
  ``g₁, g₂`` white noise smoothed by Gaussians of two correlation lengths (ripples,
  sediment patches) — a log-normal texture as in the side-scan literature
  (e.g. Bell & Linnett, *IEE Proc.* 1997, simulation of side-scan images);
* **objects** (rocks, debris): half-ellipsoids ``z = h sqrt(1 − (d/r)²)`` with a higher
  reflectivity; their heights make the renderer cast acoustic shadows.

Known object positions are the ground truth for landmark tests.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import gaussian_filter


@dataclass(frozen=True, eq=False)
class Seabed:
    """A gridded seabed (read-only arrays).

    Attributes
    ----------
    reflectivity : numpy.ndarray, shape (Rn, Re), float32
        Backscatter strength (mean ≈ 1 on sediment).
    height_m : numpy.ndarray, shape (Rn, Re), float32
        Height above the flat seabed (m, up positive).
    res_m : float
        Grid spacing (m); cell ``(i, j)`` is centred at ``(i res, j res)`` (n, e).
    objects_n_m : numpy.ndarray, shape (K, 2)
        Object centres (north, east), m.
    objects_radius_m : numpy.ndarray, shape (K,)
    objects_height_m : numpy.ndarray, shape (K,)
    """

    reflectivity: np.ndarray
    height_m: np.ndarray
    res_m: float
    objects_n_m: np.ndarray
    objects_radius_m: np.ndarray
    objects_height_m: np.ndarray

    @property
    def extent_n_m(self) -> tuple[float, float]:
        """(north, east) extent in metres."""
        return ((self.reflectivity.shape[0] - 1) * self.res_m,
                (self.reflectivity.shape[1] - 1) * self.res_m)

    @classmethod
    def random(cls, extent_n_m, rng: np.random.Generator, n_objects: int = 30, *,
               res_m: float = 0.1, radius_m: tuple[float, float] = (0.25, 0.6),
               height_m: tuple[float, float] = (0.3, 1.0), object_reflectivity: float = 4.0,
               texture_scales_m: tuple[float, float] = (0.4, 3.0),
               texture_amplitudes: tuple[float, float] = (0.5, 0.35),
               margin_m: float = 2.0) -> "Seabed":
        """A random seabed.

        Parameters
        ----------
        extent_n_m : float or (2,) sequence
            North and east extent (m); a scalar means a square.
        rng : numpy.random.Generator
        n_objects : int
            Shadow-casting objects, placed uniformly (``margin_m`` from the edges).
        res_m : float
            Grid spacing (m).
        radius_m, height_m : (min, max)
            Uniform ranges of the object radius and height (m).
        object_reflectivity : float
            Reflectivity multiplier on objects.
        texture_scales_m, texture_amplitudes : 2-tuples
            Correlation lengths (m) and log-amplitudes of the two texture components.
        margin_m : float

        Returns
        -------
        Seabed
        """
        ext = np.broadcast_to(np.asarray(extent_n_m, dtype=float), (2,))
        shape = tuple(int(round(e / res_m)) + 1 for e in ext)
        log_refl = np.zeros(shape, np.float32)
        for scale, amp in zip(texture_scales_m, texture_amplitudes):
            g = gaussian_filter(rng.standard_normal(shape).astype(np.float32), scale / res_m)
            log_refl += amp * g / max(float(g.std()), 1e-12)
        refl = np.exp(log_refl)
        refl /= refl.mean()
        height = np.zeros(shape, np.float32)
        pos = np.column_stack([rng.uniform(margin_m, ext[0] - margin_m, n_objects),
                               rng.uniform(margin_m, ext[1] - margin_m, n_objects)])
        rad = rng.uniform(*radius_m, n_objects)
        hgt = rng.uniform(*height_m, n_objects)
        for (pn, pe), r, h in zip(pos, rad, hgt):
            i0, i1 = int((pn - r) / res_m), int((pn + r) / res_m) + 2
            j0, j1 = int((pe - r) / res_m), int((pe + r) / res_m) + 2
            i0, j0 = max(i0, 0), max(j0, 0)
            ii, jj = np.meshgrid(np.arange(i0, min(i1, shape[0])) * res_m,
                                 np.arange(j0, min(j1, shape[1])) * res_m, indexing="ij")
            d2 = ((ii - pn) ** 2 + (jj - pe) ** 2) / r ** 2
            inside = d2 < 1.0
            z = np.where(inside, h * np.sqrt(np.clip(1.0 - d2, 0.0, 1.0)), 0.0)
            sl = (slice(i0, i0 + z.shape[0]), slice(j0, j0 + z.shape[1]))
            height[sl] = np.maximum(height[sl], z)
            refl[sl] = np.where(inside, refl[sl] * object_reflectivity, refl[sl])
        refl.setflags(write=False)
        height.setflags(write=False)
        return cls(refl.astype(np.float32), height, float(res_m), pos, rad, hgt)
