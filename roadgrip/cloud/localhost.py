"""Ports on 127.0.0.1 for the servers roadgrip starts itself (Mosquitto, PostgreSQL, RabbitMQ nodes, the service):
one owner for picking free ports and waiting for a listener, used by transport, storage and the assemblies alike."""

from __future__ import annotations

import socket
import time

HOST = "127.0.0.1"


def free_port(host: str = HOST) -> int:
    """A TCP port free on `host` now (the OS picks it; another process may still take it before it is bound)."""
    return free_ports(1, host)[0]


def free_ports(n: int, host: str = HOST) -> list[int]:
    """`n` distinct TCP ports free on `host` now (all held open together while the OS picks them)."""
    socks = [socket.socket() for _ in range(n)]
    try:
        for s in socks:
            s.bind((host, 0))
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
