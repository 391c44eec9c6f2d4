"""Side-scan sonar front end (DESIGN.md "Sonar"; the seed, sec. 3.2 and 3.4).

A leaf package: numpy, scipy, OpenCV and pyxtf only.

* :mod:`adaptnav.sonar.ping` — :class:`~sonar.ping.SonarPing`, the bus/log sample of one ping.
* :mod:`adaptnav.sonar.xtf` — :func:`~sonar.xtf.read_xtf`: XTF files → pings (robust reader).
* :mod:`adaptnav.sonar.waterfall` — :func:`~sonar.waterfall.build_waterfall`: ground-range,
  gain-normalised, median-filtered image (port left, starboard right, time down).
* :mod:`adaptnav.sonar.features` — SIFT (default) / ORB detectors keeping the K strongest.
* :mod:`adaptnav.sonar.matching` — KNN ratio-test matching, RANSAC similarity with covariance.
* :mod:`adaptnav.sonar.motion` — :class:`~sonar.motion.WindowRegistrar` →
  :class:`~sonar.motion.VisualMotion` between windows.
* :mod:`adaptnav.sonar.landmarks` — :class:`~sonar.landmarks.LandmarkObservation`,
  :func:`~sonar.landmarks.extract_landmarks`, :class:`~sonar.landmarks.LandmarkTracker`.
* :mod:`adaptnav.sonar.stream` — :class:`~sonar.stream.SonarFrontEnd`: the same, ping by ping.

Submodules are imported explicitly (``from sonar.ping import SonarPing``) so that
reading a ping does not load OpenCV.
"""
