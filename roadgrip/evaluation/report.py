"""The paper's tables (Tables 2-6) and figures (Figures 4-8) from the paper benchmark's two artefacts.

metrics rows (dicts; metrics.csv), one per (condition, model, feature_set, trained_on):

    condition    low | medium | high | increasing | decreasing
    model        display name: "DNN", "CNN", "ConvLSTM", "SA-CNN-LSTM", "Improved SA-CNN-LSTM",
                 "Constant (training mean)", ... (any name; the paper's come first)
    feature_set  "paper" | "terminal" (any other name is shown after these)
    trained_on   "condition": trained on the condition's first experiment, as the paper does
                 | "all": one model trained on all five conditions
    rmse, mae    eq. 14, in units of mu; None or NaN where missing
    n            number of test estimates

predictions (pyarrow.Table), one row per estimate: condition, trained_on, model, feature_set, run_id (the test
run), road ("straight" | "circular"), t_s (time of the estimate in the run, s), mu_true, mu_pred.

Figures follow section 5.1 of the paper: on fixed roads, the truth and each model's prediction at randomly selected
estimate times of the second experiment; on changing roads, the estimates near each change of the true mu; the
abscissa is the sequence number of the displayed point.

Size: over 500 lines because the paper's Tables 2-6 and Figures 4-8 in the paper's layout, one function per table,
sharing the checks of the metrics.
"""

import csv
import logging
import math
from collections.abc import Mapping
from importlib import resources
from pathlib import Path

import numpy as np
import pyarrow as pa
from matplotlib.figure import Figure

log = logging.getLogger(__name__)

CONDITIONS = ("low", "medium", "high", "increasing", "decreasing")
CHANGING_CONDITIONS = ("increasing", "decreasing")
TABLE_NUMBER = dict(zip(CONDITIONS, range(2, 7)))  # paper, Tables 2-6
FIGURE_NUMBER = dict(zip(CONDITIONS, range(4, 9)))  # paper, Figures 4-8
PAPER_MODELS = ("DNN", "CNN", "ConvLSTM", "SA-CNN-LSTM", "Improved SA-CNN-LSTM")
PROPOSED = "SA-CNN-LSTM"
BASELINES = ("DNN", "CNN", "ConvLSTM")
# acceptance criterion of the issue: SA-CNN-LSTM beats DNN, CNN and ConvLSTM (RMSE) on at least 4 of 5 conditions
CRITERION_WINS = 4
SCOPES = ("condition", "all")
SCOPE_TITLES = {
    "condition": "Trained per condition (the paper's protocol: the first experiment trains, the second tests)",
    "all": "One model trained on all five conditions (tested on each condition's second experiment)",
}
SCOPE_SHORT = {"condition": "per condition", "all": "on all conditions"}
FEATURE_SETS = ("paper", "terminal")
ROADS = ("straight", "circular")
METRICS_COLUMNS = ("condition", "model", "feature_set", "trained_on", "rmse", "mae", "n")
PREDICTION_COLUMNS = ("condition", "trained_on", "model", "feature_set", "run_id", "road", "t_s", "mu_true", "mu_pred")
DASH = "-"

# Fixed styles for the paper's models, so that a model looks the same in every figure; others cycle through the rest.
_PAPER_STYLES = {
    "DNN": ("s", "tab:blue"),
    "CNN": ("^", "tab:orange"),
    "ConvLSTM": ("v", "tab:green"),
    "SA-CNN-LSTM": ("o", "tab:red"),
    "Improved SA-CNN-LSTM": ("D", "tab:purple"),
}
_OTHER_MARKERS = ("x", "P", "*", "h", "<", ">", "+", "p")
_OTHER_COLOURS = ("tab:brown", "tab:pink", "tab:gray", "tab:olive", "tab:cyan")


def _ordered(values, first) -> list:
    """`first` in its order (those present), then the other values sorted."""
    present = set(values)
    return [v for v in first if v in present] + sorted(present - set(first), key=str)


def _number(value) -> float | None:
    """A finite float, or None for a missing value (None, NaN, '')."""
    if value is None or value == "":
        return None
    value = float(value)
    return value if math.isfinite(value) else None


# -------------------------------------------------------------------------------------------------------- paper values


