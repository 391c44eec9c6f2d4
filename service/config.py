"""The live service's configuration: one typed tree loaded from TOML.

``ServiceConfig`` is a tree of frozen dataclasses built strictly by
:mod:`adaptnav.fusion.typed_config` (unknown keys are errors naming their dotted path; CLI
overrides ``--set section.key=value`` go through the same validation). Sections:

- ``vehicle``   name (the ``<v>`` of every Zenoh key expression)
- ``zenoh``     session mode, endpoints, multicast scouting
- ``mavlink``   bridge to ArduSub (its :class:`BridgeConfig`) + on/off and output rate
- ``origin``    mission origin of the local NED frame (degrees at the edge, converted once)
- ``filter``    the ESKF's own config (:class:`adaptnav.fusion.config.FilterConfig`: lever arms,
                noises, gates), embedded as is
- ``motion``    static RPM → speed table and the initial :class:`MotionParams`
- ``calibrator`` where the EM calibrator runs, restart backoff, and its own
                :class:`adaptnav.calibration.online.CalibratorConfig` under ``[calibrator.online]``
- ``outputs``   publication rates
- ``health``    silence thresholds
- ``state_dir`` where learned parameters and slow filter states persist

``deploy/adaptnav.toml`` documents every key.
"""
from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Literal


from adaptnav.fusion.frames import GeoOrigin
from adaptnav.fusion.motion_model import MotionParams, RpmSpeedTable
from adaptnav.fusion.typed_config import ConfigError, apply_overrides, as_dict, build

from adaptnav.service.transport.mavlink_config import BridgeConfig

from adaptnav.calibration.online import CalibratorConfig
from adaptnav.fusion.config import FilterConfig

log = logging.getLogger(__name__)

MAX_QUEUE_SIZE = 10_000_000  # items; a bound on the memory a burst may take (a test replays an hour through one)


def _check_queue_size(name: str, value: int) -> None:
    if not 1 <= value <= MAX_QUEUE_SIZE:
        raise ValueError(f"{name} must be within [1, {MAX_QUEUE_SIZE}], got {value!r}")


@dataclass(frozen=True)
class VehicleConfig:
    """``name``: the vehicle's name, the ``<v>`` in ``adaptnav/<v>/...`` keys."""

    name: str = "auv1"

    def validate(self) -> None:
        if not self.name or any(c in self.name for c in "/*$?#"):
            raise ValueError(f"name {self.name!r}: must be non-empty without / * $ ? #")


_ACL_MESSAGES = ("put", "delete", "declare_subscriber", "query", "reply", "declare_queryable",
                 "liveliness_token", "liveliness_query", "declare_liveliness_subscriber")
_ACL_FLOWS = ("ingress", "egress")


@dataclass(frozen=True)
class ZenohTlsConfig:
    """``[zenoh.tls]``: Zenoh's ``transport.link.tls`` (used by ``tls/<host>:<port>`` endpoints).

    Paths of PEM files: ``root_ca_certificate`` (the CA that signed the other side's
    certificate), ``listen_certificate``/``listen_private_key`` (this node's, when it listens),
    ``connect_certificate``/``connect_private_key`` (this node's, when it connects; needed
    with mutual TLS). ``enable_mtls``: the listener asks connecting peers for a certificate
    signed by ``root_ca_certificate`` and refuses those without one. ``verify_name_on_connect``:
    the listener's certificate must name the host connected to.
    ``close_link_on_expiration``: links close when the other side's certificate expires.
    Empty path = not set.
    """

    root_ca_certificate: str = ""
    listen_certificate: str = ""
    listen_private_key: str = ""
    connect_certificate: str = ""
    connect_private_key: str = ""
    enable_mtls: bool = False
    verify_name_on_connect: bool = True
    close_link_on_expiration: bool = False

    def validate(self) -> None:
        for a, b in (("listen_certificate", "listen_private_key"), ("connect_certificate", "connect_private_key")):
            if bool(getattr(self, a)) != bool(getattr(self, b)):
                raise ValueError(f"{a} and {b} go together (both set or both empty)")
        if self.enable_mtls and not self.root_ca_certificate:
            raise ValueError("enable_mtls needs root_ca_certificate (the CA peers' certificates are checked against)")


