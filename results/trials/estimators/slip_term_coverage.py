"""Where the physics validation split's coverage moves between two pmf versions: the pmf [base] estimates of every
validation run saved per sample (run, manoeuvre, true mu, interval), to compare two checkouts' outputs sample by sample.

    PYTHONPATH=<checkout> nice -n 19 python results/trials/estimators/slip_term_coverage.py OUT.npz
    python results/trials/estimators/slip_term_coverage.py --compare BEFORE.npz AFTER.npz

Validation split only (never the test split)."""

import argparse
import collections

import numpy as np


def save(path: str) -> None:
    from roadgrip.estimators.learned import load_estimator
    from roadgrip.evaluation.bins import estimates_on_runs
    from roadgrip.evaluation.physics_benchmark import simulate_split

    split = simulate_split("validation", channels=("base",))  # as run_physics_benchmark's "base" set
    est = estimates_on_runs(load_estimator("pmf"), split.tables["base"][0], split.profiles)
    est["manoeuvre"] = np.array([split.manoeuvres[r] for r in est["run_id"]])
    np.savez(path, **est)


def compare(before_path: str, after_path: str) -> None:
    a, b = np.load(before_path, allow_pickle=True), np.load(after_path, allow_pickle=True)
    mu = a["mu"]
    covered = {}
    for name, d in (("before", a), ("after", b)):
        covered[name] = (d["mu_lower"] <= mu) & (mu <= d["mu_upper"])
        low = mu <= 0.3
        print(
            f"{name}: coverage {covered[name].mean():.4f}, mu <= 0.3 {covered[name][low].mean():.4f};"
            f" mu <= 0.3 missed above (upper < mu) {int(((d['mu_upper'] < mu) & low).sum())},"
            f" below (lower > mu) {int(((d['mu_lower'] > mu) & low).sum())}"
        )
    lost = covered["before"] & ~covered["after"]
    print(f"newly uncovered {int(lost.sum())}, newly covered {int((covered['after'] & ~covered['before']).sum())}")
    print(collections.Counter(zip(b["run_id"][lost].tolist(), b["manoeuvre"][lost].tolist())).most_common(10))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("paths", nargs="+")
    parser.add_argument("--compare", action="store_true")
    args = parser.parse_args()
    if args.compare:
        compare(*args.paths)
    else:
        save(args.paths[0])


if __name__ == "__main__":
    main()