def load_paper_results() -> list[dict]:
    """The paper's Tables 2-6: [{condition, model, rmse, mae}], 25 rows."""
    text = resources.files("roadgrip.evaluation").joinpath("reference/paper_results.csv").read_text()
    rows = csv.DictReader(line for line in text.splitlines() if line.strip() and not line.startswith("#"))
    return [
        {"condition": r["condition"], "model": r["model"], "rmse": float(r["rmse"]), "mae": float(r["mae"])}
        for r in rows
    ]


# ------------------------------------------------------------------------------------------------------------- metrics


def _check_metrics(metrics) -> dict[tuple[str, str, str, str], Mapping]:
    """{(trained_on, feature_set, condition, model): row}; ValueError on a missing key, unknown condition, duplicate."""
    if isinstance(metrics, (Mapping, str, bytes)):
        raise TypeError(f"metrics must be a list of dicts, got {type(metrics).__name__}")
    index = {}
    for i, row in enumerate(metrics):
        if not isinstance(row, Mapping):
            raise TypeError(f"metrics[{i}] must be a dict, got {type(row).__name__}")
        missing = [k for k in ("condition", "model", "feature_set", "trained_on") if k not in row]
        if missing:
            raise ValueError(f"metrics[{i}] lacks key(s) {missing}; got {sorted(row)}")
        if row["condition"] not in CONDITIONS:
            raise ValueError(f"metrics[{i}].condition must be one of {list(CONDITIONS)}, got {row['condition']!r}")
        key = (row["trained_on"], row["feature_set"], row["condition"], row["model"])
        if key in index:
            raise ValueError(f"metrics[{i}] repeats (trained_on, feature_set, condition, model) = {key}")
        index[key] = row
    return index


def summary_rows(metrics: list[dict]) -> list[dict]:
    """On how many of the five conditions SA-CNN-LSTM has a lower RMSE than each baseline, and than all three at once.

    One row for the paper's Tables 2-6, then one per (trained_on, feature_set) of `metrics`: {source, trained_on,
    feature_set, wins: {baseline: count}, wins_all, compared (conditions where SA-CNN-LSTM and all three baselines
    have an RMSE), conditions (5), criterion_met (wins_all >= 4)}. A missing RMSE is never a win, nor is a tie.
    """
    index = _check_metrics(metrics)
    paper = {(r["condition"], r["model"]): r["rmse"] for r in load_paper_results()}
    rows = [_win_row("paper", "condition", "paper", paper)]
    for scope in _ordered({k[0] for k in index}, SCOPES):
        for fs in _ordered({k[1] for k in index if k[0] == scope}, FEATURE_SETS):
            rmse = {(k[2], k[3]): _number(r.get("rmse")) for k, r in index.items() if k[:2] == (scope, fs)}
            rows.append(_win_row("ours", scope, fs, rmse))
    return rows


def _win_row(source, scope, feature_set, rmse: dict) -> dict:
    wins = dict.fromkeys(BASELINES, 0)
    wins_all = compared = 0
    for condition in CONDITIONS:
        ours = rmse.get((condition, PROPOSED))
        others = [rmse.get((condition, b)) for b in BASELINES]
        beaten = [ours is not None and other is not None and ours < other for other in others]
        for baseline, won in zip(BASELINES, beaten):
            wins[baseline] += won
        compared += ours is not None and all(other is not None for other in others)
        wins_all += all(beaten)
    return {
        "source": source,
        "trained_on": scope,
        "feature_set": feature_set,
        "wins": wins,
        "wins_all": wins_all,
        "compared": compared,
        "conditions": len(CONDITIONS),
        "criterion_met": wins_all >= CRITERION_WINS,
    }


def _markdown_table(header: list[str], rows: list[list[str]], n_text=1) -> list[str]:
    """Rows of a markdown table: the first n_text columns left-aligned, the numbers right-aligned."""
    rule = [":---"] * n_text + ["---:"] * (len(header) - n_text)
    return ["| " + " | ".join(cells) + " |" for cells in (header, rule, *rows)]


def _fmt(value) -> str:
    value = _number(value)
    return DASH if value is None else f"{value:.3f}"


def _fmt_n(value) -> str:
    value = _number(value)
    if value is None:
        return DASH
    return str(int(value)) if value.is_integer() else f"{value:.3f}"