@dataclass(frozen=True)
class ZenohAuthConfig:
    """``[zenoh.auth]``: Zenoh's user/password authentication (``transport.auth.usrpwd``).

    ``user`` + ``password_file`` (a file holding the password, so that the password is in
    neither the logged effective config nor the ``query/config`` answer): the identity this
    node presents. ``dictionary_file``: a listening node's accepted ``user:password`` lines.
    Empty = not set.
    """

    user: str = ""
    password_file: str = ""
    dictionary_file: str = ""

    def validate(self) -> None:
        if bool(self.user) != bool(self.password_file):
            raise ValueError("user and password_file go together (both set or both empty)")


@dataclass(frozen=True)
class AclRule:
    """One access-control rule: ``permission`` for ``messages`` in ``flows`` on ``key_exprs``."""

    id: str
    messages: tuple[str, ...]
    key_exprs: tuple[str, ...]
    permission: Literal["allow", "deny"] = "allow"
    flows: tuple[str, ...] = _ACL_FLOWS

    def validate(self) -> None:
        for name, values, allowed in (("messages", self.messages, _ACL_MESSAGES), ("flows", self.flows, _ACL_FLOWS)):
            bad = sorted(set(values) - set(allowed))
            if not values or bad:
                raise ValueError(f"rule {self.id!r}: {name} must be a non-empty list of {list(allowed)}"
                                 + (f", got {bad}" if bad else ""))
        if not self.key_exprs:
            raise ValueError(f"rule {self.id!r}: key_exprs must not be empty")


@dataclass(frozen=True)
class AclSubject:
    """Who a rule applies to: the conjunction of the non-empty lists (an empty list = anyone).

    ``cert_common_names`` (the CN of a peer's TLS certificate: needs mutual TLS),
    ``usernames`` (``[zenoh.auth]``), ``interfaces`` (network interfaces, e.g. ``lo``),
    ``link_protocols`` (``tls``, ``tcp``, ...).
    """

    id: str
    cert_common_names: tuple[str, ...] = ()
    usernames: tuple[str, ...] = ()
    interfaces: tuple[str, ...] = ()
    link_protocols: tuple[str, ...] = ()


@dataclass(frozen=True)
class AclPolicy:
    """Which ``rules`` (ids) apply to which ``subjects`` (ids)."""

    rules: tuple[str, ...]
    subjects: tuple[str, ...]
    id: str = ""


@dataclass(frozen=True)
class ZenohAccessControlConfig:
    """``[zenoh.access_control]``: Zenoh's access-control rules (``access_control``), enforced
    by this node on what other nodes send it and what it sends them (not on its own
    publications). ``default_permission`` applies to everything no rule allows or denies;
    ``rules``, ``subjects``, ``policies`` as in Zenoh's configuration (arrays of tables
    ``[[zenoh.access_control.rules]]``...). ``deploy/adaptnav-secure.toml`` holds the
    vehicle profile."""

    enabled: bool = False
    default_permission: Literal["allow", "deny"] = "deny"
    rules: tuple[AclRule, ...] = ()
    subjects: tuple[AclSubject, ...] = ()
    policies: tuple[AclPolicy, ...] = ()

    def validate(self) -> None:
        for what, items in (("rule", self.rules), ("subject", self.subjects)):
            ids = [x.id for x in items]
            if len(set(ids)) != len(ids) or not all(ids):
                raise ValueError(f"{what} ids must be non-empty and unique, got {ids}")
        rules, subjects = {r.id for r in self.rules}, {s.id for s in self.subjects}
        for p in self.policies:
            unknown = sorted((set(p.rules) - rules) | (set(p.subjects) - subjects))
            if unknown or not p.rules or not p.subjects:
                raise ValueError(f"policy {p.id or p.rules}: needs rules and subjects declared above"
                                 + (f"; unknown: {unknown}" if unknown else ""))


