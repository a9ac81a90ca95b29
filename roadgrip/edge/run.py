"""One agent's run over one source of samples: each sample into the agent (roadgrip/edge/agent.py), the outbox pumped
to the uplink (roadgrip/edge/uplink.py) as messages wait, and at the end (ignition off, the source exhausted) the
last pass, heartbeat and state, then up to `drain_s` of waiting for the outbox to empty. What is not acknowledged
by then stays in the outbox for the next run."""

from __future__ import annotations

import time
from collections.abc import Iterable
from dataclasses import dataclass

from roadgrip.edge.agent import EdgeAgent
from roadgrip.edge.uplink import Uplink


@dataclass(frozen=True)
class RunSummary:
    samples: int
    estimates: int
    observations: int
    pending: int  # messages left in the outbox
    dropped: int
    sent_messages: int
    sent_payload_bytes: int
    cpu_s: float
    wall_s: float


def run_agent(agent: EdgeAgent, samples: Iterable[dict], uplink: Uplink | None = None, drain_s: float = 10.0):
    """Feed every sample, pumping the uplink; finish; drain (module docstring). The RunSummary."""
    cpu0, wall0 = time.process_time(), time.monotonic()
    outbox = agent.outbox
    for sample in samples:
        agent.feed(sample)
        if uplink is not None and outbox.pending > uplink.inflight:
            uplink.pump()
    agent.finish()
    if uplink is not None:
        deadline = time.monotonic() + drain_s
        while outbox.pending and time.monotonic() < deadline:
            uplink.pump()
            time.sleep(0.01)
    return RunSummary(
        samples=agent.samples,
        estimates=agent.estimates,
        observations=agent.observations,
        pending=outbox.pending,
        dropped=outbox.dropped,
        sent_messages=0 if uplink is None else uplink.sent_messages,
        sent_payload_bytes=0 if uplink is None else uplink.sent_payload_bytes,
        cpu_s=time.process_time() - cpu0,
        wall_s=time.monotonic() - wall0,
    )
