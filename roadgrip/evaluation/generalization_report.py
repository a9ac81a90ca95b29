"""The generalization benchmark's outputs: metrics.csv, tables.md and a figure of estimates with their intervals."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.csv as pacsv
import pyarrow.parquet as pq
from matplotlib.figure import Figure

COLUMNS = [
    ("model", "model", "{}"),
    ("feature_set", "features", "{}"),
    ("rmse_excited", "RMSE excited", "{:.3f}"),
    ("mae_excited", "MAE excited", "{:.3f}"),
    ("rmse_excited_045_055", "RMSE excited, mu 0.45-0.55", "{:.3f}"),
    ("rmse_excited_085_100", "RMSE excited, mu 0.85-1.0", "{:.3f}"),
    ("rmse_all", "RMSE all", "{:.3f}"),
    ("mae_all", "MAE all", "{:.3f}"),
    ("coverage_excited", "coverage excited", "{:.2f}"),
    ("coverage_not_excited", "coverage not excited", "{:.2f}"),
    ("coverage_all", "coverage all", "{:.2f}"),
    ("width_excited", "width excited", "{:.2f}"),
    ("width_not_excited", "width not excited", "{:.2f}"),
    ("judged_excited", "judged excited", "{:.1%}"),
    ("truly_excited", "truly excited", "{:.1%}"),
    ("out_of_range", "out of [0, 1.2]", "{}"),
]


def generalization_markdown(metrics: list[dict]) -> str:
    n, n_exc = metrics[0]["n"], metrics[0]["n_excited"]
    lines = [
        "# Generalization benchmark",
        "",
        (
            "Test: runs of the held-out compact hatchback on roads whose mu lies only in the held-out bands [0.45, 0.55] and "
            f"[0.85, 1.0]; {n} test estimates, {n_exc} of them excited (CONTRACTS 4). 'coverage' is the share of true mu "
            "inside the 90 % interval (target 0.87-0.93), 'width' its mean width; 'judged excited' is the share the "
            "estimator flagged excited. Sorted by RMSE over excited samples (the target: at most 0.05)."
        ),
        "",
        "| " + " | ".join(label for _, label, _ in COLUMNS) + " |",
        "| " + " | ".join(":---" if key in ("model", "feature_set") else "---:" for key, _, _ in COLUMNS) + " |",
    ]
    for row in sorted(metrics, key=lambda r: r["rmse_excited"]):
        cells = []
        for key, _, fmt in COLUMNS:
            value = row.get(key)
            cells.append(
                "-" if value is None or (isinstance(value, float) and math.isnan(value)) else fmt.format(value)
            )
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def plot_run(predictions: pa.Table, run_id: str, models: list[tuple[str, str]], path: Path) -> Path:
    """Truth, estimates and 90 % intervals of some (model, feature set) estimators along one test run."""
    fig = Figure(figsize=(10, 3.2 * len(models)))
    axes = fig.subplots(len(models), 1, sharex=True, squeeze=False)[:, 0]
    run = predictions.filter(pc.equal(predictions["run_id"], run_id))
    for ax, (model, feature_set) in zip(axes, models):
        rows = run.filter(pc.and_(pc.equal(run["model"], model), pc.equal(run["feature_set"], feature_set)))
        if rows.num_rows == 0:
            continue
        t = rows["t_s"].to_numpy()
        ax.plot(t, rows["mu_true"].to_numpy(), color="k", lw=1.5, label="true mu")
        ax.plot(t, rows["mu_pred"].to_numpy(), lw=1.0, label=f"{model} ({feature_set} features)")
        ax.fill_between(t, rows["mu_lower"].to_numpy(), rows["mu_upper"].to_numpy(), alpha=0.2, label="90 % interval")
        excited = rows["excited"].to_numpy()
        ax.scatter(t[excited], rows["mu_true"].to_numpy()[excited], s=6, color="r", label="excited samples", zorder=3)
        ax.set_ylim(-0.1, 1.4)
        ax.set_ylabel("mu")
        ax.grid(alpha=0.3)
        ax.legend(loc="upper right", fontsize=8)
    axes[-1].set_xlabel("time [s]")
    fig.suptitle(f"generalization test run {run_id} (held-out vehicle and mu)")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    return path


def write_generalization_report(metrics: list[dict], predictions: pa.Table, out_dir: str | Path) -> dict:
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    pacsv.write_csv(pa.Table.from_pylist(metrics), out / "metrics.csv")
    (out / "tables.md").write_text(generalization_markdown(metrics))
    pq.write_table(predictions, out / "predictions.parquet")
    best = min((r for r in metrics if r["feature_set"] != "-"), key=lambda r: r["rmse_excited"])
    excited_share = {}
    for run_id in np.unique(predictions["run_id"].to_numpy(zero_copy_only=False)):
        run = predictions.filter(pc.equal(predictions["run_id"], run_id))
        excited_share[run_id] = float(run["excited"].to_numpy().mean())
    run_id = max(excited_share, key=excited_share.get)
    figure = plot_run(
        predictions,
        run_id,
        [("pmf", "-"), (best["model"], best["feature_set"]), ("EKF", "-")],
        out / "estimates_with_intervals.png",
    )
    return {
        "metrics_csv": out / "metrics.csv",
        "tables_md": out / "tables.md",
        "predictions": out / "predictions.parquet",
        "figures": [figure],
    }
