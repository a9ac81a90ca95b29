"""The cloud: telemetry in, estimates stored, a friction map and warnings out. One folder per role; the embedded
default (`roadgrip serve`) and the cluster mode (`roadgrip worker`, `roadgrip api`, docs/CLUSTER.md) run the same
code of each role and differ only in how messages arrive and who owns which vehicles.

| folder | role | embedded default | cluster mode |
| --- | --- | --- | --- |
| edge/ | vehicles in: MQTT broker, payload parsing, credentials, rate limit, admission | Mosquitto started here (broker.py) | RabbitMQ nodes, keyed partition queues (rabbitmq.py) |
| worker/ | per-vehicle pipeline: reorder, estimator, checkpoints, storage writes | in this process or shards over processes (shards.py) | `roadgrip worker`, one active consumer per partition (consumer.py) |
| fanout/ | friction map, warnings, roadside stations, publishing | in this process | by region |
| api/ | HTTP API, dashboard, exports | in serve | `roadgrip api` replicas |
| storage/ | SQLite or PostgreSQL: telemetry, estimates, warnings, credentials, estimator states | SQLite | PostgreSQL |

Beside them: settings.py (one typed settings class for every role), service.py (the embedded default assembled),
metrics.py (Prometheus), process.py, bench.py and latency.py (the service's benchmarks).
"""
