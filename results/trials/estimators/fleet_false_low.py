"""Every vehicle of a fleet benchmark seed through pmf offline (each vehicle's trips in order, a restart between trips,
as the service runs it): samples whose mu_upper is below 0.5 on roads of 0.6 or more (false lows), and samples of
roads of 0.3 or less read below 0.4, with the vehicles that hold false lows.

    python results/trials/estimators/fleet_false_low.py 100      # a tuning seed (100, 101, 102)
"""

import sys

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from roadgrip.estimators import pmf
from roadgrip.evaluation.fleet_benchmark import make_scenario
from roadgrip.sim.sensors import SensorModel
from roadgrip.sim.simulate import simulate


def main(seed: int) -> None:
    scenario = make_scenario(seed)
    origin = scenario.network.origin
    table = simulate(
        [t.scenario for t in scenario.trips], SensorModel(origin_lat_deg=origin[0], origin_lon_deg=origin[1])
    )
    totals = {"false_low": 0, "dry": 0, "low_read": 0, "low": 0}
    cars = []
    for vehicle_id in sorted(scenario.kinds):
        trips = [t for t in scenario.trips if t.vehicle_id == vehicle_id]
        ids = [t.scenario.run_id for t in trips]
        part = table.filter(pc.is_in(table["run_id"], pa.array(ids)))
        run_ids = part["run_id"].to_pylist()
        depart = {t.scenario.run_id: t.depart_s for t in trips}
        t_s = np.array([depart[r] for r in run_ids]) + part["t_s"].to_numpy()
        order = np.argsort(t_s, kind="stable")
        part, t_s = part.take(pa.array(order)), t_s[order]
        field = part.schema.field("timestamp_ms")
        part = part.set_column(
            part.column_names.index("timestamp_ms"), field, pa.array(np.round(t_s * 1000).astype(int))
        )
        segments = np.array([ids.index(run_ids[k]) for k in order])
        out = pmf.PMFEstimator().estimate_batch(part, segments, scenario.kinds[vehicle_id])
        upper, mu = out["mu_upper"].to_numpy(), part["mu"].to_numpy()
        false_low = int(((upper < 0.5) & (mu >= 0.6)).sum())
        totals["false_low"] += false_low
        totals["dry"] += int((mu >= 0.6).sum())
        totals["low_read"] += int(((upper < 0.4) & (mu <= 0.3)).sum())
        totals["low"] += int((mu <= 0.3).sum())
        if false_low:
            cars.append((vehicle_id, scenario.kinds[vehicle_id].name, scenario.styles[vehicle_id], false_low))
    print(f"seed {seed}: {totals}")
    print("vehicles with false lows:", cars)


if __name__ == "__main__":
    main(int(sys.argv[1]))
