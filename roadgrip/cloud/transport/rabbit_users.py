"""Vehicles' and readers' logins on the RabbitMQ cluster (cluster mode, issue 17 item 4), managed through the broker's
own users and permissions, by the management plugin's HTTP API (rabbitmq_management; httpx).

Why the HTTP API and not `rabbitmqctl`: rabbitmqctl is an Erlang node of its own that must share the cluster's Erlang
cookie and reach the nodes' distribution ports, and starts a virtual machine for every call; the HTTP API needs only a
URL and an administrator's login (what a load balancer or a firewall can give an API replica), answers in
milliseconds, and does what registration and revocation need: one request for a whole fleet's users and permissions
(POST /api/definitions, which merges), deleting users, listing a user's open connections.

What a login may do (the same rules as the Mosquitto ACL of roadgrip/cloud/transport/mosquitto.py, in RabbitMQ's terms). The
MQTT plugin publishes into amq.topic with the topic's '/' as '.' in the routing key (`routing_key`); an MQTT subscription
is a queue `mqtt-subscription-{client id}qos{0|1}` that the plugin declares (configure), binds to amq.topic (write on
the queue, read on amq.topic and, for a topic exchange, topic permission *read* on the binding key, wildcards as sent)
and consumes (read on the queue). A login's MQTT client id must therefore be its name, optionally followed by '-' and 8
hex digits (what `roadgrip.cloud.transport.mqtt.UserClient` and `VehicleClient` use): its subscription queues are the only
queues it may touch. The suffix matters: a CONNECT with a client id in use closes the connection that had it,
whatever the login (measured, docs/CLUSTER.md "Stateless API"), so a bare vehicle id can be taken by another vehicle.

| role | publish (topic write) | subscribe (topic read) |
| --- | --- | --- |
| vehicle | its own telemetry, observations and heartbeat | its own friction and errors topics, the warnings |
| reader | nothing | every vehicle's friction topic, the warnings |

Stations and the admin get no broker login in the cluster: stations report over HTTP there (nothing consumes their
MQTT topic in the cluster yet). The passwords sent are RabbitMQ's salted SHA-256 hashes of the secrets
(`rabbit_password_hashing_sha256`), never the secrets.

Revocation: deleting a user (DELETE /api/users/{name}) refuses its next login and closes its open connections, MQTT
included, on every node (measured on 3.10.8: a vehicle's MQTT 3.1.1 connection on another node than the one whose API
was called was closed 16 ms after the DELETE, and its reconnects were refused with "Bad user name or password";
tests/cloud/cluster/test_api_backend.py holds the API to it).

Also measured on 3.10.8: a vehicle that publishes outside its topic permission, or subscribes with another login's
client id, has its MQTT connection closed by the broker (log: access_refused); a subscription within its permissions
is granted with QoS 1.
"""

from __future__ import annotations

import logging
import re
import threading
from urllib.parse import quote

import httpx

from roadgrip.cloud.transport.amqp import MQTT_EXCHANGE, rabbit_password_hash
from roadgrip.cloud.transport.mqtt import (
    WARNINGS_TOPIC,
    WARNINGS_UPER_TOPIC,
    check_vehicle_id,
    errors_topic,
    friction_topic,
    heartbeat_topic,
    observations_topic,
    telemetry_topic,
)

log = logging.getLogger(__name__)

BROKER_ROLES = ("vehicle", "reader")
TIMEOUT_S = 10.0


class BrokerUnavailable(RuntimeError):
    """The broker did not answer in time (the API answers 503): no management API of the list answered (every node
    down or unreachable; nothing was changed), or no node confirmed a station's evidence (the message says what was
    stored, roadgrip/cloud/cluster/api_backend.py `station_reports`)."""


def routing_key(topic: str) -> str:
    """The AMQP routing key RabbitMQ 3.10's MQTT plugin gives an MQTT topic (and a topic filter its binding key): '/'
    becomes '.' and '+' becomes '*' ('#' stays); a '.' stays a '.' (measured: vehicle car.1's errors topic binds
    with the key roadgrip.v1.vehicles.car.1.errors), so a vehicle id with dots spans several words of the key."""
    return topic.replace("/", ".").replace("+", "*")


def _key_pattern(*topics: str) -> str:
    return "^(" + "|".join(re.escape(routing_key(t)) for t in topics) + ")$"


