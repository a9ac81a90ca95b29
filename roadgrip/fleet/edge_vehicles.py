"""Edge vehicles in a simulated fleet (`roadgrip fleet --mode edge|mixed`, `roadgrip demo --mode edge`): each vehicle
runs the vehicle end (roadgrip/edge/: `EdgeAgent` with its own estimator and a disk-backed `Outbox`) on its simulated
samples and sends friction observations and heartbeats (CONTRACTS 3.7) through the edge package's own `Uplink`
(paho-mqtt, QoS 1, persistent session), logged in with the credentials `register_fleet` issued: the same
registration as a raw vehicle's, only the sending differs.

`send(vehicle_id, samples)` feeds a batch of the vehicle's samples (its simulated 10 Hz, as the replay paces them)
into its agent and pumps its uplink; `close(timeout_s)` is ignition off for every vehicle (the pass in progress, a
last heartbeat, the estimator state), then waits for the outboxes to empty. Counts in messages: `counts` per vehicle
(`EdgeCounts`); `lost` is what was dropped at the outbox's limit, refused by the broker, or still waiting at the end.
"""

from __future__ import annotations

import shutil
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

from roadgrip.edge.agent import EdgeAgent
from roadgrip.edge.outbox import Outbox
from roadgrip.edge.uplink import Uplink
from roadgrip.estimators.learned import load_estimator
from roadgrip.fleet.transport import CONNECT_TIMEOUT_S, MAX_MQTT_VEHICLES, FleetError, protocol_of
from roadgrip.vehicle.params import VEHICLES, VehicleParams

DRAIN_STEP_S = 0.01


@dataclass
class EdgeCounts:
    """One edge vehicle: samples fed to its agent, observations and heartbeats it made, messages handed to the
    broker (`sent`, repeats after a reconnect included), and at the end `pending` (still in the outbox), `dropped`
    (pushed out at the outbox's limit) and `refused` (a PUBACK with a failure reason code)."""

    samples: int = 0
    observations: int = 0
    heartbeats: int = 0
    sent: int = 0
    pending: int = 0
    dropped: int = 0
    refused: int = 0

    @property
    def lost(self) -> int:
        return self.pending + self.dropped + self.refused


def profile_of(profile: str | dict | VehicleParams) -> VehicleParams:
    """A registration's profile (a shipped vehicle's name or a CONTRACTS 3.2 mapping) as the agent's VehicleParams."""
    if isinstance(profile, VehicleParams):
        return profile
    if isinstance(profile, dict):
        return VehicleParams.from_dict(profile)
    if profile not in VEHICLES:
        raise ValueError(f"vehicle profile must be one of {sorted(VEHICLES)} or a mapping, got {profile!r}")
    return VEHICLES[profile]