@dataclass(frozen=True)
class ZenohConfig:
    """Zenoh session.

    ``mode`` peer (embedded, default) | client (through a router) | router.
    ``connect``/``listen``: endpoint lists such as ``"tcp/127.0.0.1:7447"`` or, encrypted,
    ``"tls/127.0.0.1:7447"`` (with ``[zenoh.tls]``).
    ``scouting``: multicast scouting on/off (off on a vehicle LAN you do not own).
    ``connect_timeout_s``: in client mode, how long opening the session waits for a
    ``connect`` endpoint to answer (the daemon or router may start later); -1 = forever.
    ``tls``, ``auth``, ``access_control``: the bus's security (see their classes and
    docs/vehicle.md "Security").
    ``shared_memory``: Zenoh's shared-memory transport between processes on this computer.
    Off by default: it maps a 16 MB pool and sends every message above 3 kB through it, and
    ours are small JSON (a nav state ~6 kB) — on the daemon of an ArduSub vehicle it cost
    38 MB of resident memory (`adaptnav bench service --only memory_mavlink`).
    """

    mode: Literal["peer", "client", "router"] = "peer"
    connect: tuple[str, ...] = ()
    listen: tuple[str, ...] = ("tcp/127.0.0.1:7447",)
    scouting: bool = False
    connect_timeout_s: float = 30.0
    shared_memory: bool = False
    tls: ZenohTlsConfig = field(default_factory=ZenohTlsConfig)
    auth: ZenohAuthConfig = field(default_factory=ZenohAuthConfig)
    access_control: ZenohAccessControlConfig = field(default_factory=ZenohAccessControlConfig)

    def validate(self) -> None:
        if self.mode == "client" and not self.connect:
            raise ValueError("mode 'client' needs at least one connect endpoint (the router)")
        for ep in (*self.connect, *self.listen):
            if "/" not in ep:
                raise ValueError(f"endpoint {ep!r}: expected <proto>/<address>, e.g. tcp/127.0.0.1:7447")
        tls = self.tls
        if any(ep.startswith("tls/") for ep in self.listen) and not tls.listen_certificate:
            raise ValueError("a tls/ listen endpoint needs tls.listen_certificate and tls.listen_private_key")
        if any(ep.startswith("tls/") for ep in self.connect):
            if not tls.root_ca_certificate:
                raise ValueError("a tls/ connect endpoint needs tls.root_ca_certificate")
            if tls.enable_mtls and not tls.connect_certificate:
                raise ValueError("tls/ connect with enable_mtls needs tls.connect_certificate and "
                                 "tls.connect_private_key")
        if self.access_control.enabled and self.access_control.default_permission == "deny" \
                and not self.access_control.policies:
            raise ValueError("access_control enabled with default_permission 'deny' and no policies "
                             "would refuse every other node")

    def as_client(self, connect: tuple[str, ...] = ()) -> "ZenohConfig":
        """The config of another program joining this bus (recorder, calibrator node): a
        *client* of ``connect`` (default: this config's connect, else listen endpoints),
        listening nowhere, with the same TLS and user/password identity; access control
        stays with the listener that enforces it (daemon or router)."""
        import dataclasses

        return dataclasses.replace(self, mode="client", connect=tuple(connect) or tuple(self.connect)
                                   or tuple(self.listen), listen=(),
                                   access_control=ZenohAccessControlConfig())


@dataclass(frozen=True)
class MavlinkConfig(BridgeConfig):
    """MAVLink bridge to ArduSub: :class:`adaptnav.service.transport.mavlink_bridge.BridgeConfig` (``url``,
    identity, stream rates, ``convert`` incl. the thruster PWM → RPM curve under
    ``convert.thrusters``, ``output``) plus ``enabled`` and the ODOMETRY
    ``output_rate_hz`` (ArduSub wants ≥ 4 Hz)."""

    enabled: bool = False
    output_rate_hz: float = 10.0

    def validate(self) -> None:
        super().validate()
        if not 4.0 <= self.output_rate_hz <= 100.0:
            raise ValueError("output_rate_hz must be within [4, 100] (ArduSub wants >= 4 Hz)")


@dataclass(frozen=True)
class OriginConfig:
    """Mission origin of the local NED frame (WGS-84)."""

    lat_deg: float = 0.0
    lon_deg: float = 0.0
    alt_m: float = 0.0

    def validate(self) -> None:
        if not (-90.0 <= self.lat_deg <= 90.0 and -180.0 <= self.lon_deg <= 180.0):
            raise ValueError("lat_deg/lon_deg out of range")

    def geo(self) -> GeoOrigin:
        return GeoOrigin(math.radians(self.lat_deg), math.radians(self.lon_deg), self.alt_m)


