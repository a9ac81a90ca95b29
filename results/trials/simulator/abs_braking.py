"""Hardest braking with ABS from 25 m/s on uniform roads: mean deceleration between 20 and 5 m/s as a share of mu g.

Run: python results/trials/simulator/abs_braking.py   (prints the table of docs/SIMULATOR.md)
"""

from roadgrip.sim.driver import SpeedProfile
from roadgrip.sim.integrator import CHANNELS
from roadgrip.sim.roads import MuProfile, Path
from roadgrip.sim.scenario import Scenario
from roadgrip.sim.simulate import simulate_truth
from roadgrip.units import G_MPS2
from roadgrip.vehicle.params import MIDSIZE_SEDAN, PAPER_SUV
from roadgrip.vehicle.tires import BurckhardtTire, DugoffTire, MagicFormulaTire

MUS = (0.3, 0.6, 0.9)
CH = {name: k for k, name in enumerate(CHANNELS)}


def main():
    cases = [(v, t) for v in (PAPER_SUV, MIDSIZE_SEDAN) for t in (DugoffTire(), MagicFormulaTire(), BurckhardtTire())]
    scenarios = [
        Scenario(
            run_id=f"{v.name}-{t.name}-{mu}",
            path=Path.straight(500.0),
            mu=MuProfile.uniform(mu),
            speed=SpeedProfile([0.0, 1.0, 1.3, 10.0], [25.0, 25.0, 0.0, 0.0]),
            vehicle=v,
            tire=t,
            duration_s=10.0,
        )
        for v, t in cases
        for mu in MUS
    ]
    outs = iter(simulate_truth(scenarios))
    print("| vehicle, tire | " + " | ".join(f"mu {mu}" for mu in MUS) + " |")
    print("| --- |" + " ---: |" * len(MUS))
    for v, t in cases:
        shares = []
        for mu in MUS:
            out = next(outs)
            vx = out[:, CH["vx_mps"]]
            window = (out[:, CH["t_s"]] > 1.0) & (vx < 20.0) & (vx > 5.0)
            shares.append(-out[window, CH["ax_mps2"]].mean() / (mu * G_MPS2))
        print(f"| {v.name}, {t.name} | " + " | ".join(f"{s:.2f}" for s in shares) + " |")


if __name__ == "__main__":
    main()
