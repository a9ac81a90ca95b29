"""Figures of the fleet benchmark: the map against the truth at a few instants, and detection delay per patch."""

from __future__ import annotations

from pathlib import Path

import h3
import numpy as np
import pymap3d
from matplotlib import colormaps
from matplotlib.cm import ScalarMappable
from matplotlib.collections import PolyCollection
from matplotlib.colors import Normalize
from matplotlib.figure import Figure
from matplotlib.patches import Circle

from roadgrip.cloud.domain.friction_map import MEASURED

MU_NORM = Normalize(0.0, 1.2)
CMAP = "RdYlGn"


def _hexagon(cell: str, origin: tuple[float, float]) -> np.ndarray:
    boundary = np.array(h3.cell_to_boundary(cell))
    east, north, _ = pymap3d.geodetic2enu(boundary[:, 0], boundary[:, 1], 0.0, *origin, 0.0)
    return np.column_stack([east, north])


def plot_map_vs_truth(result, path: Path, instants: int = 4) -> Path:
    """For the first seed, at `instants` snapshot times spread over the run: the map's cells coloured by their mu
    (grey: driven, no excited evidence), the patches there at that instant as discs coloured by their true mu (dashed
    outline: not there now), the active warnings' cells outlined in black."""
    scenario, run = result.scenario, result.run
    network = scenario.network
    times = sorted(run.snapshots)
    chosen = [times[k] for k in np.linspace(0, len(times) - 1, min(instants, len(times))).round().astype(int)]
    columns = min(len(chosen), 2)
    rows = -(-len(chosen) // columns)
    fig = Figure(figsize=(6.5 * columns, 3.6 * rows + 0.6), layout="constrained")
    axes = fig.subplots(rows, columns, squeeze=False).ravel()
    for ax, t in zip(axes, chosen):
        for road in network.roads:
            ax.plot(*road.points_m.T, color="0.75", lw=0.8, zorder=1)
        cells = run.snapshots[t]
        measured = [c for c in cells if c.status == MEASURED]
        unknown = [c for c in cells if c.status != MEASURED]
        if unknown:
            ax.add_collection(
                PolyCollection(
                    [_hexagon(c.cell, network.origin) for c in unknown],
                    facecolor="0.9",
                    edgecolor="0.8",
                    lw=0.3,
                    zorder=2,
                )
            )
        if measured:
            ax.add_collection(
                PolyCollection(
                    [_hexagon(c.cell, network.origin) for c in measured],
                    array=np.array([c.mu for c in measured]),
                    cmap=CMAP,
                    norm=MU_NORM,
                    edgecolor="0.4",
                    lw=0.3,
                    zorder=3,
                )
            )
        for patch in network.patches:
            there = bool(patch.active(t))
            ax.add_patch(
                Circle(
                    (patch.east_m, patch.north_m),
                    patch.radius_m,
                    zorder=4,
                    lw=1.2,
                    facecolor=_colour(patch.mu) if there else "none",
                    alpha=0.9 if there else 1.0,
                    edgecolor="k" if there else "0.5",
                    ls="-" if there else "--",
                )
            )
        active = [w.cell for w in result.warnings if w.detection_s <= t and (w.end_s is None or w.end_s > t)]
        if active:
            ax.add_collection(
                PolyCollection(
                    [_hexagon(c, network.origin) for c in active], facecolor="none", edgecolor="k", lw=1.6, zorder=5
                )
            )
        ax.set_title(f"t = {t / 60:.0f} min: {len(measured)} cells with evidence, {len(active)} warnings", fontsize=9)
        ax.set_aspect("equal")
        ax.set_xlim(-2700, 2900)
        ax.set_ylim(-1600, 900)
        ax.set_xlabel("east (m)")
        ax.set_ylabel("north (m)")
    fig.colorbar(
        ScalarMappable(norm=MU_NORM, cmap=CMAP), ax=axes, shrink=0.8, label="mu (cells: the map; discs: the truth)"
    )
    fig.suptitle(
        f"Fleet benchmark, seed {result.seed}: the friction map against the true patches\n(black hexagons: "
        f"active warnings; dashed discs: patches not there at that instant; grey cells: driven, no excited "
        f"evidence)",
        fontsize=10,
    )
    fig.savefig(path, dpi=110)
    return path


def _colour(mu: float):
    return colormaps[CMAP](MU_NORM(mu))


def plot_detection_delay(patch_rows: list[dict], path: Path) -> Path:
    """Per patch: time from its appearance to its first warning, and the passes until then, against its mu;
    patches never warned at the top (x), by seed."""
    fig = Figure(figsize=(10, 4.2), layout="constrained")
    ax_t, ax_p = fig.subplots(1, 2)
    seeds = sorted({r["seed"] for r in patch_rows})
    markers = "osD^v<>"
    top_t = max([r["time_to_first_s"] / 60 for r in patch_rows if r["detected"]] + [10.0]) * 1.15
    top_p = max([r["passes_to_first"] for r in patch_rows if r["detected"]] + [5]) * 1.15
    for k, seed in enumerate(seeds):
        rows = [r for r in patch_rows if r["seed"] == seed]
        hit = [r for r in rows if r["detected"]]
        miss = [r for r in rows if not r["detected"]]
        ax_t.scatter(
            [r["mu"] for r in hit],
            [r["time_to_first_s"] / 60 for r in hit],
            marker=markers[k % 7],
            label=f"seed {seed}",
        )
        ax_p.scatter(
            [r["mu"] for r in hit], [r["passes_to_first"] for r in hit], marker=markers[k % 7], label=f"seed {seed}"
        )
        ax_t.scatter([r["mu"] for r in miss], [top_t] * len(miss), marker="x", color=f"C{k}")
        ax_p.scatter([r["mu"] for r in miss], [top_p] * len(miss), marker="x", color=f"C{k}")
    for ax, top, label in ((ax_t, top_t, "time to first warning (min)"), (ax_p, top_p, "passes until first warning")):
        ax.axhline(top, color="0.6", lw=0.8, ls=":")
        ax.text(0.02, top, " never warned (x)", va="bottom", fontsize=8, transform=ax.get_yaxis_transform())
        ax.axvline(0.3, color="0.6", lw=0.8, ls="--")
        ax.axvline(0.4, color="0.8", lw=0.8, ls="--")
        ax.set_xlabel("patch mu (dashed: 0.3 target, 0.4 warning threshold)")
        ax.set_ylabel(label)
        ax.set_ylim(0, top * 1.1)
    ax_p.axhline(3, color="r", lw=0.8)
    ax_t.legend(fontsize=8)
    fig.suptitle("Detection delay per patch (the fleet benchmark)", fontsize=10)
    fig.savefig(path, dpi=110)
    return path


def plot_tradeoff(rows: list[dict], chosen: dict | None, path: Path) -> Path:
    """The warning engine's trade-off: recall of the mu <= 0.3 patches against false warnings per 100 km of dry road,
    one point per setting (colour: share warned by the 3rd pass), the product's setting and the chosen one marked."""
    fig = Figure(figsize=(7.5, 4.8), layout="constrained")
    ax = fig.subplots()
    x = np.array([r["false_per_100km"] for r in rows], float)
    y = np.array([np.nan if r["recall"] is None else r["recall"] for r in rows], float)
    c = np.array([0.0 if r["within_3rd_pass"] is None else r["within_3rd_pass"] for r in rows], float)
    jitter = np.random.default_rng(0).uniform(-0.004, 0.004, y.size)  # settings on the same point stay visible
    points = ax.scatter(x, y + jitter, c=c, cmap="viridis", vmin=0, vmax=1, s=22, alpha=0.8)
    fig.colorbar(points, ax=ax, label="share warned by the 3rd pass")
    product = next((r for r in rows if r["product"]), None)
    marks = (
        (product, {"marker": "s", "s": 140, "facecolor": "none", "edgecolor": "r", "lw": 1.8}, "product now"),
        (chosen, {"marker": "*", "s": 220, "facecolor": "none", "edgecolor": "k", "lw": 1.2}, "the rule's pick"),
    )
    for row, style, label in marks:
        if row is not None and row["recall"] is not None:
            ax.scatter(
                [row["false_per_100km"]],
                [row["recall"]],
                label=f"{label}: mu {row['threshold_mu']}, "
                f"{row['min_low_passes']} passes, {row['min_excited_per_pass']} excited, "
                f"{row['validity_s']:.0f} s",
                **style,
            )
    ax.axhline(0.95, color="0.6", ls="--", lw=0.8)
    ax.set_xlabel("false warnings per 100 km of dry road (seeds pooled)")
    ax.set_ylabel("recall, patches mu <= 0.3")
    ax.set_ylim(-0.03, 1.05)
    ax.legend(fontsize=8, loc="lower right")
    fig.suptitle("Warning engine settings: recall against false warnings (fleet benchmark, replayed)", fontsize=10)
    fig.savefig(path, dpi=110)
    return path
