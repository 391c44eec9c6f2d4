"""Simulation scenarios: one typed, frozen configuration tree per TOML file.

A scenario fixes everything the simulator draws from: the seed, the trajectory
pattern, the true motion-model parameters before and after an *environment change*
(DESIGN.md "Motion model"), the sea current, and every sensor's rate and noise.
It is loaded strictly with :mod:`adaptnav.fusion.typed_config` (unknown keys are errors) from
``sim/scenarios/<name>.toml`` (package data) or a path, with ``--set a.b=v`` overrides.

Motion parameters are given as standard deviations (``sigma_*``) because that is how
people think about them; :meth:`MotionConfig.params_before` / :meth:`Scenario.params_after`
turn them into :class:`adaptnav.fusion.motion_model.MotionParams` variances.  After
``environment.change_at_s`` the true ``k_V`` becomes ``environment.k_v_after`` and
σ_Vv becomes ``motion.sigma_vv_after``; the other ``environment.*_after`` keys change
the remaining sigmas and the water density (``None`` keeps the value before).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Literal

import numpy as np

from adaptnav.fusion.frames import GeoOrigin
from adaptnav.fusion.motion_model import MotionParams, RpmSpeedTable
from adaptnav.fusion.typed_config import ConfigError, load_toml

SCENARIO_DIR = Path(__file__).resolve().parent / "scenarios"


@dataclass(frozen=True)
class OriginConfig:
    """Mission origin of the local NED frame (degrees at the edge, radians inside)."""

    lat_deg: float = 43.0
    lon_deg: float = 5.9

    def geo(self) -> GeoOrigin:
        return GeoOrigin(math.radians(self.lat_deg), math.radians(self.lon_deg), 0.0)


@dataclass(frozen=True)
class TrajectoryConfig:
    """Path the guidance law follows (line-of-sight steering between waypoints)."""

    pattern: Literal["lawnmower", "straight", "circle"] = "lawnmower"
    speed_m_s: float = 1.5
    leg_length_m: float = 500.0
    leg_spacing_m: float = 50.0
    heading_deg: float = 0.0            # direction of the first leg / of the straight line
    circle_radius_m: float = 100.0
    depth_m: float = 20.0               # survey depth
    start_depth_m: float = 0.0          # 0 = at the surface (GNSS possible) at t = 0
    start_delay_s: float = 0.0          # propeller stopped (rpm 0, no steering) this long first;
                                        # the descent starts after it (alignment at rest)
    dive_rate_m_s: float = 0.3          # peak vertical speed of the (smooth) descent
    lookahead_m: float = 20.0           # LOS guidance look-ahead distance
    yaw_gain_per_s: float = 0.5         # yaw-rate command per rad of heading error
    turn_rate_max_deg_s: float = 6.0
    roll_amp_deg: float = 0.5           # small roll/pitch oscillations (sea state, trim)
    pitch_amp_deg: float = 0.5
    roll_period_s: float = 8.0
    pitch_period_s: float = 11.0
    pitch_trim_deg: float = 0.0

    def validate(self) -> None:
        if self.speed_m_s < 0 or self.leg_length_m <= 0 or self.circle_radius_m <= 0:
            raise ValueError("speed must be ≥ 0, leg_length_m and circle_radius_m > 0")
        if self.dive_rate_m_s <= 0 or self.lookahead_m <= 0 or self.turn_rate_max_deg_s <= 0:
            raise ValueError("dive_rate_m_s, lookahead_m and turn_rate_max_deg_s must be > 0")


@dataclass(frozen=True)
class MotionConfig:
    """True motion-model parameters before the environment change (sigmas, not variances)."""

    step_s: float = 1.0
    ramp_s: float = 0.5                 # body velocity blends between steps over this time
    k_v: float = 1.0
    b_w_deg_s: float = 0.0
    sigma_vv: float = 0.05
    sigma_vw: float = 0.01
    sigma_v1: float = 0.01
    sigma_wv: float = 0.001
    sigma_ww: float = 0.05
    sigma_w1: float = 0.001
    sigma_s: float = 0.01
    sigma_vv_after: float | None = None

    def validate(self) -> None:
        if self.step_s <= 0:
            raise ValueError("step_s must be > 0")
        if not 0 < self.ramp_s <= 0.5 * self.step_s:
            raise ValueError("ramp_s must be in (0, step_s/2] (keeps the step recursion stable)")

    def params_before(self) -> MotionParams:
        return MotionParams(
            var_vv=self.sigma_vv**2, var_vw=self.sigma_vw**2, var_v1=self.sigma_v1**2,
            var_wv=self.sigma_wv**2, var_ww=self.sigma_ww**2, var_w1=self.sigma_w1**2,
            var_s=self.sigma_s**2, k_v=self.k_v, b_w=math.radians(self.b_w_deg_s))


@dataclass(frozen=True)
class EnvironmentConfig:
    """Water and seabed; the change at ``change_at_s`` (None/∞ = never)."""

    change_at_s: float | None = None
    k_v_after: float | None = None
    sigma_vw_after: float | None = None
    sigma_v1_after: float | None = None
    sigma_wv_after: float | None = None
    sigma_ww_after: float | None = None
    sigma_w1_after: float | None = None
    sigma_s_after: float | None = None
    density_kg_m3: float = 1025.0
    density_after_kg_m3: float | None = None
    atmospheric_pressure_pa: float = 101325.0
    bottom_depth_m: float = 30.0        # flat seabed depth (DVL altitude, side-scan)
    # a trench across the survey: between these east coordinates (m) the seabed lies
    # trench_depth_m deeper, with slopes trench_slope_m wide (empty: no trench)
    trench_east_m: tuple[float, ...] = ()
    trench_depth_m: float = 0.0
    trench_slope_m: float = 20.0

    def bottom_depth_at(self, east_m):
        """Seabed depth (m, down) under east coordinates ``east_m`` (array or float)."""
        import numpy as np

        east = np.asarray(east_m, dtype=float)
        if len(self.trench_east_m) != 2 or self.trench_depth_m == 0.0:
            return np.full_like(east, self.bottom_depth_m)
        a, b = self.trench_east_m
        w = max(self.trench_slope_m, 1e-6)
        inside = np.clip((east - a) / w + 0.5, 0.0, 1.0) * np.clip((b - east) / w + 0.5, 0.0, 1.0)
        return self.bottom_depth_m + self.trench_depth_m * inside


@dataclass(frozen=True)
class CurrentConfig:
    """Horizontal sea current; directions are where it flows *towards*, from north to east.

    ``speed_m_s``/``direction_deg``: the current at depth, constant. ``surface_drift_*``: what
    moves a vehicle at the surface besides it (wind drift of the top layer, waves' Stokes
    drift, a floating hull's leeway), full at the surface and fading linearly to none at
    ``surface_layer_m`` — the drift a GNSS sees before a dive and the water under it does not
    share (default none: the published scenarios unchanged).
    """

    speed_m_s: float = 0.1
    direction_deg: float = 45.0
    surface_drift_speed_m_s: float = 0.0
    surface_drift_direction_deg: float = 0.0
    surface_layer_m: float = 2.0

    def validate(self) -> None:
        if self.speed_m_s < 0 or self.surface_drift_speed_m_s < 0 or self.surface_layer_m <= 0:
            raise ValueError("current: speeds must be ≥ 0 and surface_layer_m > 0")

    def vel_n_m_s(self) -> tuple[float, float]:
        """The current at depth (north, east), m/s."""
        a = math.radians(self.direction_deg)
        return (self.speed_m_s * math.cos(a), self.speed_m_s * math.sin(a))

    def surface_drift_n_m_s(self, depth_m) -> np.ndarray:
        """The surface drift (…, 2) (north, east) m/s at ``depth_m`` (down, m; any shape)."""
        a = math.radians(self.surface_drift_direction_deg)
        fade = np.clip(1.0 - np.asarray(depth_m, dtype=float) / self.surface_layer_m, 0.0, 1.0)
        return self.surface_drift_speed_m_s * fade[..., None] * np.array([math.cos(a), math.sin(a)])


@dataclass(frozen=True)
class ImuConfig:
    grade: Literal["consumer", "tactical", "navigation", "perfect"] = "tactical"
    rate_hz: float = 100.0


@dataclass(frozen=True)
class HeadingConfig:
    enabled: bool = True
    rate_hz: float = 10.0
    sigma_deg: float = 0.5


@dataclass(frozen=True)
class DepthConfig:
    enabled: bool = True
    rate_hz: float = 10.0
    sigma_m: float = 0.05               # pressure noise expressed as depth at 1025 kg/m³
    # what the vehicle's filter is told of the water density it converts pressure with
    # (filter.depth.density_sigma_kg_m3): 0 = known; a vehicle without a CTD that may meet
    # fresher water says how unsure it is
    density_sigma_kg_m3: float = 0.0


@dataclass(frozen=True)
class GnssConfig:
    """GNSS fixes at the listed times (and at ``rate_hz`` if > 0), only while at the surface."""

    fix_times_s: tuple[float, ...] = (0.0,)
    rate_hz: float = 0.0
    max_depth_m: float = 0.5
    sigma_m: float = 1.5                # the σ a fix reports per axis: its whole error
    # of it, a part shared by fixes minutes apart (multipath, atmosphere; sim/sensors.py):
    # 0 = every fix independent (the default scenarios, whose figures are published so)
    bias_sigma_m: float = 0.0
    bias_time_s: float = 300.0

    def validate(self) -> None:
        _check_bias("gnss", self.sigma_m, self.bias_sigma_m, self.bias_time_s)


@dataclass(frozen=True)
class UsblConfig:
    enabled: bool = True
    period_s: float = 60.0
    start_s: float = 60.0
    lost_after_s: float | None = None   # no fixes after this time (None = never lost)
    outages_s: tuple[tuple[float, float], ...] = ()   # [start, end) intervals without fixes
    sigma_m: float = 2.0                # the horizontal σ a fix reports per axis: its whole error
    sigma_depth_m: float = 1.0
    # of sigma_m, a part shared by fixes within tens of seconds (the transducer's residual
    # misalignment, the sound-speed profile, multipath; sim/sensors.py): 0 = independent fixes
    bias_sigma_m: float = 0.0
    bias_time_s: float = 60.0

    def validate(self) -> None:
        _check_bias("usbl", self.sigma_m, self.bias_sigma_m, self.bias_time_s)


def _check_bias(name: str, sigma_m: float, bias_sigma_m: float, bias_time_s: float) -> None:
    if not 0.0 <= bias_sigma_m <= sigma_m:
        raise ValueError(f"{name}.bias_sigma_m must be in [0, sigma_m] (the reported σ is the whole error), "
                         f"got {bias_sigma_m} with sigma_m {sigma_m}")
    if not bias_time_s > 0.0:
        raise ValueError(f"{name}.bias_time_s must be > 0, got {bias_time_s}")


@dataclass(frozen=True)
class DvlConfig:
    """A 4-beam Janus DVL (sim/sensors.py ``dvl_samples`` for the model and the datasheets).

    Defaults are a 600 kHz-class unit (Teledyne RDI Workhorse Navigator / Pathfinder class):
    beams 30° from the vertical, per-beam single-ping noise 5 mm/s at 5 Hz, a scale-factor
    error of 0.3 % (sound speed), a head misalignment of a few tenths of a degree left after
    installation, mm/s beam biases, rare outlier beams, bottom lock to ~80 m altitude.
    """

    enabled: bool = False
    rate_hz: float = 5.0
    start_s: float = 0.0                # first ping (a DVL's own clock: pings need not fall on motion steps)
    beam_angle_deg: float = 30.0        # Janus beams, from the head's z axis
    beam_sigma_m_s: float = 0.005       # white noise per beam and ping
    scale_factor_error: float = 0.003   # all beams × (1 + this): sound-speed error
    # true head orientation = configured mount ⊗ this (roll, pitch, yaw; deg): what the
    # installation survey missed
    misalignment_rpy_deg: tuple[float, float, float] = (0.1, -0.15, 0.4)
    beam_bias_m_s: tuple[float, float, float, float] = (0.001, -0.0005, 0.0008, -0.001)
    outlier_prob: float = 0.001         # per beam and ping (fish, bubbles, side lobes)
    outlier_sigma_m_s: float = 0.3
    dropout_prob: float = 0.02          # independent per-sample lost lock
    outages_s: tuple[tuple[float, float], ...] = ()   # [start, end) intervals without lock
    lever_arm_b_m: tuple[float, float, float] = (0.5, 0.0, 0.2)
    mount_rpy_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)   # R_bd as ZYX Euler
    min_altitude_m: float = 0.5
    max_altitude_m: float = 80.0        # bottom lock while every beam's slant range ≤ this / cos(beam angle)
    max_tilt_deg: float = 25.0          # roll/pitch beyond this: beams graze, no lock
    water_track: bool = False           # without bottom lock, velocity relative to a water layer
    water_track_sigma_m_s: float = 0.02  # per axis


@dataclass(frozen=True)
class VehicleConfig:
    """Which truth model moves the vehicle, and the physical vehicle (sim/vehicle.py).

    ``model = "motion_model"``: velocities are drawn from the motion model with the
    parameters of ``[motion]``/``[environment]`` (the thesis experiments). ``"fossen3dof"``:
    a surge–sway–yaw rigid body with added mass, linear + quadratic drag and thrust from
    RPM (Fossen 2011), REMUS-100 coefficients (Prestero 2001); the water density, trim,
    payload and fouling act on it and the motion-model parameters follow from them.
    The ``*_after`` values apply from ``environment.change_at_s`` (None keeps the value).
    """

    model: Literal["motion_model", "fossen3dof"] = "motion_model"
    trim_deg: float = 0.0               # pitch offset from ballast/payload placement
    payload_kg: float = 0.0             # added dry mass (not buoyancy-compensated)
    fouling: float = 0.0                # fractional increase of the hull's drag
    trim_after_deg: float | None = None
    payload_after_kg: float | None = None
    fouling_after: float | None = None
    # turbulence: white fluctuations of the hull's forces, relative to the quadratic drag
    # at the current surge (so a vehicle at rest is not pushed around), per √Hz: surge and
    # sway force as a fraction of |X_uu| u², yaw moment of |N_uv| u² (at 1.5 m/s: 0.55 N/√Hz)
    surge_force_rel_rthz: float = 0.15
    sway_force_rel_rthz: float = 0.15
    yaw_moment_rel_rthz: float = 0.002
    integration_step_s: float = 0.02


@dataclass(frozen=True)
class BeaconsConfig:
    """Acoustic range beacons at known NED positions (the thesis's landmark sim)."""

    enabled: bool = False
    positions_n_m: tuple[tuple[float, float, float], ...] = (
        (0.0, 0.0, 30.0), (500.0, 0.0, 30.0), (0.0, 500.0, 30.0), (500.0, 500.0, 30.0))
    period_s: float = 1.0
    sigma_m: float = 2.0


@dataclass(frozen=True)
class RpmConfig:
    rate_hz: float = 10.0
    table_rpm: tuple[float, ...] = RpmSpeedTable().rpm
    table_speed_m_s: tuple[float, ...] = RpmSpeedTable().speed_m_s

    def table(self) -> RpmSpeedTable:
        return RpmSpeedTable(rpm=self.table_rpm, speed_m_s=self.table_speed_m_s)


@dataclass(frozen=True)
class TruthConfig:
    rate_hz: float = 10.0


@dataclass(frozen=True)
class SonarConfig:
    enabled: bool = False
    ping_rate_hz: float = 4.0
    range_m: float = 50.0
    samples_per_side: int = 512
    seabed_res_m: float = 0.1
    objects_per_hectare: float = 25.0   # shadow-casting objects (landmarks) per 10 000 m²


@dataclass(frozen=True)
class Scenario:
    """The whole scenario tree (see the module docstring)."""

    seed: int = 1
    duration_s: float = 300.0
    name: str = ""
    # real (UTC) time of t = 0, ISO 8601 ("2026-05-01T08:00:00Z"); "" = the time of the run.
    # Only log times use it (Foxglove's timeline): the simulation itself is timeless.
    start_utc: str = ""
    origin: OriginConfig = field(default_factory=OriginConfig)
    trajectory: TrajectoryConfig = field(default_factory=TrajectoryConfig)
    motion: MotionConfig = field(default_factory=MotionConfig)
    environment: EnvironmentConfig = field(default_factory=EnvironmentConfig)
    current: CurrentConfig = field(default_factory=CurrentConfig)
    vehicle: VehicleConfig = field(default_factory=VehicleConfig)
    imu: ImuConfig = field(default_factory=ImuConfig)
    heading: HeadingConfig = field(default_factory=HeadingConfig)
    depth: DepthConfig = field(default_factory=DepthConfig)
    gnss: GnssConfig = field(default_factory=GnssConfig)
    usbl: UsblConfig = field(default_factory=UsblConfig)
    dvl: DvlConfig = field(default_factory=DvlConfig)
    beacons: BeaconsConfig = field(default_factory=BeaconsConfig)
    rpm: RpmConfig = field(default_factory=RpmConfig)
    truth: TruthConfig = field(default_factory=TruthConfig)
    sonar: SonarConfig = field(default_factory=SonarConfig)

    def validate(self) -> None:
        if self.duration_s <= 0:
            raise ValueError("duration_s must be > 0")
        if self.seed < 0:
            raise ValueError("seed must be ≥ 0")
        if self.start_utc:
            start_unix_s(self.start_utc)  # raises on a malformed time
        steps_per_imu = self.motion.step_s * self.imu.rate_hz
        if abs(steps_per_imu - round(steps_per_imu)) > 1e-9 or round(steps_per_imu) < 2:
            raise ValueError(f"motion.step_s × imu.rate_hz must be an integer ≥ 2, got {steps_per_imu}")
        n_steps = self.duration_s / self.motion.step_s
        if abs(n_steps - round(n_steps)) > 1e-9:
            raise ValueError("duration_s must be a whole number of motion.step_s")
        self.params_after()  # raises on invalid values

    @property
    def change_at_s(self) -> float:
        c = self.environment.change_at_s
        return math.inf if c is None else c

    def params_before(self) -> MotionParams:
        """True :class:`MotionParams` before the environment change."""
        return self.motion.params_before()

    def params_after(self) -> MotionParams:
        """True :class:`MotionParams` after the environment change."""
        env, p = self.environment, self.motion.params_before()
        changes = {}
        for name in ("vw", "v1", "wv", "ww", "w1", "s"):
            value = getattr(env, f"sigma_{name}_after")
            if value is not None:
                changes[f"var_{name}"] = value**2
        if self.motion.sigma_vv_after is not None:
            changes["var_vv"] = self.motion.sigma_vv_after**2
        if env.k_v_after is not None:
            changes["k_v"] = env.k_v_after
        return replace(p, **changes)

    def params_at(self, t_s: float) -> MotionParams:
        return self.params_after() if t_s >= self.change_at_s else self.params_before()

    def density_at(self, t_s: float) -> float:
        env = self.environment
        if t_s >= self.change_at_s and env.density_after_kg_m3 is not None:
            return env.density_after_kg_m3
        return env.density_kg_m3


def scenario_path(name_or_path: str | Path) -> Path:
    """A bare name → ``sim/scenarios/<name>.toml``; anything else is a file path."""
    p = Path(name_or_path)
    if p.suffix == ".toml" or p.parent != Path("."):
        return p
    return SCENARIO_DIR / f"{p.name}.toml"


def available_scenarios() -> list[str]:
    return sorted(p.stem for p in SCENARIO_DIR.glob("*.toml"))


def load_scenario(name_or_path: str | Path, overrides=()) -> Scenario:
    """Load a scenario by name or path and apply ``key=value`` overrides.

    Raises
    ------
    ConfigError
        Unknown scenario, unknown key (named with its dotted path), bad value.
    """
    path = scenario_path(name_or_path)
    if not path.is_file():
        raise ConfigError(f"scenario {str(name_or_path)!r} not found (looked for {path}; "
                          f"built-in: {', '.join(available_scenarios())})")
    scenario = load_toml(Scenario, path.read_text(), list(overrides))
    if not scenario.name:
        scenario = replace(scenario, name=path.stem)
    return scenario


def start_unix_s(start_utc: str) -> float:
    """UNIX seconds of an ISO 8601 time (``Z`` or an offset; naive = UTC)."""
    from datetime import datetime, timezone

    try:
        t = datetime.fromisoformat(start_utc.replace("Z", "+00:00"))
    except ValueError as e:
        raise ValueError(f"start_utc {start_utc!r} is not an ISO 8601 time: {e}") from None
    if t.tzinfo is None:
        t = t.replace(tzinfo=timezone.utc)
    return t.timestamp()