class EdgeTerminals:
    """Edge vehicles (module docstring). `mqtt_url`: one broker or a list (vehicle k uses the (k mod n)-th: the
    edge uplink keeps one broker, its persistent session lives there). `protocol`: "5", "3.1.1" or "auto" (MQTT 5,
    else 3.1.1 when the broker does not take 5: RabbitMQ 3.10), found once with the first vehicle's login, as
    roadgrip/fleet/transport.py `MqttTerminals` does. `profiles`: vehicle_id -> profile.
    `state_dir`: where each vehicle keeps its outbox and estimator state (a temporary folder, removed at `close`,
    when None). Returns once every uplink has connected (FleetError otherwise)."""

    def __init__(
        self,
        mqtt_url: str | list[str],
        secrets: dict[str, str],
        profiles: dict,
        *,
        estimator: str = "pmf",
        protocol: str = "5",
        resolution: int = 10,
        state_dir: Path | None = None,
        connect_timeout_s: float = CONNECT_TIMEOUT_S,
    ):
        if len(secrets) > MAX_MQTT_VEHICLES:
            raise ValueError(f"at most {MAX_MQTT_VEHICLES} MQTT vehicles in one process, got {len(secrets)} edge ones")
        urls = [mqtt_url] if isinstance(mqtt_url, str) else list(mqtt_url)
        if not urls:
            raise ValueError("mqtt_url must name at least one broker, got an empty list")
        if protocol == "auto" and secrets:
            protocol = protocol_of(urls, *next(iter(secrets.items())))
        self.protocol = protocol
        self._scratch = state_dir is None
        self.state_dir = Path(tempfile.mkdtemp(prefix="roadgrip-edge-fleet-")) if state_dir is None else state_dir
        self.agents: dict[str, EdgeAgent] = {}
        self.uplinks: dict[str, Uplink] = {}
        self._closed = False
        self._counts: dict[str, EdgeCounts] | None = None  # the last count, kept once closed
        for k, (vid, secret) in enumerate(secrets.items()):
            folder = self.state_dir / vid
            outbox = Outbox(folder / "outbox.sqlite")
            self.agents[vid] = EdgeAgent(
                vid,
                profile_of(profiles[vid]),
                load_estimator(estimator),
                outbox,
                state_path=folder / "estimator-state.json",
                resolution=resolution,
            )
            uplink = Uplink(urls[k % len(urls)], vid, secret, outbox, protocol=protocol)
            uplink.start()
            self.uplinks[vid] = uplink
        deadline = time.monotonic() + connect_timeout_s
        for vid, uplink in self.uplinks.items():
            if not uplink.wait_connected(max(0.0, deadline - time.monotonic())):
                self._stop()
                raise FleetError(
                    f"edge vehicle {vid} did not connect to {uplink.url} within {connect_timeout_s:.0f} s "
                    "(refused login or no broker: see the log)"
                )

    def send(self, vehicle_id: str, samples: list[dict]) -> None:
        agent, uplink = self.agents[vehicle_id], self.uplinks[vehicle_id]
        for sample in samples:
            agent.feed(sample)
        if agent.outbox.pending > uplink.inflight:
            uplink.pump()

    def close(self, timeout_s: float = 60.0) -> None:
        """Ignition off for every vehicle, then up to `timeout_s` for the outboxes to empty (module docstring)."""
        if self._closed:
            return
        for agent in self.agents.values():
            agent.finish()
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            waiting = [vid for vid, agent in self.agents.items() if agent.outbox.pending]
            if not waiting:
                break
            for vid in waiting:
                self.uplinks[vid].pump()
            time.sleep(DRAIN_STEP_S)
        self._counts = self._count()
        self._stop()

    @property
    def counts(self) -> dict[str, EdgeCounts]:
        return self._count() if self._counts is None else self._counts

    @property
    def lost(self) -> int:
        return sum(c.lost for c in self.counts.values())

    def _count(self) -> dict[str, EdgeCounts]:
        out = {}
        for vid, agent in self.agents.items():
            uplink = self.uplinks[vid]
            out[vid] = EdgeCounts(
                samples=agent.samples,
                observations=agent.observations,
                heartbeats=agent.heartbeats,
                sent=uplink.sent_messages,
                pending=agent.outbox.pending,
                dropped=agent.outbox.dropped,
                refused=uplink.refused,
            )
        return out

    def _stop(self) -> None:
        self._closed = True
        for uplink in self.uplinks.values():
            uplink.close()
        for agent in self.agents.values():
            agent.outbox.close()
        if self._scratch:
            shutil.rmtree(self.state_dir, ignore_errors=True)


MODES = ("raw", "edge", "mixed")


def edge_vehicle_ids(vehicle_ids: list[str], mode: str) -> set[str]:
    """The vehicles of a fleet that run the vehicle end: none in raw mode, all in edge mode, every other one (the
    second, fourth, ... in the given order) in mixed mode."""
    if mode not in MODES:
        raise ValueError(f"mode must be one of {list(MODES)}, got {mode!r}")
    if mode == "raw":
        return set()
    return set(vehicle_ids if mode == "edge" else vehicle_ids[1::2])
