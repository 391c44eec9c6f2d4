r"""Object landmarks on side-scan: highlight → acoustic shadow, with view-independent attributes.

An object standing on a flat seabed, seen from the side at altitude ``H``, returns a
*highlight* on its face towards the sonar and hides the seabed behind it: an acoustic
*shadow* that starts at the object's top (ground range ``g``) and is ``L`` long. Similar
triangles give its height (independent of the side it is seen from, which is what makes
it a landmark for reciprocal legs; Blondel, *The Handbook of Sidescan Sonar*, §4.5; Reed
et al., IEEE JOE 2003):

.. math:: h = H \, L / (g + L)

Canonical image (Xu et al. 2023, "canonical transformation" of side-scan): the
ground-range waterfall of :func:`adaptnav.sonar.waterfall.build_waterfall` (slant → ground
range with the altitude; every column divided by its median over pings — the beam pattern
and the incidence-angle falloff, which depend on range only; every row by its median —
ping gain) is further divided by a local background (a box mean over a few metres) so that
a mud patch (dark) or gravel (bright) does not look like a shadow or a highlight.

Detection (:func:`detect_objects`), per side with columns ordered outwards:

1. shadow pixels: local level < ``shadow_level``; connected components (8-neighbours) of
   at least ``min_shadow_px`` pixels and ``min_shadow_m`` long across-track;
2. a component is an object when, on some of its rows, the ``highlight_window_m`` just
   before its near edge holds a highlight (local level > ``highlight_level``);
3. attributes, over the object's own rows (the run of highlight rows around the brightest
   and the shadow beside them: a component may run on into dark seabed): the ping (row) at
   its centre, ground range of the top ``g`` (the shadow's near edge, median over rows), the
   leading edge of the highlight, shadow length ``L`` (largest over rows of the *deep*
   shadow — noise only, below ``deep_shadow_level`` — not of dark seabed), height ``h``, along-track extent (rows × metres per row) and
   across-track extent (leading edge to top). The position reported is ``top_weight``
   (0.7, measured) of the way from the leading edge to the top; its across-track error is a fraction of the object's
   size (the face seen differs between the two sides), in the covariance.

Near the nadir (``near_range_m``) objects are also taken by their highlight alone followed
by a darker strip: the shadow there is too short to measure (height NaN).

Weak sightings (``fine_range_m``): the shadowed-object test also runs on the waterfall before
its 3×3 median, which fills in the 1–3 px shadow of a small object near the nadir (a tyre's:
the dark hole inside its ring) and dims a tyre's one- or two-pixel tread further out. What it
finds that is not one of the usual sightings is marked :attr:`ObjectSighting.weak`: many are
speckle, so the associator never founds a set on them, and only adds them to a set the others
established, where its fitted drift predicts them (:class:`~adaptnav.sonar.association.LegAssociator`).

A shadowed sighting nearer than 20 m of contrast 5–6 is also weak (``short_strong_contrast``):
as often sediment as an object there.

Horizontal-line noise: :class:`ObjectFrontEnd` builds its waterfall with
``WaterfallConfig.line_removal`` (:func:`adaptnav.sonar.waterfall.remove_lines`): a ping with a
ping-wide additive offset came out of the gain normalisation as a flat row, near the nadir
(where the echo is weakest) without its objects.

Jump-free track: :class:`ObjectFrontEnd` given the navigation's velocity accumulates the
position changes the velocity does not explain (fixes, fused loop closures) in each
sighting's ``jump_n_m``; the associator compares sightings on ``pos_n_m − jump_n_m``.

SIFT/ORB keypoints (:mod:`adaptnav.sonar.landmarks`) remain for texture-rich seabeds.
"""
from __future__ import annotations

import functools
import itertools
import math
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

if TYPE_CHECKING:
    from adaptnav.sonar.waterfall import Waterfall
# scipy.ndimage and the waterfall (OpenCV) are imported where the detector runs: the daemon
# imports this module for the sighting type and with_navigation only (~15 MB less resident)


@dataclass(frozen=True)
class ObjectDetectorConfig:
    """Thresholds of :func:`detect_objects` (levels relative to the local background).

    Attributes
    ----------
    shadow_level, highlight_level : float
        Local level below which a pixel is shadow, above which it is highlight.
    deep_shadow_level : float
        The shadow's length (hence the height) is measured from its near edge to where the level
        rises to this for three pixels: inside a cast shadow there is only noise (level ≲ 0.1),
        while the dark seabed a shadow component often runs into (mud, a ripple trough) is
        0.3–0.5. Measured (survey seeds 1–5, true navigation): with the component's full
        length, of the objects detected on both reciprocal legs 17 had heights or along-track
        lengths more than 3σ apart (heights 1.4–2.3 m at 7–18 m ground range for 0.4–0.5 m
        objects; lengths 6–16 m), with the deep shadow and the object's own rows
        (:func:`_object_run`) 3; false sightings 219 → 70 (merged ripple shadows now read as
        the low objects ``min_height_m`` drops), objects detected on both legs 757 → 759.
    background_m : float
        Side (m) of the box over which the local background is averaged.
    smooth_px : (float, float)
        Gaussian smoothing (rows, columns; pixels) before thresholding (speckle).
    min_contrast : float
        Mean highlight level over mean shadow level of an object, at least.
    min_shadow_px : int
        Smallest shadow component (pixels).
    min_shadow_m : float
        Shortest shadow across-track (m) on its longest row.
    highlight_window_m : float
        Ground-range window before the shadow's near edge searched for the highlight (m).
    min_highlight_rows : int
        Rows of the component that must have a highlight before them.
    min_ground_range_m : float
        Objects nearer the track are dropped (nadir: shadows too short to measure).
    min_height_m : float
        Lower objects (height from the shadow) are dropped: far out, sand ripples 2–4 cm high
        cast shadows that read as 0.08–0.1 m objects (survey seed 4: 108 false sightings at
        40–50 m), while of 516 sightings of real objects re-found on two legs 0.2 % were
        below 0.15 m (the smallest kind, a tyre, stands 0.2 m).
    short_shadow_range_m, short_min_shadow_m, short_min_contrast : float
        Nearer than ``short_shadow_range_m`` the shortest shadow and the least contrast are
        these instead: a shadow is ``h g / (H − h)`` long, 0.3–0.6 m for a 0.3 m tyre or
        boulder at 10–20 m (H = 10 m), and there the incidence is steep enough that sand
        ripples hardly cast shadows (the false objects the far range's contrast keeps out).
        Measured (3 survey seabeds, true navigation): recall at 10–20 m 65/90 → 78/90, false
        detections nearer than 20 m 3 → 17 (of ~100 true). Contrast 5 once the shadow length
        is the deep shadow's (``deep_shadow_level``: far fewer false sightings to begin with):
        survey seeds 1–5, true navigation, objects detected on both legs 759 → 778 of 988,
        false sightings 70 → 311 (4: 795, 1590); ``adaptnav experiment landmarks``
        re-associated 72.0/69.9/76.7/73.8/69.4 → 75.7/71.5/75.2/74.9/74.2 %, false links ≤ 1.2 %.
    compact_width_m, compact_min_contrast : float
        Beyond ``short_shadow_range_m`` an object whose highlight runs into its shadow — the
        brightest return of the window at most ``compact_width_m`` before the shadow's start,
        the lit face of a small object ending at its crest — needs only this contrast. A
        tyre's tread is 0.2–0.3 m across: its highlight is a pixel or two, smoothed to 2–2.3
        of the background, and its shadow is interrupted by the far side of the ring, so its
        contrast is 5–7; a sand ripple's shadow is preceded by the lit crest of the next
        ripple, not a compact face. Measured (3 survey seabeds, true navigation, beyond 20 m,
        contrast 6–8): with the face ≤ 1 m 48 sightings of objects and 11 false ones; without
        the limit 58 and 138.
    merge_m : float
        Detections closer than this (across and along) are one object (a tyre casts two
        shadows; a wreck several): the one with the longer shadow is kept.
    top_weight : float
        The position reported across-track is ``lead + top_weight (top − lead)`` (highlight's
        leading edge to the shadow's start). Measured (3 survey seabeds, true navigation,
        ~200 sightings beyond 12 m): the midpoint (0.5) lay 0.15–0.2 m short of the centre
        (a boulder's shadow starts just past its crest, its highlight at its near flank),
        the top (1.0) 0.25–0.35 m beyond; 0.7 is within ±0.05 m. On reciprocal legs the
        short-fall had the same sign on every leg pair, so each loop closure pulled the
        navigation ~0.3 m across-track the same way (seed 2: drift 0.135 % with landmarks
        vs 0.103 % with the weight).
    sigma_across_m, sigma_along_m : float
        Base 1-σ of the reported position (m), before the size-dependent part.
    size_fraction : float
        Position 1-σ grows by this fraction of the object's extent.
    near_range_m : float
        Nearer than this (ground range) an object is also sought by its highlight alone
        (:func:`_detect_near`): near the nadir the rays are steep, a 0.5 m object's shadow is
        0.25–0.6 m (h g / (H − h) at g = 5–12 m, H = 10 m), too short for the shadow test,
        while its lit top and face stand out (0 disables). Height is then unknown (NaN).
    near_highlight_level, near_min_px, near_min_rows, near_mean_level : float, int, int, float
        A near highlight: pixels above ``near_highlight_level``, at least ``near_min_px`` of
        them on ``near_min_rows`` rows, mean level at least ``near_mean_level``.
    near_shadow_level, near_min_contrast, near_min_along_m : float
        …followed by a darker strip (0.4 m just beyond it, mean level below
        ``near_shadow_level`` and the blob's mean over it at least ``near_min_contrast``), at
        least ``near_min_along_m`` long along-track. Measured on survey seabeds (3 seeds,
        true navigation): objects' blobs have contrast median 2.6 (10 % below 1.7), sediment
        and speckle blobs 1.6 (90 % below 1.9); along-track 1.2 m vs 0.6 m.
    fine_range_m : float
        Nearer than this (ground range; 50: the whole swath) objects are also sought on the
        waterfall *without* its 3×3 median (:func:`detect_objects`' ``unfiltered``), and kept
        as *weak* sightings (:attr:`ObjectSighting.weak`): near the nadir a small object's
        shadow is 1–3 px (``h g / (H − h)``: 0.2–0.5 m for a 0.25 m tyre at 8–20 m, H = 10 m)
        and a tyre's is the dark hole inside its ring, which the median fills in; further out a
        tyre's lit tread is a pixel or two, which it dims. Measured (survey seeds 1–5, true
        navigation; objects abeam of a leg found / false sightings): tyres alone were found
        1/64 at 5–10 m, 48/138 at 10–20 m, 248/341 at 20–45 m; with the unfiltered image nearer
        than 20 m, recall at 5–10 / 10–20 m 0.63 / 0.84 → 0.78 / 0.92, false sightings 311 →
        ~5300; over the whole swath 20–45 m also 0.93 → 0.96 for ~240 more; objects
        found on both of two reciprocal legs 786 → 886 of 999. Too many false ones to found a
        loop closure on, hence weak (0 disables).
        The tests are the filtered image's (measured, seeds 1–5 as above: the short-range
        thresholds over the whole swath gave 7 more objects found on both legs for 2700 more
        false sightings; at most 1.2 / 1.0 m across-track from the highlight's leading edge to
        the shadow, 98 / 87 of the 161 objects the filtered image missed nearer than 20 m for
        1708 / 941 of the 5115 false sightings, before the associator's test made the false
        ones harmless).
    short_strong_contrast : float
        With the weak sightings on (``fine_range_m``), a shadowed sighting nearer than
        ``short_shadow_range_m`` whose contrast is below this (≥ ``short_min_contrast``) is also
        weak: it joins a set the others founded but founds none. Measured (survey seeds 1–3,
        true navigation, shadowed sightings nearer than 20 m): contrast 5–6, 62 on objects and
        152 not; contrast ≥ 6, 496 and 32. The false links of ``adaptnav experiment landmarks``
        seed 7 with the line removal (3 of 192 pairs) each had one such sighting at 6–9 m.
        Seeds 1–15 (``--no-calibrator``): false pairs 14 → 4 of ~3060, re-associated mean
        81.4 → 80.7 % (0 disables).
    """

    shadow_level: float = 0.5
    deep_shadow_level: float = 0.3
    highlight_level: float = 1.7
    min_contrast: float = 8.0
    background_m: float = 6.0
    smooth_px: tuple[float, float] = (0.5, 0.7)
    min_shadow_px: int = 6
    min_shadow_m: float = 0.45
    highlight_window_m: float = 1.5
    min_highlight_rows: int = 1
    min_ground_range_m: float = 4.0
    min_height_m: float = 0.15
    short_shadow_range_m: float = 20.0
    short_min_shadow_m: float = 0.3
    short_min_contrast: float = 5.0
    compact_width_m: float = 1.0
    compact_min_contrast: float = 6.0
    merge_m: float = 1.5
    top_weight: float = 0.7
    sigma_across_m: float = 0.15
    sigma_along_m: float = 0.2
    size_fraction: float = 0.15
    near_range_m: float = 12.0
    near_highlight_level: float = 2.2
    near_min_px: int = 12
    near_min_rows: int = 3
    near_mean_level: float = 3.0
    near_shadow_level: float = 2.0
    near_min_contrast: float = 2.0
    near_min_along_m: float = 0.7
    fine_range_m: float = 50.0
    short_strong_contrast: float = 6.0


