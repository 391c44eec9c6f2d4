"""Frames, rotations and the mission origin — the one place conventions are fixed.

Frames
------
``n``  local NED tangent plane at the mission origin (x north, y east, z down), metres.
``b``  body FRD (x forward, y starboard, z down).
``d``  DVL head, ``s`` sonar (each related to ``b`` by a fixed mounting rotation).

Rotations
---------
``R_nb`` maps body vectors into the navigation frame: ``vel_n = R_nb @ vel_b``.
Quaternions are stored ``(w, x, y, z)`` (scalar first, Hamilton product), ``q_nb``
rotates b→n.  scipy uses ``(x, y, z, w)`` and MAVLink ``(w, x, y, z)``: the only
conversions to and from scipy live here (:func:`quat_to_scipy`, :func:`quat_from_scipy`).

Euler angles are ZYX (yaw ψ about down, pitch θ, roll φ), radians:
``R_nb = Rz(ψ) Ry(θ) Rx(φ)``.

Geodetic ↔ local NED uses a flat-earth tangent plane at :class:`GeoOrigin` on the
WGS-84 ellipsoid (meridian and prime-vertical radii at the origin latitude); that is
well under 1 m of error within 10 km of the origin, the scale of an AUV mission.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import math

import numpy as np
from scipy.spatial.transform import Rotation

GRAVITY_M_S2 = 9.80665
EARTH_RATE_RAD_S = 7.2921150e-5
WGS84_A_M = 6378137.0
WGS84_E2 = 6.69437999014e-3


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrix ``[v]×`` such that ``skew(a) @ b == cross(a, b)``."""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def wrap_angle(angle_rad):
    """Wrap to [-π, π). Works on scalars and arrays."""
    return (np.asarray(angle_rad) + np.pi) % (2.0 * np.pi) - np.pi


