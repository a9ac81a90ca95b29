"""A Mosquitto broker that the service starts and configures itself (`ManagedBroker`), in a working directory of its own.

Files in the working directory (all but logins.json and mosquitto.db rewritten by `start()`):

| file             | what                                                                                        |
| ---------------- | ------------------------------------------------------------------------------------------- |
| mosquitto.conf   | the configuration below                                                                     |
| logins.json      | the vehicle and reader logins (name, role, password hash), mode 0600: they outlive the      |
|                  | process, so a new `ManagedBroker` on the same directory starts with them                    |
| passwd           | one `name:$7$...` line per login (`password_hash`), mode 0600                               |
| acl              | the access rules below, mode 0600                                                           |
| mosquitto.db     | the persistence database: sessions, their subscriptions and queued messages                 |
| mosquitto.log    | the broker's log (connections, refusals, reloads)                                           |
| mosquitto.out    | the broker's stdout and stderr (errors before the log is open, e.g. a bad configuration)    |

Configuration: one listener on 127.0.0.1 only; no anonymous clients; persistence on (saved every `AUTOSAVE_INTERVAL_S`
and on a clean stop, so a crash loses at most that much of the queued messages); up to `max_queued_messages` QoS 1
messages queued per client beyond those in flight, up to MAX_INFLIGHT_MESSAGES in flight. `user` is set to the user
running Python: started as root, Mosquitto would otherwise drop to the `mosquitto` user, which may not reach the
working directory.

Access rules (the ACL file), with the topics of `roadgrip.cloud.transport.mqtt`; nothing else is allowed to anyone:

| login                               | read                                               | write                                      |
| ----------------------------------- | -------------------------------------------------- | ------------------------------------------ |
| the service (`service_user`)        | roadgrip/v1/vehicles/+/telemetry                   | roadgrip/v1/vehicles/+/friction, +/errors, |
|                                     |                                                    | roadgrip/v1/warnings, warnings/uper        |
| a vehicle (login name = vehicle_id) | roadgrip/v1/vehicles/<id>/friction, <id>/errors,   | roadgrip/v1/vehicles/<id>/telemetry,       |
|                                     | roadgrip/v1/warnings, warnings/uper                | <id>/observations, <id>/heartbeat          |
| a reader                            | roadgrip/v1/vehicles/+/friction,                   | -                                          |
|                                     | roadgrip/v1/warnings, warnings/uper                |                                            |
| a station (login name = station_id) | roadgrip/v1/stations/<id>/errors                   | roadgrip/v1/stations/<id>/reports          |

The service also reads roadgrip/v1/stations/+/reports, roadgrip/v1/vehicles/+/observations and +/heartbeat (edge
vehicles, CONTRACTS 3.7), and writes roadgrip/v1/stations/+/errors.

Each login gets a `user` section with its own `topic` lines. `pattern ... %u` lines are not used on purpose: a pattern
applies to every login, so `pattern write roadgrip/v1/vehicles/%u/telemetry` would also let the service and every
reader publish telemetry under their own names. Mosquitto finds a login's section by a linear scan at connect (and for
every connected client on a reload), which is fine for thousands of logins.

Changes to logins (`set_user`, `remove_user`) rewrite the files and reload the broker (SIGHUP); they return once the
reload is done. On a reload Mosquitto 2.0.11 re-checks every live connection: a client whose login was removed, or whose
password changed, is disconnected at once (and refused when it reconnects); ACL changes apply to live connections from
the next message on, because Mosquitto checks the ACL on every publish and every delivery. Other clients stay connected.
The sessions of removed logins stay in the broker until they expire; nothing can be delivered through them.
"""

from __future__ import annotations

import base64
import ctypes
import hashlib
import json
import os
import pwd
import secrets
import shutil
import signal
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Self