@dataclass(frozen=True, eq=False)
class ObjectSighting:
    """One object seen on one side-scan pass.

    Attributes
    ----------
    t_s : float
        Time of the ping that saw it abeam (s).
    side : str
        ``"port"`` or ``"starboard"``.
    ground_range_m : float
        Horizontal distance of the object's centre from the track (m).
    height_m : float
        Height from the shadow, ``H L / (g + L)`` (m).
    shadow_length_m : float
        Longest shadow (m).
    length_along_m, width_across_m : float
        Along-track extent (rows × metres per row; NaN when the along spacing is unknown)
        and across-track extent (highlight leading edge to top), m.
    contrast : float
        Mean highlight level / mean shadow level.
    altitude_m : float
        Altitude used (m).
    row : float
        Waterfall row of the centre.
    pos_n_m : numpy.ndarray or None, shape (2,)
        Local (north, east) from the navigation at ``t_s`` (set by the front end).
    nav_cov : numpy.ndarray or None, shape (2, 2)
        Covariance of the navigation's horizontal position at ``t_s`` (m²).
    det_cov : numpy.ndarray or None, shape (2, 2)
        Covariance (north, east) of the position relative to the vehicle (m²): the
        detector's error.
    heading_rad : float
        Heading at ``t_s`` (rad).
    jump_n_m : numpy.ndarray or None, shape (2,)
        The navigation's accumulated jumps up to ``t_s`` (its position minus the integral of
        its velocity, m; set by the front end when it has the velocity): ``pos_n_m − jump_n_m``
        is the *jump-free* track, smooth across the filter's updates (a fix, a fused loop
        closure), on which sightings of different times agree on one rigid offset.
    vel_cov : numpy.ndarray or None, shape (2, 2)
        Covariance of the navigation's horizontal velocity at ``t_s`` (m²/s²): the jump-free
        track drifts from its value at ``t_s`` by about the velocity error times the time.
    weak : bool
        Found only on the unfiltered image near the nadir (``ObjectDetectorConfig.fine_range_m``),
        or nearer than 20 m with a contrast below ``ObjectDetectorConfig.short_strong_contrast``:
        false ones are too frequent to found a loop closure, so the associator only adds such a
        sighting to a set that its other sightings established (:class:`~adaptnav.sonar.association.LegAssociator`).
    guided : bool
        Not found by the detector: re-detected where a loop closure predicted an object seen on
        the other leg (:func:`adaptnav.sonar.guided.redetect`; also ``weak``).
    """

    t_s: float
    side: str
    ground_range_m: float
    height_m: float
    shadow_length_m: float
    length_along_m: float
    width_across_m: float
    contrast: float
    altitude_m: float
    row: float = math.nan
    pos_n_m: np.ndarray | None = None
    nav_cov: np.ndarray | None = None
    det_cov: np.ndarray | None = None
    heading_rad: float = math.nan
    jump_n_m: np.ndarray | None = None
    vel_cov: np.ndarray | None = None
    weak: bool = False
    guided: bool = False

    @property
    def smooth_pos_n_m(self) -> np.ndarray | None:
        """Position on the jump-free track (``pos_n_m − jump_n_m``; ``pos_n_m`` without it)."""
        if self.pos_n_m is None or self.jump_n_m is None:
            return self.pos_n_m
        return self.pos_n_m - self.jump_n_m

    def offset_n_m(self, yaw_rad: float) -> np.ndarray:
        """(north, east) of the object relative to the vehicle at ``t_s`` (m)."""
        return np.array(self._offset_floats(yaw_rad))

    def _offset_floats(self, yaw_rad: float) -> tuple[float, float]:
        """:meth:`offset_n_m` as two Python floats (the same products)."""
        c, s = math.cos(yaw_rad), math.sin(yaw_rad)
        k = (1.0 if self.side == "starboard" else -1.0) * self.ground_range_m
        return k * -s, k * c

    def detector_covariance(self, yaw_rad: float, config: "ObjectDetectorConfig") -> np.ndarray:
        """2×2 (north, east) covariance of :meth:`offset_n_m` (m²).

        Along-track: base σ + a fraction of the along extent; across-track: base σ + a
        fraction of the across extent (which face is lit depends on the side).
        """
        along = self.length_along_m if math.isfinite(self.length_along_m) else 1.0
        s_al = config.sigma_along_m + config.size_fraction * along
        s_ac = config.sigma_across_m + config.size_fraction * self.width_across_m
        c, s = math.cos(yaw_rad), math.sin(yaw_rad)
        R = np.array([[c, -s], [s, c]])  # columns: forward, starboard in (n, e)
        # R diag(σ²) Rᵀ: np.dot is np.matmul's BLAS product, bit for bit, for ~1 µs less each
        return np.dot(np.dot(R, np.array([[s_al ** 2, 0.0], [0.0, s_ac ** 2]])), R.T)


