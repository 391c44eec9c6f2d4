"""Synthetic seabed for the side-scan simulator: sediment texture + shadow-casting objects.

The seabed is a flat plane (``z = 0``, heights positive upwards) over the local NED
rectangle ``[0, extent_n] × [0, extent_e]`` sampled every ``res_m``.

Two generators:

* :meth:`Seabed.random` (the original test seabed): log-normal texture
  ``ρ = exp(a₁ g₁ + a₂ g₂)`` (``g`` white noise smoothed at two correlation lengths; Bell &
  Linnett, *IEE Proc.* 1997) and half-ellipsoid objects of one size range.
* :meth:`Seabed.survey` (the simulator's): sediment *provinces* (mud, sand, gravel patches
  tens of metres across with different mean backscatter — a thresholded smooth field),
  sand ripples (wavelength 0.6–1.2 m, a few cm high, only on sand: they modulate the
  incidence angle, so the renderer shows them as the stripes real side-scan does),
  fine-grain log-normal texture, and objects of realistic kinds and sizes
  (Blondel, *The Handbook of Sidescan Sonar*, ch. 5; target sizes of MCM/debris surveys):

  ===========  ===================================  ===============  ==============
  kind         shape                                 horizontal size  height
  ===========  ===================================  ===============  ==============
  boulder      half-ellipsoid                        0.6–2.4 m         0.3–1.2 m
  debris       rotated box (crates, drums, pipes)    0.5–2.5 × 0.3–1   0.25–0.8 m
  tyre         torus lying flat                      0.6–1.0 m Ø       0.2–0.3 m
  wreck        box hull with a rounded bow, one      15–30 × 4–8 m     2–4 m
  ===========  ===================================  ===============  ==============

Known object positions, kinds, extents and heights are the ground truth for the landmark
tests and ``adaptnav experiment landmarks``.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.ndimage import gaussian_filter

OBJECT_KINDS = ("boulder", "debris", "tyre", "wreck")
# relative frequencies of the small kinds (the wreck is placed once per seabed)
_KIND_WEIGHTS = {"boulder": 0.5, "debris": 0.3, "tyre": 0.2}
# backscatter multipliers: rock < rubber < metal
_KIND_REFLECTIVITY = {"boulder": 3.0, "debris": 5.0, "tyre": 2.5, "wreck": 4.0}


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
        Half the largest horizontal extent (m).
    objects_height_m : numpy.ndarray, shape (K,)
    objects_kind : tuple of str, length K
        One of :data:`OBJECT_KINDS` ("boulder" for :meth:`random`).
    objects_size_m : numpy.ndarray, shape (K, 2)
        Horizontal (length, width) of each object (m).
    """

    reflectivity: np.ndarray
    height_m: np.ndarray
    res_m: float
    objects_n_m: np.ndarray
    objects_radius_m: np.ndarray
    objects_height_m: np.ndarray
    objects_kind: tuple = field(default=())
    objects_size_m: np.ndarray | None = None

    def __post_init__(self) -> None:
        k = len(self.objects_n_m)
        if not self.objects_kind:
            object.__setattr__(self, "objects_kind", ("boulder",) * k)
        if self.objects_size_m is None:
            d = 2.0 * np.asarray(self.objects_radius_m, float)
            object.__setattr__(self, "objects_size_m", np.column_stack([d, d]).reshape(k, 2))

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
        """A random seabed of half-ellipsoid objects on log-normal texture.

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
        refl = _lognormal_texture(shape, res_m, texture_scales_m, texture_amplitudes, rng)
        height = np.zeros(shape, np.float32)
        pos = np.column_stack([rng.uniform(margin_m, ext[0] - margin_m, n_objects),
                               rng.uniform(margin_m, ext[1] - margin_m, n_objects)])
        rad = rng.uniform(*radius_m, n_objects)
        hgt = rng.uniform(*height_m, n_objects)
        for (pn, pe), r, h in zip(pos, rad, hgt):
            _stamp(height, refl, res_m, pn, pe, r, object_reflectivity,
                   lambda dn, de, r=r, h=h: _ellipsoid(dn, de, r, r, h))
        refl.setflags(write=False)
        height.setflags(write=False)
        return cls(refl.astype(np.float32), height, float(res_m), pos, rad, hgt)

    @classmethod
    def survey(cls, extent_n_m, rng: np.random.Generator, n_objects: int = 30, *,
               res_m: float = 0.1, wreck: bool = True, margin_m: float = 3.0,
               min_separation_m: float = 4.0) -> "Seabed":
        """A survey-area seabed: sediment provinces, ripples, realistic objects and a wreck.

        Parameters
        ----------
        extent_n_m : float or (2,) sequence
            North and east extent (m).
        rng : numpy.random.Generator
        n_objects : int
            Small objects (boulders, debris, tyres in the proportions 5:3:2).
        res_m : float
            Grid spacing (m); ≤ 0.1 m resolves tyres.
        wreck : bool
            Place one wreck (when the area is at least 60 m on each side).
        margin_m : float
            Objects keep this far from the edges.
        min_separation_m : float
            Objects are at least this far apart (centre to centre, plus their radii):
            a landmark is one object, not a cluster (rejection sampling, bounded tries).

        Returns
        -------
        Seabed
        """
        ext = np.broadcast_to(np.asarray(extent_n_m, dtype=float), (2,))
        shape = tuple(int(round(e / res_m)) + 1 for e in ext)
        refl, height = _sediment(shape, res_m, rng)
        kinds: list[str] = []
        pos: list[tuple[float, float]] = []
        size: list[tuple[float, float]] = []
        hgt: list[float] = []
        yaw: list[float] = []
        if wreck and min(ext) >= 60.0:
            length, beam = rng.uniform(15.0, 30.0), rng.uniform(4.0, 8.0)
            kinds.append("wreck")
            pos.append((rng.uniform(0.3, 0.7) * ext[0], rng.uniform(0.3, 0.7) * ext[1]))
            size.append((length, beam))
            hgt.append(rng.uniform(2.0, 4.0))
            yaw.append(rng.uniform(0.0, np.pi))
        names = list(_KIND_WEIGHTS)
        weights = np.array([_KIND_WEIGHTS[k] for k in names])
        tries = 0
        while len(kinds) < n_objects + (1 if kinds and kinds[0] == "wreck" else 0) and tries < 20 * n_objects:
            tries += 1
            kind = names[int(rng.choice(len(names), p=weights / weights.sum()))]
            if kind == "boulder":
                d = rng.uniform(0.6, 2.4)
                s = (d * rng.uniform(0.8, 1.0), d * rng.uniform(0.6, 1.0))
                h = min(rng.uniform(0.3, 1.2), 0.7 * s[0])
            elif kind == "debris":
                s = (rng.uniform(0.5, 2.5), rng.uniform(0.3, 1.0))
                h = rng.uniform(0.25, 0.8)
            else:  # tyre
                d = rng.uniform(0.6, 1.0)
                s, h = (d, d), rng.uniform(0.2, 0.3)
            s = (max(s), min(s))  # (length, width)
            p = (rng.uniform(margin_m, ext[0] - margin_m), rng.uniform(margin_m, ext[1] - margin_m))
            r = 0.5 * max(s)
            if any(np.hypot(p[0] - q[0], p[1] - q[1]) < min_separation_m + r + 0.5 * max(sq)
                   for q, sq in zip(pos, size)):
                continue
            kinds.append(kind)
            pos.append(p)
            size.append(s)
            hgt.append(h)
            yaw.append(rng.uniform(0.0, np.pi))
        for kind, (pn, pe), (length, width), h, a in zip(kinds, pos, size, hgt, yaw):
            _stamp(height, refl, res_m, pn, pe, 0.5 * max(length, width), _KIND_REFLECTIVITY[kind],
                   _shape_fn(kind, 0.5 * length, 0.5 * width, h, a))
        refl.setflags(write=False)
        height.setflags(write=False)
        size_a = np.array(size, float).reshape(-1, 2)
        return cls(refl.astype(np.float32, copy=False), height, float(res_m),
                   np.array(pos, float).reshape(-1, 2), 0.5 * size_a.max(axis=1) if len(size_a) else np.zeros(0),
                   np.array(hgt, float), tuple(kinds), size_a)


def _lognormal_texture(shape, res_m, scales_m, amplitudes, rng, coarse: bool = False) -> np.ndarray:
    """``exp(Σ a g)`` normalised to mean 1 (g: unit-variance smoothed white noise).

    ``coarse``: a component whose correlation length spans many cells is drawn on a grid of
    a quarter of that length and interpolated (bilinear): the same statistics for a fraction
    of the filtering cost on a survey-sized grid (:meth:`Seabed.random` keeps the full grid:
    its seabeds are the fixtures of earlier tests).
    """
    import cv2

    log_refl = np.zeros(shape, np.float32)
    for scale, amp in zip(scales_m, amplitudes):
        step = max(int(scale / res_m / 4.0), 1) if coarse else 1
        cshape = (shape[0] // step + 2, shape[1] // step + 2) if step > 1 else shape
        g = gaussian_filter(rng.standard_normal(cshape).astype(np.float32), scale / res_m / step)
        if step > 1:
            g = cv2.resize(g, (cshape[1] * step, cshape[0] * step), interpolation=cv2.INTER_LINEAR)[: shape[0], : shape[1]]
        log_refl += amp * g / max(float(g.std()), 1e-12)
    refl = np.exp(log_refl)
    refl /= refl.mean()
    return refl


def _sediment(shape, res_m, rng) -> tuple[np.ndarray, np.ndarray]:
    """Reflectivity and ripple heights of a mixed sediment seabed.

    Provinces: a smooth field (correlation ~15 m) cut at its terciles into mud (backscatter
    ×0.5), sand (×1) and gravel (×1.8), with the boundaries blurred over ~1 m. Ripples on
    sand: ``z = a sin(2π x·k̂ / λ)`` with λ 0.6–1.2 m, a 2–4 cm, crest direction random.
    Fine texture: log-normal at 0.3 m and 2 m (grain, shell patches).
    """
    coarse_res = 1.0  # provinces computed on a 1 m grid and interpolated (cheap)
    cshape = tuple(max(int(round(s * res_m / coarse_res)) + 1, 2) for s in shape)
    field_c = gaussian_filter(rng.standard_normal(cshape), 15.0 / coarse_res)
    t1, t2 = np.quantile(field_c, [1 / 3, 2 / 3])
    level_c = np.where(field_c < t1, np.log(0.5), np.where(field_c < t2, 0.0, np.log(1.8)))
    level_c = gaussian_filter(level_c, 1.0 / coarse_res)
    sand_c = gaussian_filter(((field_c >= t1) & (field_c < t2)).astype(float), 1.0 / coarse_res)
    import cv2

    def up(a):  # bilinear, coarse → fine (cv2: an order of magnitude faster than ndimage.zoom)
        return cv2.resize(a.astype(np.float32), (shape[1], shape[0]), interpolation=cv2.INTER_LINEAR)

    level, sand = up(level_c), up(sand_c)
    refl = _lognormal_texture(shape, res_m, (0.3, 2.0), (0.35, 0.25), rng, coarse=True) * np.exp(level)
    refl /= refl.mean()
    wavelength = rng.uniform(0.6, 1.2)
    amp = rng.uniform(0.02, 0.04)
    ang = rng.uniform(0.0, np.pi)
    ii = (np.arange(shape[0], dtype=np.float32) * res_m)[:, None]
    jj = (np.arange(shape[1], dtype=np.float32) * res_m)[None, :]
    phase = (2.0 * np.pi / wavelength) * (ii * np.float32(np.cos(ang)) + jj * np.float32(np.sin(ang)))
    height = (amp * sand * np.sin(phase)).astype(np.float32)
    height += np.float32(amp)  # ripples sit on the bed: heights ≥ 0
    np.maximum(height, 0.0, out=height)
    return refl.astype(np.float32), height


def _ellipsoid(dn, de, a, b, h):
    d2 = (dn / a) ** 2 + (de / b) ** 2
    return np.where(d2 < 1.0, h * np.sqrt(np.clip(1.0 - d2, 0.0, 1.0)), 0.0), d2 < 1.0


def _shape_fn(kind, half_len, half_wid, h, yaw):
    """Height function of one object in its rotated frame: ``f(dn, de) → (z, inside)``."""
    c, s = np.cos(yaw), np.sin(yaw)

    def rot(dn, de):
        return c * dn + s * de, -s * dn + c * de

    if kind == "boulder":
        return lambda dn, de: _ellipsoid(*rot(dn, de), half_len, half_wid, h)
    if kind == "debris":
        def box(dn, de):
            u, v = rot(dn, de)
            inside = (np.abs(u) <= half_len) & (np.abs(v) <= half_wid)
            return np.where(inside, h, 0.0), inside
        return box
    if kind == "tyre":
        tube = 0.5 * h  # the tread's half-width is half the lying tyre's height

        def torus(dn, de):
            rho = np.hypot(dn, de)
            d = np.abs(rho - (half_len - tube))
            inside = d < tube
            return np.where(inside, h * np.sqrt(np.clip(1.0 - (d / tube) ** 2, 0.0, 1.0)), 0.0), inside
        return torus

    def hull(dn, de):  # wreck: flat-topped hull, rounded bow (ellipse over the front third)
        u, v = rot(dn, de)
        bow = u > half_len / 3.0
        du = np.where(bow, (u - half_len / 3.0) / (2.0 * half_len / 3.0), 0.0)
        inside = (np.abs(u) <= half_len) & ((du ** 2 + (v / half_wid) ** 2 <= 1.0) & (np.abs(v) <= half_wid))
        z = h * np.clip(1.2 - 0.4 * (v / half_wid) ** 2, 0.0, 1.0)
        return np.where(inside, z, 0.0), inside
    return hull


def _stamp(height, refl, res_m, pn, pe, radius_m, refl_gain, fn) -> None:
    """Raise ``height`` to the object's and multiply ``refl`` inside it (in place)."""
    shape = height.shape
    i0, i1 = max(int((pn - radius_m) / res_m), 0), min(int((pn + radius_m) / res_m) + 2, shape[0])
    j0, j1 = max(int((pe - radius_m) / res_m), 0), min(int((pe + radius_m) / res_m) + 2, shape[1])
    if i1 <= i0 or j1 <= j0:
        return
    ii, jj = np.meshgrid(np.arange(i0, i1) * res_m - pn, np.arange(j0, j1) * res_m - pe, indexing="ij")
    z, inside = fn(ii, jj)
    sl = (slice(i0, i1), slice(j0, j1))
    height[sl] = np.maximum(height[sl], z.astype(np.float32))
    refl[sl] = np.where(inside, refl[sl] * refl_gain, refl[sl])
