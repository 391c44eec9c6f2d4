"""An authenticated, encrypted bus: the "vehicle" profile (deploy/adaptnav-secure.toml) on
loopback ``tls/127.0.0.1:<port>``, scouting off, with a CA and certificates made here.

- the profile's TLS, user/password and access-control settings reach the Zenoh session
  config, and the router config in deploy/ carries the same rules;
- mutual TLS: a peer without a certificate, or with one from another CA, cannot connect; a
  peer with a certificate from the vehicle's CA can, and its samples arrive;
- user/password: a wrong password is refused, the right one accepted;
- access control on the real daemon (remote calibrator): a peer the rules do not name may
  read and query, but its release and its samples never reach the daemon, while the named
  calibrator's release and the named driver's sample do (and the release is applied).

Ordering without sleeps: a Zenoh session sends a put and then a query over the same link, and
the daemon's session handles them in that order, so when the query's answer is back the put
has been delivered to the daemon's subscriber — or dropped by the access control.
"""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest
import zenoh

from adaptnav.calibration.online import Release
from adaptnav.fusion.motion_model import MotionParams
from adaptnav.fusion.samples import DepthSample, HeadingSample
from adaptnav.service.config import ZenohAuthConfig, ZenohConfig, ZenohTlsConfig, config_dict, load_config
from adaptnav.service.daemon import Daemon
from adaptnav.service.transport import codec
from adaptnav.service.transport.bus import Bus, zenoh_config

from .test_daemon_support import free_port, wait_until

# a declared test dependency (pyproject [test]); a venv made before it was added skips with
# the command that fixes it instead of failing the whole run at collection
pytest.importorskip("cryptography", reason="pip install -e '.[test]' (cryptography makes the test certificates)")
from .tls_certs import Authority  # noqa: E402

pytestmark = pytest.mark.timeout(150)

DEPLOY = Path(__file__).resolve().parents[2] / "deploy"
VEHICLE = "testauv"


@pytest.fixture
def pki(tmp_path):
    return Authority(tmp_path / "pki")


def secure_config(pki: Authority, port: int, state_dir: Path, *extra: str):
    """The vehicle profile as shipped, with this test's certificates and port."""
    pem, key = pki.issue("adaptnav-daemon")
    return load_config(DEPLOY / "adaptnav-secure.toml", [
        f'zenoh.listen=["tls/127.0.0.1:{port}"]', f'zenoh.tls.root_ca_certificate="{pki.ca_pem}"',
        f'zenoh.tls.listen_certificate="{pem}"', f'zenoh.tls.listen_private_key="{key}"',
        f'zenoh.tls.connect_certificate="{pem}"', f'zenoh.tls.connect_private_key="{key}"',
        f'state_dir="{state_dir}"', f"vehicle.name={VEHICLE}", *extra])


def program(cfg, cert: tuple[str, str] | None, ca_pem: str | None = None, timeout_s: float = 30.0) -> Bus:
    """Another program joining the daemon's bus as a client: with its own certificate, or
    with none (it only trusts ``ca_pem``, default the vehicle's CA)."""
    tls = cfg.zenoh.tls
    if cert is None:
        tls = ZenohTlsConfig(root_ca_certificate=ca_pem or tls.root_ca_certificate)
    else:
        tls = dataclasses.replace(tls, connect_certificate=cert[0], connect_private_key=cert[1])
    return Bus(dataclasses.replace(cfg.zenoh.as_client(), tls=tls, connect_timeout_s=timeout_s), VEHICLE)


def refused(make) -> bool:
    try:
        bus = make()
    except zenoh.ZError:
        return True
    bus.close()
    return False


def release(k_v: float, t_s: float = 10.0) -> bytes:
    return codec.encode(Release(t_s=t_s, params=MotionParams(k_v=k_v), log_likelihood=0.0, accepted=True,
                                reason="", iterations=1))


