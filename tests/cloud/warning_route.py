"""A route of estimate rows for the warning engine's tests (tests/cloud/domain/test_warnings.py, the fleet sweep's
tests/evaluation/test_fleet_sweep.py): a vehicle at 20 m/s and 10 Hz heading east along the parallel 38 N in Hebei,
1.4 km through resolution-10 cells, reporting in each cell what an estimator would: low and excited on the icy PATCH,
an interval straddling the threshold in STRADDLING, steady driving (not excited) in STEADY, dry elsewhere."""

import calendar

import h3

T0_MS = calendar.timegm((2026, 1, 15, 8, 0, 0)) * 1000
LAT_DEG, LON0_DEG = 38.0, 114.5  # Hebei
STEP_DEG = 2.0 / (111_320.0 * 0.788010754)  # 20 m/s at 10 Hz along the parallel 38 N: 2 m of longitude per sample
N_SAMPLES = 700  # 1.4 km, 70 s


def route_cells():
    """The resolution-10 cells along the route in driving order, and the samples in each."""
    order, counts = [], {}
    for i in range(N_SAMPLES):
        cell = h3.latlng_to_cell(LAT_DEG, LON0_DEG + i * STEP_DEG, 10)
        if not order or order[-1] != cell:
            assert cell not in counts, "the route must not come back into a cell"
            order.append(cell)
        counts[cell] = counts.get(cell, 0) + 1
    return order, counts


ROUTE, SAMPLES_IN = route_cells()
WELL_DRIVEN = [c for c in ROUTE if SAMPLES_IN[c] >= 30]
PATCH = set(WELL_DRIVEN[4:7])  # icy
STRADDLING = WELL_DRIVEN[3]  # excited, but the interval straddles the threshold: unknown
STEADY = WELL_DRIVEN[7]  # driven steadily: not excited, unknown


def surface(cell, slippery=PATCH):
    """(mu, mu_lower, mu_upper, excited) that an estimator would report in this cell."""
    if cell in slippery:
        return 0.2, 0.1, 0.3, True
    if cell == STRADDLING:
        return 0.4, 0.3, 0.55, True
    if cell == STEADY:
        return 0.5, 0.0, 1.2, False
    return 0.8, 0.6, 0.95, True


def drive(vehicle, start_ms, slippery=PATCH, reverse=False):
    rows = []
    for i in range(N_SAMPLES):
        lon = LON0_DEG + (N_SAMPLES - 1 - i if reverse else i) * STEP_DEG
        mu, lo, hi, excited = surface(h3.latlng_to_cell(LAT_DEG, lon, 10), slippery)
        rows.append(
            {
                "vehicle_id": vehicle,
                "timestamp_ms": start_ms + 100 * i,
                "latitude_deg": LAT_DEG,
                "longitude_deg": lon,
                "mu": mu,
                "mu_lower": lo,
                "mu_upper": hi,
                "excited": excited,
            }
        )
    return rows
