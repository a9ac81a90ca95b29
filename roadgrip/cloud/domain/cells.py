"""The H3 cells the cloud keys its friction map, warnings, stations, stored estimates and cluster regions by: which cell
a position lies in (`cell_of`, `cells_of` for many), which region a cell belongs to (`region_of`), and what a resolution may be
(`validate_resolution`). Everything that computes a cell of a position or a region of a cell uses these, so the map,
the warning engine, the stations' coverage, the stored estimates' h3_cell and the regions of cluster mode always
agree."""

from __future__ import annotations

import h3

from roadgrip.cloud.domain import checks


def validate_resolution(resolution) -> int:
    """An H3 resolution, an integer in 0..15 (ValueError otherwise)."""
    return checks.integer_in("resolution", resolution, 0, 15, "an integer H3 resolution")


def cell_of(latitude_deg: float | None, longitude_deg: float | None, resolution: int) -> str | None:
    """The H3 cell (at `resolution`) of a WGS84 position in degrees; None without a position."""
    if latitude_deg is None or longitude_deg is None:
        return None
    return h3.latlng_to_cell(latitude_deg, longitude_deg, resolution)


def cells_of(latitudes_deg, longitudes_deg, resolution: int) -> list[str | None]:
    """cell_of for many positions (sequences of floats or None), in order. h3-py v4 has no vectorised point lookup
    (uber/h3-py issue 341): one call each, without cell_of's own call."""
    latlng_to_cell = h3.latlng_to_cell
    return [
        None if lat is None or lon is None else latlng_to_cell(lat, lon, resolution)
        for lat, lon in zip(latitudes_deg, longitudes_deg)
    ]


def region_of(cell: str, region_resolution: int) -> str:
    """The region of an H3 cell: its parent at `region_resolution` (the cell itself at that resolution)."""
    return h3.cell_to_parent(cell, region_resolution)