def tables_markdown(metrics: list[dict]) -> str:
    """Tables 2-6 (paper's values beside ours) for each training scope, then the SA-CNN-LSTM win summary; markdown."""
    index = _check_metrics(metrics)
    paper = {(r["condition"], r["model"]): r for r in load_paper_results()}
    lines = [
        "# Paper benchmark: Tables 2-6",
        "",
        (
            "RMSE and MAE (eq. 14) of the adhesion coefficient on each condition's second experiment. Paper values "
            "are those of the seed paper's Tables 2-6; n is the number of test estimates; a dash marks a missing "
            "value."
        ),
        "",
    ]
    for scope in _ordered({k[0] for k in index}, SCOPES):
        feature_sets = _ordered({k[1] for k in index if k[0] == scope}, FEATURE_SETS)
        lines += [f"## {SCOPE_TITLES.get(scope, f'Trained on {scope}')}", ""]
        header = ["model", "paper RMSE", "paper MAE"]
        for fs in feature_sets:
            header += [f"ours, {fs} features RMSE", f"ours, {fs} features MAE"]
        header.append("n")
        for condition in CONDITIONS:
            ours_models = {k[3] for k in index if k[0] == scope and k[2] == condition}
            body = []
            for model in _ordered(set(PAPER_MODELS) | ours_models, PAPER_MODELS):
                ref = paper.get((condition, model), {})
                cells = [model, _fmt(ref.get("rmse")), _fmt(ref.get("mae"))]
                ours = [index.get((scope, fs, condition, model), {}) for fs in feature_sets]
                for row in ours:
                    cells += [_fmt(row.get("rmse")), _fmt(row.get("mae"))]
                ns = [_fmt_n(row.get("n")) for row in ours]
                known = {n for n in ns if n != DASH}
                cells.append(known.pop() if len(known) == 1 else " / ".join(ns) if known else DASH)
                body.append(cells)
            lines += [f"### Table {TABLE_NUMBER[condition]}: {condition} adhesion coefficient", ""]
            lines += _markdown_table(header, body) + [""]
    lines += [
        "## Summary: SA-CNN-LSTM against DNN, CNN and ConvLSTM",
        "",
        (
            f"Conditions (of {len(CONDITIONS)}) on which SA-CNN-LSTM has a lower RMSE than the model named. "
            f"Acceptance criterion: lower than DNN, CNN and ConvLSTM on at least {CRITERION_WINS} of "
            f"{len(CONDITIONS)} conditions. "
            "'compared' counts the conditions where all four models have an RMSE."
        ),
        "",
    ]
    header = [
        "results",
        "trained",
        "features",
        *(f"vs {b}" for b in BASELINES),
        "vs all three",
        "compared",
        f"criterion (>= {CRITERION_WINS} of {len(CONDITIONS)})",
    ]
    body = []
    for row in summary_rows(metrics):
        of = f" of {row['conditions']}"
        body.append(
            [
                "paper (Tables 2-6)" if row["source"] == "paper" else "ours",
                SCOPE_SHORT.get(row["trained_on"], f"on {row['trained_on']}"),
                row["feature_set"],
                *(f"{row['wins'][b]}{of}" for b in BASELINES),
                f"{row['wins_all']}{of}",
                f"{row['compared']}{of}",
                "met" if row["criterion_met"] else "not met",
            ]
        )
    lines += _markdown_table(header, body, n_text=3)
    return "\n".join(lines) + "\n"


def write_metrics_csv(metrics: list[dict], path) -> Path:
    """metrics.csv: the columns of METRICS_COLUMNS, then any extra keys sorted; rows in the order given."""
    _check_metrics(metrics)
    extra = sorted({k for row in metrics for k in row} - set(METRICS_COLUMNS))
    path = Path(path)
    with path.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=[*METRICS_COLUMNS, *extra], restval="")
        writer.writeheader()
        for row in metrics:
            writer.writerow({k: "" if v is None else v for k, v in row.items()})
    return path


def _parse_cell(text: str):
    if text == "":
        return None
    try:
        value = float(text)
    except ValueError:
        return text
    return int(value) if value.is_integer() and "." not in text and "e" not in text.lower() else value


