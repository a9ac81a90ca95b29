"""The `roadgrip` command line: thin commands over the package's parts."""

from __future__ import annotations

import functools
import subprocess
import time
from pathlib import Path

import numpy as np
import pyarrow.compute as pc
import typer
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

import roadgrip
from roadgrip.data.dataset import write_dataset
from roadgrip.sim.presets import PRESETS, preset_scenarios

app = typer.Typer(help="roadgrip: tire-road adhesion (mu) estimation from connected-vehicle telemetry.",
                  no_args_is_help=True, add_completion=False)
bench_app = typer.Typer(help="Performance benchmarks.", no_args_is_help=True)
app.add_typer(bench_app, name="bench")
console = Console()


def friendly_errors(fn):
    """Bad input ends the command with its message and exit status 2, not a traceback."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except (ValueError, TypeError, FileExistsError, FileNotFoundError) as err:
            console.print(f"[bold red]error:[/] {err}")
            raise typer.Exit(2) from err

    return wrapper


def _code_version() -> str:
    try:
        sha = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, timeout=5,
                             cwd=Path(__file__).parent).stdout.strip()
    except OSError:
        sha = ""
    return f"{roadgrip.__version__}+{sha}" if sha else roadgrip.__version__


def _simulate_dataset(preset: str, runs: int | None, seed: int, out: Path, overwrite: bool,
                      scenario_file: Path | None = None):
    from roadgrip.sim.scenario_file import load_scenarios
    from roadgrip.sim.simulate import simulate

    scenarios = load_scenarios(scenario_file) if scenario_file else preset_scenarios(preset, runs, seed)
    start = time.perf_counter()
    with Progress(TextColumn("[bold]simulating[/] {task.description}"), BarColumn(), MofNCompleteColumn(),
                  TimeElapsedColumn(), console=console, transient=True) as progress:
        task = progress.add_task(f"{preset} preset", total=len(scenarios))
        table = simulate(scenarios, progress=lambda n: progress.advance(task, n))
    manifest = {
        "format": "roadgrip simulation dataset (DESIGN 3.3)",
        "preset": preset,
        "scenario_file": str(scenario_file) if scenario_file else None,
        "seed": seed,
        "runs": len(scenarios),
        "code_version": _code_version(),
        "vehicles": sorted({s.vehicle.name for s in scenarios}),
        "scenarios": [s.describe() for s in scenarios],
    }
    write_dataset(out, table, manifest, overwrite=overwrite)
    return scenarios, table, time.perf_counter() - start


@app.command()
@friendly_errors
def simulate(
    out: Path = typer.Option(..., help="output folder (Parquet + manifest)"),
    preset: str = typer.Option(None, help=f"scenario preset: {' | '.join(PRESETS)}"),
    scenario: Path = typer.Option(None, help="a scenario YAML file (see roadgrip/sim/scenario_file.py) instead of a preset"),
    runs: int = typer.Option(None, help="number of runs (random preset; the paper preset has 20)"),
    seed: int = typer.Option(0, help="seed: the same seed gives the same data"),
    overwrite: bool = typer.Option(False, help="replace an existing dataset in OUT"),
):
    """Simulate a preset (or the runs of a scenario file) and write the dataset (DESIGN 3.3)."""
    if (preset is None) == (scenario is None):
        raise ValueError("give exactly one of --preset and --scenario")
    scenarios, table, wall = _simulate_dataset(preset or "custom", runs, seed, out, overwrite, scenario)
    console.print(f"wrote {table.num_rows} samples of {len(scenarios)} runs to {out} in {wall:.1f} s")


@bench_app.command("sim")
@friendly_errors
def bench_sim_command(
    runs: int = typer.Option(256, help="runs in the batch case"),
    seed: int = typer.Option(0, help="seed of the scenarios"),
):
    """Simulated seconds per wall-clock second: one run, the paper preset, a batch."""
    from roadgrip.sim.bench import bench_sim, machine_description

    with console.status("benchmarking the simulator..."):
        rows = bench_sim(runs, seed)
    table = Table(title="roadgrip bench sim")
    for name in ("case", "runs", "simulated s", "wall s", "x real time"):
        table.add_column(name, justify="left" if name == "case" else "right")
    for row in rows:
        table.add_row(row["case"], str(row["runs"]), f"{row['simulated_s']:.0f}", f"{row['wall_s']:.3f}",
                      f"{row['realtime_factor']:,.0f}")
    console.print(table)
    console.print(f"machine: {machine_description()}")


@app.command()
@friendly_errors
def demo(
    out: Path = typer.Option(Path("roadgrip-demo"), help="folder for the demo's dataset and figure"),
):
    """The main job end to end on this machine: simulate the paper's data set and show what the road did to the car."""
    from roadgrip.sim.plots import plot_run

    scenarios, table, wall = _simulate_dataset("paper", None, 0, out / "paper-dataset", overwrite=True)
    summary = Table(title=f"paper preset: {len(scenarios)} runs, {table.num_rows} samples, simulated in {wall:.1f} s")
    for name in ("run", "road mu", "top speed km/h", "end speed km/h", "max |a_x| m/s^2", "ABS samples", "max |slip|"):
        summary.add_column(name, justify="left" if name == "run" else "right", no_wrap=name == "run")
    for s in scenarios:
        run = table.filter(pc.equal(table["run_id"], s.run_id))
        vx = run["vx_true_mps"].to_numpy()
        slip = np.abs(np.column_stack([run[f"slip_ratio_{w}"].to_numpy() for w in ("fl", "fr", "rl", "rr")]))
        mu = np.unique(run["mu"].to_numpy())
        summary.add_row(s.run_id, "/".join(f"{m:.1f}" for m in mu), f"{vx.max() * 3.6:.0f}", f"{vx[-1] * 3.6:.0f}",
                        f"{np.abs(run['ax_true_mps2'].to_numpy()).max():.2f}",
                        str(int(run["abs_active"].to_numpy().sum())), f"{slip.max():.2f}")
    console.print(summary)
    figure = plot_run(table, "paper-decreasing-straight-e1", out / "paper-decreasing-straight-e1.png")
    console.print(f"dataset: {out / 'paper-dataset'}\nfigure: {figure}")
