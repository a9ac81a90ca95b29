"""The vehicle end (`roadgrip edge`, docs/EDGE.md): the estimator runs next to the car's bus and the car sends friction
observations and a sparse heartbeat (CONTRACTS 3.7) instead of its raw telemetry.

| module | owns |
| --- | --- |
| agent.py | estimator, passes, observations and heartbeats of one vehicle; its estimator state on disk |
| outbox.py | the disk-backed outbox (SQLite): kept until PUBACKed, its limit |
| uplink.py | the MQTT uplink (paho-mqtt, QoS 1, persistent session) that empties the outbox |
| sources.py | samples from wire-format lines, a recorded log, a live CAN interface (python-can) |
| run.py | one run of an agent over a source |

Imports: of the cloud, only what the car shares with it: the domain (cells, passes, observations), the topic names
(cloud/transport/mqtt.py) and the wire parser (cloud/ingest/wire.py); the cloud never imports this package
(tests/test_layers.py).
"""
