"""The place of a warning within its cell (warnings.py, rules 4-7 and 9): where in the cell low friction was read, and
whether a dry pass speaks of that place.

A warning's cell (H3 resolution 10) is about 150 m across; a patch of ice is often smaller (the fleet benchmark's are
80-140 m, the demo's 60 m), so a pass that proves grip in one part of the cell says nothing about another. This module
keeps, per cell, the *spots* of its low evidence and whether each has been shown dry since:

- A spot is an H3 cell at SPOT_RESOLUTION (12: cells about 19 m across, 9.4 m edge) holding an estimate that read low
  (excited, mu_upper below the threshold) in a low pass. A roadside station's low report speaks for the stretch of road
  its station stands for (roadgrip/cloud/domain/stations.py, COVERAGE_RADIUS_M), not a point: its spot is the whole cell
  (the spot's key is the cell itself).
- A vehicle's dry pass speaks of a spot when one of its estimates that proved grip (excited with mu_lower at or above
  the threshold, or mu_proven at or above it) lies in the spot or in one of its six neighbours (SPOT_RING 1): within
  about 15-30 m of a low reading, which allows for GNSS error (a few metres) and for an estimate's window (pmf reads
  the last second or so of driving, 10-30 m at road speeds). A vehicle's pass never speaks for a station's whole-cell
  spot (it proved grip along its own track only). A station's dry report speaks for every spot of the cells it covers.
- A spot is shown dry when `min_dry_passes` dry passes later than its last low reading spoke of it; a low reading at the
  spot later than its last dry pass makes it low again (its count starts over). A low reading no newer than the
  spot's last dry pass is superseded there (a late row: the spot was shown dry after it).
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


class Spot:
    """One spot of a cell: its last low reading, its last dry pass that spoke of it, and the dry passes since the low."""

    __slots__ = ("dry_passes", "last_dry_ms", "last_low_ms")

    def __init__(self, last_low_ms: int):
        self.last_low_ms = last_low_ms
        self.last_dry_ms = _NEVER
        self.dry_passes = 0


class Place:
    """The spots of one cell's low evidence (module docstring)."""

    __slots__ = ("spots",)

    def __init__(self):
        self.spots: dict[str, Spot] = {}

    def __bool__(self) -> bool:
        return bool(self.spots)

    def low(self, keys: Iterable[str], t: int) -> bool:
        """Low readings at `keys` at time t; False when every one is superseded by a later dry pass there."""
        fresh = False
        for key in keys:
            spot = self.spots.get(key)
            if spot is None:
                self.spots[key] = Spot(t)
            elif t <= spot.last_dry_ms:
                continue
            elif t > spot.last_low_ms:
                spot.last_low_ms, spot.dry_passes = t, 0
            fresh = True
        return fresh

    def spoken_of(self, grip: set[str] | None) -> list[str]:
        """The keys a dry pass speaks of: a vehicle's (`grip`: the reach of its grip spots) or, with None, a station's
        (every spot)."""
        if grip is None:
            return list(self.spots)
        return [k for k in self.spots if k in grip or k == UNKNOWN_PLACE]

    def dry(self, keys: list[str], t: int) -> None:
        """A dry pass at t over `keys` (from `spoken_of`): it counts at each spot whose last low reading is older."""
        for key in keys:
            spot = self.spots[key]
            if t > spot.last_low_ms:
                spot.dry_passes += 1
            spot.last_dry_ms = max(spot.last_dry_ms, t)

    def all_dry(self, min_dry_passes: int) -> bool:
        """Every spot shown dry (False for a place without spots)."""
        return bool(self.spots) and all(s.dry_passes >= min_dry_passes for s in self.spots.values())

    def still_low(self, min_dry_passes: int) -> tuple[str, ...]:
        """The keys not yet shown dry, sorted (what a warning's event carries)."""
        return tuple(sorted(k for k, s in self.spots.items() if s.dry_passes < min_dry_passes))

    def forget(self, horizon_ms: float) -> None:
        """Forget the spots whose last reading, low or dry, is older than horizon_ms."""
        for key in [k for k, s in self.spots.items() if max(s.last_low_ms, s.last_dry_ms) < horizon_ms]:
            del self.spots[key]

    def clear(self) -> None:
        self.spots.clear()
