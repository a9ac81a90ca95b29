"""Road networks and patches: geometry, adhesion along roads, GeoJSON input."""

from __future__ import annotations

import json

import numpy as np
import pytest

from roadgrip.fleet.network import SURFACE_MU, Network, Patch, Road, generated_network, network_from_geojson


def test_surface_adhesion_is_the_burckhardt_peak_and_ordered():
    assert SURFACE_MU["dry"] > SURFACE_MU["wet"] > SURFACE_MU["snow"] > SURFACE_MU["ice"] > 0
    assert SURFACE_MU["dry"] == pytest.approx(1.17, abs=0.01) and SURFACE_MU["ice"] == pytest.approx(0.05)


def test_a_patch_replaces_the_dry_road_exactly_where_the_road_crosses_it():
    road = Road("r", "urban", np.array([[0.0, 0.0], [1000.0, 0.0]]))
    network = Network((road,), (Patch("p", "ice", 500.0, 30.0, 50.0),))
    profile = network.mu_profile(road)
    half_chord = np.sqrt(50.0**2 - 30.0**2)  # 40 m either side of x = 500
    mu = profile.at(np.array([400.0, 500.0 - half_chord + 3, 500.0, 500.0 + half_chord - 3, 600.0]))
    np.testing.assert_allclose(mu, [SURFACE_MU["dry"], 0.05, 0.05, 0.05, SURFACE_MU["dry"]])
    ((first, last, patch),) = network.patch_stations(road)
    assert patch.name == "p" and first == pytest.approx(460.0, abs=2.0) and last == pytest.approx(540.0, abs=2.0)


def test_the_generated_network_has_every_kind_of_road_and_a_patch_on_each_slippery_road():
    network = generated_network()
    assert {r.kind for r in network.roads} == {"expressway", "ramp", "urban"}
    on_road = {p.name for road in network.roads for _, _, p in network.patch_stations(road)}
    assert on_road == {p.name for p in network.patches}
    for road in network.roads:
        assert road.path.length_m > 500
        assert [p.name for _, _, p in network.patch_stations(road.reversed())] == [
            p.name for _, _, p in network.patch_stations(road)
        ]


def test_bad_roads_and_patches_are_refused():
    with pytest.raises(ValueError, match="kind"):
        Road("r", "motorway", np.array([[0.0, 0.0], [1.0, 0.0]]))
    with pytest.raises(ValueError, match="surface"):
        Patch("p", "dry", 0.0, 0.0, 10.0)
    with pytest.raises(ValueError, match="radius_m"):
        Patch("p", "ice", 0.0, 0.0, 0.0)


def test_a_geojson_network_round_trips_positions(tmp_path):
    origin = (38.0428, 114.5149)
    collection = {
        "type": "FeatureCollection",
        "features": [
            {
                "type": "Feature",
                "properties": {"name": "main", "kind": "expressway"},
                "geometry": {"type": "LineString", "coordinates": [[114.5149, 38.0428], [114.5263, 38.0428]]},
            },
            {
                "type": "Feature",
                "properties": {"surface": "snow", "radius_m": 30},
                "geometry": {"type": "Point", "coordinates": [114.5200, 38.0428]},
            },
        ],
    }
    path = tmp_path / "net.geojson"
    path.write_text(json.dumps(collection))
    network = network_from_geojson(path)
    assert network.origin == pytest.approx(origin)
    road = network.roads[0]
    assert road.path.length_m == pytest.approx(1000.0, rel=0.01)  # 0.0114 deg of longitude at 38 N
    assert network.patches[0].east_m == pytest.approx(447.0, rel=0.01)
    assert network.patch_stations(road)
    path.write_text(json.dumps({"type": "Feature"}))
    with pytest.raises(ValueError, match="FeatureCollection"):
        network_from_geojson(path)