def test_profile_passes_tls_auth_and_access_control_to_zenoh(pki, tmp_path):
    cfg = secure_config(pki, 7447, tmp_path)
    z = zenoh_config(cfg.zenoh)
    tls = json.loads(z.get_json("transport/link/tls"))
    assert tls["enable_mtls"] is True and tls["root_ca_certificate"] == pki.ca_pem
    assert tls["listen_certificate"].endswith("adaptnav-daemon.pem")
    acl = json.loads(z.get_json("access_control"))
    assert acl["enabled"] is True and acl["default_permission"] == "deny"
    publishers = {p["subjects"][0]: p["rules"] for p in acl["policies"]}
    assert publishers["calibrators"] == ["publish_releases"] and publishers["sensor_drivers"] == ["publish_sensors"]
    # the router in deploy/ enforces exactly the profile's rules
    router = zenoh.Config.from_file(str(DEPLOY / "zenoh-router-secure.json5"))
    assert json.loads(router.get_json("access_control")) == acl
    assert json.loads(router.get_json("transport/link/tls/enable_mtls")) is True
    # user/password: the password comes from its file into the session, never into the config
    (tmp_path / "pw").write_text("s3cret\n")
    with_user = dataclasses.replace(cfg.zenoh, auth=ZenohAuthConfig(user="sonar-driver",
                                                                    password_file=str(tmp_path / "pw")))
    usrpwd = json.loads(zenoh_config(with_user).get_json("transport/auth/usrpwd"))
    assert (usrpwd["user"], usrpwd["password"]) == ("sonar-driver", "s3cret")
    assert "s3cret" not in json.dumps(config_dict(dataclasses.replace(cfg, zenoh=with_user)))
    # the programs that join the bus (recorder, calibrator node) keep the TLS and user identity
    # as clients; the access control stays with the listener that enforces it
    from adaptnav.service.commands.record import recorder_zenoh

    joined = recorder_zenoh(dataclasses.replace(cfg, zenoh=with_user))
    assert (joined.mode, joined.listen, joined.connect) == ("client", (), cfg.zenoh.listen)
    assert joined.tls == cfg.zenoh.tls and joined.auth == with_user.auth and not joined.access_control.enabled


def test_mutual_tls_refuses_a_peer_without_a_certificate_and_accepts_one_with_it(pki, tmp_path):
    cfg = secure_config(pki, free_port(), tmp_path)
    daemon_bus = Bus(cfg.zenoh, VEHICLE)  # the daemon's session, as the daemon opens it
    got: list = []
    daemon_bus.subscribe_samples(got.append)
    try:
        assert refused(lambda: program(cfg, None, timeout_s=1.0)), "a peer without a certificate got in"
        other_ca = Authority(tmp_path / "other")
        assert refused(lambda: program(cfg, other_ca.issue("sonar-driver"), other_ca.ca_pem, timeout_s=1.0)), \
            "a certificate from another CA was accepted"
        plain = dataclasses.replace(cfg.zenoh.as_client(), tls=ZenohTlsConfig(), connect_timeout_s=1.0,
                                    connect=tuple(e.replace("tls/", "tcp/") for e in cfg.zenoh.listen))
        assert refused(lambda: Bus(plain, VEHICLE)), "plain TCP reached the TLS listener"
        driver = program(cfg, pki.issue("sonar-driver"))
        try:
            assert driver.wait_subscribed(driver.keys.sensor("depth"), 30)
            driver.publish_sample(DepthSample(5.0, 150_000.0))
            assert wait_until(lambda: got, 30), "the certified driver's sample did not arrive"
        finally:
            driver.close()
    finally:
        daemon_bus.close()
    assert got == [DepthSample(5.0, 150_000.0)]


def test_user_password_refuses_a_wrong_password(tmp_path):
    port = free_port()
    (tmp_path / "users").write_text("sonar-driver:s3cret\n")
    (tmp_path / "good").write_text("s3cret\n")
    (tmp_path / "bad").write_text("guess\n")
    listener = Bus(ZenohConfig(listen=(f"tcp/127.0.0.1:{port}",),
                               auth=ZenohAuthConfig(dictionary_file=str(tmp_path / "users"))), VEHICLE)

    def client(password_file: str, timeout_s: float) -> Bus:
        return Bus(ZenohConfig(mode="client", connect=(f"tcp/127.0.0.1:{port}",), listen=(),
                               connect_timeout_s=timeout_s,
                               auth=ZenohAuthConfig(user="sonar-driver", password_file=password_file)), VEHICLE)

    try:
        assert refused(lambda: client(str(tmp_path / "bad"), 1.0)), "a wrong password was accepted"
        assert not refused(lambda: client(str(tmp_path / "good"), 30.0)), "the right password was refused"
    finally:
        listener.close()


