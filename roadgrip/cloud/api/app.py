"""The HTTP API (FastAPI; OpenAPI at /docs): `create_app` assembles the routers of roadgrip/cloud/api/routes/ (one per
resource), the dependencies they share (roadgrip/cloud/api/deps.py: the backend, settings, authenticator and metrics
registry on `app.state`) and the one error handler (roadgrip/cloud/api/errors.py). Routes are thin: they parse,
authenticate, check the role, and call the backend (roadgrip/cloud/api/backend.py): the embedded service (`roadgrip
serve`) or the cluster's (`roadgrip api`, any number of replicas on one PostgreSQL and one RabbitMQ cluster:
roadgrip/cloud/cluster/api_backend.py). The same routes serve both; what differs in the cluster is said below the table.

Every call authenticates with HTTP Basic (name and secret; vehicles use their vehicle_id as name):

| route | who | does | routes/ |
| --- | --- | --- | --- |
| POST /v1/vehicles | admin | register a vehicle with its profile (CONTRACTS 3.2); returns its secret once | vehicles.py |
| GET /v1/vehicles/{id} | admin, reader, the vehicle | its profile | vehicles.py |
| POST /v1/readers | admin | create a reader credential; returns its secret once | credentials.py |
| POST /v1/observations, POST /v1/heartbeats | vehicle | an edge vehicle's friction observations and heartbeats (CONTRACTS 3.7) | observations.py |
| POST /v1/stations | admin | register a roadside station (its own credential); returns its secret once | credentials.py |
| POST /v1/stations/{id}/reports | the station | its reports (roadgrip/cloud/domain/stations.py: one JSON object or an array) | stations.py |
| GET /v1/stations | admin, reader | each station's newest report, with the evidence drawn from it and its cells | stations.py |
| DELETE /v1/credentials/{name} | admin | revoke a credential, at once | credentials.py |
| POST /v1/telemetry | vehicle | ingest samples (CONTRACTS 3.1: NDJSON, a JSON array or object; wire v1 or VSS keys) | telemetry.py |
| GET /v1/vehicles/{id}/estimates | admin, reader, the vehicle | estimates (CONTRACTS 3.4) over a time range | vehicles.py |
| GET /v1/map | admin, reader | the friction map as GeoJSON | map.py |
| GET /v1/map/datex2 | admin, reader | the map as DATEX II v3 (RoadSurfaceConditionMeasurements, friction) | map.py |
| GET /v1/map/datex2/sites | admin, reader | its DATEX II v3 measurement site table (a site per H3 cell) | map.py |
| GET /v1/warnings | admin, reader, vehicles | slippery-road warnings as DENMs | warnings.py |
| GET /v1/warnings/uper | admin, reader, vehicles | the same DENMs UPER-encoded, each after its 4-byte length | warnings.py |
| GET /v1/health | anyone authenticated | storage, broker and pipeline state; 503 when storage is down | health.py |
| GET /metrics | anyone authenticated | Prometheus metrics (docs/CLOUD.md "Metrics (Prometheus)") | health.py |
| GET /v1/vehicles/latest | admin, reader | each vehicle's newest estimate and position | dashboard.py |
| GET /dashboard | anyone (the page holds no data; it calls the API with a reader's credentials) | the live map | dashboard.py |

What ingest answers: roadgrip/cloud/api/routes/telemetry.py. Every error status of every route is declared in the
OpenAPI document, with its body (`ErrorAnswer`, roadgrip/cloud/api/errors.py); the schemathesis tests of
tests/cloud/test_fuzz.py hold the API to it.

In the cluster (docs/CLUSTER.md, "Stateless API"), a replica keeps nothing another replica needs:
- Credentials are read from PostgreSQL on every call (`Authenticator(revalidate=True)`): a credential revoked through
  any replica is refused by every replica from the next call on. Registering a vehicle (or a reader) also creates its
  RabbitMQ user with its permissions (roadgrip/cloud/transport/rabbit_users.py) before the database commits; revoking
  deletes the user, which closes its open MQTT connections. A vehicle's `mqtt_url` is the `mqtt` setting (the
  broker's load balancer); stations report over HTTP only (their `mqtt_url` is null).
- POST /v1/telemetry validates as embedded, then publishes the valid samples to amq.topic with the vehicle's telemetry
  routing key, as the vehicle's own MQTT publish would arrive, and answers **202** (`Accepted`) once the broker
  confirmed the message: it is in the vehicle's partition queue, replicated on a quorum of nodes, and a worker will
  store it; not "stored". 503 when no broker node confirmed it (retry: the worker stores a repeat once). The rate
  limit answered with 429 is this replica's own (a vehicle spread over N replicas gets up to N times it through
  them); the limit of the worker that owns the vehicle counts every replica's and MQTT's samples together and refuses
  the excess on the vehicle's MQTT errors topic.
- POST /v1/stations/{id}/reports: stored as embedded; the evidence of every report of the payload (a duplicate's as
  stored) is published to the owners of their regions (roadgrip/cloud/cluster/regions.py), which add it to the map and
  the warnings. 503 when no broker node confirmed it within 10 s: the reports are stored, send them again.
- GET /v1/map, /v1/map/datex2 and /v1/map/datex2/sites: the map the region owners saved
  (roadgrip/cloud/cluster/map_cells.py), at the replica's clock, read again when a second old; GET /v1/warnings and
  /v1/warnings/uper: the stored warnings.
- GET /v1/health: storage and broker reachability; GET /metrics: the replica's own counters.
"""

from __future__ import annotations

from fastapi import Depends, FastAPI

from roadgrip.cloud.api import errors
from roadgrip.cloud.api.backend import ApiBackend
from roadgrip.cloud.api.deps import single_query_values
from roadgrip.cloud.api.routes import (
    credentials,
    dashboard,
    health,
    observations,
    stations,
    telemetry,
    vehicles,
    warnings,
)
from roadgrip.cloud.api.routes import map as map_routes
from roadgrip.cloud.metrics import registry_with

# dashboard first: its GET /v1/vehicles/latest before GET /v1/vehicles/{vehicle_id}
ROUTERS = (
    dashboard.router,
    vehicles.router,
    credentials.router,
    stations.router,
    telemetry.router,
    observations.router,
    map_routes.router,
    warnings.router,
    health.router,
)


def create_app(backend: ApiBackend) -> FastAPI:
    app = FastAPI(
        title="roadgrip cloud",
        version="1",
        description="Tire-road friction from connected-vehicle telemetry: ingest, estimates, map, warnings.",
        responses=errors.errors(401, 403, 503),  # every route authenticates and reads storage
        dependencies=[Depends(single_query_values)],
    )
    app.state.backend = backend
    app.state.metrics_registry = registry_with(backend.metrics_collector())
    errors.install(app)
    for router in ROUTERS:
        app.include_router(router)
    return app
