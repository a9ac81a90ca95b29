"""The place of a warning within its cell (warnings.py, rules 4-7 and 9): where in the cell low friction was read, and
whether a dry pass speaks of that place.

A warning's cell (H3 resolution 10) is about 150 m across; a patch of ice is often smaller (the fleet benchmark's are
80-140 m, the demo's 60 m), so a pass that proves grip in one part of the cell says nothing about another. This module
keeps, per cell, the *spots* of its low evidence:

- A spot is an H3 cell at SPOT_RESOLUTION (12: cells about 19 m across, 9.4 m edge) holding an estimate that read low
  (excited, mu_upper below the threshold) in a low pass. A roadside station's low report speaks for the stretch of road
  its station stands for (roadgrip/cloud/domain/stations.py, COVERAGE_RADIUS_M), not a point: its spot is the whole cell
  (the spot's key is the cell itself).
- A vehicle's dry pass speaks of the place when one of its estimates that proved grip (excited with mu_lower at or
  above the threshold, or mu_proven at or above it) lies on one of the spots or one of their six neighbours
  (SPOT_RING 1): within about 15-30 m of a low reading, which allows for GNSS error (a few metres) and for an
  estimate's window (pmf reads the last second or so of driving, 10-30 m at road speeds). A vehicle's pass never speaks
  for a station's whole-cell spot (it proved grip along its own track only), and a station's dry report speaks only
  of a place a station read low (the whole-cell spot): the evidence row of a report holds the cell, not where the
  station stands, and a station up to COVERAGE_RADIUS_M away says nothing of where a vehicle read ice.
- One such pass speaks for the whole place, not only for the spots it touched: an estimator's low readings go on for
  a while after the braking that measured them (pmf's posterior carries the ice along: in
  tests/cloud/test_api.py a 46 m braking on a 150 m patch read low over all 150 m), while grip is proven only where a
  vehicle brakes or turns hard enough, so asking for every spot to be proven dry would keep nearly every warning to its
  expiry. What the place rules out is grip proven elsewhere in the cell.
- UNKNOWN_PLACE: a warning restored from an event stored before warnings kept their place (no `spots` in the event);
  any dry pass in the cell speaks of it, the rule before places were kept.

Pure and in memory, like the engine.
"""

from __future__ import annotations

from collections.abc import Iterable

import h3

SPOT_RESOLUTION = 12
SPOT_RING = 1
UNKNOWN_PLACE = ""
_NEVER = -(2**62)


def spots_of(positions: Iterable[tuple[float, float]]) -> set[str]:
    """The spots (H3 cells at SPOT_RESOLUTION) of (latitude_deg, longitude_deg) positions."""
    return {h3.latlng_to_cell(lat, lon, SPOT_RESOLUTION) for lat, lon in positions}


def reach(spots: Iterable[str]) -> set[str]:
    """The spots a dry pass with grip proven in `spots` speaks of: each and its neighbours within SPOT_RING."""
    out: set[str] = set()
    for spot in spots:
        out.update(h3.grid_disk(spot, SPOT_RING))
    return out


class Place:
    """The spots of one cell's low evidence (module docstring): spot key -> the time of its last low reading."""

    __slots__ = ("spots",)

    def __init__(self):
        self.spots: dict[str, int] = {}

    def __bool__(self) -> bool:
        return bool(self.spots)

    def low(self, keys: Iterable[str], t: int) -> None:
        """Low readings at `keys` at time t."""
        for key in keys:
            if t > self.spots.get(key, _NEVER):
                self.spots[key] = t

    def spoken_of(self, grip: set[str]) -> bool:
        """Whether a dry pass whose grip reaches `grip` (a vehicle's: the reach of its grip spots; a station's: its
        cell, the whole-cell spot) touches a spot of the place."""
        return any(k in grip or k == UNKNOWN_PLACE for k in self.spots)

    def keys(self) -> tuple[str, ...]:
        """The spots, sorted (what a warning's event carries)."""
        return tuple(sorted(self.spots))

    def forget(self, horizon_ms: float, *, inclusive: bool = False) -> None:
        """Forget the spots whose last low reading is older than horizon_ms (or at it, when inclusive)."""
        for key in [k for k, t in self.spots.items() if t < horizon_ms or (inclusive and t == horizon_ms)]:
            del self.spots[key]

    def clear(self) -> None:
        self.spots.clear()
