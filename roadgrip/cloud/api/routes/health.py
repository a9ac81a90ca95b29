"""The service's state: GET /v1/health (storage, broker, pipeline; 503 when storage is down) and GET /metrics
(Prometheus, docs/CLOUD.md "Metrics (Prometheus)"), for any authenticated caller."""

from fastapi import APIRouter, Response
from fastapi.responses import JSONResponse
from prometheus_client import CONTENT_TYPE_PLAIN_0_0_4, generate_latest

from roadgrip.cloud.api.deps import Backend, Caller, MetricsRegistry

router = APIRouter()


@router.get("/v1/health", responses={503: {"description": "storage unavailable (the body says so, as for 200)"}})
def health(caller: Caller, backend: Backend) -> JSONResponse:
    status = backend.health()
    return JSONResponse(status, status_code=503 if status["status"] == "unavailable" else 200)


@router.get(
    "/metrics",
    response_class=Response,
    responses={
        200: {
            "content": {"text/plain": {}},
            "description": 'Prometheus text exposition format (docs/CLOUD.md, "Metrics")',
        }
    },
)
def metrics(caller: Caller, registry: MetricsRegistry) -> Response:
    """Prometheus metrics of this service and its ingest processes; who may read them: as /v1/health."""
    return Response(generate_latest(registry), media_type=CONTENT_TYPE_PLAIN_0_0_4)
