"""ManagedBroker against a real Mosquitto: password file format, logins, revocation, restarts."""

import base64
import os
import re
import shutil
import socket
import stat
import subprocess
import sys

import broker_fixtures
import pytest
from broker_fixtures import wait_until

from roadgrip.cloud.transport.mosquitto import INSTALL_HINT, ManagedBroker, password_hash
from roadgrip.cloud.transport.mqtt import BrokerRefused, UserClient, VehicleClient

HASH_RE = re.compile(r"^\$7\$101\$[A-Za-z0-9+/]{16}\$[A-Za-z0-9+/]{86}==$")  # 12-byte salt, 64-byte SHA-512

managed_broker = broker_fixtures.managed_broker  # the fixture


def mosquitto_passwd(path, user, password):
    exe = shutil.which("mosquitto_passwd") or "/usr/bin/mosquitto_passwd"
    if not os.access(exe, os.X_OK):
        pytest.fail(f"mosquitto_passwd is not installed: {INSTALL_HINT}", pytrace=False)
    subprocess.run([exe, "-c", "-b", str(path), user, password], check=True, capture_output=True)
    name, hashed = path.read_text().strip().split(":", 1)
    assert name == user
    return hashed


def test_password_hash_equals_mosquitto_passwd(tmp_path):
    theirs = mosquitto_passwd(tmp_path / "pw", "v1", "s3cret ünïcode")
    iterations, salt_b64 = theirs.split("$")[2:4]
    ours = password_hash("s3cret ünïcode", salt=base64.b64decode(salt_b64), iterations=int(iterations))
    assert ours == theirs
    assert HASH_RE.match(theirs) and HASH_RE.match(password_hash("x"))
    assert password_hash("x") != password_hash("x")  # a fresh salt each time


@pytest.mark.parametrize("kwargs", [{"salt": b"short"}, {"iterations": 0}])
def test_password_hash_rejects_bad_arguments(kwargs):
    with pytest.raises(ValueError, match=next(iter(kwargs))):
        password_hash("x", **kwargs)


def test_logins_we_write_are_accepted_and_others_refused(managed_broker):
    managed_broker.set_user("car-1", "right", "vehicle")
    url = managed_broker.url
    with VehicleClient(url, "car-1", "right").connect():
        pass
    with pytest.raises(BrokerRefused) as wrong:
        VehicleClient(url, "car-1", "wrong").connect()
    with pytest.raises(BrokerRefused) as unknown:
        VehicleClient(url, "car-2", "right").connect()
    with pytest.raises(BrokerRefused) as anonymous:
        UserClient(url, None, None).connect()
    for refused in (wrong, unknown, anonymous):
        assert refused.value.reason_code.value == 0x87  # Not authorized


def test_config_listens_on_loopback_only_and_keeps_secrets_private(managed_broker):
    conf = managed_broker.conf_path.read_text()
    assert f"listener {managed_broker.port} 127.0.0.1\n" in conf
    assert "allow_anonymous false" in conf and "persistence true" in conf
    managed_broker.set_user("car-1", "pw1", "vehicle")
    for name in ("passwd", "acl", "logins.json"):
        assert stat.S_IMODE((managed_broker.workdir / name).stat().st_mode) == 0o600, name
    assert "pw1" not in (managed_broker.workdir / "logins.json").read_text()
    assert managed_broker.url == f"mqtt://127.0.0.1:{managed_broker.port}"


@pytest.mark.parametrize(
    ("args", "match"),
    [
        (("car-1", "pw", "vehicle", "car-2"), "login name is its vehicle_id"),
        (("car/1", "pw", "vehicle"), "name must match"),
        (("car+", "pw", "reader"), "name must match"),
        (("alice", "pw", "reader", "car-1"), "vehicle_id is for role 'vehicle'"),
        (("alice", "pw", "admin"), "role must be one of"),
        (("roadgrip-cloud", "pw", "reader"), "service's own login"),
        (("alice", "", "reader"), "password"),
    ],
)
def test_set_user_rejects_bad_logins(tmp_path, args, match):
    with pytest.raises(ValueError, match=match):
        ManagedBroker(tmp_path).set_user(*args)


