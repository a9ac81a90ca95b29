import numpy as np
import pyarrow as pa
import pyarrow.csv as pacsv

from roadgrip.evaluation.generalization import evaluate_predictions
from roadgrip.evaluation.generalization_report import generalization_markdown, write_generalization_report
from roadgrip.training.fit import PreparedData


def _test_data(n=200):
    rng = np.random.default_rng(0)
    excited = np.arange(n) % 4 == 0
    return PreparedData(
        windows=np.zeros((n, 10, 3), np.float32),
        targets=rng.uniform(0.45, 0.55, n).astype(np.float32),
        runs=np.repeat(["test-00000", "test-00001"], n // 2),
        blocks=np.zeros(n, int),
        t_s=np.tile(np.arange(n // 2) * 0.1, 2),
        feature_set="physics",
        excited=excited,
        measured=np.column_stack([np.where(excited, 5.0, 0.1), np.zeros(n), np.zeros(n)]),
    )


def test_metrics_of_a_perfect_and_a_biased_estimator():
    test = _test_data()
    perfect = evaluate_predictions(
        "A", "physics", test, test.targets.astype(float), test.targets - 0.1, test.targets + 0.1
    )
    assert perfect["rmse_excited"] == 0.0 and perfect["coverage_all"] == 1.0 and perfect["width_excited"] > 0.19
    biased = evaluate_predictions("B", "-", test, test.targets + 0.3, test.targets + 0.2, test.targets + 0.4)
    assert abs(biased["rmse_all"] - 0.3) < 1e-6 and biased["coverage_all"] == 0.0
    assert perfect["truly_excited"] == 0.25 and perfect["judged_excited"] > 0.2


def test_report_files_and_table_order(tmp_path):
    test = _test_data()
    rows, tables = [], []
    for model, fs, bias in (("SA-CNN-LSTM", "physics", 0.2), ("EKF", "-", 0.05)):
        pred = test.targets + bias
        rows.append(evaluate_predictions(model, fs, test, pred, pred - 0.1, pred + 0.1))
        tables.append(
            pa.table(
                {
                    "model": [model] * 200,
                    "feature_set": [fs] * 200,
                    "run_id": test.runs.tolist(),
                    "t_s": test.t_s,
                    "mu_true": test.targets.astype(float),
                    "mu_pred": pred.astype(float),
                    "mu_lower": pred - 0.1,
                    "mu_upper": pred + 0.1,
                    "excited": test.excited,
                }
            )
        )
    text = generalization_markdown(rows)
    assert text.index("| EKF |") < text.index("| SA-CNN-LSTM |"), "sorted by RMSE over excited samples"
    paths = write_generalization_report(rows, pa.concat_tables(tables), tmp_path)
    assert pacsv.read_csv(paths["metrics_csv"]).num_rows == 2
    assert paths["figures"][0].stat().st_size > 10_000
