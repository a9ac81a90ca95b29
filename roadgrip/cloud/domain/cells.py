"""The H3 cells the cloud keys its friction map, warnings, stations, stored estimates and cluster regions by: which cell
a position lies in (`cell_of`), which region a cell belongs to (`region_of`), and what a resolution may be
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


def region_of(cell: str, region_resolution: int) -> str:
    """The region of an H3 cell: its parent at `region_resolution` (the cell itself at that resolution)."""
    return h3.cell_to_parent(cell, region_resolution)