def quat_mul(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hamilton product ``p ⊗ q`` of (w, x, y, z) quaternions."""
    pw, px, py, pz = p
    qw, qx, qy, qz = q
    return np.array([
        pw * qw - px * qx - py * qy - pz * qz,
        pw * qx + px * qw + py * qz - pz * qy,
        pw * qy - px * qz + py * qw + pz * qx,
        pw * qz + px * qy - py * qx + pz * qw,
    ])


def quat_from_rotvec(rotvec: np.ndarray) -> np.ndarray:
    """Quaternion of a rotation vector (axis × angle, rad); exact, small-angle safe."""
    angle = float(np.linalg.norm(rotvec))
    half = 0.5 * angle
    # sin(half)/angle with its Taylor limit, so tiny rotations keep full precision
    k = 0.5 - angle * angle / 48.0 if angle < 1e-6 else np.sin(half) / angle
    return np.array([np.cos(half), k * rotvec[0], k * rotvec[1], k * rotvec[2]])


def quat_conj(q: np.ndarray) -> np.ndarray:
    """The inverse of a unit (w, x, y, z) quaternion."""
    return np.array([q[0], -q[1], -q[2], -q[3]])


def rotvec_from_quat(q: np.ndarray) -> np.ndarray:
    """Rotation vector (axis × angle, rad, |angle| ≤ π) of a unit quaternion; the inverse of
    :func:`quat_from_rotvec`, small-angle safe."""
    w, v = float(q[0]), np.asarray(q[1:], dtype=float)
    if w < 0.0:  # the same rotation, the shorter way
        w, v = -w, -v
    s = float(np.linalg.norm(v))
    if s < 1e-9:
        return 2.0 * v / max(w, 1e-300)
    return v * (2.0 * math.atan2(s, w) / s)


def quat_to_dcm(q: np.ndarray) -> np.ndarray:
    """Rotation matrix of a unit (w, x, y, z) quaternion (``R_nb`` from ``q_nb``)."""
    w, x, y, z = q
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def quat_normalize(q: np.ndarray) -> np.ndarray:
    q = np.asarray(q, dtype=float)
    q = q / np.linalg.norm(q)
    return q if q[0] >= 0.0 else -q


def quat_to_scipy(q: np.ndarray) -> Rotation:
    """Our (w, x, y, z) → scipy Rotation (which stores x, y, z, w)."""
    return Rotation.from_quat([q[1], q[2], q[3], q[0]])


def quat_from_scipy(rot: Rotation) -> np.ndarray:
    x, y, z, w = rot.as_quat()
    return quat_normalize(np.array([w, x, y, z]))


def euler_to_quat(roll_rad: float, pitch_rad: float, yaw_rad: float) -> np.ndarray:
    """ZYX Euler angles → ``q_nb``."""
    return quat_from_scipy(Rotation.from_euler("ZYX", [yaw_rad, pitch_rad, roll_rad]))


def quat_to_euler(q: np.ndarray) -> tuple[float, float, float]:
    """``q_nb`` (unit, w x y z) → (roll, pitch, yaw) in rad, ZYX, yaw in [-π, π).

    Closed form on the rows of ``R_nb`` (as :func:`dcm_to_euler`): every published nav
    state and output row converts its attitude, and a scipy ``Rotation`` round trip costs
    ~15 µs of the output epoch (issue 17); the same angles to 1e-12 away from gimbal lock.
    """
    w, x, y, z = q.tolist() if isinstance(q, np.ndarray) else (float(v) for v in q)  # tolist: C speed
    r20 = 2.0 * (x * z - w * y)
    # min(1.0, max(-1.0, r20)) without the two builtins' calls: max keeps -1.0 unless r20 is
    # greater (NaN → -1.0, as max gives it), min keeps 1.0 unless that is smaller
    r20 = r20 if r20 > -1.0 else -1.0
    pitch = -math.asin(r20 if r20 < 1.0 else 1.0)
    roll = math.atan2(2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y))
    yaw = math.atan2(2.0 * (x * y + w * z), 1.0 - 2.0 * (y * y + z * z))
    if yaw >= math.pi:  # [-π, π) as wrap_angle
        yaw -= 2.0 * math.pi
    return roll, pitch, yaw


def dcm_to_euler(R_nb: np.ndarray) -> tuple[float, float, float]:
    """``R_nb`` → (roll, pitch, yaw) in rad (closed form, no scipy round trip)."""
    pitch = -np.arcsin(np.clip(R_nb[2, 0], -1.0, 1.0))
    roll = np.arctan2(R_nb[2, 1], R_nb[2, 2])
    yaw = np.arctan2(R_nb[1, 0], R_nb[0, 0])
    return float(roll), float(pitch), float(yaw)


@dataclass(frozen=True)
class GeoOrigin:
    """Mission origin of the local NED frame (geodetic, WGS-84)."""

    lat_rad: float
    lon_rad: float
    alt_m: float = 0.0

    def _radii_m(self) -> tuple[float, float]:
        return self._constants[:2]

    @cached_property
    def _constants(self) -> tuple[float, float, float]:
        """Meridian and normal radii (m) and cos(lat) of the origin, computed once (every
        published nav state converts its position)."""
        s2 = np.sin(self.lat_rad) ** 2
        denom = np.sqrt(1.0 - WGS84_E2 * s2)
        r_meridian = WGS84_A_M * (1.0 - WGS84_E2) / denom**3
        r_normal = WGS84_A_M / denom
        return r_meridian, r_normal, np.cos(self.lat_rad)

    def to_ned(self, lat_rad, lon_rad, alt_m=0.0) -> np.ndarray:
        """Geodetic → local NED position (m); vectorised over inputs."""
        r_m, r_n, cos_lat = self._constants
        north = (np.asarray(lat_rad) - self.lat_rad) * (r_m + self.alt_m)
        east = (np.asarray(lon_rad) - self.lon_rad) * (r_n + self.alt_m) * cos_lat
        down = self.alt_m - np.asarray(alt_m)
        return np.stack(np.broadcast_arrays(north, east, down), axis=-1).astype(float)

    def to_geodetic(self, pos_n_m) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Local NED position (m) → (lat_rad, lon_rad, alt_m)."""
        pos = np.asarray(pos_n_m, dtype=float)
        r_m, r_n, cos_lat = self._constants
        lat = self.lat_rad + pos[..., 0] / (r_m + self.alt_m)
        lon = self.lon_rad + pos[..., 1] / ((r_n + self.alt_m) * cos_lat)
        alt = self.alt_m - pos[..., 2]
        return lat, lon, alt

    def to_geodetic_ne(self, north_m: float, east_m: float) -> tuple[float, float]:
        """(lat_rad, lon_rad) of one local position, in Python floats: :meth:`to_geodetic`'s
        numbers (the same IEEE operations) without its arrays (every output row converts one)."""
        r_m, r_n, cos_lat = self._scalar_constants
        return self.lat_rad + north_m / (r_m + self.alt_m), self.lon_rad + east_m / ((r_n + self.alt_m) * cos_lat)

    @cached_property
    def _scalar_constants(self) -> tuple[float, float, float]:
        return tuple(float(c) for c in self._constants)