def test_access_control_keeps_an_unnamed_peers_release_and_samples_from_the_daemon(pki, tmp_path):
    cfg = secure_config(pki, free_port(), tmp_path / "state", "calibrator.location=remote",
                        "health.sensor_timeout_s=3600")
    daemon = Daemon(cfg)
    daemon.start()
    buses: list[Bus] = []
    try:
        intruder = program(cfg, pki.issue("recorder"))  # certified, but named nowhere in the rules
        buses.append(intruder)
        # it may read: it sees the daemon's subscriptions and queryables, and gets answers
        assert intruder.wait_subscribed(intruder.keys.params, 30)
        assert intruder.wait_subscribed(intruder.keys.sensor("depth"), 30)
        intruder.put(intruder.keys.params, release(k_v=1.2))
        intruder.publish_sample(DepthSample(5.0, 150_000.0))
        assert intruder.get("config", 10.0) is not None  # answered after the puts were handled
        assert daemon.calibrator.received == 0, "the unnamed peer's release reached the daemon"

        calibrator = program(cfg, pki.issue("adaptnav-calibrator"))
        driver = program(cfg, pki.issue("sonar-driver"))
        buses += [calibrator, driver]
        assert calibrator.wait_subscribed(calibrator.keys.params, 30)
        calibrator.put(calibrator.keys.params, release(k_v=1.1))
        # the release's subscriber callback may still be running when the query is answered
        # (Zenoh serves them on different threads): wait for it, bounded
        assert wait_until(lambda: daemon.calibrator.received == 1, 30), \
            "the named calibrator's release did not reach the daemon"
        assert driver.wait_subscribed(driver.keys.sensor("depth"), 30)
        driver.publish_sample(DepthSample(6.0, 150_000.0))
        # the runner applies held releases after a sample the calibrator uses
        driver.publish_sample(HeadingSample(6.0, 0.3))
        applied = wait_until(lambda: daemon.params.k_v == pytest.approx(1.1), 30)
        health = daemon._health_report()
    finally:
        for bus in buses:
            bus.close()
        daemon.stop()
    assert applied, f"the named calibrator's release was not applied: k_v {daemon.params.k_v}"
    # the runner takes its queue in order: had the intruder's sample got in, it would count too
    assert health["sensors"]["depth"]["count"] == 1
    assert health["calibrator"]["releases"] == 1 and health["calibrator"]["last_release"]["params"]["k_v"] == 1.1


def test_only_named_nodes_answer_queries_through_the_daemon(pki, tmp_path):
    """The calibrator node's status queryable is reachable through the daemon; a queryable an
    unnamed peer declares (e.g. a fake ``query/state``) is not routed to anyone."""
    cfg = secure_config(pki, free_port(), tmp_path)
    daemon_bus = Bus(cfg.zenoh, VEHICLE)
    buses = [program(cfg, pki.issue(cn)) for cn in ("adaptnav-calibrator", "recorder", "impostor")]
    node, reader, impostor = buses
    try:
        node.queryable("calibrator", lambda: json.dumps({"type": "calibrator_status", "ok": True}).encode())
        impostor.queryable("state", lambda: json.dumps({"type": "nav_state", "valid": True}).encode())
        assert reader.wait_queryable("calibrator", 30)
        assert reader.get("calibrator", 10.0) == {"type": "calibrator_status", "ok": True}
        assert not reader.wait_queryable("state", 2.0), "an unnamed peer's queryable was routed"
        assert reader.get("state", 1.0) is None
    finally:
        for bus in (*buses, daemon_bus):
            bus.close()