@dataclass(frozen=True)
class MotionConfig:
    """Static RPM → speed table and the initial motion parameters.

    ``prior``: what ``params0``'s surge and sway variances are worth for this vehicle.
    ``calibrated``: as given (a tank test, a vehicle profile, the calibrator). ``uncalibrated``:
    the surge σ widened to ``uncalibrated_sigma_surge`` of the speed and the sway σ to
    ``uncalibrated_sigma_sway_m_s`` — what the embedded table (a REMUS-100-class AUV's) is worth
    on a vehicle it was not made for: on ArduSub's BlueROV2 (SITL, thrust from PWM through the
    T200 curve) its shape is not the vehicle's, so with ``k_speed`` fitted to one thrust level the
    surge is 17 % slow at another, and the sway 0.07 m/s off, where the calibrated σ say 5 % and
    0.01 m/s: 5.9–8.2 % of the valid epochs of those logs lay outside their own 99 % ellipse.
    7 % and 0.03 m/s left at most 0.9 % there (what a consistent filter leaves: 1 %) on five
    ArduSub logs and kept them within issue 11's 5 % / 15 m; 10 % and 0.05 m/s left none but
    took a fresh DataFlash drive to 5.1 % (3.8 % with the calibrated σ). (A log of that simulator
    now goes through the simulator's own thruster curve, ``mavlink.convert.thrusters.simulator_curve``;
    the σ stay for a real vehicle, whose ESC and hull the embedded table does not know either.)
    ``auto``: uncalibrated when the
    thrust comes from an autopilot (MAVLink/DataFlash) and ``rpm_table`` is the embedded one
    (nobody calibrated this vehicle), else calibrated.
    """

    rpm_table: RpmSpeedTable = field(default_factory=RpmSpeedTable)
    params0: MotionParams = field(default_factory=MotionParams)
    prior: Literal["auto", "calibrated", "uncalibrated"] = "auto"
    uncalibrated_sigma_surge: float = 0.07
    uncalibrated_sigma_sway_m_s: float = 0.03
    # what else an uncalibrated vehicle leaves unknown (the filter's own keys are raised to
    # these, never lowered: :meth:`prior_filter`). On drives of other shapes than the one the
    # figures above were set on (python -m tests.sitl.bin_drive OUT --pattern survey|brisk|arcs|stops),
    # two things the embedded table does not know about a BlueROV2 moved the scale: the vehicle's
    # response to a thrust change (a stop coasts for ~10 s, quadratic drag: 0.35 / 0.17 / 0.12 /
    # 0.06 m/s 1 / 2 / 3 / 5 s after the cut; fused as "speed 0 ± 0.01 m/s" at once it cut
    # k_speed by 4–8 % and moved the position back 2–3 m at every stop: the stops drive ended
    # 14.8 % off), and the initial k_speed (the table is 1.7× this vehicle's speed: k ≈ 0.58
    # against the prior's 1 ± 0.1, a 4σ start that only those stops had been pulling down).
    uncalibrated_sigma_k_speed: float = 0.3          # filter.initial.sigma_k_speed
    uncalibrated_transient_time_s: float = 2.0       # filter.learned_velocity.transient_time_s
    uncalibrated_skid_sigma_s: float = 2.0           # filter.learned_velocity.skid_sigma_s
    uncalibrated_heave_sigma_per_vertical_speed: float = 1.0  # filter.learned_velocity.heave_sigma_per_vertical_speed
    uncalibrated_vertical_drift_sigma_per_m: float = 0.1      # filter.learned_velocity.vertical_drift_sigma_per_m
    # ... and an IMU stream from this rate up is integrated (filter.alignment.min_imu_rate_hz
    # lowered to it, never raised): the attitude-driven strapdown has no accelerometer to check
    # a model nobody calibrated, integrating even instantaneous samples has (the freedrive with
    # RAW_IMU, ATTITUDE and thrust at 10 Hz: attitude-driven 22.8 % off, integrated 1.9 %)
    uncalibrated_min_imu_rate_hz: float = 8.0

    def validate(self) -> None:
        if not (0.0 < self.uncalibrated_sigma_surge <= 1.0 and 0.0 < self.uncalibrated_sigma_sway_m_s <= 2.0):
            raise ValueError("motion: uncalibrated_sigma_surge must be within (0, 1] and "
                             "uncalibrated_sigma_sway_m_s within (0, 2] m/s")
        if not self.uncalibrated_min_imu_rate_hz > 0.0:
            raise ValueError("motion.uncalibrated_min_imu_rate_hz must be > 0")
        if not (self.uncalibrated_sigma_k_speed >= 0.0 and self.uncalibrated_transient_time_s >= 0.0
                and self.uncalibrated_skid_sigma_s >= 0.0 and self.uncalibrated_heave_sigma_per_vertical_speed >= 0.0
                and self.uncalibrated_vertical_drift_sigma_per_m >= 0.0):
            raise ValueError("motion: uncalibrated_sigma_k_speed, uncalibrated_transient_time_s, "
                             "uncalibrated_skid_sigma_s, uncalibrated_heave_sigma_per_vertical_speed and "
                             "uncalibrated_vertical_drift_sigma_per_m must be ≥ 0")

    def prior_filter(self, filt: FilterConfig, why: str) -> FilterConfig:
        """``filt`` with what an uncalibrated prior (``why`` from :meth:`initial_params`) leaves
        unknown: the initial ``k_speed`` σ, the thrust-transient time, the skid σ in a turn, the
        heave σ per vertical speed and the horizontal drift per metre of a vertical run raised to
        the ``uncalibrated_*`` figures (never lowered),
        the slowest IMU stream integrated lowered to ``uncalibrated_min_imu_rate_hz`` (never
        raised), and its velocity no measurement of the motion for an attitude-driven strapdown
        (``filter.attitude_driven.model_measures_motion``: nothing checks its scale there);
        a calibrated prior: ``filt`` as it is."""
        if not why.startswith("uncalibrated"):
            return filt
        lv = filt.learned_velocity
        return replace(
            filt,
            alignment=replace(filt.alignment, min_imu_rate_hz=min(filt.alignment.min_imu_rate_hz,
                                                                  self.uncalibrated_min_imu_rate_hz)),
            initial=replace(filt.initial, sigma_k_speed=max(filt.initial.sigma_k_speed, self.uncalibrated_sigma_k_speed)),
            attitude_driven=replace(filt.attitude_driven, model_measures_motion=False),
            learned_velocity=replace(lv, transient_time_s=max(lv.transient_time_s, self.uncalibrated_transient_time_s),
                                     skid_sigma_s=max(lv.skid_sigma_s, self.uncalibrated_skid_sigma_s),
                                     heave_sigma_per_vertical_speed=max(
                                         lv.heave_sigma_per_vertical_speed,
                                         self.uncalibrated_heave_sigma_per_vertical_speed),
                                     vertical_drift_sigma_per_m=max(
                                         lv.vertical_drift_sigma_per_m,
                                         self.uncalibrated_vertical_drift_sigma_per_m)))

    def initial_params(self, autopilot_thrust: bool) -> tuple[MotionParams, str]:
        """``params0`` as the filter and the calibrator start from, and why (see ``prior``).

        ``autopilot_thrust``: the RPM come from an autopilot's thruster outputs (a MAVLink or
        DataFlash log, the live MAVLink bridge).
        """
        if self.prior == "calibrated":
            return self.params0, "calibrated (motion.prior)"
        if self.prior == "auto":
            if not autopilot_thrust:
                return self.params0, "calibrated (auto: the thrust is not an autopilot's)"
            if self.rpm_table != RpmSpeedTable():
                return self.params0, "calibrated (auto: motion.rpm_table is this vehicle's)"
            why = "uncalibrated (auto: an autopilot's thrust through the embedded table, another vehicle's)"
        else:
            why = "uncalibrated (motion.prior)"
        p = self.params0
        return replace(p, var_vv=max(p.var_vv, self.uncalibrated_sigma_surge ** 2),
                       var_s=max(p.var_s, self.uncalibrated_sigma_sway_m_s ** 2)), why


