r"""Streaming side-scan front end: pings in, landmark observations and visual motion out.

The batch pieces of :mod:`sonar` (waterfall, landmarks, registration; the seed, sec. 3.2
and 3.4; DESIGN.md "Sonar") work on a whole waterfall.  A vehicle produces pings one by
one, so :class:`SonarFrontEnd` cuts the ping stream into overlapping windows of ``W``
pings with step ``S`` (``S ≤ W``) and processes each window exactly once:

1. ground-range waterfall of the window (:func:`adaptnav.sonar.waterfall.build_waterfall`), rows
   resampled by distance travelled at one along-track resolution for the whole stream
   (fixed from the first window, so consecutive windows register at scale 1);
2. landmarks (:func:`adaptnav.sonar.landmarks.extract_landmarks`).  Window ``k`` starting at ping
   ``s_k`` only *emits* the sightings whose ping index lies in its central part
   ``[s_k + (W − S)/2, s_k + (W + S)/2)`` (the first window from its first ping): these
   parts tile the ping stream, so a sighting is reported once, never twice from the
   overlap of two windows (a side-scan sees a seabed point once per pass: a second
   report of the same ping would be counted by the calibrator as independent evidence),
   and away from the window edges where keypoints are unreliable.  The latency of a
   sighting is therefore at most ``(W + S)/2`` pings (:attr:`SonarFrontEnd.latency_s`);
3. track ids (:class:`adaptnav.sonar.landmarks.LandmarkTracker`) from the sighting's estimated
   position ``p = (n, e) + ρ u_side(ψ)``, with ``(n, e)`` the vehicle position at the
   ping: given by the caller (``push(ping, pos_n_m)``, e.g. from the navigation) or
   dead-reckoned from the pings' own speed over ground and heading,
   ``p_i = p_{i−1} + ½ (v_{i−1} + v_i)(t_i − t_{i−1}) (cos ψ̄, sin ψ̄)``;
4. visual motion between consecutive windows (:class:`adaptnav.sonar.motion.WindowRegistrar`),
   each window's keypoints detected once and kept for the next registration.

Pure: no clock, no transport, no randomness.  Bad pings (non-finite or non-increasing
time, no usable geometry) are counted in :attr:`SonarFrontEnd.rejected` by reason and
skipped.  A ping of another sample count or slant range than the stream's first (the range
changed) is resampled onto that geometry (:meth:`adaptnav.sonar.ping.SonarPing.resampled`;
beyond the stream's range nothing is kept) and counted in :attr:`SonarFrontEnd.resampled`.
"""
from __future__ import annotations

import math
import statistics
from collections import Counter, deque
from dataclasses import dataclass, replace
from typing import Literal

import numpy as np

from adaptnav.sonar.features import Features, OrbDetector, SiftDetector
from adaptnav.sonar.landmarks import LandmarkObservation, LandmarkTracker, extract_landmarks
from adaptnav.sonar.motion import VisualMotion, WindowRegistrar
from adaptnav.sonar.dead_reckoning import AnchoredDeadReckoning  # noqa: F401 (its home before)
from adaptnav.sonar.ping import SonarPing
from adaptnav.sonar.waterfall import Waterfall, WaterfallConfig, build_waterfall, to_uint8


