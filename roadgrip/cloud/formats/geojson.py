"""The friction map as GeoJSON (RFC 7946): one Polygon Feature per cell, the H3 boundary as a closed ring in
[longitude, latitude] order, the CellSummary fields (roadgrip/cloud/domain/friction_map.py) as properties. A cell
crossing the antimeridian is not split. A pure function; no I/O."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import asdict
from typing import TYPE_CHECKING

import h3

if TYPE_CHECKING:
    from roadgrip.cloud.domain.friction_map import CellSummary


def geojson(cells: Iterable[CellSummary]) -> dict:
    """A GeoJSON FeatureCollection: one Polygon per cell (closed ring, [lon, lat]), the CellSummary as properties."""
    features = []
    for summary in cells:
        ring = [[lng, lat] for lat, lng in h3.cell_to_boundary(summary.cell)]
        ring.append(ring[0])
        features.append(
            {
                "type": "Feature",
                "id": summary.cell,
                "geometry": {"type": "Polygon", "coordinates": [ring]},
                "properties": asdict(summary),
            }
        )
    return {"type": "FeatureCollection", "features": features}