@dataclass(frozen=True)
class CalibratorSection:
    """Background EM calibrator.

    ``enabled``: run it at all. ``location``: ``process`` (child process of the daemon)
    or ``remote`` (another node runs ``adaptnav run --calibrator-only`` and publishes
    releases on ``adaptnav/<v>/calibration/params``). ``restart_backoff_s``: first
    restart delay after a crash, doubled up to ``restart_backoff_max_s``.
    ``queue_size``: samples buffered towards the process before new ones are dropped
    (counted) — fusion never waits for EM. ``seed``: its RNG seed. ``latency_s``: a
    release computed from data up to data time τ is applied once the runner's data time
    reaches τ + latency_s, live and in replay (replay waits for the calibrator's
    progress, so its output is deterministic; see :mod:`adaptnav.service.calibrator.lagged`).
    ``product_latency_s``: the same rule for the calibrator's side products, the side-scan
    objects it detects for the filter (≤ ``latency_s``). ``nice``: the child process's
    niceness (0–19, 0 = the daemon's): EM is background work, and its bursts must not hold
    a core the navigation loop (or the computer's other services) wants.
    """

    enabled: bool = True
    location: Literal["process", "remote"] = "process"
    restart_backoff_s: float = 0.5
    restart_backoff_max_s: float = 30.0
    queue_size: int = 20000
    seed: int = 0
    latency_s: float = 60.0  # > one EM window's run time × the replay speed-up (deploy/adaptnav.toml)
    # side-scan objects are measurements for the filter, due as soon as a block is detected:
    # held for latency_s, a loop closure reached the filter a minute after its sightings and
    # the closures in between were associated and fused on a track a minute less corrected
    # (landmark survey seed 2, no release applied: drift 0.217 % against 0.092 % with the
    # objects fused as detected). A detection block takes the child well under a second live;
    # in replay with side-scan the runner waits for the child to be within this of its data
    product_latency_s: float = 5.0
    # an EM window is a burst of ~0.1 s of one core each minute: at its own priority it took
    # a core from the daemon when the other was busy (outside-client latency at 200 Hz, two
    # pairs alternated: p99 3.52 / 3.80 ms → 2.83 / 3.06 ms niced by 10)
    nice: int = 10
    online: CalibratorConfig = field(default_factory=CalibratorConfig)

    def validate(self) -> None:
        if not (math.isfinite(self.latency_s) and self.latency_s >= 0.0):
            raise ValueError("latency_s must be a finite number ≥ 0")
        if not 0.0 <= self.product_latency_s <= self.latency_s:
            raise ValueError("product_latency_s must be within [0, latency_s]")
        if not 0.0 < self.restart_backoff_s <= self.restart_backoff_max_s <= 3600.0:
            raise ValueError("restart backoff: need 0 < restart_backoff_s ≤ restart_backoff_max_s ≤ 3600 s")
        _check_queue_size("queue_size", self.queue_size)
        if not 0 <= self.nice <= 19:
            raise ValueError("nice must be within [0, 19] (0: the daemon's priority)")


