"""The friction map in the database, for cluster mode (issue 17 item 3): a region's owner (roadgrip/cloud/cluster/regions.py)
saves the state of every cell it changed (`cell_rows`, at most about once a second per cell) to the table map_cells
(roadgrip/cloud/storage/database.py); a stateless API replica reads them back into a FrictionMap
(`stored_friction_map`) and renders the GeoJSON, DATEX II and cell statuses at its own `now` exactly as the owner's
map would, faded the same; a new owner of the region goes on from them (`restore_region`).

A cell's state is what `FrictionMap.cells` needs of it (roadgrip/cloud/domain/friction_map.py `cell_states`): its time
buckets, the passes in progress in it, its stations' reports and its vehicles' newest times. Not the estimates.

    from roadgrip.cloud.cluster.map_cells import stored_friction_map
    fmap = stored_friction_map(storage, settings, now_ms)
    geojson(fmap.cells(now_ms))  # roadgrip/cloud/formats/geojson.py
"""

from __future__ import annotations

from collections.abc import Iterable

from roadgrip.cloud.domain.cells import region_of
from roadgrip.cloud.domain.friction_map import FrictionMap
from roadgrip.cloud.pipeline.fanout import new_friction_map
from roadgrip.cloud.settings import Settings
from roadgrip.cloud.storage.database import Storage


def cell_rows(fmap: FrictionMap, cells: Iterable[str], region_resolution: int) -> list[dict]:
    """Rows of the map_cells table (cell, region, last_ms, state) for those of `cells` the map holds."""
    return [
        {"cell": cell, "region": region_of(cell, region_resolution), "last_ms": state["last_ms"], "state": state}
        for cell, state in fmap.cell_states(cells).items()
    ]


def stored_friction_map(storage: Storage, settings: Settings, now_ms: int | None = None) -> FrictionMap:
    """The map as the region owners last saved it: every stored cell (with evidence younger than map_max_age_s at
    `now_ms`, when given) in one FrictionMap of the settings."""
    since = None if now_ms is None else int(now_ms - settings.map_max_age_s * 1000)
    fmap = new_friction_map(settings)
    fmap.load_cell_states({row["cell"]: row["state"] for row in storage.map_cells(since_ms=since)})
    return fmap


def restore_region(fmap: FrictionMap, storage: Storage, region: str) -> int:
    """Load one region's stored cells into `fmap` (a region's new owner); how many."""
    rows = storage.map_cells(region=region)
    fmap.load_cell_states({row["cell"]: row["state"] for row in rows})
    return len(rows)