def read_metrics_csv(path) -> list[dict]:
    """Rows of a metrics.csv: rmse and mae as float, n and other numbers as int or float, empty cells as None."""
    with Path(path).open(newline="") as f:
        rows = list(csv.DictReader(f))
    out = []
    for row in rows:
        parsed = {k: v if k in METRICS_COLUMNS[:4] else _parse_cell(v) for k, v in row.items()}
        for k in ("rmse", "mae"):
            if parsed.get(k) is not None:
                parsed[k] = float(parsed[k])
        out.append(parsed)
    return out


# ------------------------------------------------------------------------------------------------------------- figures


def _prediction_arrays(predictions: pa.Table) -> dict[str, np.ndarray]:
    if not isinstance(predictions, pa.Table):
        raise TypeError(f"predictions must be a pyarrow.Table, got {type(predictions).__name__}")
    missing = [c for c in PREDICTION_COLUMNS if c not in predictions.column_names]
    if missing:
        raise ValueError(f"predictions lack column(s) {missing}; got {predictions.column_names}")
    cols = {c: predictions.column(c).to_numpy(zero_copy_only=False) for c in PREDICTION_COLUMNS}
    for c in ("t_s", "mu_true", "mu_pred"):
        cols[c] = cols[c].astype(np.float64)
    unknown = sorted(set(cols["condition"]) - set(CONDITIONS), key=str)
    if unknown:
        raise ValueError(f"predictions.condition must be one of {list(CONDITIONS)}, got {unknown}")
    return cols


def _model_styles(models) -> dict[str, dict]:
    styles, k = {}, 0
    for model in _ordered(models, PAPER_MODELS):
        if model in _PAPER_STYLES:
            marker, colour = _PAPER_STYLES[model]
        else:
            marker, colour = _OTHER_MARKERS[k % len(_OTHER_MARKERS)], _OTHER_COLOURS[k % len(_OTHER_COLOURS)]
            k += 1
        styles[model] = {"marker": marker, "color": colour}
    return styles


def _nearest(t_model: np.ndarray, values: np.ndarray, t_query: np.ndarray) -> np.ndarray:
    """Value of the estimate nearest to each query time (t_model sorted); NaN farther than half the estimate spacing."""
    if t_model.size == 0:
        return np.full(t_query.shape, np.nan)
    i = np.searchsorted(t_model, t_query)
    lo, hi = np.clip(i - 1, 0, t_model.size - 1), np.clip(i, 0, t_model.size - 1)
    pick = np.where(np.abs(t_model[hi] - t_query) < np.abs(t_model[lo] - t_query), hi, lo)
    tolerance_s = 0.5 * float(np.median(np.diff(t_model))) if t_model.size > 1 else 0.0
    return np.where(np.abs(t_model[pick] - t_query) <= tolerance_s + 1e-9, values[pick], np.nan)


def _change_times(t_s: np.ndarray, mu: np.ndarray, min_step=0.05, gap_s=1.0) -> list[float]:
    """Times of the changes of the true mu (t_s sorted): a run of moving samples (a step or a ramp, runs less than gap_s
    apart joined) whose total change is >= min_step changes at the first sample that has covered half of it."""
    moving = np.flatnonzero(np.abs(np.diff(mu)) > 1e-6)
    if moving.size == 0:
        return []
    breaks = np.flatnonzero(t_s[moving[1:]] - t_s[moving[:-1] + 1] > gap_s)
    times = []
    for i0, i1 in zip(np.r_[moving[0], moving[breaks + 1]], np.r_[moving[breaks], moving[-1]]):
        step = mu[i1 + 1] - mu[i0]
        if abs(step) >= min_step:
            covered = np.abs(mu[i0 : i1 + 2] - mu[i0]) >= 0.5 * abs(step) - 1e-9
            times.append(float(t_s[i0 + np.argmax(covered)]))
    return times


