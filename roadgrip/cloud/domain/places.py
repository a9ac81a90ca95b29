"""The place of a warning within its cell and next door (warnings.py, rules 4-7 and 9): where low friction was read, and
whether a dry pass speaks of that place.

A warning's cell (H3 resolution 10) is about 150 m across; a patch of ice is often smaller (the fleet benchmark's are
80-140 m, the demo's 60 m), so a pass that proves grip in one part of the cell says nothing about another. This module
keeps, per cell, the *spots* of its low evidence:

- A spot is an H3 cell at SPOT_RESOLUTION (12: cells about 19 m across, 9.4 m edge) holding an estimate that read low
  (excited, mu_upper below the threshold) in a low pass. A roadside station's low report speaks for the stretch of road
  its station stands for (roadgrip/cloud/domain/stations.py, COVERAGE_RADIUS_M), not a point: its spot is the whole cell
  (the spot's key is the cell itself).
- A vehicle's dry pass shows a spot dry when one of its estimates that proved grip (excited with mu_lower at or above
  the threshold, or mu_proven at or above it) lies on the spot or one of its six neighbours (SPOT_RING 1): within about
  15-30 m, which allows for GNSS error (a few metres) and for an estimate's window (pmf reads the last second or so of
  driving, 10-30 m at road speeds). Grip proves friction only where the tires were worked, so a pass shows dry only the
  spots it reaches, and never a spot where the same pass read low (a pass that crosses a patch's edge reads low on it
  and proves grip past it: its grip says nothing of where it read ice). A vehicle's pass never speaks for a station's
  whole-cell spot (it proved grip along its own track only); its grip reaches the spots of the cells next door as well
  as its own cell's (a spot near a border, or straddling it, is shown dry by grip proven beside it whichever cell the
  pass is counted in: `Place.dry`'s next_door). A station's dry report speaks only of a place a station read low (the
  whole-cell spot): the evidence row of a report holds the cell, not where the station stands, and a station up to
  COVERAGE_RADIUS_M away says nothing of where a vehicle read ice.
- The place is shown dry when every spot is: grip proven on it (or beside it) after its last low reading. Until then
  a warning stays, and ends by expiry if nobody proves the rest dry. Grip at one end of the place (a vehicle that
  braked where the patch begins, or skirted its edge) is not the patch drying: in the fleet benchmark's tuning seeds
  (issue 23) both warnings cancelled while their patch was there were of that kind: grip proven at the patch's edge or
  past it while the place held low readings 30-60 m further in (docs/RESULTS.md, "Warnings that last").
- The ice goes on next door (`ice_continues`): a patch does not stop at a cell border, and a cell often holds only its
  rim. The place of a cell's warning extends to the low evidence of its neighbouring cells that continues it: their
  spots read low within the validity, reached by a chain of spots each within LINK_RING of the cell's spots or of one
  before it in the chain. LINK_RING is 2 * SPOT_RING: a low reading speaks for about as far as a grip reading does
  (GNSS error, the estimate's window), so two low spots whose reaches meet are one stretch of ice. Grip proven on the
  rim spot of one cell is not the patch drying while the rest of that stretch, next door, has not been shown dry: the
  place is shown dry when its own spots are and the ice it continues into is too (or has aged out of the validity;
  docs/RESULTS.md, "Warnings that last: the last two misses").
  Only vehicles' spots link: a station's whole-cell spot and UNKNOWN_PLACE are not positions.
- UNKNOWN_PLACE: a warning restored from an event stored before warnings kept their place (no `spots` in the event);
  any dry pass in the cell speaks of it, the rule before places were kept.

Pure and in memory, like the engine.
"""

from __future__ import annotations

from collections.abc import Iterable

import h3

SPOT_RESOLUTION = 12
SPOT_RING = 1
LINK_RING = 2 * SPOT_RING
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
    """The spots of one cell's low evidence (module docstring): spot key -> [the time of its last low reading, the time
    of the last grip proven on it or beside it]. A spot is shown dry when grip was proven there after its last low
    reading; the place is shown dry when every spot is."""

    __slots__ = ("spots",)

    def __init__(self):
        self.spots: dict[str, list[int]] = {}

    def __bool__(self) -> bool:
        return bool(self.spots)

    def low(self, keys: Iterable[str], t: int) -> None:
        """Low readings at `keys` at time t."""
        for key in keys:
            times = self.spots.setdefault(key, [_NEVER, _NEVER])
            times[0] = max(times[0], t)

    def dry(self, grip: set[str], t: int, *, next_door: bool = False) -> bool:
        """Grip proven at time t on `grip` (a vehicle's: the reach of its grip spots less the spots where the same pass
        read low; a station's: its cell, the whole-cell spot), by a pass in this place's cell or, `next_door`, in a
        neighbouring one: marks the spots it touches, and says whether it touched any (whether the pass speaks of the
        place). UNKNOWN_PLACE is touched by any pass in the cell, none next door."""
        touched = False
        for key, times in self.spots.items():
            if key in grip or (key == UNKNOWN_PLACE and not next_door):
                times[1] = max(times[1], t)
                touched = True
        return touched

    def shown_dry(self) -> bool:
        """Whether grip was proven on every spot after its last low reading."""
        return all(dry_ms > low_ms for low_ms, dry_ms in self.spots.values())

    def keys(self) -> tuple[str, ...]:
        """The spots not yet shown dry, sorted (what a warning's event carries)."""
        return tuple(sorted(k for k, (low_ms, dry_ms) in self.spots.items() if dry_ms <= low_ms))

    def last_dry_ms(self) -> int:
        """The time of the last grip proven on the place (when it is shown dry: the dry pass that completed it)."""
        return max((dry_ms for _, dry_ms in self.spots.values()), default=_NEVER)

    def forget(self, horizon_ms: float) -> None:
        """Forget the spots whose last low reading is older than horizon_ms."""
        for key in [k for k, (t, _) in self.spots.items() if t < horizon_ms]:
            del self.spots[key]

    def clear(self) -> None:
        self.spots.clear()


def _is_spot(key: str) -> bool:
    """Whether a place's key is a vehicle's spot (a position), not a station's whole cell or UNKNOWN_PLACE."""
    return key != UNKNOWN_PLACE and h3.get_resolution(key) == SPOT_RESOLUTION


def ice_continues(place: Place, next_door: Iterable[Place], since_ms: float) -> bool:
    """Whether the ice of `place` goes on, not yet shown dry, in the places of the neighbouring cells (`next_door`;
    module docstring): a chain of their spots read low after since_ms, each within LINK_RING of a spot of `place` or of
    one before it, that reaches a spot not shown dry."""
    still_ice: dict[str, bool] = {}
    for other in next_door:
        for key, (low_ms, dry_ms) in other.spots.items():
            if low_ms > since_ms and _is_spot(key):
                still_ice[key] = dry_ms <= low_ms
    if not still_ice:
        return False
    frontier = [key for key in place.spots if _is_spot(key)]
    seen: set[str] = set()
    while frontier:
        for near in h3.grid_disk(frontier.pop(), LINK_RING):
            if near in still_ice and near not in seen:
                if still_ice[near]:
                    return True
                seen.add(near)
                frontier.append(near)
    return False