@functools.lru_cache(maxsize=8)
def _gaussian_weights(sigma: float, truncate: float = 4.0) -> np.ndarray:
    """The weights of ``scipy.ndimage.gaussian_filter1d`` (order 0, its default radius); made once
    per σ (four times per block before) and shared: not to be written."""
    radius = int(truncate * float(sigma) + 0.5)
    x = np.arange(-radius, radius + 1)
    phi = np.exp(-0.5 / (sigma * sigma) * x ** 2)
    return (phi / phi.sum())[::-1].copy()


_THRESHOLDS = (1e-3, 1e-3, 1e-6)  # the weight, count and background below which a pixel has none


def local_level(image: np.ndarray, ground_res_m: float, along_res_m: float,
                config: ObjectDetectorConfig, work: dict | None = None) -> np.ndarray:
    """Image divided by its local background (box mean over ``background_m``), smoothed.

    Pixels without data (0) stay 1 (neither shadow nor highlight). A float32 image larger
    than the filters is done by :func:`adaptnav.sonar._kernels.local_level` (the numbers of
    the scipy filters below, bit for bit); ``work``, a dict the caller keeps (one per
    detector), holds its scratch arrays from call to call.
    """
    along = along_res_m if math.isfinite(along_res_m) and along_res_m > 0 else ground_res_m
    box = (max(int(round(config.background_m / along)), 3), max(int(round(config.background_m / ground_res_m)), 3))
    s_rows, s_cols = (float(v) for v in np.broadcast_to(np.asarray(config.smooth_px, float), (2,)))
    if image.ndim == 2 and image.dtype == np.float32 and min(s_rows, s_cols) > 1e-15:
        w_rows, w_cols = _gaussian_weights(s_rows), _gaussian_weights(s_cols)
        shape = image.shape
        if w_rows.size // 2 <= shape[0] and w_cols.size // 2 <= shape[1] and box[0] <= shape[0] \
                and box[1] <= shape[1]:
            from adaptnav.sonar import _kernels

            scratch = None if work is None else work.get(shape)
            if scratch is None:
                scratch = (np.empty((5,) + shape, np.float32), np.empty(shape, bool))
                if work is not None:  # one shape kept (~4 MB for 200 pings of 1000 columns); with
                    # the weak sightings on, a block's image and its near-nadir slice alternate, so it
                    # is mostly reallocated: keeping both measured no faster (0.114-0.116 ms per ping)
                    work.clear()
                    work[shape] = scratch
            lev = np.empty(shape, np.float32)
            if not image.flags.carray:  # contiguous and writeable: what the compiled kernel takes
                image = np.array(image, order="C")
            _kernels.local_level(image, w_rows, w_cols, box[0], box[1], *_THRESHOLDS, scratch[0], scratch[1], lev)
            return lev
    return local_level_filters(image, box, config.smooth_px)


def local_level_filters(image: np.ndarray, box: tuple[int, int], smooth_px) -> np.ndarray:
    """:func:`local_level` with scipy.ndimage's filters (the compiled kernel's reference):
    ``box`` the background's (rows, columns) in pixels, ``smooth_px`` the Gaussian's σ."""
    from scipy.ndimage import gaussian_filter, uniform_filter

    data = image > 0
    img = gaussian_filter(np.where(data, image, 0.0).astype(np.float32), smooth_px)
    wgt = gaussian_filter(data.astype(np.float32), smooth_px)
    min_weight, min_count, min_background = _THRESHOLDS
    img = np.divide(img, wgt, out=np.zeros_like(img), where=wgt > min_weight)
    num = uniform_filter(np.where(data, img, 0.0), box)
    den = uniform_filter(data.astype(np.float32), box)
    bg = np.divide(num, den, out=np.ones_like(num), where=den > min_count)
    lev = np.divide(img, bg, out=np.ones_like(img), where=bg > min_background)
    lev[~data] = 1.0
    return lev


def detect_objects(waterfall: Waterfall, along_m: np.ndarray | None = None,
                   config: ObjectDetectorConfig = ObjectDetectorConfig(),
                   unfiltered: np.ndarray | None = None, work: dict | None = None) -> list[ObjectSighting]:
    """Highlight → shadow objects of a ground-range waterfall (see the module docstring).

    Parameters
    ----------
    waterfall : Waterfall
        Ground-range image (any along-track sampling; one row per ping is typical).
    along_m : numpy.ndarray, shape (M,), optional
        Along-track distance of every row (m), e.g. from the navigation; default the
        waterfall's own ``along_m`` (NaN when the speed was unknown: along extents NaN).
    config : ObjectDetectorConfig
    unfiltered : numpy.ndarray, optional
        The waterfall's image before its median filter (same shape): nearer than
        ``config.fine_range_m`` objects are also sought there, as weak sightings.
    work : dict, optional
        Scratch arrays kept from call to call (:func:`local_level`): one per detector.

    Returns
    -------
    list of ObjectSighting
        Sorted by time, without navigation (``pos_n_m`` etc. None).
    """
    img = waterfall.image
    n_rows = img.shape[0]
    if n_rows < 3:
        return []
    along = np.asarray(waterfall.along_m if along_m is None else along_m, dtype=float)
    step = np.diff(along)
    along_res = float(np.median(step)) if step.size and np.all(np.isfinite(step)) else math.nan
    res = waterfall.ground_res_m
    lev = local_level(img, res, along_res, config, work)
    w = waterfall.n_side
    rows = np.arange(n_rows, dtype=float)
    out: list[ObjectSighting] = []
    for side, sub in (("starboard", lev[:, w:]), ("port", _port_outwards(lev, w))):
        alt = waterfall.altitude_m[:, 1 if side == "starboard" else 0]
        out += _detect_side(sub, side, res, along, along_res, rows, waterfall, alt, config)
    out = _merge(out, config.merge_m, along_res)
    if unfiltered is not None and config.fine_range_m > 0:
        out += _detect_fine(unfiltered, out, res, along, along_res, rows, waterfall, config, work)
        if config.short_strong_contrast > config.short_min_contrast:
            # near the nadir, a shadowed object of low contrast is as often sediment: weak
            # (ObjectDetectorConfig.short_strong_contrast)
            out = [_replaced(o, weak=True) if (not o.weak and o.shadow_length_m > 0
                                                and o.contrast < config.short_strong_contrast
                                                and o.ground_range_m < config.short_shadow_range_m) else o
                   for o in out]
    return sorted(out, key=lambda o: o.t_s)


def _port_outwards(lev: np.ndarray, w: int) -> np.ndarray:
    """The port half of ``lev`` (its first ``w`` columns) with its columns outwards: the same values
    as the view ``lev[:, w - 1::-1]``, for a float32 image a contiguous copy by OpenCV's flip (0.02
    ms): the side's mask, labels and compiled scans then read memory forwards (the components of
    a reversed view took ~1.4 times as long)."""
    if lev.dtype == np.float32 and lev.ndim == 2 and w > 0 and lev.shape[0] > 0:
        import cv2

        return cv2.flip(lev[:, :w], 1)
    return lev[:, w - 1::-1]


def _detect_fine(image, strong, res, along, along_res, rows, wf, config, work=None) -> list[ObjectSighting]:
    """Weak sightings: shadowed objects nearer than ``fine_range_m`` on the unfiltered image, with
    a height, that are not one of the ``strong`` sightings."""
    w = image.shape[1] // 2
    # the columns up to fine_range_m and a background box beyond, so that the local level there is
    # the full image's
    ncol = min(int(round((config.fine_range_m + config.background_m) / res)), w)
    lev = local_level(image[:, w - ncol:w + ncol], res, along_res, config, work)
    weak = []
    for side, sub in (("starboard", lev[:, ncol:]), ("port", _port_outwards(lev, ncol))):
        alt = wf.altitude_m[:, 1 if side == "starboard" else 0]
        for o in _detect_shadowed(sub, side, res, along, along_res, rows, wf, alt, config, weak=True):
            if o.ground_range_m < config.fine_range_m and math.isfinite(o.height_m):
                weak.append(o)
    # one sighting per object: the strong one where there is one
    weak = _merge(weak, config.merge_m, along_res)
    return [o for o in weak if not _near_any(o, strong, config.merge_m, along_res)]


def _near_any(o: ObjectSighting, others: list[ObjectSighting], merge_m: float, along_res: float) -> bool:
    """``o`` within the merge distance of one of ``others`` (same side): the same object."""
    row_m = along_res if math.isfinite(along_res) and along_res > 0 else 0.4
    return any(k.side == o.side and abs(k.ground_range_m - o.ground_range_m) <= merge_m + 0.5 * k.width_across_m
               and abs(k.row - o.row) * row_m <= merge_m + 0.5 * (k.length_along_m if math.isfinite(k.length_along_m) else 0)
               for k in others)