def _change_selection(t_s, changes, before_s, after_s, max_points_per_change):
    """Indices into t_s of the points from before_s before to after_s after each change (overlapping windows merged),
    thinned evenly to at most max_points_per_change per change; and the start of each merged segment."""
    segments = []  # [start_s, end_s, n_changes]
    for tc in sorted(changes):
        if segments and tc - before_s <= segments[-1][1]:
            segments[-1][1], segments[-1][2] = tc + after_s, segments[-1][2] + 1
        else:
            segments.append([tc - before_s, tc + after_s, 1])
    picked, seg_starts = [], []
    for start_s, end_s, n_changes in segments:
        idx = np.flatnonzero((t_s >= start_s) & (t_s <= end_s))
        stride = max(1, math.ceil(idx.size / (max_points_per_change * n_changes)))
        seg_starts.append(sum(p.size for p in picked))
        picked.append(idx[::stride])
    return np.concatenate(picked) if picked else np.array([], dtype=int), seg_starts


def _draw_panel(ax, cols, rows, condition, road, styles, rng, n_points, before_s, after_s, max_points_per_change):
    runs = sorted(set(cols["run_id"][rows]), key=str)
    if len(runs) > 1:
        log.info("%s %s road: %d test runs, plotting the first (%s)", condition, road, len(runs), runs[0])
    rows = rows[cols["run_id"][rows] == runs[0]]
    t_all, mu_all = cols["t_s"][rows], cols["mu_true"][rows]
    t_s, first = np.unique(t_all, return_index=True)  # every estimate time of the run, sorted
    mu_true = mu_all[first]
    series = {}
    for model in _ordered(set(cols["model"][rows]), PAPER_MODELS):
        own = rows[cols["model"][rows] == model]
        order = np.argsort(cols["t_s"][own], kind="stable")
        series[model] = _nearest(cols["t_s"][own][order], cols["mu_pred"][own][order], t_s)

    changes = _change_times(t_s, mu_true) if condition in CHANGING_CONDITIONS else []
    seg_starts = []
    if changes:
        picked, seg_starts = _change_selection(t_s, changes, before_s, after_s, max_points_per_change)
        what = f"estimates from {before_s:g} s before to {after_s:g} s after each change of the true μ"
    else:
        covered = np.flatnonzero(np.all([np.isfinite(v) for v in series.values()], axis=0))
        candidates = covered if covered.size else np.arange(t_s.size)
        picked = np.sort(rng.choice(candidates, size=min(n_points, candidates.size), replace=False))
        what = f"{picked.size} randomly selected estimates"
        if condition in CHANGING_CONDITIONS:
            what += " (no change of the true μ found)"
    x = np.arange(1, picked.size + 1)  # sequence number of the displayed point, as in the paper

    ax.plot(x, mu_true[picked], color="black", linewidth=1.8, label="true μ", zorder=3)
    for model, values in series.items():
        ax.plot(
            x,
            values[picked],
            linestyle="-",
            linewidth=0.7,
            markersize=4,
            alpha=0.85,
            label=model,
            markerfacecolor="none" if styles[model]["marker"] not in "x+" else None,
            **styles[model],
        )
    for k, start in enumerate(seg_starts[1:]):
        ax.axvline(start + 0.5, color="0.75", linestyle=":", linewidth=1.0, label="join of windows" if k == 0 else None)
    t_picked = t_s[picked]
    for k, tc in enumerate(changes):
        position = np.searchsorted(t_picked, tc) + 0.5  # between the last point before and the first after the change
        ax.axvline(position, color="0.35", linestyle="--", linewidth=1.0, label="change of true μ" if k == 0 else None)
    ax.set_title(f"{road} road ({runs[0]}): {what}", fontsize=9)
    ax.set_xlabel("sequence number of the displayed estimate")
    ax.set_ylabel("adhesion coefficient μ")
    ax.grid(True, alpha=0.3)


def _condition_figure(cols, rows, condition, feature_set, trained_on, styles, seed, **selection) -> Figure:
    roads = _ordered(set(cols["road"][rows]), ROADS)
    fig = Figure(figsize=(10, 3.6 * len(roads) + 0.9), layout="constrained")
    axes = fig.subplots(len(roads), 1, squeeze=False)[:, 0]
    for k, (ax, road) in enumerate(zip(axes, roads)):
        # one generator per panel, so that a panel's points do not depend on which other panels exist
        rng = np.random.default_rng([seed, CONDITIONS.index(condition), ROADS.index(road) if road in ROADS else 2 + k])
        _draw_panel(ax, cols, rows[cols["road"][rows] == road], condition, road, styles, rng, **selection)
    scope = SCOPE_SHORT.get(trained_on, f"on {trained_on}")
    fig.suptitle(
        f"Figure {FIGURE_NUMBER[condition]}: prediction results under {condition} adhesion coefficient "
        f"({feature_set} features, trained {scope})",
        fontsize=11,
    )
    handles = {}
    for ax in axes:
        for handle, label in zip(*ax.get_legend_handles_labels()):
            handles.setdefault(label, handle)
    fig.legend(handles.values(), handles.keys(), loc="outside lower center", ncol=min(len(handles), 5), fontsize=8)
    return fig