@dataclass(frozen=True)
class OutputsConfig:
    """Publication rates (Hz): nav state, aid statuses and health. ``rehearsal_lead_s``: live,
    the nav state's path is rehearsed this long before an output epoch's IMU sample is
    expected, so that the sample finds it in the caches (0: off;
    :mod:`adaptnav.service.runtime.rehearsal`). ``cpu_wakeup_latency_us``: live, the longest an idle
    CPU may take to wake, held while the daemon runs (Linux PM QoS, root's
    ``/dev/cpu_dma_latency``; 0: the CPUs poll instead of sleeping; −1: no bound, the kernel's
    choice): an IMU sample that finds the CPUs asleep waits for them
    (:mod:`adaptnav.service.runtime.wakeup`). ``cpu_wakeup_scope``: "always" (start to stop) or
    "epochs" (around each output epoch's sample only, from its rehearsal's planning to 3.5 ms after
    the sample is expected: needs ``rehearsal_lead_s`` > 0)."""

    nav_rate_hz: float = 10.0
    health_rate_hz: float = 1.0
    aid_rate_hz: float = 1.0
    # a rehearsal takes ~0.3 ms of CPU here (p99 0.4): 1.5 ms leaves it done well before the
    # sample, and the caches still warm (outside client at 100 Hz: decode → put p50
    # 0.32–0.39 → 0.23–0.26 ms)
    rehearsal_lead_s: float = 0.0015
    # 0 µs around each epoch (issue 17; docs/measurements.md, stop 49): the outside client's p99
    # in alternated 120 s windows, 100 Hz 1.37 / 1.24 ms against 1.72 / 1.61 without, 200 Hz
    # 2.91 (a host stall) / 1.52 against 1.72 / 1.84; held all along it did no better, and that
    # keeps the CPUs polling between epochs
    cpu_wakeup_latency_us: int = 0
    cpu_wakeup_scope: str = "epochs"

    def validate(self) -> None:
        # above 1 kHz the output epochs outrun any IMU (and 1e308 Hz made the loop spin)
        for name, top in (("nav_rate_hz", 1000.0), ("health_rate_hz", 100.0), ("aid_rate_hz", 100.0)):
            if not 0.0 < getattr(self, name) <= top:
                raise ValueError(f"{name} must be within (0, {top:g}] Hz, got {getattr(self, name)!r}")
        if not 0.0 <= self.rehearsal_lead_s <= 0.05:  # longer ago, the caches are cold again
            raise ValueError(f"rehearsal_lead_s must be within [0, 0.05] s, got {self.rehearsal_lead_s!r}")
        w = self.cpu_wakeup_latency_us
        if type(w) is not int or not -1 <= w <= 2_000_000:  # (beyond 2 s it bounds nothing)
            raise ValueError(f"cpu_wakeup_latency_us must be an integer within [-1, 2000000] µs, got {w!r}")
        if self.cpu_wakeup_scope not in ("always", "epochs"):
            raise ValueError(f"cpu_wakeup_scope must be \"always\" or \"epochs\", got {self.cpu_wakeup_scope!r}")
        if self.cpu_wakeup_scope == "epochs" and w >= 0 and self.rehearsal_lead_s == 0.0:
            raise ValueError("cpu_wakeup_scope \"epochs\" needs the rehearsals (rehearsal_lead_s > 0): they "
                             "open each epoch's window; without them cpu_wakeup_scope = \"always\" or "
                             "cpu_wakeup_latency_us = -1")