def _detect_near(lev, side, res, along, along_res, rows, wf, alt_per_ping, config,
                 pretest: bool = True) -> list[ObjectSighting]:
    """Objects near the nadir by their highlight (see ``ObjectDetectorConfig.near_range_m``);
    ``pretest`` False takes every large blob through the per-blob tests (the reference of the
    tests made for all blobs at once)."""
    ncol = min(int(config.near_range_m / res), lev.shape[1])
    if ncol <= 0:
        return []
    sub = lev[:, :ncol + int(2.0 / res)]
    lab, n, runs, n_px, level_sum = _components(sub > config.near_highlight_level, sub)
    # every blob's box (scipy.ndimage.find_objects) from its rows (runs by label, then row)
    first = np.flatnonzero(np.r_[True, runs.label[1:] != runs.label[:-1]])
    stop = np.r_[first[1:], runs.label.size]
    row0, row1 = runs.row[first].tolist(), (runs.row[stop - 1] + 1).tolist()
    col0 = np.minimum.reduceat(runs.near, first) if first.size else np.zeros(0, np.int64)
    col1 = np.maximum.reduceat(runs.far, first).tolist() if first.size else []
    # the tests below that need no pixel gathered, for all blobs at once (most are speckle, and
    # nine in ten large ones fail them): the size, the rows (one run per row), the nearest column
    # exactly; the mean level on the float64 sum, with a margin for the float32 mean tested below
    maybe = n_px[1:] >= config.near_min_px
    if pretest:
        maybe &= ((stop - first >= config.near_min_rows) & (col0 < ncol) & (col0 >= int(config.min_ground_range_m / res))
                  & (level_sum[1:] >= n_px[1:] * (config.near_mean_level * (1.0 - 1e-4))))
    col0 = col0.tolist()
    out = []
    for k in (np.flatnonzero(maybe) + 1).tolist():
        sl = (slice(row0[k - 1], row1[k - 1]), slice(col0[k - 1], col1[k - 1]))
        comp = lab[sl] == k
        rr = np.flatnonzero(comp.any(axis=1))
        if rr.size < config.near_min_rows:
            continue
        c0 = sl[1].start
        if c0 >= ncol or c0 < int(config.min_ground_range_m / res):
            continue
        vals = sub[sl][comp]
        if float(vals.mean()) < config.near_mean_level:
            continue
        # behind the blob: darker than the background (a short shadow)
        far = np.array([sl[1].start + np.flatnonzero(row).max() + 1 for row in comp if row.any()])
        behind = [lev[r0, f:f + max(int(0.4 / res), 2)] for r0, f in zip(rr + sl[0].start, far)]
        bmean = float(np.mean(np.concatenate(behind))) if behind else 1.0
        if bmean > config.near_shadow_level:
            continue
        rc = float(sl[0].start + rr.mean())
        ping = float(np.interp(rc, rows, wf.ping_index))
        H = float(np.interp(ping, np.arange(alt_per_ping.size), alt_per_ping))
        length = (float(np.interp(sl[0].stop - 0.5, rows, along) - np.interp(sl[0].start - 0.5, rows, along))
                  if math.isfinite(along_res) else math.nan)
        g_lead, g_far = (c0 + 0.5) * res, (float(np.median(far)) + 0.5) * res
        contrast = float(vals.mean()) / max(bmean, 1e-3)
        if contrast < config.near_min_contrast or not abs(length) >= config.near_min_along_m:
            continue
        out.append(ObjectSighting(
            t_s=float(np.interp(rc, rows, wf.t_s)), side=side, ground_range_m=0.5 * (g_lead + g_far),
            height_m=math.nan, shadow_length_m=0.0, length_along_m=abs(length),
            width_across_m=max(g_far - g_lead, res), contrast=contrast,
            altitude_m=H, row=rc, heading_rad=float(np.interp(rc, rows, wf.heading_unwrapped_rad))))
    return out


def _detect_side(lev, side, res, along, along_res, rows, wf, alt_per_ping, config) -> list[ObjectSighting]:
    near = _detect_near(lev, side, res, along, along_res, rows, wf, alt_per_ping, config) if config.near_range_m > 0 else []
    return near + _detect_shadowed(lev, side, res, along, along_res, rows, wf, alt_per_ping, config)


def _detect_shadowed(lev, side, res, along, along_res, rows, wf, alt_per_ping, config,
                     compiled: bool = True, weak: bool = False) -> list[ObjectSighting]:
    """Shadowed objects on one side's local level ``lev`` (columns outwards), marked ``weak``
    (:attr:`ObjectSighting.weak`) as asked; ``compiled`` False takes the reference steps the
    compiled ones replaced: scipy's labels, the components' rows, tests and deep shadows in
    numpy, the candidates measured one by one in Python (:func:`_shadowed_loop`)."""
    if compiled:
        lab, n, runs, n_px, shadow_sum = _components(lev < config.shadow_level, lev)
    else:
        from scipy.ndimage import label

        lab, n = label(lev < config.shadow_level, structure=np.ones((3, 3), bool))
        runs, n_px, shadow_sum = _component_rows_numpy(lab, n, lev)
    if n == 0:
        return []
    hw = max(int(round(config.highlight_window_m / res)), 2)
    min_cols = max(int(round(config.min_shadow_m / res)), 1)
    short_cols = max(int(round(config.short_min_shadow_m / res)), 1)
    min_col0 = int(config.min_ground_range_m / res)
    # the tests every component must pass before its attributes are measured, for all
    # components at once (a side has hundreds of speckle components; testing them one by one
    # in Python was most of the detector's cost): size, shadow length, range, a highlight
    least = min(config.short_min_contrast, config.compact_min_contrast, config.min_contrast)
    deep = (_deep_shadow_rows if compiled else _deep_shadow_rows_scan)(lev, runs, config.deep_shadow_level)
    out = []
    kernel_ok = compiled and lev.dtype == np.float32 and lev.flags.aligned and lev.flags.writeable \
        and lab.dtype == np.int32
    if kernel_ok:
        # the tests below, all in one compiled pass (they were a tenth of the detector's CPU)
        hl, todo = _candidates_compiled(lev, runs, n_px, shadow_sum, deep, alt_per_ping, res, config, min_cols,
                                        short_cols, min_col0, hw, least)
        hl_label = runs.label[hl.run]
    else:
        hl, hl_label, todo = _candidates_numpy(lev, runs, n, n_px, shadow_sum, deep, alt_per_ping, res, config,
                                               min_cols, short_cols, min_col0, hw, least)
    if todo.size == 0:
        return out
    if not (kernel_ok and hl.level.dtype == np.float32):
        return _shadowed_loop(lev, lab, runs, deep, hl, hl_label, todo, side, res, along, along_res, rows, wf,
                              alt_per_ping, config, weak)
    m = _shadowed_measures(lev, lab, runs, n_px, deep, hl, todo)
    # the floating-point steps of the loop this replaced (_shadowed_loop, the reference), for
    # all candidates at once: numpy's element-wise arithmetic and interpolation are its scalars'
    short = m.med_near_all * res < config.short_shadow_range_m
    g_top = (m.med_near_own + 0.5) * res
    g_lead = (m.med_lead + 0.5) * res
    L = m.deep_px.astype(float) * res
    rc = m.row_sum / m.n_rows_centre
    ping = np.interp(rc, rows, wf.ping_index)
    H = np.interp(ping, np.arange(alt_per_ping.size), alt_per_ping)
    with np.errstate(invalid="ignore", divide="ignore"):
        height = np.where(m.touches_end, math.nan, H * L / (g_top + L))
        shadow_mean = (m.shadow_sum32.astype(float) / m.n_px).astype(np.float32).astype(float)  # numpy.mean's steps
        contrast = (m.hl_sum / m.hl_count) / np.maximum(shadow_mean, 1e-3)
        compact = g_top - g_lead <= config.compact_width_m
        need = np.where(short, config.short_min_contrast,
                        np.where(compact, config.compact_min_contrast, config.min_contrast))
        keep = np.isfinite(H) & (H > 0) & ~(height < config.min_height_m) & ~(contrast < need)  # (NaN height: unknown, kept)
    kept = np.flatnonzero(keep)
    if kept.size == 0:
        return out
    if math.isfinite(along_res):
        length = np.interp(m.span1[kept] + 0.5, rows, along) - np.interp(m.span0[kept] - 0.5, rows, along)
    else:
        length = np.full(kept.size, math.nan)
    t_s = np.interp(rc[kept], rows, wf.t_s)
    heading = np.interp(rc[kept], rows, wf.heading_unwrapped_rad)
    for q, i in enumerate(kept.tolist()):
        gt, gl = float(g_top[i]), float(g_lead[i])
        out.append(ObjectSighting(
            t_s=float(t_s[q]), side=side,
            ground_range_m=gl + config.top_weight * (gt - gl), height_m=float(height[i]), shadow_length_m=float(L[i]),
            length_along_m=abs(float(length[q])), width_across_m=max(gt - gl, res),
            contrast=float(contrast[i]), altitude_m=float(H[i]), row=float(rc[i]),
            heading_rad=float(heading[q]), weak=weak))
    return out


