"""Friction observations (CONTRACTS 3.7, `roadgrip.data.schema.OBSERVATION`): one pass of a vehicle through one cell,
summarised where the vehicle estimates (`roadgrip edge`, roadgrip/edge/), and taken by the cloud as that same pass.

This module owns both directions, so that they stay each other's inverse for what the map and the warning engine read
of a pass. What a pass is stays passes.py's: the vehicle cuts its estimates into passes with `Passes` and this module's
`ObservationPass`; the cloud hands the rows of `pass_rows` to the map and the warning engine like estimates made from
raw telemetry, so the same rule cuts them into the same pass there.

A pass -> an observation (`observation_of`, on the vehicle):
- mu, mu_lower, mu_upper: the medians over the pass's excited estimates, as the warning engine judges a pass (its
  rule 2 takes the median mu_upper and mu_lower of the excited estimates); without an excited estimate, the last
  estimate's (the estimator's answer below excitation: a wide interval that still holds ice). VSS
  Vehicle.ADAS.ESC.RoadFriction.MostProbable / LowerBound / UpperBound.
- Numbers rounded: mu and its bounds to MU_DECIMALS, the position to POSITION_DECIMALS (unless that would move it
  out of the cell).
- mu_proven: the largest bound of the pass (the map and the engine take the largest); n_estimates, n_excited.
- position: the pass's telling sample: the excited estimate with the lowest mu_upper (the reading a warning's place
  is made of, warnings.py rule 9), else the estimate that proved the largest bound, else the last one.
- A pass is sent only where it has evidence (`has_evidence`): an excited estimate, or a bound of at least
  MIN_PROVEN_MU, the map's min_proven_mu: a calm pass that proves less tells the map and the engine nothing.

An observation -> the rows of its pass (`pass_rows`, in the cloud): n_excited excited rows with the observation's
interval (their medians and their mean log-likelihood in the map are the interval's), plus one row that is not excited
when the pass had other estimates (or none excited), every row at the observation's position with its mu_proven,
their timestamps spread from first_ms to last_ms (a pass's time is its last estimate's). What differs from the pass
made of raw telemetry: the map's plateau is the median interval's rather than the geometric mean of each estimate's
(equal when the pass's intervals agree), the calm estimates count as one row (n_estimates in the map's summary), and
every reading sits at one spot.
"""

from __future__ import annotations

import statistics

import h3

from roadgrip.cloud.domain.cells import cell_of
from roadgrip.cloud.domain.passes import Pass

MIN_PROVEN_MU = 0.1  # the friction map's min_proven_mu: a smaller bound is not counted (friction_map.py)
MU_DECIMALS = 4  # 1e-4 of mu: far below what any estimate can tell, and bytes on the uplink saved
POSITION_DECIMALS = 7  # 1e-7 degrees: about a centimetre


class ObservationPass(Pass):
    """A pass (passes.py) as the vehicle keeps it until it ends: its excited readings, its largest bound, its last
    estimate and the kinds of evidence met."""

    __slots__ = ("evidence", "excited", "last", "n", "proven", "proven_at")

    def __init__(self, vehicle_id: str, cell: str, t: int):
        super().__init__(vehicle_id, cell, t)
        self.n = 0
        self.excited: list[tuple[float, float, float, float, float]] = []  # mu, lower, upper, latitude, longitude
        self.last: tuple[float, float, float, float, float] | None = None
        self.proven = 0.0
        self.proven_at: tuple[float, float] | None = None
        self.evidence: set[str] = set()

    def add(self, estimate: dict, latitude_deg: float, longitude_deg: float, evidence=()) -> None:
        """One estimate (CONTRACTS 3.4) of the pass, at the sample's position, with its kinds of evidence."""
        reading = (estimate["mu"], estimate["mu_lower"], estimate["mu_upper"], latitude_deg, longitude_deg)
        self.n += 1
        self.last = reading
        if estimate["excited"]:
            self.excited.append(reading)
        proven = estimate.get("mu_proven")
        if proven is not None and proven > self.proven:
            self.proven, self.proven_at = float(proven), (latitude_deg, longitude_deg)
        self.evidence.update(evidence)


def has_evidence(p: ObservationPass) -> bool:
    """Whether the pass tells the map or the warning engine anything (module docstring)."""
    return bool(p.excited) or p.proven >= MIN_PROVEN_MU


def observation_of(p: ObservationPass, *, vehicle_class: str, channels, estimator: str) -> dict:
    """The observation (OBSERVATION's fields) of an ended pass with at least one estimate."""
    if p.excited:
        mu = statistics.median(r[0] for r in p.excited)
        lower = statistics.median(r[1] for r in p.excited)
        upper = statistics.median(r[2] for r in p.excited)
        latitude, longitude = min(p.excited, key=lambda r: r[2])[3:]
    else:
        mu, lower, upper, latitude, longitude = p.last
        if p.proven_at is not None:
            latitude, longitude = p.proven_at
    rounded = round(latitude, POSITION_DECIMALS), round(longitude, POSITION_DECIMALS)
    if cell_of(*rounded, h3.get_resolution(p.cell)) == p.cell:  # a position on the cell's very edge stays as it is
        latitude, longitude = rounded
    return {
        "vehicle_id": p.vehicle_id,
        "h3_cell": p.cell,
        "first_ms": int(p.first_ms),
        "last_ms": int(p.last_ms),
        "latitude_deg": float(latitude),
        "longitude_deg": float(longitude),
        "mu": round(float(mu), MU_DECIMALS),
        "mu_lower": round(float(lower), MU_DECIMALS),
        "mu_upper": round(float(upper), MU_DECIMALS),
        "mu_proven": round(p.proven, MU_DECIMALS) if p.proven_at is not None else None,
        "excited": bool(p.excited),
        "n_estimates": p.n,
        "n_excited": len(p.excited),
        "evidence": sorted(p.evidence),
        "channels": sorted(channels),
        "vehicle_class": vehicle_class,
        "estimator": estimator,
    }


def pass_rows(observation: dict) -> list[dict]:
    """The estimate rows (ESTIMATE's fields) that make the observation's pass in the map and the warning engine."""
    n_excited = observation["n_excited"]
    calm = 1 if observation["n_estimates"] > n_excited or n_excited == 0 else 0
    k = n_excited + calm
    first, last = observation["first_ms"], observation["last_ms"]
    times = [last] if k == 1 else [first + (last - first) * i // (k - 1) for i in range(k)]
    base = {
        "vehicle_id": observation["vehicle_id"],
        "mu": observation["mu"],
        "mu_lower": observation["mu_lower"],
        "mu_upper": observation["mu_upper"],
        "estimator": observation["estimator"],
        "mu_proven": observation["mu_proven"],
        "latitude_deg": observation["latitude_deg"],
        "longitude_deg": observation["longitude_deg"],
        "h3_cell": observation["h3_cell"],
    }
    return [{**base, "timestamp_ms": t, "excited": i >= calm} for i, t in enumerate(times)]