@dataclass(frozen=True)
class HealthConfig:
    """``sensor_timeout_s``: a sensor silent longer than this (data time) is reported
    stale. ``queue_size``: the runner's input queue bound (overflow counted)."""

    sensor_timeout_s: float = 10.0
    queue_size: int = 10000

    def validate(self) -> None:
        if not 0.0 < self.sensor_timeout_s <= 3600.0:
            raise ValueError(f"sensor_timeout_s must be within (0, 3600] s, got {self.sensor_timeout_s!r}")
        _check_queue_size("queue_size", self.queue_size)  # 0 would make queue.Queue unbounded


@dataclass(frozen=True)
class PersistenceConfig:
    """``period_s``: how often (wall seconds) learned state is written; also on shutdown."""

    period_s: float = 30.0

    def validate(self) -> None:
        if not 0.1 <= self.period_s <= 86400.0:  # each save is an fsync
            raise ValueError(f"period_s must be within [0.1, 86400] s, got {self.period_s!r}")


@dataclass(frozen=True)
class FoxgloveConfig:
    """``[foxglove]``: a live Foxglove WebSocket server (off by default; loopback unless
    ``host`` says otherwise) with the solution in Foxglove's well-known schemas
    (:mod:`adaptnav.service.runtime.foxglove`). ``port`` 0 = any free port (logged)."""

    enabled: bool = False
    host: str = "127.0.0.1"
    port: int = 8765

    def validate(self) -> None:
        if not 0 <= self.port <= 65535:
            raise ValueError("port must be within [0, 65535]")
        if not self.host:
            raise ValueError("host must not be empty")


@dataclass(frozen=True)
class ServiceConfig:
    """The whole live-service configuration (see module docstring)."""

    vehicle: VehicleConfig = field(default_factory=VehicleConfig)
    zenoh: ZenohConfig = field(default_factory=ZenohConfig)
    mavlink: MavlinkConfig = field(default_factory=MavlinkConfig)
    origin: OriginConfig = field(default_factory=OriginConfig)
    filter: FilterConfig = field(default_factory=FilterConfig)
    motion: MotionConfig = field(default_factory=MotionConfig)
    calibrator: CalibratorSection = field(default_factory=CalibratorSection)
    outputs: OutputsConfig = field(default_factory=OutputsConfig)
    health: HealthConfig = field(default_factory=HealthConfig)
    persistence: PersistenceConfig = field(default_factory=PersistenceConfig)
    foxglove: FoxgloveConfig = field(default_factory=FoxgloveConfig)
    state_dir: str = "/var/lib/adaptnav"

    def resolved(self, autopilot_thrust: bool) -> "ServiceConfig":
        """This configuration with the "auto" choices that depend on the vehicle class decided.

        ``autopilot_thrust``: the thrust comes from an autopilot's outputs (a MAVLink or
        DataFlash log, the live MAVLink bridge) — ArduSub's vectored ROVs, whose hull may crab on
        a straight (lateral thrusters, a tether): ``filter.dvl.hull_sideslip`` "auto" → "free";
        otherwise (propeller RPM, a torpedo AUV) → "none"; and the filter's figures an
        uncalibrated motion prior raises (:meth:`MotionConfig.prior_filter`). Idempotent.
        """
        filt = self.filter
        if filt.dvl.hull_sideslip == "auto":
            filt = replace(filt, dvl=replace(filt.dvl, hull_sideslip="free" if autopilot_thrust else "none"))
        # and what an uncalibrated motion prior leaves unknown (MotionConfig.prior_filter)
        filt = self.motion.prior_filter(filt, self.motion.initial_params(autopilot_thrust)[1])
        return replace(self, filter=filt)

    def validate(self) -> None:
        lv, rate_hz = self.filter.learned_velocity, self.outputs.nav_rate_hz
        if lv.enabled and any(_near_grid(k / lv.rate_hz + lv.phase_s, 1.0 / rate_hz) for k in range(100)):
            # allowed (the numbers are right), but an update then may run in an epoch's own IMU
            # sample, before its state is published: on its latency path
            log.warning("filter.learned_velocity.phase_s = %g s puts updates at or next to the output epochs of "
                        "outputs.nav_rate_hz = %g Hz (each then delays that nav state)%s", lv.phase_s, rate_hz,
                        f"; {0.5 / rate_hz:g} s lies between them" if lv.rate_hz <= rate_hz else "")
        # a DVL delta is valid dvl_latency_s before it arrives, a "mean" one another Δt/2
        # earlier (mid-interval): the filter must still hold that past (late measurements are
        # re-fused up to filter.max_delay_s, older ones rejected as too late — every sample of
        # a "mean" DVL slower than 1/(2 max_delay_s) Hz would be, silently but for the count)
        c = self.mavlink.convert
        mean = c.dvl_delta == "mean"
        lag_s = (0.5 * c.dvl_max_interval_s if mean else 0.0) + c.dvl_latency_s
        if lag_s > self.filter.max_delay_s:
            fix = (f"lower mavlink.convert.dvl_max_interval_s to {2.0 * (self.filter.max_delay_s - c.dvl_latency_s):g} "
                   f"(the longest DVL interval it accepts)" if mean and self.filter.max_delay_s > c.dvl_latency_s
                   else "lower mavlink.convert.dvl_latency_s")
            raise ValueError(
                f"mavlink.convert.dvl_delta = \"{c.dvl_delta}\" places a DVL sample up to "
                f"{'dvl_max_interval_s/2 + ' if mean else ''}dvl_latency_s = {lag_s:g} s before it arrives, beyond "
                f"filter.max_delay_s = {self.filter.max_delay_s:g} s (older samples are rejected as too late): raise "
                f"filter.max_delay_s to {lag_s:g} or {fix}")