from roadgrip.cloud.localhost import free_port
from roadgrip.cloud.transport.mqtt import (
    ERRORS_SUBSCRIPTION,
    FRICTION_SUBSCRIPTION,
    HEARTBEAT_SUBSCRIPTION,
    OBSERVATIONS_SUBSCRIPTION,
    STATION_ERRORS_SUBSCRIPTION,
    STATION_REPORTS_SUBSCRIPTION,
    TELEMETRY_SUBSCRIPTION,
    WARNINGS_TOPIC,
    WARNINGS_UPER_TOPIC,
    BrokerRefused,
    connect_paho,
    errors_topic,
    friction_topic,
    heartbeat_topic,
    observations_topic,
    station_errors_topic,
    station_reports_topic,
    telemetry_topic,
)
from roadgrip.data.telemetry import VEHICLE_ID_RE

INSTALL_HINT = "run `bash scripts/install_system_deps.sh`"
ROLES = ("vehicle", "reader", "station")
SALT_BYTES = 12  # what mosquitto_passwd 2.0 writes
PBKDF2_ITERATIONS = 101  # mosquitto_passwd 2.0's default
# Queued messages per client: one minute of a 1,000-vehicle fleet at 10 Hz, for the service (the one subscriber to all
# telemetry) to restart without losing any. About 0.3 kB each in the broker's memory, so at most about 200 MB.
MAX_QUEUED_MESSAGES = 1_000 * 10 * 60
# QoS 1 messages a client may have unacknowledged, each way (`max_inflight_messages`; to MQTT 5 clients it is the
# Receive Maximum of the CONNACK). Mosquitto's default, 20, caps the service's estimate messages at 20 a round trip,
# against 1,000 a second from 1,000 vehicles. Not more than 100: paho walks its whole window on every PUBACK
# (`Client._update_inflight`), 2.5 % of the service's interpreter time at 1,000. The service's client is set to the same
# (roadgrip.cloud.transport.mqtt.MqttClient, max_inflight).
MAX_INFLIGHT_MESSAGES = 100
AUTOSAVE_INTERVAL_S = 60
STOP_TIMEOUT_S = 10.0
RELOAD_LINE = "Reloading config."
LOGINS_FILE = "logins.json"


def mosquitto_executable() -> str | None:
    """The `mosquitto` program: on PATH, or Debian's /usr/sbin/mosquitto (not on a normal user's PATH)."""
    found = shutil.which("mosquitto")
    if found is None and os.access("/usr/sbin/mosquitto", os.X_OK):
        found = "/usr/sbin/mosquitto"
    return found


def mosquitto_available() -> bool:
    return mosquitto_executable() is not None


def password_hash(password: str, *, salt: bytes | None = None, iterations: int = PBKDF2_ITERATIONS) -> str:
    """The password in Mosquitto 2.0's `$7$` format, as `mosquitto_passwd` writes it:
    `$7$<iterations>$<base64 salt>$<base64 PBKDF2-HMAC-SHA512(password, salt, iterations), 64 bytes>`, with a random
    12-byte salt unless `salt` is given."""
    if not isinstance(password, str) or not password:
        raise ValueError("password must be a non-empty str")
    if salt is None:
        salt = secrets.token_bytes(SALT_BYTES)
    if len(salt) != SALT_BYTES:
        raise ValueError(f"salt must be {SALT_BYTES} bytes, got {len(salt)}")
    if iterations < 1:
        raise ValueError(f"iterations must be >= 1, got {iterations}")
    digest = hashlib.pbkdf2_hmac("sha512", password.encode("utf-8"), salt, iterations)
    return f"$7${iterations}${base64.b64encode(salt).decode()}${base64.b64encode(digest).decode()}"


def _check_name(field: str, name: str) -> None:
    """Login names follow the vehicle_id rule (CONTRACTS 3.1), so that none can break the password or ACL file."""
    if not isinstance(name, str) or VEHICLE_ID_RE.fullmatch(name) is None:
        raise ValueError(f"{field} must match {VEHICLE_ID_RE.pattern}, got {name!r}")


@dataclass(frozen=True)
class _Login:
    password_hash: str
    role: str  # "service", "vehicle", "reader" or "station"


