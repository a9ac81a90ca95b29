"""The dashboard's routes (roadgrip/cloud/api/dashboard.py says what the page does): the page, its config, its static
files, and GET /v1/vehicles/latest, the data only the page asks for. Included before routes/vehicles.py: GET
/v1/vehicles/{vehicle_id} (a vehicle's profile) would otherwise take "latest" for a vehicle id."""

from fastapi import APIRouter
from fastapi.responses import FileResponse
from fastapi.staticfiles import StaticFiles

from roadgrip.cloud.api.dashboard import STATIC_DIR, page_config, page_headers
from roadgrip.cloud.api.deps import Backend, Caller, SettingsDep, require

router = APIRouter()


@router.get("/v1/vehicles/latest", tags=["dashboard"])
def latest_estimates(caller: Caller, backend: Backend) -> dict:
    """Each vehicle's newest estimate (CONTRACTS 3.4) with its position (latitude_deg, longitude_deg, h3_cell; null
    where the sample had none), by vehicle_id."""
    require(caller, "admin", "reader")
    return {"vehicles": backend.storage.latest_estimates()}


@router.get("/dashboard", include_in_schema=False)
def dashboard_page(settings: SettingsDep) -> FileResponse:
    return FileResponse(STATIC_DIR / "index.html", headers=page_headers(settings))


@router.get("/dashboard/config.json", include_in_schema=False)
def dashboard_config(settings: SettingsDep) -> dict:
    return page_config(settings)


router.mount("/dashboard/static", StaticFiles(directory=STATIC_DIR), name="dashboard-static")