@dataclass(frozen=True)
class FrontEndConfig:
    """Settings of :class:`SonarFrontEnd` (typed_config-compatible).

    Attributes
    ----------
    window_pings, step_pings : int
        Window length ``W`` and step ``S`` in pings (``8 ≤ W``, ``1 ≤ S ≤ W``).
    ground_res_m : float
        Across-track pixel size (m).
    along_res_m : float
        Along-track pixel size (m); 0 → the mean ping spacing of the first window.
    median_ksize : int
        Median filter of the waterfall (odd, 1 = off).
    max_landmarks : int
        Strongest landmarks kept per window (before the emission range cut).
    min_ground_range_m : float
        Sightings closer to the track (nadir) are dropped.
    min_edge_contrast : float
        Highlight/shadow contrast a landmark needs (:func:`extract_landmarks`).
    gate_m, max_descriptor_distance, tracker_ratio : float
        :class:`LandmarkTracker` association settings.
    detector : {"sift", "orb"}
    register : bool
        Register consecutive windows (visual motion).
    registration_min_inliers : int
    registration_threshold_m : float
        RANSAC inlier threshold (m).
    gate_sigmas, max_gate_m : float
        With a navigation σ given to :meth:`SonarFrontEnd.push`, the tracker's gate is
        ``clip(gate_sigmas · √2 · σ, gate_m, max_gate_m)`` (√2: the error of the track's
        first sighting and of the new one, both about σ); the tracker's consensus on the
        batch's common offset then tightens it again.
    wide_gate_ratio, wide_gate_max_descriptor_distance : float
        Stricter descriptor tests while the gate is wider than ``gate_m`` (more
        similar-looking landmarks lie inside a wide gate).
    detect_margin_pings : int
        ``-1``: landmarks are detected on the whole window. ``m ≥ 0``: only on the rows of
        the window's emission part ± ``m`` pings (the other sightings are not emitted
        anyway), with ``max_landmarks`` scaled by ``step_pings / window_pings`` (the
        share of a window's landmarks its emission part holds on average): SIFT costs in
        proportion to the rows. The margin keeps keypoints near the emission part's
        edges away from the crop's.
    """

    window_pings: int = 128
    step_pings: int = 64
    ground_res_m: float = 0.1
    along_res_m: float = 0.0
    median_ksize: int = 3
    max_landmarks: int = 20
    min_ground_range_m: float = 2.0
    min_edge_contrast: float = 3.0
    gate_m: float = 1.5
    max_descriptor_distance: float = 650.0
    tracker_ratio: float = 0.95
    detector: Literal["sift", "orb"] = "sift"
    register: bool = True
    registration_min_inliers: int = 8
    registration_threshold_m: float = 0.3
    gate_sigmas: float = 3.0
    max_gate_m: float = 3.0
    wide_gate_ratio: float = 0.8
    wide_gate_max_descriptor_distance: float = 650.0
    detect_margin_pings: int = -1

    def validate(self) -> None:
        if self.window_pings < 8 or not 1 <= self.step_pings <= self.window_pings:
            raise ValueError("need window_pings ≥ 8 and 1 ≤ step_pings ≤ window_pings")
        if not self.ground_res_m > 0 or not self.along_res_m >= 0:
            raise ValueError("ground_res_m must be > 0 and along_res_m ≥ 0")
        if self.median_ksize < 1 or self.median_ksize % 2 == 0:
            raise ValueError("median_ksize must be odd and ≥ 1")
        if self.detector not in ("sift", "orb"):
            raise ValueError("detector must be 'sift' or 'orb'")
        if not (self.gate_sigmas >= 0 and self.max_gate_m >= self.gate_m > 0):
            raise ValueError("need gate_sigmas ≥ 0 and 0 < gate_m ≤ max_gate_m")
        if self.detect_margin_pings < -1:
            raise ValueError("detect_margin_pings must be -1 (whole window) or ≥ 0")

    def __post_init__(self) -> None:
        self.validate()


@dataclass
class _Window:
    index: int
    waterfall: Waterfall
    features: Features | None


