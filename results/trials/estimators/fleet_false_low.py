"""Every vehicle of a fleet benchmark seed through pmf offline (each vehicle's trips in order, a restart between trips,
as the service runs it): samples whose mu_upper is below 0.5 on roads of 0.6 or more (false lows), and samples of
roads of 0.3 or less read below 0.4, with the vehicles that hold false lows.

    python results/trials/estimators/fleet_false_low.py 100      # a tuning seed (100, 101, 102)
"""

import sys

from roadgrip.estimators import pmf
from roadgrip.evaluation.fleet_benchmark import make_scenario, vehicle_drive


def main(seed: int) -> None:
    scenario = make_scenario(seed)
    totals = {"false_low": 0, "dry": 0, "low_read": 0, "low": 0}
    cars = []
    for vehicle_id in sorted(scenario.kinds):
        run, trips = vehicle_drive(scenario, vehicle_id)
        out = pmf.PMFEstimator().estimate_batch(run, trips, scenario.kinds[vehicle_id])
        upper, mu = out["mu_upper"].to_numpy(), run["mu"].to_numpy()
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