class ManagedBroker:
    """A Mosquitto process of our own on 127.0.0.1, configured from `workdir`; a context manager (start on enter, stop
    on exit). `port=0` picks a free port at the first `start()` and keeps it for restarts. The service logs in as
    `service_user` with `service_password` (a random one unless given)."""

    host = "127.0.0.1"

    def __init__(
        self,
        workdir: Path,
        port: int = 0,
        service_user: str = "roadgrip-cloud",
        service_password: str | None = None,
        *,
        max_queued_messages: int = MAX_QUEUED_MESSAGES,
    ):
        if not 0 <= port <= 65_535:
            raise ValueError(f"port must be in [0, 65535], got {port}")
        _check_name("service_user", service_user)
        if max_queued_messages < 1:
            raise ValueError(f"max_queued_messages must be >= 1, got {max_queued_messages}")
        self.workdir = Path(workdir).resolve()
        self.port = port
        self.service_user = service_user
        self.service_password = service_password or secrets.token_urlsafe(24)
        self.max_queued_messages = max_queued_messages
        self._logins = self._load_logins()
        self._logins[service_user] = _Login(password_hash(self.service_password), "service")
        self._process: subprocess.Popen | None = None

    @property
    def url(self) -> str:
        return f"mqtt://{self.host}:{self.port}"

    @property
    def running(self) -> bool:
        return self._process is not None and self._process.poll() is None

    @property
    def users(self) -> dict[str, str]:
        """Role by login name, the service included."""
        return {name: login.role for name, login in self._logins.items()}

    @property
    def conf_path(self) -> Path:
        return self.workdir / "mosquitto.conf"

    @property
    def log_path(self) -> Path:
        return self.workdir / "mosquitto.log"

    def start(self, timeout_s: float = 10) -> None:
        """Write the configuration, start `mosquitto -c mosquitto.conf` and return once it accepts the service's login.
        RuntimeError, with the end of the broker's log, when it does not come up within `timeout_s`."""
        if self.running:
            return
        executable = mosquitto_executable()
        if executable is None:
            raise RuntimeError(f"mosquitto is not installed: {INSTALL_HINT}")
        self.workdir.mkdir(parents=True, exist_ok=True)
        pick_port = self.port == 0
        for attempt in range(3):  # a port picked free can be taken before mosquitto binds it
            if pick_port:
                self.port = free_port(self.host)
            self._write_config()
            with open(self.workdir / "mosquitto.out", "ab") as out:
                self._process = subprocess.Popen(
                    [executable, "-c", str(self.conf_path)],
                    stdin=subprocess.DEVNULL,
                    stdout=out,
                    stderr=subprocess.STDOUT,
                    start_new_session=True,
                    preexec_fn=_stop_with_parent,  # noqa: PLW1509 (fork-safe: one prctl call)
                )
            try:
                self._wait_ready(timeout_s)
                return
            except RuntimeError:
                self._kill()
                if not (pick_port and attempt < 2 and "Address already in use" in self._output_tail()):
                    raise

    def stop(self) -> None:
        """Stop the broker (SIGTERM: it saves its persistence database first). Idempotent."""
        process, self._process = self._process, None
        if process is None or process.poll() is not None:
            return
        process.terminate()
        try:
            process.wait(STOP_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()

    def restart(self, timeout_s: float = 10) -> None:
        """Stop and start again on the same port, with the same logins and the persisted sessions."""
        self.stop()
        self.start(timeout_s)

    def set_user(self, name: str, password: str, role: str, vehicle_id: str | None = None) -> None:
        """Add a login, or replace one (password and role). A vehicle's login name is its vehicle_id (`vehicle_id`, if
        given, must equal `name`), a station's its station_id; a reader has none. Applies at once when the broker runs (see the module docstring)."""
        self.set_users([(name, password, role, vehicle_id)])

    def set_users(self, logins: list[tuple[str, str, str, str | None]]) -> None:
        """`set_user` for many (name, password, role, vehicle_id) at once, with one reload: a fleet's registration.
        All are checked before any is applied."""
        new = {}
        for name, password, role, vehicle_id in logins:
            new[name] = self._checked_login(name, password, role, vehicle_id)
        self._logins.update(new)
        self._apply()

    def _checked_login(self, name: str, password: str, role: str, vehicle_id: str | None) -> _Login:
        _check_name("name", name)
        if name == self.service_user:
            raise ValueError(f"name {name!r} is the service's own login")
        if role not in ROLES:
            raise ValueError(f"role must be one of {ROLES}, got {role!r}")
        if role == "vehicle":
            if vehicle_id is not None and vehicle_id != name:
                raise ValueError(
                    f"a vehicle's login name is its vehicle_id: got name {name!r}, vehicle_id {vehicle_id!r}"
                )
        elif vehicle_id is not None:
            raise ValueError(f"vehicle_id is for role 'vehicle' only, got {vehicle_id!r} for role {role!r}")
        return _Login(password_hash(password), role)

    def remove_user(self, name: str) -> bool:
        """Revoke a login: new connections are refused and a live one is disconnected at once (when the broker runs).
        False, and nothing done, when there is no such login (revoking twice is not an error)."""
        if name == self.service_user:
            raise ValueError(f"name {name!r} is the service's own login")
        if self._logins.pop(name, None) is None:
            return False
        self._apply()
        return True

    def __enter__(self) -> Self:
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

    # internals

    def _load_logins(self) -> dict[str, _Login]:
        path = self.workdir / LOGINS_FILE
        if not path.exists():
            return {}
        saved = json.loads(path.read_text())
        return {
            name: _Login(entry["password_hash"], entry["role"])
            for name, entry in saved.items()
            if entry["role"] in ROLES
        }

    def _save_logins(self) -> None:
        self.workdir.mkdir(parents=True, exist_ok=True)
        saved = {
            name: {"password_hash": login.password_hash, "role": login.role}
            for name, login in self._logins.items()
            if login.role in ROLES
        }
        _write_private(self.workdir / LOGINS_FILE, json.dumps(saved, indent=1) + "\n")

    def _write_config(self) -> None:
        lines = [
            "# Written by roadgrip.cloud.transport.mosquitto.ManagedBroker on every start; edits are lost.",
            f"user {pwd.getpwuid(os.geteuid()).pw_name}",
            f"listener {self.port} {self.host}",
            "allow_anonymous false",
            f"password_file {self.workdir / 'passwd'}",
            f"acl_file {self.workdir / 'acl'}",
            "persistence true",
            f"persistence_location {self.workdir}/",
            f"autosave_interval {AUTOSAVE_INTERVAL_S}",
            f"max_queued_messages {self.max_queued_messages}",
            f"max_inflight_messages {MAX_INFLIGHT_MESSAGES}",
            f"log_dest file {self.log_path}",
            *(f"log_type {t}" for t in ("error", "warning", "notice", "information")),
            "log_timestamp_format %Y-%m-%dT%H:%M:%S",
            "connection_messages true",
        ]
        self.conf_path.write_text("\n".join(lines) + "\n")
        self._write_logins()

    def _write_logins(self) -> None:
        passwd = "".join(f"{name}:{login.password_hash}\n" for name, login in self._logins.items())
        _write_private(self.workdir / "passwd", passwd)
        _write_private(self.workdir / "acl", self._acl())

    def _acl(self) -> str:
        sections = []
        for name, login in self._logins.items():
            if login.role == "service":
                rules = [
                    ("read", TELEMETRY_SUBSCRIPTION),
                    ("write", FRICTION_SUBSCRIPTION),
                    ("write", ERRORS_SUBSCRIPTION),
                    ("write", WARNINGS_TOPIC),
                    ("write", WARNINGS_UPER_TOPIC),
                    ("read", STATION_REPORTS_SUBSCRIPTION),
                    ("write", STATION_ERRORS_SUBSCRIPTION),
                    ("read", OBSERVATIONS_SUBSCRIPTION),
                    ("read", HEARTBEAT_SUBSCRIPTION),
                ]
            elif login.role == "vehicle":
                rules = [
                    ("write", telemetry_topic(name)),
                    ("write", observations_topic(name)),
                    ("write", heartbeat_topic(name)),
                    ("read", friction_topic(name)),
                    ("read", errors_topic(name)),
                    ("read", WARNINGS_TOPIC),
                    ("read", WARNINGS_UPER_TOPIC),
                ]
            elif login.role == "station":
                rules = [("write", station_reports_topic(name)), ("read", station_errors_topic(name))]
            else:
                rules = [("read", FRICTION_SUBSCRIPTION), ("read", WARNINGS_TOPIC), ("read", WARNINGS_UPER_TOPIC)]
            sections.append(f"# {login.role}\nuser {name}\n" + "".join(f"topic {a} {t}\n" for a, t in rules))
        return "\n".join(sections)

    def _apply(self) -> None:
        """Save the logins; when running, rewrite the broker's files, reload it and return once the reload is done."""
        self._save_logins()
        if not self.running:
            return
        self._write_logins()
        log_size = self.log_path.stat().st_size
        self._process.send_signal(signal.SIGHUP)
        deadline = time.monotonic() + 10
        while RELOAD_LINE not in _read_from(self.log_path, log_size):
            if time.monotonic() > deadline or not self.running:
                raise RuntimeError(f"mosquitto did not reload its logins:\n{self._output_tail()}")
            time.sleep(0.01)
        # Mosquitto logs that line and then reloads, in the same turn of its single-threaded loop: a connection it
        # answers after that line comes after the reload.
        self._probe(timeout_s=10)

    def _wait_ready(self, timeout_s: float) -> None:
        deadline = time.monotonic() + timeout_s
        while True:
            if self._process.poll() is not None:
                raise RuntimeError(f"mosquitto exited with status {self._process.returncode}:\n{self._output_tail()}")
            try:
                self._probe(timeout_s=1.0)  # short: what listens may not be our mosquitto (a port taken)
                return
            except (OSError, TimeoutError):  # not listening yet (a refused login is a RuntimeError: no retry)
                if time.monotonic() > deadline:
                    raise RuntimeError(
                        f"mosquitto not accepting connections on {self.url} after {timeout_s} s:\n{self._output_tail()}"
                    ) from None
                time.sleep(0.02)

    def _probe(self, timeout_s: float) -> None:
        """Log in as the service (a clean session, closed again); RuntimeError when the broker refuses it."""
        try:
            client = connect_paho(
                self.url,
                self.service_user,
                self.service_password,
                timeout_s=timeout_s,
                client_id=f"{self.service_user}-probe-{secrets.token_hex(4)}",
            )
        except BrokerRefused as err:
            raise RuntimeError(f"mosquitto refused the service's login: {err}\n{self._output_tail()}") from err
        client.disconnect()
        client.loop_stop()

    def _kill(self) -> None:
        process, self._process = self._process, None
        if process is not None and process.poll() is None:
            process.kill()
            process.wait()

    def _output_tail(self, lines: int = 30) -> str:
        parts = []
        for path in (self.log_path, self.workdir / "mosquitto.out"):
            if path.exists():
                text = path.read_text(errors="replace").splitlines()[-lines:]
                parts.append(f"--- {path.name}\n" + "\n".join(text))
        return "\n".join(parts) or "(no output)"


_LIBC = ctypes.CDLL(None, use_errno=True)  # looked up here, not in the forked child (no imports between fork and exec)
_PR_SET_PDEATHSIG = 1  # <linux/prctl.h>


def _stop_with_parent() -> None:
    """In the broker's process before exec: SIGTERM when the process that started it dies (Linux), even by SIGKILL,
    so that a killed service leaves no broker behind holding its port; on SIGTERM Mosquitto saves its persistence
    file and exits. Linux ties this to the starting *thread*: start the broker from a thread that lives as long as
    the service (the service starts it from its main thread). One foreign call, no locks taken: safe to run in the
    child of a threaded process."""
    _LIBC.prctl(_PR_SET_PDEATHSIG, signal.SIGTERM)


def _write_private(path: Path, text: str) -> None:
    """Write `text` to `path` (mode 0600) through a temporary file, so that a reload never reads half a file."""
    tmp = path.with_name(path.name + ".tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(text)
    os.replace(tmp, path)


def _read_from(path: Path, offset: int) -> str:
    with open(path, "rb") as f:
        f.seek(offset)
        return f.read().decode(errors="replace")
