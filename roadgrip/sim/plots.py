"""Figures of simulated runs: what happened to the car, its tires and the road."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import pyarrow as pa
import pyarrow.compute as pc

from roadgrip.units import mps_to_kmh


def plot_run(table: pa.Table, run_id: str, path: str | Path) -> Path:
    """Speed, road mu, slip ratios and accelerations of one run against time, as a PNG."""
    run = table.filter(pc.equal(table["run_id"], run_id))
    if run.num_rows == 0:
        raise ValueError(f"run_id {run_id!r} is not in the table")
    col = {name: run[name].to_numpy() for name in run.column_names if name not in ("vehicle_id", "run_id")}
    t = col["t_s"]
    fig, axes = plt.subplots(4, 1, figsize=(9, 10), sharex=True)
    axes[0].plot(t, mps_to_kmh(col["vx_true_mps"]), label="true speed")
    axes[0].plot(t, mps_to_kmh(col["speed_mps"]), lw=0.8, alpha=0.7, label="terminal speed")
    axes[0].set_ylabel("speed [km/h]")
    axes[1].plot(t, col["mu"], color="k", label="road mu (label)")
    for w in ("fl", "rr"):
        axes[1].plot(t, col[f"mu_{w}"], lw=0.8, ls="--", label=f"mu under {w}")
    axes[1].set_ylabel("adhesion coefficient")
    for w in ("fl", "fr", "rl", "rr"):
        axes[2].plot(t, col[f"slip_ratio_{w}"], lw=0.8, label=w)
    axes[2].set_ylabel("slip ratio (eq. 6)")
    axes[3].plot(t, col["accel_lon_mps2"], lw=0.8, label="a_x measured")
    axes[3].plot(t, col["accel_lat_mps2"], lw=0.8, label="a_y measured")
    abs_on = col["abs_active"]
    if abs_on.any():
        axes[3].fill_between(t, -10, 10, where=abs_on, color="r", alpha=0.1, label="ABS active")
    axes[3].set_ylim(-10, 10)
    axes[3].set_ylabel("acceleration [m/s^2]")
    axes[3].set_xlabel("time [s]")
    for ax in axes:
        ax.grid(alpha=0.3)
        ax.legend(loc="upper right", fontsize=8)
    fig.suptitle(f"roadgrip simulator: {run_id}")
    fig.tight_layout()
    out = Path(path)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out
