"""What the optional channels change in the estimates the warning engine and the map took (issue 26, item 2): for two
fleet-benchmark runs of the same seeds, one without the channels and one with them on every second vehicle, the share
of excited estimates and their interval, for the vehicles that send the channels in the second run and the others.

    python results/trials/results/fleet_channels/excitation.py BASE_DIR HALF_DIR [--seeds 0 1 2]

BASE_DIR and HALF_DIR: the --out folders of `roadgrip evaluate --benchmark fleet --channel-share 0` and `0.5` (their
estimates_seed{S}.parquet)."""

import argparse
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq

from roadgrip.evaluation.fleet_benchmark import FleetConfig, make_scenario


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("base", type=Path)
    parser.add_argument("half", type=Path)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    args = parser.parse_args()
    print(
        "| seed | run | vehicles | estimates | excited share | excited: mu_lower median | excited: mu_upper p10 / median |"
    )
    print("| --- | --- | --- | ---: | ---: | ---: | --- |")
    for seed in args.seeds:
        senders = sorted(make_scenario(seed, FleetConfig(channel_share=0.5)).with_channels)
        for name, folder in (("without channels", args.base), ("half with channels", args.half)):
            table = pq.read_table(folder / f"estimates_seed{seed}.parquet")
            vehicle = table["vehicle_id"].to_numpy(zero_copy_only=False)
            excited = table["excited"].to_numpy(zero_copy_only=False).astype(bool)
            lower, upper = table["mu_lower"].to_numpy(), table["mu_upper"].to_numpy()
            sends = np.isin(vehicle, senders)
            for group, mask in (("senders", sends), ("the others", ~sends)):
                e = mask & excited
                print(
                    f"| {seed} | {name} | {group} | {mask.sum():,} | {e.sum() / mask.sum():.4f} | "
                    f"{np.median(lower[e]):.3f} | {np.quantile(upper[e], 0.1):.3f} / {np.median(upper[e]):.3f} |"
                )


if __name__ == "__main__":
    main()