def permissions(name: str, role: str, vhost: str = "/") -> tuple[dict, dict]:
    """(the vhost permission, the topic permission on amq.topic) of login `name` with `role`, as definitions."""
    check_vehicle_id(name)  # the same rule names every login
    queues = f"mqtt-subscription-{re.escape(name)}(-[0-9a-f]{{8}})?qos[01]"
    if role == "vehicle":
        write = _key_pattern(telemetry_topic(name), observations_topic(name), heartbeat_topic(name))
        read = _key_pattern(friction_topic(name), errors_topic(name), WARNINGS_TOPIC, WARNINGS_UPER_TOPIC)
    elif role == "reader":
        write = "^$"
        # a subscription to roadgrip/v1/vehicles/+/friction binds with the key roadgrip.v1.vehicles.*.friction
        read = (
            "^("
            + re.escape(routing_key(friction_topic("X"))).replace("X", r"[^.]+")
            + "|"
            + re.escape(routing_key(WARNINGS_TOPIC))
            + "|"
            + re.escape(routing_key(WARNINGS_UPER_TOPIC))
            + ")$"
        )
    else:
        raise ValueError(f"broker logins are for roles {BROKER_ROLES}, got {role!r}")
    exchange = re.escape(MQTT_EXCHANGE)
    permission = {
        "user": name,
        "vhost": vhost,
        "configure": f"^{queues}$",
        "write": f"^({exchange}|{queues})$",
        "read": f"^({exchange}|{queues})$",
    }
    topic = {"user": name, "vhost": vhost, "exchange": MQTT_EXCHANGE, "write": write, "read": read}
    return permission, topic


class RabbitUsers:
    """Logins on a RabbitMQ cluster through the management HTTP API of any of its nodes (`management_urls`, tried in
    turn from the last one that answered), as `username` (an administrator). Safe across threads."""

    def __init__(
        self, management_urls: list[str], username: str, password: str, vhost: str = "/", timeout_s: float = TIMEOUT_S
    ):
        if not management_urls:
            raise ValueError("at least one management URL is needed")
        for url in management_urls:
            if not url.startswith(("http://", "https://")):
                raise ValueError(f"a management URL is http(s)://host:port, got {url!r}")
        self.urls = [url.rstrip("/") for url in management_urls]
        self.vhost = vhost
        self._client = httpx.Client(auth=(username, password), timeout=timeout_s)
        self._next = 0
        self._lock = threading.Lock()

    def close(self) -> None:
        self._client.close()

    def _request(self, method: str, path: str, *, json=None, ok: tuple[int, ...] = (200, 201, 204)) -> httpx.Response:
        """`method path` on the first node that answers; BrokerUnavailable when none does (a connection error or a
        5xx from each); RuntimeError naming the status and body for a refusal (4xx) not in `ok`."""
        with self._lock:
            start = self._next
        failures = []
        for k in range(len(self.urls)):
            index = (start + k) % len(self.urls)
            url = self.urls[index] + path
            try:
                response = self._client.request(method, url, json=json)
            except httpx.TransportError as exc:
                failures.append(f"{url}: {exc!r}")
                continue
            if response.status_code >= 500:
                failures.append(f"{url}: {response.status_code} {response.text[:200]}")
                continue
            with self._lock:
                self._next = index
            if response.status_code not in ok:
                raise RuntimeError(f"{method} {url} refused: {response.status_code} {response.text[:300]}")
            return response
        raise BrokerUnavailable(f"no RabbitMQ management API answered {method} {path}: {'; '.join(failures)}")

    def put_logins(self, logins: list[tuple[str, str, str]]) -> None:
        """Create (or replace) the logins (name, secret, role) with their permissions, in one request."""
        users, perms, topics = [], [], []
        for name, secret, role in logins:
            permission, topic = permissions(name, role, self.vhost)
            users.append(
                {
                    "name": name,
                    "password_hash": rabbit_password_hash(secret),
                    "hashing_algorithm": "rabbit_password_hashing_sha256",
                    "tags": "",
                }
            )
            perms.append(permission)
            topics.append(topic)
        if users:
            self._request(
                "POST", "/api/definitions", json={"users": users, "permissions": perms, "topic_permissions": topics}
            )

    def delete_login(self, name: str) -> None:
        """Delete the user: nothing logs in as it any more and its open connections are closed (module docstring).
        Deleting a user that is not there is no error."""
        self._request("DELETE", f"/api/users/{quote(name, safe='')}", ok=(204, 404))

    def delete_logins(self, names: list[str]) -> None:
        """Delete several users in one request (POST /api/users/bulk-delete)."""
        if names:
            self._request("POST", "/api/users/bulk-delete", json={"users": names}, ok=(204,))

    def connections(self, name: str) -> list[dict]:
        """The open connections of user `name` (each a dict of the management API: name, node, protocol, ...)."""
        return self._request("GET", f"/api/connections/username/{quote(name, safe='')}").json()

    def exists(self, name: str) -> bool:
        return self._request("GET", f"/api/users/{quote(name, safe='')}", ok=(200, 404)).status_code == 200

    def ping(self) -> None:
        """BrokerUnavailable unless a node's management API answers as this login."""
        self._request("GET", "/api/whoami")
