import numpy as np
import pyarrow as pa
import pytest

from roadgrip.evaluation.report import (
    CONDITIONS,
    PAPER_MODELS,
    _change_times,
    load_paper_results,
    read_metrics_csv,
    summary_rows,
    tables_markdown,
    write_all_figures,
    write_figures,
    write_metrics_csv,
    write_report,
)

OURS = ("DNN", "CNN", "ConvLSTM", "SA-CNN-LSTM", "Constant (training mean)")
STEPS = {"increasing": [0.1, 0.3, 0.6, 0.9], "decreasing": [0.9, 0.6, 0.3, 0.1]}
FIXED = {"low": 0.2, "medium": 0.5, "high": 0.8}


def make_metrics(sa_wins=frozenset(CONDITIONS), feature_sets=("paper", "terminal"), scopes=("condition", "all")):
    """SA-CNN-LSTM RMSE 0.01 where it wins (baselines 0.02-0.04), 0.05 elsewhere (worst of all)."""
    rows = []
    for scope in scopes:
        for fs in feature_sets:
            for condition in CONDITIONS:
                for k, model in enumerate(OURS):
                    rmse = {"DNN": 0.04, "CNN": 0.02, "ConvLSTM": 0.03, "Constant (training mean)": 0.2}.get(model)
                    if model == "SA-CNN-LSTM":
                        rmse = 0.01 if condition in sa_wins else 0.05
                    rows.append(
                        {
                            "condition": condition,
                            "model": model,
                            "feature_set": fs,
                            "trained_on": scope,
                            "rmse": rmse,
                            "mae": 0.8 * rmse,
                            "n": 400,
                        }
                    )
    return rows


def make_predictions(seed=0, scopes=(("terminal", "condition"), ("paper", "all"))):
    """Per condition and road, a 40 s test run at 10 Hz: sine-like truth on fixed roads, four mu steps on the others."""
    rng = np.random.default_rng(seed)
    t_s = np.arange(400) / 10.0
    columns = {
        c: []
        for c in ("condition", "trained_on", "model", "feature_set", "run_id", "road", "t_s", "mu_true", "mu_pred")
    }
    for fs, scope in scopes:
        for condition in CONDITIONS:
            if condition in FIXED:
                truth = FIXED[condition] + 0.02 * np.sin(2 * np.pi * t_s / 13.0)
            else:
                truth = np.repeat(STEPS[condition], 100)
            for road in ("straight", "circular"):
                for k, model in enumerate(PAPER_MODELS):
                    start = 5 if model == "ConvLSTM" else 0  # a sequence model has no estimate before its first window
                    pred = truth + rng.normal(0.0, 0.01 * (5 - k), t_s.size)
                    n = t_s.size - start
                    columns["condition"] += [condition] * n
                    columns["trained_on"] += [scope] * n
                    columns["model"] += [model] * n
                    columns["feature_set"] += [fs] * n
                    columns["run_id"] += [f"paper-{condition}-{road}-e2"] * n
                    columns["road"] += [road] * n
                    columns["t_s"] += t_s[start:].tolist()
                    columns["mu_true"] += truth[start:].tolist()
                    columns["mu_pred"] += pred[start:].tolist()
    return pa.table(columns)


def test_paper_results_load():
    rows = load_paper_results()
    assert len(rows) == 25
    assert {(r["condition"], r["model"]) for r in rows} == {(c, m) for c in CONDITIONS for m in PAPER_MODELS}
    low_sa = next(r for r in rows if r["condition"] == "low" and r["model"] == "SA-CNN-LSTM")
    assert (low_sa["rmse"], low_sa["mae"]) == (0.012, 0.010)