class SonarFrontEnd:
    """Pings → landmark observations (with track ids) and visual motion, as a stream.

    Parameters
    ----------
    config : FrontEndConfig

    Attributes
    ----------
    rejected : collections.Counter
        Skipped pings by reason.
    windows : int
        Windows processed.
    """

    def __init__(self, config: FrontEndConfig = FrontEndConfig()) -> None:
        self.config = config
        c = config
        self.rejected: Counter[str] = Counter()
        self.windows = 0
        self.emitted_landmarks = 0
        self.emitted_motions = 0
        self.reassociated_landmarks = 0  # sightings given an existing track id
        self.tracker = LandmarkTracker(gate_m=c.gate_m, max_descriptor_distance=c.max_descriptor_distance,
                                       ratio=c.tracker_ratio, hamming=c.detector == "orb")
        make = SiftDetector if c.detector == "sift" else OrbDetector
        self._make = make
        self._lm_detector = make(max_keypoints=4 * c.max_landmarks)
        self._lm_detectors: dict[int, object] = {c.max_landmarks: self._lm_detector}
        self._registrar = WindowRegistrar(make(max_keypoints=400, downsample=2) if c.detector == "sift"
                                          else make(max_keypoints=1500),
                                          ransac_threshold_m=c.registration_threshold_m,
                                          min_inliers=c.registration_min_inliers)
        self._pings: deque[SonarPing] = deque(maxlen=c.window_pings)
        # per-ping navigation of the buffered pings: global index, t, north, east, yaw
        self._nav: deque[tuple[int, float, float, float, float]] = deque(maxlen=c.window_pings)
        self._n = 0                    # pings accepted so far (global index of the next)
        self._next_start = 0           # global index of the next window's first ping
        self._emit_from = 0            # first ping index not yet covered by an emission range
        self._shape: tuple[int, float] | None = None  # the stream's geometry: its first ping's
        self.resampled = 0             # pings of another geometry put on the stream's
        self._along_res_m = c.along_res_m if c.along_res_m > 0 else math.nan
        self._prev: _Window | None = None
        self._pos = np.zeros(2)
        self._last: tuple[float, float, float] | None = None  # t, speed, yaw
        self._dt_s: deque[float] = deque(maxlen=64)
        self._latency_s: float | None = None
        self._sigma: deque[float] = deque(maxlen=c.window_pings)  # nav σ of the buffered pings

    # ------------------------------------------------------------------ input
    @property
    def pos_n_m(self) -> np.ndarray:
        """Vehicle (north, east) at the last ping, as used for the tracker (m)."""
        return self._pos.copy()

    @property
    def latency_s(self) -> float:
        """Largest delay between a ping and the emission of its sightings (data s)."""
        if self._latency_s is None:  # cached until the next ping (asked once or twice per ping)
            c = self.config
            # statistics.median: the same value as np.median, ~20x cheaper on 64 floats
            dt = float(statistics.median(self._dt_s)) if self._dt_s else math.nan
            self._latency_s = 0.5 * (c.window_pings + c.step_pings) * dt
        return self._latency_s

    def push(self, ping: SonarPing, pos_n_m=None, pos_sigma_m: float | None = None) -> list:
        """Take one ping; return what became available (possibly nothing).

        Parameters
        ----------
        ping : SonarPing
        pos_n_m : (2,) array-like, optional
            Vehicle (north, east) at the ping (m), e.g. from the navigation; by default
            dead-reckoned from the pings' speed and heading.
        pos_sigma_m : float, optional
            Horizontal 1-σ of ``pos_n_m`` (m): widens the association gate
            (``FrontEndConfig.gate_sigmas``); default: the fixed ``gate_m``.

        Returns
        -------
        list of LandmarkObservation and VisualMotion
            Landmark observations (``track_id`` set, ``along_track_m`` from the start of
            their window) of the window that just completed, then its visual motion
            relative to the previous window if the registration succeeded.
        """
        reason = self._check(ping)
        if reason:
            self.rejected[reason] += 1
            return []
        if (ping.n_samples, ping.slant_range_m) != self._shape:
            # the sonar's range or sample count changed (the operator, auto-range): the ping
            # on the stream's first geometry, so that windows stay one image width
            ping = ping.resampled(*self._shape)
            self.resampled += 1
        self._dead_reckon(ping, pos_n_m)
        sig = math.nan if pos_sigma_m is None else float(pos_sigma_m)
        self._sigma.append(sig if math.isfinite(sig) and sig >= 0 else math.nan)
        self._pings.append(ping)
        self._nav.append((self._n, ping.t_s, float(self._pos[0]), float(self._pos[1]), ping.heading_rad))
        self._n += 1
        if self._n - self._next_start < self.config.window_pings:
            return []
        start = self._next_start
        self._next_start += self.config.step_pings
        return self._process(start)

    def _check(self, ping: SonarPing) -> str:
        t = ping.t_s
        if not math.isfinite(t):
            return "non-finite time"
        if self._last is not None and t <= self._last[0]:
            return "non-increasing time"
        if not ping.has_geometry:
            return "bad geometry"
        if self._shape is None:
            self._shape = (ping.n_samples, ping.slant_range_m)
        return ""

    def _dead_reckon(self, ping: SonarPing, pos_n_m) -> None:
        speed = ping.speed_m_s if math.isfinite(ping.speed_m_s) else (self._last[1] if self._last else 0.0)
        yaw = ping.heading_rad if math.isfinite(ping.heading_rad) else (self._last[2] if self._last else 0.0)
        if pos_n_m is not None:
            self._pos = np.asarray(pos_n_m, dtype=float).reshape(-1)[:2].copy()
        elif self._last is not None:
            t0, v0, yaw0 = self._last
            dt = ping.t_s - t0
            mid = yaw0 + 0.5 * math.remainder(yaw - yaw0, 2.0 * math.pi)
            self._pos = self._pos + 0.5 * (v0 + speed) * dt * np.array([math.cos(mid), math.sin(mid)])
        if self._last is not None:
            self._dt_s.append(ping.t_s - self._last[0])
            self._latency_s = None
        self._last = (ping.t_s, speed, yaw)

    # ------------------------------------------------------------------ windows
    def _process(self, start: int) -> list:
        c = self.config
        pings = list(self._pings)
        nav = np.array(self._nav, dtype=float)  # rows match pings
        wcfg = WaterfallConfig(ground_res_m=c.ground_res_m,
                               along_res_m=self._along_res_m if math.isfinite(self._along_res_m) else None,
                               median_ksize=c.median_ksize)
        try:
            wf = build_waterfall(pings, wcfg)
        except ValueError:
            self.rejected["waterfall failed"] += 1
            return []
        if not math.isfinite(self._along_res_m) and math.isfinite(wf.along_res_m):
            self._along_res_m = wf.along_res_m  # one resolution for the whole stream
        self.windows += 1
        img = to_uint8(wf.image)
        out: list = self._landmarks(wf, img, start, nav)
        motion = self._motion(wf, img)
        if motion is not None:
            out.append(motion)
        return out

    def _landmarks(self, wf: Waterfall, img: np.ndarray, start: int, nav: np.ndarray) -> list:
        c = self.config
        hi = start + 0.5 * (c.window_pings + c.step_pings)
        lo = self._emit_from
        self._emit_from = int(math.ceil(hi))
        max_lm = c.max_landmarks
        if c.detect_margin_pings >= 0:
            m = c.detect_margin_pings
            sel = np.flatnonzero((wf.ping_index >= lo - start - m) & (wf.ping_index < hi - start + m))
            n_rows = wf.image.shape[0]
            if sel.size and sel.size < n_rows:
                r0, r1 = int(sel[0]), int(sel[-1]) + 1
                # as many as the whole window gave in its emission part on average
                max_lm = max(1, round(c.max_landmarks * c.step_pings / c.window_pings))
                wf, img = wf.rows(r0, r1), img[r0:r1]
        det = self._lm_detectors.get(max_lm)
        if det is None:
            det = self._lm_detectors[max_lm] = self._make(max_keypoints=4 * max_lm)
        obs = extract_landmarks(wf, det, max_landmarks=max_lm,
                                min_ground_range_m=c.min_ground_range_m, image_u8=img,
                                min_edge_contrast=c.min_edge_contrast)
        idx_g, t_p = nav[:, 0], nav[:, 1]
        kept, pos = [], []
        yaw_u = np.unwrap(nav[:, 4])
        for o in obs:
            gi = float(np.interp(o.t_s, t_p, idx_g))
            if not lo - 1e-9 <= gi < hi - 1e-9:
                continue
            p = (float(np.interp(o.t_s, t_p, nav[:, 2])), float(np.interp(o.t_s, t_p, nav[:, 3])))
            kept.append(o)
            pos.append(o.position_n_m(p, float(np.interp(o.t_s, t_p, yaw_u))))
        if not kept:
            return []
        self.emitted_landmarks += len(kept)
        pos = np.array(pos)
        sig = np.array(self._sigma, dtype=float)
        sig = sig[np.isfinite(sig)]
        wide = c.gate_m if sig.size == 0 else c.gate_sigmas * math.sqrt(2.0) * float(sig.max())
        wide = min(max(wide, c.gate_m), c.max_gate_m)
        tr = self.tracker
        # an uncertain navigation: a gate as wide as its error, but a stricter descriptor
        # test there (more similar-looking landmarks lie inside a wide gate)
        tr.gate_m = wide
        tr.ratio = c.tracker_ratio if wide <= c.gate_m else min(c.tracker_ratio, c.wide_gate_ratio)
        tr.max_descriptor_distance = (c.max_descriptor_distance if wide <= c.gate_m
                                      else min(c.max_descriptor_distance, c.wide_gate_max_descriptor_distance))
        n_before = tr.n_tracks
        out = tr.update(kept, pos)
        self.reassociated_landmarks += len(kept) - (self.tracker.n_tracks - n_before)
        return out

    def _motion(self, wf: Waterfall, img: np.ndarray) -> VisualMotion | None:
        if not self.config.register or not (math.isfinite(wf.along_res_m) and wf.along_res_m > 0):
            self._prev = None
            return None
        feats = self._registrar.features(wf, img)
        prev, self._prev = self._prev, _Window(self.windows, wf, feats)
        if prev is None or not math.isclose(prev.waterfall.along_res_m, wf.along_res_m, rel_tol=1e-6):
            return None
        m = self._registrar.register(prev.waterfall, wf, feats_a=prev.features, feats_b=feats)
        if m is not None:
            self.emitted_motions += 1
        return m


def reference_landmark(obs: LandmarkObservation, t_ref_s: float, speed_m_s: float) -> LandmarkObservation:
    """The sighting with ``along_track_m`` re-referenced to the vehicle position at ``t_ref_s``.

    A side-scan sees a point abeam at the ping time ``t_s``; from the pose at ``t_ref_s``
    (e.g. a calibrator's time-grid pose) it lies ``v (t_s − t_ref)`` ahead along the track
    (straight track at speed ``v`` between the two times).
    """
    return replace(obs, along_track_m=float(speed_m_s) * (obs.t_s - float(t_ref_s)))