def _near_grid(t_s: float, period_s: float) -> bool:
    """Whether ``t_s`` lies near a whole multiple of ``period_s``: within 10 ms (an IMU sample
    or two: the epoch's own sample is the one nearest it) or a quarter of the period."""
    return abs(math.remainder(t_s, period_s)) < min(0.01, 0.25 * period_s)


def read_config_file(path: str | Path) -> dict:
    """The raw TOML tree of a config file; :class:`ConfigError` (one line) when it is
    missing, unreadable, not text or not TOML."""
    import tomllib

    try:
        return tomllib.loads(Path(path).read_text())
    except FileNotFoundError as e:
        raise ConfigError(f"config file {path}: not found") from e
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"config file {path}: TOML syntax: {e}") from e
    except UnicodeDecodeError as e:  # a binary or foreign file
        raise ConfigError(f"config file {path}: not a text (UTF-8) TOML file ({e.reason} at byte {e.start})") from e
    except OSError as e:
        raise ConfigError(f"config file {path}: {e.strerror or e}") from e


def load_config(path: str | Path | None = None, overrides: list[str] | tuple[str, ...] = ()) -> ServiceConfig:
    """Load ``path`` (TOML; ``None`` = all defaults), apply ``overrides``, validate.

    Raises
    ------
    ConfigError
        With the offending dotted key in the message.
    """
    raw: dict = read_config_file(path) if path is not None else {}
    return build(ServiceConfig, apply_overrides(raw, list(overrides)))


def config_dict(cfg: ServiceConfig) -> dict:
    """Effective config as plain data (for the log, the ``query/config`` queryable)."""
    return as_dict(cfg)


def log_effective(cfg: ServiceConfig) -> None:
    """One INFO line of what matters to an operator; the whole effective config at DEBUG."""
    z = cfg.zenoh
    log.info("config: vehicle %s; zenoh %s%s%s; mavlink %s; calibrator %s; foxglove %s; state in %s",
             cfg.vehicle.name, z.mode, f" listen {','.join(z.listen)}" if z.listen else "",
             f" connect {','.join(z.connect)}" if z.connect else "",
             cfg.mavlink.url if cfg.mavlink.enabled else "off",
             cfg.calibrator.location if cfg.calibrator.enabled else "off",
             f"ws://{cfg.foxglove.host}:{cfg.foxglove.port}" if cfg.foxglove.enabled else "off", cfg.state_dir)
    log.debug("effective config: %s", json.dumps(config_dict(cfg), sort_keys=True))