def test_tables_have_every_condition_with_paper_values_beside_ours():
    metrics = make_metrics()
    for row in metrics:
        key = (row["condition"], row["model"], row["feature_set"], row["trained_on"])
        if key == ("low", "SA-CNN-LSTM", "paper", "condition"):
            row["rmse"], row["mae"] = 0.0123, 0.0099
    text = tables_markdown(metrics)
    for number, condition in zip(range(2, 7), CONDITIONS):
        assert f"### Table {number}: {condition} adhesion coefficient" in text
    assert text.index("Trained per condition") < text.index("One model trained on all")
    header = (
        "| model | paper RMSE | paper MAE | ours, paper features RMSE | ours, paper features MAE | "
        "ours, terminal features RMSE | ours, terminal features MAE | n |"
    )
    assert header in text
    assert "| SA-CNN-LSTM | 0.012 | 0.010 | 0.012 | 0.010 | 0.010 | 0.008 | 400 |" in text
    # the reference row has no paper value; the paper's improved model has none of ours
    assert "| Constant (training mean) | - | - | 0.200 | 0.160 | 0.200 | 0.160 | 400 |" in text
    assert "| Improved SA-CNN-LSTM | 0.009 | 0.008 | - | - | - | - | - |" in text
    low = text.split("### Table 2")[1].split("###")[0]
    models = [line.split(" | ")[0][2:] for line in low.splitlines() if line.startswith("| ") and "---" not in line][1:]
    assert models == [*PAPER_MODELS, "Constant (training mean)"]


def test_tables_show_other_models_after_the_papers():
    metrics = make_metrics(feature_sets=("terminal",), scopes=("condition",))
    metrics.append(
        {
            "condition": "high",
            "model": "EKF",
            "feature_set": "terminal",
            "trained_on": "condition",
            "rmse": float("nan"),
            "mae": None,
            "n": 12,
        }
    )
    text = tables_markdown(metrics)
    assert "ours, paper features" not in text and "One model trained on all" not in text
    assert "| EKF | - | - | - | - | 12 |" in text
    high = text.split("### Table 4")[1]
    assert high.index("Improved SA-CNN-LSTM") < high.index("Constant (training mean)") < high.index("EKF")


def test_summary_counts_wins():
    metrics = make_metrics(sa_wins={"low", "high", "decreasing"})
    rows = summary_rows(metrics)
    paper, ours = rows[0], rows[1:]
    assert paper["source"] == "paper" and paper["wins_all"] == 5 and paper["criterion_met"]
    assert [(r["trained_on"], r["feature_set"]) for r in ours] == [
        ("condition", "paper"),
        ("condition", "terminal"),
        ("all", "paper"),
        ("all", "terminal"),
    ]
    for row in ours:
        assert row["wins"] == {"DNN": 3, "CNN": 3, "ConvLSTM": 3}
        assert row["wins_all"] == 3 and row["compared"] == 5 and not row["criterion_met"]
    text = tables_markdown(metrics)
    assert "| ours | per condition | terminal | 3 of 5 | 3 of 5 | 3 of 5 | 3 of 5 | 5 of 5 | not met |" in text
    assert "| paper (Tables 2-6) | per condition | paper | 5 of 5 | 5 of 5 | 5 of 5 | 5 of 5 | 5 of 5 | met |" in text


def test_summary_counts_each_baseline_apart_and_missing_values_never_win():
    metrics = make_metrics(feature_sets=("terminal",), scopes=("condition",))
    for row in metrics:
        if row["model"] == "SA-CNN-LSTM" and row["condition"] in ("low", "medium"):
            row["rmse"] = 0.025  # beats DNN (0.04) and ConvLSTM (0.03), not CNN (0.02)
        if row["model"] == "CNN" and row["condition"] == "high":
            row["rmse"] = None  # not comparable
        if row["model"] == "DNN" and row["condition"] == "increasing":
            row["rmse"] = 0.01  # a tie with SA-CNN-LSTM is no win
    (ours,) = summary_rows(metrics)[1:]
    assert ours["wins"] == {"DNN": 4, "CNN": 2, "ConvLSTM": 5}
    assert ours["wins_all"] == 1 and ours["compared"] == 4
    metrics = make_metrics(sa_wins={"low", "medium", "high", "increasing"}, feature_sets=("paper",), scopes=("all",))
    assert summary_rows(metrics)[1]["wins_all"] == 4 and summary_rows(metrics)[1]["criterion_met"]