def _candidates_numpy(lev, runs, n, n_px, shadow_sum, deep, alt_per_ping, res, config, min_cols, short_cols,
                      min_col0, hw, least):
    """The components worth measuring (:func:`_detect_shadowed`) in numpy (the reference of
    :func:`adaptnav.sonar._kernels.shadow_candidates`): the highlight rows of the components that
    pass the size and height tests, their labels, the labels to measure."""
    cand = _shadow_candidates(n_px, n, runs, config, res, min_cols, short_cols, min_col0)
    labels = np.unique(runs.label[cand])
    high = labels[_may_be_high(labels, runs, deep, lev.shape[1], alt_per_ping, res, config.min_height_m)]
    hl = _highlights(lev, runs, cand[np.isin(runs.label[cand], high)], hw, config.highlight_level)
    hl_label = runs.label[hl.run]
    # an upper bound of each component's contrast, all at once (its brightest highlight over the
    # mean of the whole shadow, which the measurements divide by): most components are speckle,
    # and measuring them one by one was most of the cost on the unfiltered image
    top = np.zeros(n + 1)
    np.maximum.at(top, hl_label, hl.level.astype(float))
    bound = top / np.maximum(shadow_sum / np.maximum(n_px, 1), 1e-3)
    rows_ok = np.bincount(hl_label, minlength=n + 1) >= max(config.min_highlight_rows, 1)
    todo = np.flatnonzero(rows_ok & (bound >= least * (1 - 1e-6)))
    return hl, hl_label, todo


def _candidates_compiled(lev, runs, n_px, shadow_sum, deep, alt_per_ping, res, config, min_cols, short_cols,
                         min_col0, hw, least) -> tuple["_Highlights", np.ndarray]:
    """:func:`_candidates_numpy` by :func:`adaptnav.sonar._kernels.shadow_candidates`: the
    highlight rows and the labels to measure."""
    from adaptnav.sonar import _kernels

    alt = np.asarray(alt_per_ping, float)
    fin = np.isfinite(alt)
    h_max = float(alt[fin].max()) if fin.any() else math.nan
    m = runs.label.size
    hl_run, hl_lead, hl_level = np.empty(m, np.int64), np.empty(m, np.int64), np.empty(m, np.float32)
    todo, counts = np.empty(n_px.size, np.int64), np.zeros(2, np.int64)
    i64 = [np.ascontiguousarray(v, np.int64) for v in (runs.label, runs.row, runs.near, runs.far, n_px)]
    _kernels.shadow_candidates(lev, *i64, np.ascontiguousarray(shadow_sum, float), np.ascontiguousarray(deep, np.int64),
                               h_max, float(res), int(config.min_shadow_px), float(config.short_shadow_range_m),
                               int(min_cols), int(short_cols), int(min_col0), int(hw), float(config.highlight_level),
                               float(least), int(config.min_highlight_rows), float(config.min_height_m),
                               hl_run, hl_lead, hl_level, todo, counts)
    k, t = int(counts[0]), int(counts[1])
    return _Highlights(hl_run[:k], hl_lead[:k], hl_level[:k]), todo[:t]


def _shadowed_loop(lev, lab, runs, deep, hl, hl_label, todo, side, res, along, along_res, rows, wf, alt_per_ping,
                   config, weak=False) -> list[ObjectSighting]:
    """:func:`_detect_shadowed`'s candidates ``todo`` measured and tested one by one in Python
    (the reference of the compiled measurements and the vectorised tests)."""
    out = []
    for k in todo:
        mine = slice(*np.searchsorted(runs.label, [k, k + 1]))
        comp_rows, near, far = runs.row[mine], runs.near[mine], runs.far[mine]  # image rows
        sl = (slice(int(comp_rows[0]), int(comp_rows[-1]) + 1), slice(int(near.min()), int(far.max())))  # its box
        short = _median_int(near) * res < config.short_shadow_range_m
        lit = slice(*np.searchsorted(hl_label, [k, k + 1]))
        hl_rows, lead, hl_vals = runs.row[hl.run[lit]].tolist(), hl.lead[lit].tolist(), hl.level[lit].tolist()
        # the object's own rows: the run of highlight rows around the brightest (gaps of up to
        # two rows) and the shadow rows beside them; a shadow component that runs on along-track
        # into dark seabed has rows without a lit face before them
        hl_rows, lead, hl_vals = _object_run(hl_rows, lead, hl_vals)
        own = (comp_rows >= hl_rows[0] - 1) & (comp_rows <= hl_rows[-1] + 1)
        comp_rows, near, far = comp_rows[own], near[own], far[own]
        g_top = (_median_int(near) + 0.5) * res
        g_lead = (_median_int(lead) + 0.5) * res
        own_deep = deep[mine][own]  # _deep_shadow_px of the own rows, from every run's at once
        L = (float(own_deep.max()) if own_deep.size else 0.0) * res
        rc = float(np.mean(np.concatenate([np.asarray(hl_rows, float), comp_rows])))
        ping = float(np.interp(rc, rows, wf.ping_index))
        H = float(np.interp(ping, np.arange(alt_per_ping.size), alt_per_ping))
        if not math.isfinite(H) or H <= 0:
            continue
        touches_end = np.any(far >= lev.shape[1] - 1)
        height = H * L / (g_top + L) if not touches_end else math.nan
        if height < config.min_height_m:  # (NaN: unknown, kept)
            continue
        span_rows = (min(hl_rows + [comp_rows[0]]), max(hl_rows + [comp_rows[-1]]))
        length = (float(np.interp(span_rows[1] + 0.5, rows, along) - np.interp(span_rows[0] - 0.5, rows, along))
                  if math.isfinite(along_res) else math.nan)
        shadow_mean = float(lev[sl][lab[sl] == k].mean())
        contrast = float(np.mean(hl_vals)) / max(shadow_mean, 1e-3)
        compact = g_top - g_lead <= config.compact_width_m
        if contrast < (config.short_min_contrast if short else
                       config.compact_min_contrast if compact else config.min_contrast):
            continue
        out.append(ObjectSighting(
            t_s=float(np.interp(rc, rows, wf.t_s)), side=side,
            ground_range_m=g_lead + config.top_weight * (g_top - g_lead), height_m=height, shadow_length_m=L,
            length_along_m=abs(length), width_across_m=max(g_top - g_lead, res),
            contrast=contrast, altitude_m=H, row=rc,
            heading_rad=float(np.interp(rc, rows, wf.heading_unwrapped_rad)), weak=weak))
    return out


class _Measures(NamedTuple):
    """Per candidate component (:func:`_shadowed_measures`), what :func:`_detect_shadowed`
    tests and reports; the floating-point sums in numpy's order."""

    deep_px: np.ndarray       # deep shadow over the object's own rows (px)
    touches_end: np.ndarray   # a run reaches the image's last column
    span0: np.ndarray         # first and last row of the object (its highlight and own rows)
    span1: np.ndarray
    n_rows_centre: np.ndarray  # rows averaged for its centre (highlight rows, then own rows)
    med_near_all: np.ndarray  # median near column over all the component's rows
    med_near_own: np.ndarray  # … over its own rows (the shadow's start)
    med_lead: np.ndarray      # median leading edge of its highlight rows
    row_sum: np.ndarray       # sum of the centre's rows
    hl_sum: np.ndarray        # sum of the highlight levels (float64)
    hl_count: np.ndarray
    shadow_sum32: np.ndarray  # sum of lev over the component (float32, pairwise)
    n_px: np.ndarray          # its pixels


def _shadowed_measures(lev, lab, runs: "_Runs", n_px, deep, hl: "_Highlights", todo) -> _Measures:
    """The per-candidate measurements for the components ``todo`` by
    :func:`adaptnav.sonar._kernels.shadowed_measures` (the per-candidate Python it replaces,
    :func:`_shadowed_loop`, was a third of the detector's CPU: ~2000 candidates per 600 s of
    survey)."""
    from adaptnav.sonar import _kernels

    n = todo.size
    imeas, fmeas, sum32 = np.empty((n, 5), np.int64), np.empty((n, 6)), np.empty(n, np.float32)
    i64 = [np.ascontiguousarray(v, np.int64) for v in (runs.label, runs.row, runs.near, runs.far, deep, hl.run, hl.lead)]
    _kernels.shadowed_measures(lev, np.ascontiguousarray(lab), *i64, np.ascontiguousarray(hl.level),
                               np.ascontiguousarray(todo, np.int64), imeas, fmeas, sum32)
    return _Measures(imeas[:, 0], imeas[:, 1].astype(bool), imeas[:, 2], imeas[:, 3], imeas[:, 4],
                     fmeas[:, 0], fmeas[:, 1], fmeas[:, 2], fmeas[:, 3], fmeas[:, 4], fmeas[:, 5], sum32,
                     np.asarray(n_px)[todo])


