"""The one cell function (roadgrip/cloud/domain/cells.py): a position's cell, None without a position, a cell's region,
the resolution check; and the map, the warning engine and the stations' coverage key by it."""

import h3
import pytest

from roadgrip.cloud.domain.cells import cell_of, region_of, validate_resolution
from roadgrip.cloud.domain.friction_map import FrictionMap
from roadgrip.cloud.domain.stations import covered_cells
from roadgrip.cloud.domain.warnings import WarningEngine

HEBEI = (38.0, 114.5)
T0_MS = 1_768_464_000_000


@pytest.mark.parametrize("resolution", [0, 5, 10, 15])
def test_a_position_s_cell_and_its_region(resolution):
    cell = cell_of(*HEBEI, resolution)
    assert h3.is_valid_cell(cell) and h3.get_resolution(cell) == resolution
    assert h3.latlng_to_cell(*HEBEI, resolution) == cell
    assert region_of(cell, 0) == h3.cell_to_parent(cell, 0) and region_of(cell, resolution) == cell


@pytest.mark.parametrize(("lat", "lon"), [(None, 114.5), (38.0, None), (None, None)])
def test_no_position_no_cell(lat, lon):
    assert cell_of(lat, lon, 10) is None


@pytest.mark.parametrize("resolution", [-1, 16, 10.5, "10", True, None])
def test_a_resolution_is_an_integer_in_0_to_15(resolution):
    with pytest.raises(ValueError, match=rf"resolution.*{resolution!r}"):
        validate_resolution(resolution)
    assert validate_resolution(7) == 7


def test_the_map_the_engine_and_the_stations_key_by_it():
    row = {
        "vehicle_id": "v",
        "timestamp_ms": T0_MS,
        "latitude_deg": HEBEI[0],
        "longitude_deg": HEBEI[1],
        "mu": 0.2,
        "mu_lower": 0.1,
        "mu_upper": 0.3,
        "excited": True,
        "mu_proven": None,
    }
    fmap, engine = FrictionMap(resolution=9), WarningEngine(resolution=9)
    assert fmap.add([row]) == {cell_of(*HEBEI, 9)} == {fmap.cell_of(*HEBEI)}
    engine.update([row], T0_MS)
    assert engine.open_passes_["v"].cell == cell_of(*HEBEI, 9)
    assert cell_of(*HEBEI, 9) in covered_cells(*HEBEI, 9)