def test_bad_metrics_are_refused():
    row = {
        "condition": "low",
        "model": "CNN",
        "feature_set": "paper",
        "trained_on": "condition",
        "rmse": 0.1,
        "mae": 0.1,
    }
    with pytest.raises(ValueError, match="condition must be one of"):
        tables_markdown([{**row, "condition": "icy"}])
    with pytest.raises(ValueError, match="lacks key"):
        tables_markdown([{k: v for k, v in row.items() if k != "trained_on"}])
    with pytest.raises(ValueError, match="repeats"):
        tables_markdown([row, dict(row)])


def test_metrics_csv_round_trips(tmp_path):
    metrics = make_metrics(feature_sets=("paper",), scopes=("condition",))
    metrics[0]["epochs"] = 30
    metrics[1]["rmse"] = None
    metrics[2]["mae"] = 1 / 3
    path = write_metrics_csv(metrics, tmp_path / "metrics.csv")
    assert path.read_text().splitlines()[0] == "condition,model,feature_set,trained_on,rmse,mae,n,epochs"
    back = read_metrics_csv(path)
    expected = [{"epochs": None, **row} for row in metrics]
    assert back == expected


def test_change_times_of_steps_and_ramps():
    t_s = np.arange(100) / 10.0
    steps = np.repeat([0.1, 0.3, 0.6, 0.9], 25)
    assert _change_times(t_s, steps) == pytest.approx([2.5, 5.0, 7.5])
    ramp = np.interp(t_s, [0.0, 4.0, 6.0, 10.0], [0.9, 0.9, 0.1, 0.1])
    assert _change_times(t_s, ramp) == pytest.approx([5.0])
    assert _change_times(t_s, np.full(100, 0.5)) == []


def test_figures_are_written_for_every_condition(tmp_path):
    predictions = make_predictions()
    paths = write_figures(predictions, tmp_path)
    assert [p.name for p in paths] == [
        "figure_4_low.png",
        "figure_5_medium.png",
        "figure_6_high.png",
        "figure_7_increasing.png",
        "figure_8_decreasing.png",
    ]
    for path in paths:
        data = path.read_bytes()
        assert len(data) > 10_000 and data[:8] == b"\x89PNG\r\n\x1a\n"
    with pytest.raises(ValueError, match="no rows for feature_set='paper', trained_on='condition'"):
        write_figures(predictions, tmp_path, feature_set="paper")


@pytest.mark.slow
def test_figures_are_deterministic_for_a_seed(tmp_path):
    predictions = make_predictions()
    a = write_figures(predictions, tmp_path / "a", seed=3)[0].read_bytes()
    b = write_figures(predictions, tmp_path / "b", seed=3)[0].read_bytes()
    assert a == b


@pytest.mark.slow
def test_all_figures_and_report(tmp_path):
    predictions = make_predictions()
    metrics = make_metrics()
    out = write_report(metrics, predictions, tmp_path)
    assert out["metrics_csv"] == tmp_path / "metrics.csv" and out["tables_md"] == tmp_path / "tables.md"
    assert read_metrics_csv(out["metrics_csv"]) == metrics
    assert out["tables_md"].read_text() == tables_markdown(metrics)
    assert sorted({p.parent.name for p in out["figures"]}) == ["paper-all", "terminal-condition"]
    assert len(out["figures"]) == 10 and all(p.stat().st_size > 0 for p in out["figures"])
    assert write_all_figures(predictions, tmp_path / "again") == [
        tmp_path / "again" / p.relative_to(tmp_path) for p in out["figures"]
    ]