def write_figures(
    predictions: pa.Table,
    out_dir,
    feature_set="terminal",
    trained_on="condition",
    seed=0,
    *,
    n_points=50,
    before_s=3.0,
    after_s=5.0,
    max_points_per_change=40,
) -> list[Path]:
    """Figures 4-8 (figure_4_low.png ... figure_8_decreasing.png) for one feature set and training scope.

    One panel per road (straight, then circular) with the truth and every model's prediction on the test run:
    fixed conditions show n_points estimate times drawn at random (seeded, then put in time order); changing conditions
    the estimates from before_s before to after_s after each change of the true mu, concatenated, at most
    max_points_per_change per change (thinned evenly), with dashed lines at the changes. Conditions without predictions
    are skipped. Returns the paths written.
    """
    cols = _prediction_arrays(predictions)
    selected = np.flatnonzero((cols["feature_set"] == feature_set) & (cols["trained_on"] == trained_on))
    if selected.size == 0:
        present = sorted({(str(f), str(t)) for f, t in zip(cols["feature_set"], cols["trained_on"])})
        raise ValueError(
            f"predictions have no rows for feature_set={feature_set!r}, trained_on={trained_on!r}; "
            f"(feature_set, trained_on) present: {present}"
        )
    if not (isinstance(n_points, int) and n_points > 0):
        raise ValueError(f"n_points must be a positive int, got {n_points!r}")
    if not (isinstance(max_points_per_change, int) and max_points_per_change > 0):
        raise ValueError(f"max_points_per_change must be a positive int, got {max_points_per_change!r}")
    if before_s < 0 or after_s < 0:
        raise ValueError(f"before_s and after_s must be >= 0, got {before_s!r} and {after_s!r}")
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    styles = _model_styles(set(cols["model"]))
    paths = []
    for condition in CONDITIONS:
        rows = selected[cols["condition"][selected] == condition]
        if rows.size == 0:
            log.info(
                "no predictions for %s (%s features, trained on %s): figure skipped", condition, feature_set, trained_on
            )
            continue
        fig = _condition_figure(
            cols,
            rows,
            condition,
            feature_set,
            trained_on,
            styles,
            seed,
            n_points=n_points,
            before_s=before_s,
            after_s=after_s,
            max_points_per_change=max_points_per_change,
        )
        path = out_dir / f"figure_{FIGURE_NUMBER[condition]}_{condition}.png"
        fig.savefig(path, dpi=110)
        paths.append(path)
    return paths


def write_all_figures(predictions: pa.Table, out_dir, seed=0) -> list[Path]:
    """write_figures for each (feature_set, trained_on) of the predictions, in folders f"{feature_set}-{trained_on}"."""
    cols = _prediction_arrays(predictions)
    paths = []
    for fs in _ordered(set(cols["feature_set"]), FEATURE_SETS):
        for scope in _ordered(set(cols["trained_on"][cols["feature_set"] == fs]), SCOPES):
            paths += write_figures(predictions, Path(out_dir) / f"{fs}-{scope}", fs, scope, seed)
    return paths


def write_report(metrics: list[dict], predictions: pa.Table | None, out_dir, seed=0) -> dict:
    """metrics.csv, tables.md and all figures under out_dir.

    Returns {"metrics_csv": Path, "tables_md": Path, "figures": [Path]}; with predictions None, no figures are made."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    metrics_csv = write_metrics_csv(metrics, out_dir / "metrics.csv")
    tables_md = out_dir / "tables.md"
    tables_md.write_text(tables_markdown(metrics))
    figures = [] if predictions is None else write_all_figures(predictions, out_dir, seed=seed)
    return {"metrics_csv": metrics_csv, "tables_md": tables_md, "figures": figures}