def _deep_shadow_rows(lev: np.ndarray, runs: "_Runs", deep_level: float) -> np.ndarray:
    """Per run (row of a component): its shadow length in pixels as :func:`_deep_shadow_px`
    measures a row — from the near edge to the first of three pixels in a row at least
    ``deep_level`` inside the run, the run's whole length if there are none — for all runs at
    once; ``_deep_shadow_px`` of a set of rows is the largest of theirs."""
    near, far = runs.near, runs.far
    length = far - near
    n_cols = lev.shape[1]
    if n_cols < 3 or near.size == 0:
        return length
    if lev.dtype == np.float32 and lev.flags.aligned and lev.flags.writeable and type(deep_level) is float \
            and near.dtype == np.int64 and far.dtype == np.int64 and runs.row.dtype == np.int64:
        from adaptnav.sonar import _kernels

        # run by run instead of a scan of the whole image (the same integers)
        return _kernels.deep_shadow_rows(lev, np.ascontiguousarray(runs.row), np.ascontiguousarray(near),
                                         np.ascontiguousarray(far), float(deep_level))
    return _deep_shadow_rows_scan(lev, runs, deep_level)


def _deep_shadow_rows_scan(lev: np.ndarray, runs: "_Runs", deep_level: float) -> np.ndarray:
    """:func:`_deep_shadow_rows` by a scan of the whole image (the compiled kernel's reference)."""
    near, far = runs.near, runs.far
    length = far - near
    n_cols = lev.shape[1]
    lit = lev >= deep_level
    lit3 = lit[:, :-2] & lit[:, 1:-1] & lit[:, 2:]
    # the first column ≥ c where three lit pixels start, per row and column c
    first = np.where(lit3, np.arange(n_cols - 2), n_cols)
    first = np.minimum.accumulate(first[:, ::-1], axis=1)[:, ::-1]
    start = np.minimum(near, n_cols - 3)
    j = first[runs.row, start]
    inside = (near <= n_cols - 3) & (j <= far - 3)  # the three pixels lie within the run
    return np.where(inside, j - near, length)


def _may_be_high(ks: np.ndarray, runs: "_Runs", deep: np.ndarray, n_cols: int, alt_per_ping: np.ndarray,
                 res: float, min_height_m: float) -> np.ndarray:
    """Of the components ``ks``, those whose height (``H L / (g + L)``, :func:`_detect_shadowed`)
    can reach ``min_height_m``: an upper bound from the highest altitude, the component's deepest
    shadow over all its rows (``deep``, :func:`_deep_shadow_rows`; ≥ that of its own rows, ``L``)
    and its nearest column (≤ its shadow's near edge ``g``); a
    component touching the image's end (height unknown, kept) always passes. Three in four
    candidates failed the height test after their attributes were measured one by one."""
    if ks.size == 0:
        return np.zeros(0, bool)
    alt = np.asarray(alt_per_ping, float)
    fin = np.isfinite(alt)
    if not fin.any():
        return np.ones(ks.size, bool)
    h_max = float(alt[fin].max())
    # per label 1…n (every label has rows; runs are sorted by label), then the candidates'
    start = np.searchsorted(runs.label, np.arange(1, int(runs.label[-1]) + 1))
    longest = np.maximum.reduceat(deep, start)[ks - 1]
    near_min = np.minimum.reduceat(runs.near, start)[ks - 1]
    far_max = np.maximum.reduceat(runs.far, start)[ks - 1]
    L = longest * res
    ub = h_max * L / ((near_min + 0.5) * res + L)
    return (far_max >= n_cols - 1) | ~(ub < min_height_m * (1.0 - 1e-9))


class _Runs(NamedTuple):
    """The rows of every connected component, sorted by label then row (arrays of one length)."""

    label: np.ndarray   # component label (1…n)
    row: np.ndarray     # image row
    near: np.ndarray    # first column of the component on that row
    far: np.ndarray     # one past its last column on that row


def _label8(mask: np.ndarray) -> tuple[np.ndarray, int]:
    """``scipy.ndimage.label(mask, structure=np.ones((3, 3)))``: the same labels (int32) and
    count, by :func:`adaptnav.sonar._kernels.label8` for a 2-D boolean mask (scipy's line
    buffers were ~8 % of the detector's CPU, a tenth of a millisecond per side and image)."""
    if mask.ndim == 2 and mask.dtype == np.bool_ and mask.size:
        from adaptnav.sonar import _kernels

        lab = np.empty(mask.shape, np.int32)
        n = int(_kernels.label8(np.ascontiguousarray(mask), lab))
        return lab, n
    from scipy.ndimage import label

    return label(mask, structure=np.ones((3, 3), bool))


def _components(mask: np.ndarray, lev: np.ndarray) -> tuple[np.ndarray, int, _Runs, np.ndarray, np.ndarray]:
    """:func:`_label8` of ``mask`` and, per component and row, its first and one-past-last
    column (:class:`_Runs`); the pixel count and the sum of ``lev`` of every component (index =
    label; entry 0, the background, is 0), each component's pixels added in raster order as
    ``numpy.bincount`` over the whole image adds them: :func:`_component_rows_numpy` of the
    labels (the reference), by :func:`adaptnav.sonar._kernels.label8_runs` from the rows' runs
    of True pixels (a few per cent of the image) for a 2-D boolean mask and a float32 ``lev``
    of its shape (any strides)."""
    if mask.ndim == 2 and mask.dtype == np.bool_ and mask.size and lev.dtype == np.float32 \
            and lev.shape == mask.shape and lev.flags.aligned and lev.flags.writeable:
        from adaptnav.sonar import _kernels

        mask = np.ascontiguousarray(mask)
        n_set = int(np.count_nonzero(mask))  # ≥ segments, runs and labels: arrays of that size (a
        # bound from the image's size, megabytes touched here and there, cost a page fault each)
        lab = np.empty(mask.shape, np.int32)
        runs = np.empty((4, max(n_set, 1)), np.int64)
        n_px = np.empty(n_set + 1, np.int64)  # + the background
        shadow_sum = np.empty(n_set + 1)
        counts = np.zeros(2, np.int64)
        _kernels.label8_runs(mask, lev, lab, runs, n_px, shadow_sum, counts)
        n, m = int(counts[0]), int(counts[1])
        return lab, n, _Runs(runs[0, :m], runs[1, :m], runs[2, :m], runs[3, :m]), n_px[:n + 1], shadow_sum[:n + 1]
    lab, n = _label8(mask)
    return (lab, n) + _component_rows_numpy(lab, n, lev)


def _component_rows_numpy(lab: np.ndarray, n: int, lev: np.ndarray) -> tuple[_Runs, np.ndarray, np.ndarray]:
    """The runs, pixel counts and sums of :func:`_components` of the labels ``lab`` (1…``n``)
    in numpy (the compiled kernel's reference): the labelled pixels sorted by label, raster
    order kept within."""
    flat = np.flatnonzero(lab)
    ll = lab.ravel()[flat]
    rr, cc = np.divmod(flat, lab.shape[1])
    n_px = np.bincount(ll, minlength=n + 1)
    shadow_sum = np.bincount(ll, weights=lev[rr, cc], minlength=n + 1)
    order = np.argsort(ll, kind="stable")  # by label; raster order (row, then column) kept within
    ll, rr, cc = ll[order], rr[order], cc[order]
    brk = np.flatnonzero((ll[1:] != ll[:-1]) | (rr[1:] != rr[:-1])) + 1
    first = np.concatenate([[0], brk])
    last = np.concatenate([brk, [ll.size]]) - 1
    return _Runs(ll[first], rr[first], cc[first], cc[last] + 1), n_px, shadow_sum


