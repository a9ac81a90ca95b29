"""The warning engine's trade-off sweep: a recorded engine replays to the same warnings at the same settings, other
settings change them, the rule picks the safe setting with the best recall, and the benchmark writes the curve."""

import ast
from pathlib import Path

import pyarrow.csv as pacsv
import pyarrow.parquet as pq
import pytest
from warning_route import PATCH, T0_MS, drive

from roadgrip.cloud.domain.warnings import WarningEngine
from roadgrip.evaluation.fleet_benchmark import EngineRecorder, FleetConfig
from roadgrip.evaluation.fleet_report import run_fleet_benchmark
from roadgrip.evaluation.fleet_sweep import GRID, as_warnings, choose, grid_settings, replay, rounds_of


def _record(rounds, **kwargs):
    recorder = EngineRecorder(WarningEngine(**kwargs))
    events = []
    for rows, now_ms in rounds:
        events += recorder.update(rows, now_ms)
    return recorder, events


def _latest(events):
    return {e.warning_id: (e.cell, e.detection_ms, e.status, e.reason, e.evidence_ms) for e in events}


def _rounds():
    """Five vehicles over the icy patch, in rounds of uneven size (as the pipeline batches), then a dry one; the clock
    of each round is its newest sample (map_clock data)."""
    rows = [{**r, "mu_proven": 0.1} for k in range(5) for r in drive(f"v{k}", T0_MS + 40_000 * k)]
    rows += [{**r, "mu_proven": 0.5} for r in drive("dry", T0_MS + 400_000, slippery=set())]  # it proves grip
    rows.sort(key=lambda r: r["timestamp_ms"])
    rounds, start = [], 0
    for size in (7, 300, 1, 900, 2000, 50):
        batch = rows[start : start + size]
        if batch:
            rounds.append((batch, max(r["timestamp_ms"] for r in batch)))
        start += size
    rest = rows[start:]
    rounds.append((rest, max(r["timestamp_ms"] for r in rest)))
    rounds.append(([], rounds[-1][1] + 3_600_000))  # a late empty round: expiries
    return rounds


def test_a_replay_of_the_recorded_rounds_gives_the_engine_s_warnings():
    recorder, events = _record(_rounds())
    assert {e.cell for e in events} == PATCH and any(e.reason == "recovered" for e in events)
    table = recorder.table()
    assert table.num_rows == sum(len(rows) for rows, _ in _rounds())
    assert replay(rounds_of(table)) == _latest(events)
    assert as_warnings(replay(rounds_of(table)), T0_MS)[0].detection_s > 0


def test_other_settings_change_the_replay():
    recorder, _ = _record(_rounds())
    rounds = rounds_of(recorder.table())
    assert replay(rounds, min_low_passes=6) == {}  # five vehicles: never six low passes
    assert replay(rounds, threshold_mu=0.25) == {}  # the patch's mu_upper is 0.3
    _, strict = _record(_rounds(), min_low_passes=4)
    assert replay(rounds, min_low_passes=4) == _latest(strict)


def _row(recall, false, within=0.0, passes=5.0, linger=300.0, product=False, **setting):
    return {
        "recall": recall,
        "max_false_per_seed": false,
        "within_3rd_pass": within,
        "passes_to_first_median": passes,
        "linger_max_s": linger,
        "product": product,
        **setting,
    }


def test_the_rule_takes_the_best_recall_without_false_warnings_then_breaks_ties():
    rows = [
        _row(1.0, 1, name="unsafe"),
        _row(0.8, 0, name="a"),
        _row(0.8, 0, within=0.2, name="b"),
        _row(0.8, 0, within=0.2, passes=4.0, name="c"),
        _row(0.8, 0, within=0.2, passes=4.0, linger=200.0, name="d"),
        _row(0.5, 0, name="low"),
    ]
    assert choose(rows)["name"] == "d"
    assert choose([_row(0.8, 0, product=True, name="now"), _row(0.8, 0, name="other")])["name"] == "now"
    assert choose([_row(1.0, 2)]) is None


def test_unknown_grid_parameters_are_errors():
    with pytest.raises(ValueError, match="pass_gap"):
        grid_settings({"pass_gap": (1,)})
    assert len(grid_settings({"threshold_mu": (0.3, 0.4), "min_low_passes": (1, 2, 3)})) == 6


@pytest.mark.slow
def test_the_benchmark_keeps_the_engine_s_estimates_and_writes_the_curve(tmp_path):
    config = FleetConfig(
        vehicles=3,
        duration_s=240.0,
        patches_per_band=1,
        control_patches=1,
        appear_max_s=20.0,
        life_s=(100.0, 150.0),
        snapshot_every_s=120.0,
    )
    grid = {"threshold_mu": (0.4, 0.5), "min_low_passes": (1, 2), "min_excited_per_pass": (3,), "validity_s": (600.0,)}
    result = run_fleet_benchmark(tmp_path, seed=1, seeds=1, config=config, sweep=grid, tuning_seeds=(2,))
    estimates = pq.read_table(tmp_path / "estimates_seed1.parquet")
    assert estimates.num_rows > 0 and {"round", "now_ms", "mu_upper", "excited"} <= set(estimates.column_names)
    rows = pacsv.read_csv(tmp_path / "tradeoff.csv").to_pylist()
    assert len(rows) == 4 and sum(r["product"] for r in rows) == 1
    assert {str(r["seeds"]) for r in rows} == {"2"}  # tuned on the tuning seed, not the report's seed 1
    assert "tuning seeds 2, not the report's" in (tmp_path / "fleet.md").read_text()
    assert next(r for r in result["sweep"] if r["product"])["replay_matches_service"]
    assert (tmp_path / "tradeoff.png").stat().st_size > 0


@pytest.mark.parametrize("tuning_seeds", [(), (1, 5), (0,)])
def test_the_sweep_never_tunes_on_a_report_seed(tmp_path, tuning_seeds):
    with pytest.raises(ValueError, match="tuning_seeds"):
        run_fleet_benchmark(tmp_path, seed=0, seeds=2, sweep=GRID, tuning_seeds=tuning_seeds)


def test_the_fleet_modules_import_each_other_without_a_circle():
    """fleet_report scores, sweeps and reports; fleet_sweep replays and scores through fleet_metrics, never back."""
    folder = Path(__file__).parents[2] / "roadgrip" / "evaluation"
    imports = {}
    for path in folder.glob("fleet_*.py"):
        imports[path.stem] = {
            node.module.rsplit(".", 1)[1]
            for node in ast.walk(ast.parse(path.read_text()))
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("roadgrip.evaluation.fleet_")
        }
    assert "fleet_sweep" in imports["fleet_report"] and "fleet_report" not in imports["fleet_sweep"]

    def circle(path: list[str]) -> list[str] | None:
        for module in imports.get(path[-1], ()):
            found = [*path, module] if module in path else circle([*path, module])
            if found:
                return found
        return None

    assert [circle([m]) for m in sorted(imports)] == [None] * len(imports)