def test_set_users_checks_all_then_applies_them_in_one_reload(managed_broker):
    with pytest.raises(ValueError, match="name must match"):
        managed_broker.set_users([("car-1", "pw", "vehicle", None), ("bad/name", "pw", "vehicle", None)])
    assert "car-1" not in managed_broker.users  # nothing applied
    reloads = managed_broker.log_path.read_text().count("Reloading config.")
    managed_broker.set_users(
        [(f"car-{i}", f"pw{i}", "vehicle", f"car-{i}") for i in range(3)] + [("dash", "pw", "reader", None)]
    )
    assert managed_broker.log_path.read_text().count("Reloading config.") == reloads + 1
    for i in range(3):
        with VehicleClient(managed_broker.url, f"car-{i}", f"pw{i}").connect():
            pass


def test_remove_user_refuses_new_connections_and_drops_the_live_one(managed_broker):
    managed_broker.set_user("car-1", "pw1", "vehicle")
    managed_broker.set_user("car-2", "pw2", "vehicle")
    with (
        VehicleClient(managed_broker.url, "car-1", "pw1").connect() as live,
        VehicleClient(managed_broker.url, "car-2", "pw2").connect() as other,
    ):
        assert managed_broker.remove_user("car-1")
        wait_until(lambda: not live.paho.is_connected(), what="car-1 disconnected")
        assert other.paho.is_connected()  # a reload leaves the other logins alone
        other.publish_telemetry(b"still here")
    with pytest.raises(BrokerRefused):
        VehicleClient(managed_broker.url, "car-1", "pw1").connect()
    assert not managed_broker.remove_user("car-1")  # revoking twice is no error
    assert "car-1" not in managed_broker.users


def test_changing_a_password_drops_the_live_connection(managed_broker):
    managed_broker.set_user("car-1", "old", "vehicle")
    with VehicleClient(managed_broker.url, "car-1", "old").connect() as live:
        managed_broker.set_user("car-1", "new", "vehicle")
        wait_until(lambda: not live.paho.is_connected(), what="car-1 disconnected")
    with VehicleClient(managed_broker.url, "car-1", "new").connect():
        pass


def test_restart_keeps_port_logins_and_a_new_broker_keeps_logins(managed_broker, tmp_path):
    managed_broker.set_user("car-1", "pw1", "vehicle")
    port = managed_broker.port
    managed_broker.restart()
    assert managed_broker.port == port and managed_broker.running
    with VehicleClient(managed_broker.url, "car-1", "pw1").connect():
        pass
    managed_broker.stop()
    managed_broker.stop()  # idempotent
    assert not managed_broker.running
    with ManagedBroker(managed_broker.workdir) as again:  # the service restarted: a new object, same directory
        assert again.users == {"car-1": "vehicle", "roadgrip-cloud": "service"}
        with VehicleClient(again.url, "car-1", "pw1").connect():
            pass


def test_start_fails_with_the_log_when_the_port_is_taken(tmp_path):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        broker = ManagedBroker(tmp_path, port=taken.getsockname()[1])
        with pytest.raises(RuntimeError, match="Address already in use"):
            broker.start(timeout_s=5)
        assert not broker.running


def test_the_broker_stops_when_the_process_that_started_it_is_killed(tmp_path):
    script = (
        "import sys, time; from pathlib import Path; from roadgrip.cloud.transport.mosquitto import ManagedBroker; "
        "b = ManagedBroker(Path(sys.argv[1])); b.start(); print(b._process.pid, flush=True); time.sleep(60)"
    )
    parent = subprocess.Popen([sys.executable, "-c", script, str(tmp_path)], stdout=subprocess.PIPE, text=True)
    try:
        broker_pid = int(parent.stdout.readline())
    finally:
        parent.kill()  # SIGKILL: no stop(), no atexit
        parent.wait()
    wait_until(lambda: not _alive(broker_pid), what=f"mosquitto (pid {broker_pid}) gone")
    assert "Saving in-memory database" in (tmp_path / "mosquitto.log").read_text()  # it got SIGTERM: a clean stop


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split(") ")[1][0] != "Z"  # a zombie has exited
    except FileNotFoundError:
        return False