def _shadow_candidates(n_px, n, runs: _Runs, config, res, min_cols, short_cols, min_col0) -> np.ndarray:
    """Indices into ``runs`` of the rows of the components large, long and far enough to
    be an object's shadow (the per-component tests of :func:`_detect_shadowed`, vectorised;
    ``n_px``: pixels per label)."""
    start = np.searchsorted(runs.label, np.arange(1, n + 1))  # every label 1…n has rows
    count = np.diff(np.append(start, runs.label.size))
    longest = np.maximum.reduceat(runs.far - runs.near, start)
    # median of the near columns (as numpy's median: the mean of the two middle values)
    near_sorted = runs.near[np.lexsort((runs.near, runs.label))]
    med = (near_sorted[start + (count - 1) // 2] + near_sorted[start + count // 2]) / 2.0
    short = med * res < config.short_shadow_range_m
    ok = (n_px[1:] >= config.min_shadow_px) & (longest >= np.where(short, short_cols, min_cols)) & (med >= min_col0)
    return np.flatnonzero(ok[runs.label - 1])


class _Highlights(NamedTuple):
    """The rows of ``runs`` with a highlight before their shadow."""

    run: np.ndarray     # index into the runs
    lead: np.ndarray    # column of the highlight's leading edge
    level: np.ndarray   # its brightest level (the image's dtype)


def _highlights(lev: np.ndarray, runs: _Runs, cand: np.ndarray, hw: int, level: float) -> _Highlights:
    """Of the rows ``cand`` of ``runs``: those whose ``hw`` columns before the shadow hold a
    pixel brighter than ``level``, with the leading edge — the nearest column of the run of
    bright pixels (above ``(1 + level) / 2``) that holds the brightest one."""
    cand = cand[runs.near[cand] > 0]  # a shadow from column 0 has nothing before it
    cn = runs.near[cand]
    cols = cn[:, None] - hw + np.arange(hw)[None, :]   # the window, columns cn − hw … cn − 1
    valid = cols >= 0
    win = np.where(valid, lev[runs.row[cand][:, None], np.maximum(cols, 0)], -np.inf)
    j = np.argmax(win, axis=1)                          # the first brightest, as argmax on the window
    top = win[np.arange(cand.size), j]
    lit = top > level
    win, j, cols, valid, cand, top = win[lit], j[lit], cols[lit], valid[lit], cand[lit], top[lit]
    dim = ~(win > 0.5 * (1.0 + level)) | ~valid
    before = np.where(dim & (np.arange(hw)[None, :] < j[:, None]), np.arange(hw)[None, :], -1)
    jj = before.max(axis=1) + 1                         # first bright column of the run up to j
    return _Highlights(cand, cols[np.arange(cand.size), jj], top.astype(lev.dtype))


def _median_int(values) -> float:
    """``numpy.median`` of integers (the mean of the two middle values) without its overhead
    (called a few times per candidate object)."""
    v = np.sort(np.asarray(values))
    return (float(v[(v.size - 1) // 2]) + float(v[v.size // 2])) / 2.0


def _object_run(hl_rows: list, lead: list, hl_vals: list) -> tuple[list, list, list]:
    """The highlight rows (with their leading edges and levels) of the run around the
    brightest one, gaps of up to two rows bridged."""
    r = np.asarray(hl_rows)
    a = b = int(np.argmax(hl_vals))
    while a > 0 and r[a] - r[a - 1] <= 3:
        a -= 1
    while b < r.size - 1 and r[b + 1] - r[b] <= 3:
        b += 1
    return [int(v) for v in r[a:b + 1]], lead[a:b + 1], hl_vals[a:b + 1]


def _deep_shadow_px(lev: np.ndarray, rows: np.ndarray, near: np.ndarray, far: np.ndarray,
                    deep_level: float) -> float:
    """Longest shadow over ``rows`` (pixels): from the near edge until three pixels in a row
    are at least ``deep_level`` (the whole component's run where ``deep_level`` ≥ 1)."""
    length = np.asarray(far) - np.asarray(near)
    if length.size == 0:
        return 0.0
    width = int(length.max())
    if width < 3:
        return float(width)
    # all rows at once: each row's segment near…far−1, padded with unlit pixels
    cols = np.asarray(near)[:, None] + np.arange(width)[None, :]
    inside = cols < np.asarray(far)[:, None]
    lit = inside & (lev[np.asarray(rows)[:, None], np.minimum(cols, lev.shape[1] - 1)] >= deep_level)
    lit3 = lit[:, :-2] & lit[:, 1:-1] & lit[:, 2:]
    return float(np.where(lit3.any(axis=1), np.argmax(lit3, axis=1), length).max())


def _merge(objs: list[ObjectSighting], merge_m: float, along_res: float) -> list[ObjectSighting]:
    """One detection per object: of those within ``merge_m`` (same side), the longest shadow."""
    order = sorted(range(len(objs)), key=lambda i: -objs[i].shadow_length_m)
    kept: list[ObjectSighting] = []
    for i in order:
        if not _near_any(objs[i], kept, merge_m, along_res):
            kept.append(objs[i])
    return kept


def with_navigation(obj: ObjectSighting, pos_n_m, nav_cov, yaw_rad: float,
                    config: ObjectDetectorConfig = ObjectDetectorConfig(), jump_n_m=None,
                    vel_cov=None) -> ObjectSighting:
    """The sighting placed in the local frame from the vehicle pose at its ping.

    Parameters
    ----------
    pos_n_m : (2,) array
        Vehicle (north, east) at ``obj.t_s`` (m).
    nav_cov : (2, 2) array
        Covariance of that position (m²), e.g. the ESKF's.
    yaw_rad : float
        Heading at ``obj.t_s``.
    jump_n_m : (2,) array, optional
        The navigation's accumulated jumps at ``obj.t_s`` (:attr:`ObjectSighting.jump_n_m`).
    vel_cov : (2, 2) array, optional
        Covariance of its horizontal velocity (m²/s², :attr:`ObjectSighting.vel_cov`; not kept
        when not finite).
    """
    pn, pe = np.asarray(pos_n_m, float)[:2].tolist()
    on, oe = obj._offset_floats(yaw_rad)
    jump = None if jump_n_m is None else np.asarray(jump_n_m, float).reshape(2).copy()
    vc = None if vel_cov is None else np.asarray(vel_cov, float).reshape(2, 2).copy()
    return _replaced(obj, pos_n_m=np.array((pn + on, pe + oe)), nav_cov=np.asarray(nav_cov, float).reshape(2, 2).copy(),
                     det_cov=obj.detector_covariance(yaw_rad, config), heading_rad=float(yaw_rad),
                     jump_n_m=jump, vel_cov=vc if vc is not None and np.isfinite(vc).all() else None)


def _replaced(obj: ObjectSighting, **changes) -> ObjectSighting:
    """``dataclasses.replace(obj, **changes)`` of a sighting: its fields copied, ``changes`` set,
    without the frozen ``__init__``'s per-field ``object.__setattr__`` (the sighting has no
    ``__post_init__`` and no other attributes: the same object, fields in the same order;
    ~2 instead of ~6 µs per placed sighting)."""
    new = object.__new__(obj.__class__)
    state = new.__dict__
    state.update(obj.__dict__)
    state.update(changes)
    return new


@dataclass(frozen=True)
class ObjectFrontEndConfig:
    """How :class:`ObjectFrontEnd` cuts the ping stream into detection blocks.

    Attributes
    ----------
    block_pings : int
        Pings per block (one batch of sightings for the associator).
    context_pings : int
        Extra pings on each side of a block in its waterfall (objects at a block's edge
        are seen whole; the column normalisation has enough rows).
    ground_res_m : float
        Across-track pixel size of the canonical image (m).
    max_turn_rad : float
        Sightings where the heading changes more than this over ±``context_pings``/2 are
        dropped (the flat-track geometry of the image does not hold in a turn).
    detector : ObjectDetectorConfig
    """

    block_pings: int = 160
    context_pings: int = 20
    ground_res_m: float = 0.1
    max_turn_rad: float = 0.15
    detector: ObjectDetectorConfig = ObjectDetectorConfig()


_NAN4 = (math.nan,) * 4  # a velocity covariance not given
_NAV_COLS = 13  # per ping: pos n, pos e, yaw, cov 4, jump n, jump e, vel cov 4 (ObjectFrontEnd._nav)


class ObjectFrontEnd:
    """Pings + the navigation at each ping → batches of placed object sightings.

    Every ping comes with the navigation's horizontal position, its covariance and the
    heading at the ping time (from the filter, not from the ping's own speed); a block's
    rows are placed by that navigation, so the along-track spacing of the image is the
    filter's and the sightings' positions and covariances are the filter's at their pings.

    Parameters
    ----------
    config : ObjectFrontEndConfig
    """

    def __init__(self, config: ObjectFrontEndConfig = ObjectFrontEndConfig(), store=None) -> None:
        from collections import deque

        self.config = config
        # :class:`adaptnav.sonar.guided.ImageStore` or None: every block's own rows of the image
        # before the median, with the navigation, for guided re-detection
        self.store = store
        n = config.block_pings + 2 * config.context_pings
        self._pings: deque = deque(maxlen=n)
        self._nav: deque = deque(maxlen=n)  # (pos n, pos e, yaw, cov 4, jump n, jump e, vel cov 4)
        self._n = 0
        # the navigation's jumps so far (position minus its integrated velocity) and the last
        # (t, position, velocity) it was measured from
        self._jump = np.zeros(2)
        self._jump_nm = (0.0, 0.0)  # the same as Python floats, kept with every ping
        self._last_vel: tuple[float, np.ndarray, np.ndarray] | None = None
        self._next_emit = 0  # global index of the next block's first ping
        self.blocks = 0
        self.sightings = 0
        self.rejected: dict[str, int] = {}
        self._geometry: tuple[int, float] | None = None  # (samples, slant range m): the first ping's
        self.resampled = 0  # pings of another geometry put on the stream's
        self._work: dict = {}  # the detector's scratch arrays (detect_objects)

    @property
    def pings_taken(self) -> int:
        """Pings taken into the stream (not rejected)."""
        return self._n

    def push(self, ping, pos_n_m, nav_cov, yaw_rad: float, vel_n_m_s=None, vel_cov=None) -> list[ObjectSighting]:
        """Take one ping with the navigation at its time; return a block's sightings when one completes.

        Parameters
        ----------
        ping : SonarPing
        pos_n_m : (2,) array
            Vehicle (north, east) at ``ping.t_s`` (m).
        nav_cov : (2, 2) array
            Its covariance (m²).
        yaw_rad : float
            Heading at ``ping.t_s`` (rad).
        vel_n_m_s : (2,) array, optional
            The navigation's horizontal velocity at ``ping.t_s`` (m/s). With it, every change
            of position that the velocity does not explain (a fix, a fused loop closure) is
            accumulated as a jump (:attr:`ObjectSighting.jump_n_m`): the associator compares
            sightings of different times on the jump-free track.
        vel_cov : (2, 2) array, optional
            Its covariance (m²/s²): how fast the jump-free track may drift
            (:attr:`ObjectSighting.vel_cov`).
        """
        pn, pe = np.asarray(pos_n_m, float)[:2].tolist()
        cov = np.asarray(nav_cov, float).reshape(4).tolist()  # (Python floats: tested and kept per ping)
        return self.push_floats(ping, pn, pe, cov, yaw_rad, vel_n_m_s, vel_cov)

    def push_floats(self, ping, pn: float, pe: float, cov, yaw_rad: float, vel_n_m_s=None,
                    vel_cov=None) -> list[ObjectSighting]:
        """:meth:`push` given the position as Python floats ``pn``, ``pe`` (m) and the covariance
        as four Python floats ``cov`` (row by row, m²): what :meth:`push` converts its arrays to
        (the calibrator's pings come with floats; building and converting the arrays was a
        third of this per-ping cost)."""
        if not (math.isfinite(ping.t_s) and math.isfinite(pn) and math.isfinite(pe) and all(map(math.isfinite, cov))
                and math.isfinite(yaw_rad)):
            self.rejected["non-finite"] = self.rejected.get("non-finite", 0) + 1
            return []
        if self._pings and ping.t_s <= self._pings[-1].t_s:
            self.rejected["out of order"] = self.rejected.get("out of order", 0) + 1
            return []
        geometry = (ping.port.size, ping.slant_range_m)  # (n_samples without its property call)
        if geometry != self._geometry:  # (the stream's geometry passed the test below)
            if not ping.has_geometry:
                self.rejected["bad geometry"] = self.rejected.get("bad geometry", 0) + 1
                return []
            if self._geometry is None:
                self._geometry = geometry
            else:
                # the sonar's range or sample count changed (the operator, auto-range): every
                # later ping was refused; now on the stream's first geometry, one image width
                ping = ping.resampled(*self._geometry)
                self.resampled += 1
        if vel_n_m_s is not None:
            v = np.asarray(vel_n_m_s, float).reshape(-1)[:2]
            if np.all(np.isfinite(v)):
                p = np.array((pn, pe))
                if self._last_vel is not None:
                    t0, p0, v0 = self._last_vel
                    self._jump += p - (p0 + 0.5 * (v0 + v) * (ping.t_s - t0))  # trapezoid
                    self._jump_nm = tuple(self._jump.tolist())
                self._last_vel = (float(ping.t_s), p, v.copy())  # (p: a new array)
        self._pings.append(ping)
        vc = _NAN4 if vel_cov is None else np.asarray(vel_cov, float).reshape(4).tolist()
        self._nav.append((pn, pe, float(yaw_rad), *cov, *self._jump_nm, *vc))
        self._n += 1
        c = self.config
        if self._n < self._next_emit + c.block_pings + c.context_pings:
            return []
        start = self._next_emit
        self._next_emit += c.block_pings
        return self._block(start)

    def pings_to_block(self) -> int:
        """How many more pings complete the next block (the push that returns its sightings)."""
        c = self.config
        return self._next_emit + c.block_pings + c.context_pings - self._n

    def flush(self) -> tuple[list[ObjectSighting], float]:
        """The stream ended: the sightings of the block not yet complete that have as many
        pings after them as a complete block gives its objects (``context_pings``; nearer the
        end an object may be cut off), and the last ping's time (s; NaN without pings).
        Further pushes start a new block after them."""
        c = self.config
        t_last_ping_s = float(self._pings[-1].t_s) if self._pings else math.nan
        start, n = self._next_emit, self._n
        first = n - len(self._pings)  # global index of the buffer's first ping
        if n - start <= c.context_pings or start < first:
            return [], t_last_ping_s
        self._next_emit = n
        t_context_s = float(self._pings[-1 - c.context_pings].t_s)  # the last ping with a full context after it
        return [o for o in self._block(start) if float(o.t_s) <= t_context_s], t_last_ping_s

    def _block(self, start: int) -> list[ObjectSighting]:
        from adaptnav.sonar.waterfall import WaterfallConfig, build_waterfall, median_filtered

        c = self.config
        first = self._n - len(self._pings)  # global index of the buffer's first ping
        pings = list(self._pings)
        # (one float per value in order: np.array of the rows' tuples took 4 times as long)
        nav = np.fromiter(itertools.chain.from_iterable(self._nav), float, len(self._nav) * _NAV_COLS).reshape(-1, _NAV_COLS)
        # line_removal: a ping with the horizontal-line noise (an additive offset, 2 % of the
        # simulator's pings) came out of the gain normalisation as a flat row, its objects lost
        wcfg = WaterfallConfig(ground_res_m=c.ground_res_m, resample_along=False, line_removal=True)
        fine = c.detector.fine_range_m > 0 and wcfg.median_ksize > 1
        try:
            # near the nadir the detector also looks at the image before the median filter
            # (ObjectDetectorConfig.fine_range_m): built once without it, filtered here as
            # build_waterfall would
            wf = build_waterfall(pings, replace(wcfg, median_ksize=1) if fine else wcfg)
        except ValueError:
            self.rejected["waterfall failed"] = self.rejected.get("waterfall failed", 0) + 1
            return []
        self.blocks += 1
        step = np.hypot(np.diff(nav[:, 0]), np.diff(nav[:, 1]))
        along = np.concatenate([[0.0], np.cumsum(step)])
        raw = None
        if fine:
            raw = wf.image
            wf = replace(wf, image=median_filtered(raw, wcfg.median_ksize))
        objs = detect_objects(wf, along_m=along, config=c.detector, unfiltered=raw, work=self._work)
        if self.store is not None:
            self._store_rows(wf if raw is None else replace(wf, image=raw), nav, start - first,
                             min(start - first + c.block_pings, len(pings)), pings)
        idx = np.arange(len(pings), dtype=float)
        yaw_u = np.unwrap(nav[:, 2])
        half = max(c.context_pings // 2, 1)
        t_ping_s = np.array([q.t_s for q in pings], dtype=float)
        # every object's (fractional) ping and the navigation there, interpolated all at once
        gi_all = first + np.interp(np.array([o.t_s for o in objs], dtype=float), t_ping_s, idx)
        li_all = gi_all - first  # (the global index and back, as the navigation is read at it)
        nav_at = [np.interp(li_all, idx, col).tolist() for col in (nav[:, 0], nav[:, 1], nav[:, 3], nav[:, 4],
                                                                   nav[:, 5], nav[:, 6], yaw_u)]
        out = []
        for j, o in enumerate(objs):
            gi = float(gi_all[j])
            if not start <= gi < start + c.block_pings:
                continue
            li = float(li_all[j])
            a, b = max(int(li) - half, 0), min(int(li) + half, len(pings) - 1)
            if abs(yaw_u[b] - yaw_u[a]) > c.max_turn_rad:
                self.rejected["turning"] = self.rejected.get("turning", 0) + 1
                continue
            pn, pe, c00, c01, c10, c11, yaw = (v[j] for v in nav_at)
            cov = np.array([c00, c01, c10, c11]).reshape(2, 2)
            jump = nav[int(round(li)), 7:9] if self._last_vel is not None else None
            vc = nav[int(round(li)), 9:13].reshape(2, 2)
            out.append(with_navigation(o, (pn, pe), cov, yaw, c.detector, jump, vc))
        self.sightings += len(out)
        return out

    def _store_rows(self, wf, nav: np.ndarray, a: int, b: int, pings) -> None:
        """The block's own rows ``a…b−1`` (one per ping) of the image before the median, with the
        navigation, into :attr:`store`."""
        if b <= a:
            return
        jump = nav[a:b, 7:9] if self._last_vel is not None else None
        self.store.add(wf.image[a:b], wf.ground_res_m, np.array([q.t_s for q in pings[a:b]]), nav[a:b, 0:2],
                       np.unwrap(nav[:, 2])[a:b], nav[a:b, 3:7].reshape(-1, 2, 2), jump,
                       nav[a:b, 9:13].reshape(-1, 2, 2), wf.altitude_m[a:b])
