"""The cloud: telemetry in, estimates stored, a friction map and warnings out, laid out by layer (docs/ARCHITECTURE.md;
tests/test_layers.py fails when an import breaks the layers).

| folder | layer | holds |
| --- | --- | --- |
| domain/ | pure core | what a pass is, cells, the friction map, the warning engine, roadside stations |
| formats/ | pure | GeoJSON, DATEX II v3, ETSI DENM from the domain's objects |
| settings.py, metrics.py, process.py, localhost.py | infrastructure | typed settings, Prometheus, process set-up, ports |
| storage/ | storage | one schema, Alembic migrations, a repository per table group, the Storage facade |
| transport/ | transport | MQTT topics and client, the managed Mosquitto, RabbitMQ topology and connections |
| pipeline/ | processing | per-vehicle estimation, estimator checkpoints, the fan-out to map, warnings and topics |
| ingest/ | admission | the wire format parser, credentials, the rate limit, hand-off to the pipeline |
| api/ | HTTP | a FastAPI router per resource over a backend interface, the dashboard |
| serve/ | assembly | `roadgrip serve`: everything in one process, or vehicles sharded over ingest processes |
| cluster/ | assembly | `roadgrip worker`, the region fan-out, the API replica's backend, `roadgrip cluster up` |

The embedded default and the cluster run the same domain, pipeline, estimator and storage code; they differ only in how
messages arrive and who owns which vehicles and regions.
"""
