"""Ports on 127.0.0.1 for the servers roadgrip starts itself (Mosquitto, PostgreSQL, RabbitMQ nodes, the service):
one owner for picking free ports and waiting for a listener, used by transport, storage and the assemblies alike.

A port is picked outside the kernel's ephemeral range (net.ipv4.ip_local_port_range). A port the OS hands out for
`bind(("", 0))` comes from that range, and so does the source port of every outgoing connection: between picking such
a port and the server binding it, any client on the machine may take it (a CI run lost a service start so). Outside
the range only another explicit pick can collide, and picks are drawn at random from thousands of ports."""

from __future__ import annotations

import secrets
import socket
import time
from pathlib import Path

HOST = "127.0.0.1"
EPHEMERAL_RANGE_FILE = Path("/proc/sys/net/ipv4/ip_local_port_range")
LINUX_EPHEMERAL_RANGE = (32768, 60999)  # the kernel's default, where the file cannot be read
LOWEST_PORT = 10000  # below: the registered ports of well-known services (PostgreSQL 5432, epmd 4369, AMQP 5672)
MIN_POOL = 2000  # the fewest ports a side of the ephemeral range must offer to be drawn from
MAX_TRIES = 200


def ephemeral_range(path: Path = EPHEMERAL_RANGE_FILE) -> tuple[int, int]:
    """The kernel's ephemeral port range, both ends included."""
    try:
        low, high = (int(v) for v in path.read_text().split())
        return low, high
    except (OSError, ValueError):
        return LINUX_EPHEMERAL_RANGE


def pick_pool(ephemeral: tuple[int, int]) -> range:
    """The ports to draw from: the larger side of `ephemeral` between LOWEST_PORT and 65535; the ephemeral range itself
    when neither side offers MIN_POOL ports."""
    low, high = ephemeral
    below, above = range(LOWEST_PORT, low), range(high + 1, 65536)
    pool = max(below, above, key=len)
    return pool if len(pool) >= MIN_POOL else range(max(low, 1024), high + 1)


def free_port(host: str = HOST) -> int:
    """A TCP port free on `host` now, outside the ephemeral range (another process may still take it before it is
    bound, but no outgoing connection will)."""
    return free_ports(1, host)[0]


def free_ports(n: int, host: str = HOST) -> list[int]:
    """`n` distinct TCP ports free on `host` now, outside the ephemeral range (all held open together while picked)."""
    pool = pick_pool(ephemeral_range())
    socks: list[socket.socket] = []
    try:
        for _ in range(MAX_TRIES):
            if len(socks) == n:
                break
            s = socket.socket()
            try:
                s.bind((host, pool[secrets.randbelow(len(pool))]))
            except OSError:  # taken, or held by another pick of ours
                s.close()
                continue
            socks.append(s)
        if len(socks) < n:
            raise RuntimeError(f"found {len(socks)} of {n} free ports on {host} in {pool} after {MAX_TRIES} tries")
        return [s.getsockname()[1] for s in socks]
    finally:
        for s in socks:
            s.close()


def wait_port(port: int, timeout_s: float, host: str = HOST) -> None:
    """Return once something accepts TCP connections on host:port; TimeoutError after `timeout_s`."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            socket.create_connection((host, port), 0.5).close()
            return
        except OSError:
            time.sleep(0.1)
    raise TimeoutError(f"nothing listens on {host}:{port} after {timeout_s} s")
