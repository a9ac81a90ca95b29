"""Q-learning refinement of a trained model's output layer (paper 4, 4.4, eq. 13): the paper's "Improved SA-CNN-LSTM".

A tabular Q-learning agent adjusts the weights w (1, d) and bias b (1,) of the model's last `nn.Linear` so that its
predictions of mu stay in the physical range while staying accurate. The network below that layer is frozen: its output
h (n, d) on the validation windows is captured once (`penultimate`), and a candidate layer is evaluated from it without
re-running the network. Works for every model of the registry, and for any module whose last `nn.Linear` gives the
prediction.

Actions (p = h @ w.T + b the predictions, m their mean over the data; `scale_step` s, `bias_step` delta, f = 1 - s):

| action | effect on p                                 | on (w, b)                      |
| ------ | ------------------------------------------- | ------------------------------ |
| keep   | none; ends the episode (stop)               | none                           |
| raise  | p + delta                                   | b + delta                      |
| lower  | p - delta                                   | b - delta                      |
| narrow | m + f (p - m): less spread, same mean       | w f, b f + (1 - f) m           |
| widen  | m + (p - m) / f: more spread, undoes narrow | w / f, b / f + (1 - 1 / f) m   |

So every reachable layer is w = k w_trained (k > 0) with some bias c: an affine recalibration k z + c of the trained
output z = h @ w_trained.T, which `_AffineHead` evaluates in O(log n) from sorted z, prefix sums and moments of z and y.

States (default 7 x 3 x 3 = 63; index = (range * 3 + level) * 3 + spread):

| part   | values                                                             | meaning                             |
| ------ | ------------------------------------------------------------------ | ----------------------------------- |
| range  | 0 if all predictions lie in `allowed_range`, else                  | side 0: at least as many below as   |
|        | 1 + side * B + share bin; B = len(share_edges) + 1 bins of the     | above; side 1: more above           |
|        | share out of range (default <1 %, 1-10 %, >=10 %)                  |                                     |
| level  | mean(p) - mean(y) below -delta/2, within +/-delta/2, above delta/2 | 0 too low, 1 centred, 2 too high    |
| spread | log(var p / cov(p, y)) below -l/2, within, above l/2; l = -log f   | 0 too narrow, 1 matched, 2 too wide |

Objective (lower is better, mu units): J = accuracy_weight RMSE + share_weight share_out + excess_weight mean_excess,
with share_out the share of predictions outside `allowed_range` and mean_excess the mean over all samples of the
distance outside it (0 inside). Reward r_{t+1} = J(before the action) - J(after), the improvement: an episode's return
telescopes to J(start) - J(end) for gamma = 1, and "keep" (stop: terminal, reward 0) is the best action exactly where
nothing improves J. Update: eq. 13, Q(s, a) <- Q(s, a) + beta [r + gamma max_a' Q(s', a') - Q(s, a)]; epsilon-greedy,
epsilon decaying per episode, from a seeded `numpy.random.Generator`; every episode starts from the trained layer and
runs at most `steps` actions. The step limit truncates (it is not terminal), so the last step bootstraps.

Returned (`QResult`): the layer with the lowest J among all layers the agent visited - in its training episodes and in
one greedy rollout of the final Q table (argmax, ties to "keep") from the trained layer - the trained layer included.
So J(after) <= J(before) always, and an unimprovable layer comes back unchanged. At equal J the earliest found wins (the
greedy rollout comes last). `actions` leads from the trained layer to the returned one, `found_in` says where it was
found, and `greedy` holds the metrics of the best layer of the greedy rollout alone.

Choices beyond the paper's text and the first design, and why. Numbers: 24 synthetic heads with mis-scaled and shifted
outputs, 3 seeds each; a run "falls short" when its J exceeds that of the best affine recalibration (a fine grid over
(k, c)) by more than 0.01.
- Actions scale the whole weight vector and shift the bias; they never change the direction of w. Per-weight actions
  give 2d + 1 actions (65 for a 32-unit head), far too many for a tabular agent, and turning w without gradients is a
  random search against what training fitted. Scale and shift are what moves predictions into a range.
- Narrow/widen scale about the mean prediction (a plain w (1 +/- s) also moves the mean when mean(h @ w.T) is not 0),
  and widen divides by the factor that narrow multiplies with, so that the two undo each other exactly.
- States: the range part knows on which side predictions leave it (without it "raise" and "lower" are right in the same
  state; with it a "shift toward the range centre" action is redundant and left out). The accuracy part says in which
  direction the output is miscalibrated (dead bands one action wide, so that the calibrated point has a state of its
  own) instead of how large the RMSE is relative to the start, which says that accuracy was lost but not how to get it
  back. With share x RMSE-ratio states the greedy rollout fell short in 34 of 72 runs; with these states in 7 of 72.
- gamma defaults to 0.3: a state covers layers at different distances from the optimum, and values bootstrapped from it
  mislead; at gamma 0.9 the greedy rollout fell short in 27 of 72 runs.
- The result is the best layer visited in training as well as in the greedy rollout: the greedy rollout alone fell
  short in 7 of 72 runs, the best visited in none (largest excess 0.003, about one action's resolution).
- "keep" ends the episode. As a self-loop it is worth gamma V(s), about as much as the best action, and the greedy
  rollout stalled on it far from the optimum.
The problem is two-dimensional and smooth, so a direct search over (k, c) would do as well; Q-learning is kept because
it is the paper's method.

Simpler bounds to compare with in the tables: `clip(predictions, allowed_range)` (clipping never increases the error of
a sample whose true mu lies in the range), and a bounded output activation lo + (hi - lo) sigmoid(z), a model config
option of `sa_cnn_lstm.py`. On a head that is accurate but whose noise spills over the range edges, clipping wins (RMSE
0.049 -> 0.048 with none out of range; the agent: 2.8 % -> 0.6 % out, RMSE 0.049 -> 0.056); on a mis-scaled head the
agent wins (RMSE 0.22 -> 0.05, clipping 0.17). A model with an activation after its last `nn.Linear` cannot be refined
here (the layer's output is not its prediction); `refine_model` refuses it.

Size: over 500 lines because the paper's Q-learning refinement: its configuration, environment, agent and training loop,
read together against section 4.4.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import nn

from roadgrip.validation import bounded, check_bounds

# Real dry asphalt with good tires exceeds mu = 1.0: Burckhardt's dry-asphalt curve (c1 1.2801, c2 23.99, c3 0.52;
# roadgrip/vehicle/tires/burckhardt_surfaces.csv) peaks at 1.17 near 17 % slip. Below 0 is never physical.
DEFAULT_ALLOWED_RANGE = (0.0, 1.2)
ACTIONS = ("keep", "raise", "lower", "narrow", "widen")
KEEP = ACTIONS.index("keep")


def _check_range(name, allowed_range):
    if (
        not isinstance(allowed_range, (tuple, list))
        or len(allowed_range) != 2
        or not all(_is_number(v) and math.isfinite(v) for v in allowed_range)
        or not allowed_range[0] < allowed_range[1]
    ):
        raise ValueError(f"{name} must be two finite numbers (lo, hi) with lo < hi, got {allowed_range!r}")


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


@dataclass(frozen=True)
class QConfig:
    allowed_range: tuple[float, float] = DEFAULT_ALLOWED_RANGE  # (lo, hi), mu (dimensionless)
    beta: float = field(default=0.1, metadata=bounded(0.0, 1.0, low_open=True, doc="learning rate of eq. 13"))
    gamma: float = field(default=0.3, metadata=bounded(0.0, 1.0, doc="discount of eq. 13"))
    epsilon: float = field(default=1.0, metadata=bounded(0.0, 1.0, doc="exploration rate of the first episode"))
    epsilon_decay: float = field(default=0.98, metadata=bounded(0.0, 1.0, low_open=True, doc="factor per episode"))
    epsilon_min: float = field(default=0.05, metadata=bounded(0.0, 1.0))
    episodes: int = field(default=300, metadata=bounded(1, 1_000_000))
    steps: int = field(default=60, metadata=bounded(1, 100_000, doc="actions per episode and in the greedy rollout"))
    bias_step: float = field(default=0.01, metadata=bounded(0.0, 1.0, low_open=True, doc="mu per raise/lower"))
    scale_step: float = field(default=0.02, metadata=bounded(0.0, 0.5, low_open=True, doc="relative, per narrow"))
    accuracy_weight: float = field(default=1.0, metadata=bounded(0.0, 1e6, doc="per unit of RMSE (mu)"))
    # 1.0: one percent of the predictions out of range costs as much as 0.01 of RMSE.
    share_weight: float = field(default=1.0, metadata=bounded(0.0, 1e6, doc="per unit share out of range"))
    excess_weight: float = field(default=1.0, metadata=bounded(0.0, 1e6, doc="per mu of mean distance out of range"))
    share_edges: tuple[float, ...] = (0.01, 0.1)  # share-out-of-range bin edges of the state
    seed: int = 0

    def __post_init__(self):
        for name in ("episodes", "steps", "seed"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int):
                raise TypeError(f"QConfig.{name} must be an int, got {value!r}")
        check_bounds(self)
        _check_range("QConfig.allowed_range", self.allowed_range)
        if self.epsilon_min > self.epsilon:
            raise ValueError(f"QConfig.epsilon_min must be <= epsilon ({self.epsilon}), got {self.epsilon_min!r}")
        if self.accuracy_weight == self.share_weight == self.excess_weight == 0:
            raise ValueError("QConfig.accuracy_weight, share_weight and excess_weight must not all be 0, got 0, 0, 0")
        edges = self.share_edges
        if (
            not isinstance(edges, tuple)
            or not edges
            or not all(_is_number(v) and 0 < v <= 1 for v in edges)
            or any(a >= b for a, b in itertools.pairwise(edges))
        ):
            raise ValueError(
                f"QConfig.share_edges must be a non-empty increasing tuple of numbers in (0, 1], got {edges!r}"
            )

    @property
    def n_states(self) -> int:
        return (1 + 2 * (len(self.share_edges) + 1)) * 3 * 3

    def objective(self, metrics: RangeMetrics) -> float:
        """J (lower is better): weighted RMSE, share out of range and mean distance out of range."""
        return (
            self.accuracy_weight * metrics.rmse
            + self.share_weight * metrics.share_out_of_range
            + self.excess_weight * metrics.mean_excess
        )


@dataclass(frozen=True)
class RangeMetrics:
    """Accuracy and range of n predictions (mu units): RMSE and MAE (eq. 14), the counts below and above the allowed
    range, and the mean over all n samples of the distance outside it."""

    n: int
    rmse: float
    mae: float
    n_below: int
    n_above: int
    mean_excess: float

    @property
    def n_out_of_range(self) -> int:
        return self.n_below + self.n_above

    @property
    def share_out_of_range(self) -> float:
        return self.n_out_of_range / self.n if self.n else 0.0


@dataclass
class QResult:
    w: np.ndarray  # (1, d) refined weights, a positive multiple of w_start
    b: np.ndarray  # (1,) refined bias
    w_start: np.ndarray  # (1, d) trained weights
    b_start: np.ndarray  # (1,)
    actions: tuple[str, ...]  # from the trained layer to the returned one
    found_in: str  # "trained layer", "episode N" or "greedy rollout"
    q_table: np.ndarray  # (n_states, len(ACTIONS))
    history: list[dict]  # per episode: episode, epsilon, steps, return; objective, rmse, share_out_of_range at its end
    before: RangeMetrics  # trained layer
    after: RangeMetrics  # returned layer
    greedy: RangeMetrics  # best layer of the greedy rollout alone


def clip(predictions: np.ndarray, allowed_range: tuple[float, float] = DEFAULT_ALLOWED_RANGE) -> np.ndarray:
    """The simplest bound: predictions clipped into [lo, hi]."""
    _check_range("allowed_range", allowed_range)
    return np.clip(np.asarray(predictions), *allowed_range)


def range_metrics(
    predictions: np.ndarray, y: np.ndarray, allowed_range: tuple[float, float] = DEFAULT_ALLOWED_RANGE
) -> RangeMetrics:
    _check_range("allowed_range", allowed_range)
    lo, hi = allowed_range
    p, y = np.asarray(predictions, dtype=np.float64), np.asarray(y, dtype=np.float64)
    if p.shape != y.shape or p.ndim != 1:
        raise ValueError(f"predictions and y must be 1-D of the same length, got shapes {p.shape} and {y.shape}")
    if len(p) == 0:
        return RangeMetrics(0, 0.0, 0.0, 0, 0, 0.0)
    error = p - y
    below, above = np.maximum(lo - p, 0.0), np.maximum(p - hi, 0.0)
    return RangeMetrics(
        n=len(p),
        rmse=float(np.sqrt(np.mean(error**2))),
        mae=float(np.mean(np.abs(error))),
        n_below=int(np.count_nonzero(below)),
        n_above=int(np.count_nonzero(above)),
        mean_excess=float(np.mean(below + above)),
    )


def q_update(
    q: np.ndarray,
    state: int,
    action: int,
    reward: float,
    next_state: int | None,
    beta: float,
    gamma: float,
    terminal: bool = False,
) -> float:
    """Eq. 13 in place; returns the new Q(s, a). A terminal step (the agent stopped) has no next state to bootstrap
    from."""
    future = 0.0 if terminal else gamma * float(np.max(q[next_state]))
    # eq. 13: Q(s_t, a_t) <- Q(s_t, a_t) + beta [r_{t+1} + gamma max_a Q(s_{t+1}, a) - Q(s_t, a_t)]
    q[state, action] += beta * (reward + future - q[state, action])
    return float(q[state, action])


class QRefiner:
    """Learns a Q table over output-layer adjustments and returns the best layer it visited (module docstring)."""

    def __init__(self, config: QConfig = QConfig()):
        self.config = config

    def fit(self, h_val: np.ndarray, y_val: np.ndarray, w: np.ndarray, b: np.ndarray) -> QResult:
        """h_val (n, d): the output layer's input on validation windows; y_val (n,): true mu; w (1, d), b (1,): the
        trained layer. Sets `q_table_` and `result_`."""
        cfg = self.config
        h, y, w, b = _check_fit_inputs(h_val, y_val, w, b)
        head = _AffineHead(h @ w[0], y, cfg.allowed_range)
        start = (1.0, float(b[0]))  # (k, c): predictions k (h @ w.T) + c
        rng = np.random.default_rng(cfg.seed)
        q = np.zeros((cfg.n_states, len(ACTIONS)))
        best = (cfg.objective(head.metrics(*start)), start, (), "trained layer")
        history = []
        for episode in range(1, cfg.episodes + 1):
            epsilon = max(cfg.epsilon_min, cfg.epsilon * cfg.epsilon_decay ** (episode - 1))
            params, taken, total = start, [], 0.0
            metrics = head.metrics(*params)
            state, objective = self._state(params, metrics, head), cfg.objective(metrics)
            for _ in range(cfg.steps):
                if rng.random() < epsilon:
                    action = int(rng.integers(len(ACTIONS)))
                else:  # greedy, ties broken at random so that unseen states are explored
                    action = int(rng.choice(np.flatnonzero(q[state] == q[state].max())))
                if action == KEEP:  # stop: accept the current layer
                    q_update(q, state, action, 0.0, None, cfg.beta, cfg.gamma, terminal=True)
                    break
                params = self._act(action, params, head)
                taken.append(ACTIONS[action])
                metrics = head.metrics(*params)
                next_state, next_objective = self._state(params, metrics, head), cfg.objective(metrics)
                reward = objective - next_objective
                q_update(q, state, action, reward, next_state, cfg.beta, cfg.gamma)
                state, objective, total = next_state, next_objective, total + reward
                if objective < best[0]:
                    best = (objective, params, tuple(taken), f"episode {episode}")
            history.append(
                {
                    "episode": episode,
                    "epsilon": epsilon,
                    "steps": len(taken),
                    "return": total,
                    "objective": objective,
                    "rmse": metrics.rmse,
                    "share_out_of_range": metrics.share_out_of_range,
                }
            )
        greedy = self._greedy_rollout(q, head, start)
        if greedy[0] < best[0]:
            best = greedy
        _, (k, c), actions, found_in = best
        self.q_table_ = q
        self.result_ = QResult(
            w=k * w,
            b=np.array([c]),
            w_start=w.copy(),
            b_start=b.copy(),
            actions=actions,
            found_in=found_in,
            q_table=q,
            history=history,
            before=range_metrics(h @ w[0] + b[0], y, cfg.allowed_range),
            after=range_metrics(k * (h @ w[0]) + c, y, cfg.allowed_range),
            greedy=range_metrics(greedy[1][0] * (h @ w[0]) + greedy[1][1], y, cfg.allowed_range),
        )
        return self.result_

    def _greedy_rollout(self, q, head, start):
        """(J, params, actions, "greedy rollout") of the best layer (start included) on the greedy path of the Q
        table."""
        cfg = self.config
        params, metrics, taken = start, head.metrics(*start), []
        best = (cfg.objective(metrics), start, (), "greedy rollout")
        for _ in range(cfg.steps):
            action = int(np.argmax(q[self._state(params, metrics, head)]))  # ties: the first action, "keep"
            if action == KEEP:
                break
            params = self._act(action, params, head)
            taken.append(ACTIONS[action])
            metrics = head.metrics(*params)
            if cfg.objective(metrics) < best[0]:
                best = (cfg.objective(metrics), params, tuple(taken), "greedy rollout")
        return best

    def _act(self, action: int, params: tuple[float, float], head: _AffineHead) -> tuple[float, float]:
        """(k, c) after one action (table in the module docstring)."""
        k, c = params
        name = ACTIONS[action]
        if name == "raise":
            return k, c + self.config.bias_step
        if name == "lower":
            return k, c - self.config.bias_step
        if name in ("narrow", "widen"):
            f = 1.0 - self.config.scale_step
            f = f if name == "narrow" else 1.0 / f
            mean = head.mean_prediction(k, c)
            return f * k, f * c + (1.0 - f) * mean  # m + f (k z + c - m) = f k z + f c + (1 - f) m
        return k, c

    def _state(self, params: tuple[float, float], metrics: RangeMetrics, head: _AffineHead) -> int:
        cfg = self.config
        if metrics.n_out_of_range == 0:
            range_part = 0
        else:
            side = 0 if metrics.n_below >= metrics.n_above else 1
            share_bin = int(np.searchsorted(cfg.share_edges, metrics.share_out_of_range, side="right"))
            range_part = 1 + side * (len(cfg.share_edges) + 1) + share_bin
        k, c = params
        level = _three_way(head.mean_prediction(k, c) - head.y_mean, cfg.bias_step / 2)
        spread = _three_way(head.log_spread_ratio(k), -math.log(1.0 - cfg.scale_step) / 2)
        return (range_part * 3 + level) * 3 + spread


def _three_way(value: float, half_band: float) -> int:
    """0 below -half_band, 1 within, 2 above."""
    return 0 if value < -half_band else (2 if value > half_band else 1)


class _AffineHead:
    """The predictions p = k z + c (k > 0) of n samples, z = h @ w_trained.T, summarized so that their metrics cost
    O(log n) per (k, c): moments of z and y, and the sorted z with prefix sums. MAE (not used by the agent) is NaN."""

    def __init__(self, z: np.ndarray, y: np.ndarray, allowed_range: tuple[float, float]):
        self.lo, self.hi = allowed_range
        self.z_mean, self.y_mean = float(np.mean(z)), float(np.mean(y))
        dz, dy = z - self.z_mean, y - self.y_mean
        self.var_z, self.cov_zy, self.var_y = float(np.mean(dz * dz)), float(np.mean(dz * dy)), float(np.mean(dy * dy))
        self.z_sorted = np.sort(z)
        self.prefix = np.concatenate([[0.0], np.cumsum(self.z_sorted)])  # prefix[i] = sum of the i smallest z

    def mean_prediction(self, k: float, c: float) -> float:
        return k * self.z_mean + c

    def log_spread_ratio(self, k: float) -> float:
        """log(var p / cov(p, y)): > 0 where narrowing about the mean lowers the MSE (predictions spread too wide)."""
        if self.var_z <= 0.0:
            return 0.0  # constant predictions: narrow and widen change nothing
        if self.cov_zy <= 0.0:
            return math.inf  # predictions unrelated or anti-related to y: less spread is always better
        return math.log(k * self.var_z / self.cov_zy)

    def metrics(self, k: float, c: float) -> RangeMetrics:
        n = len(self.z_sorted)
        # mean (p - y)^2 = k^2 var z - 2 k cov(z, y) + var y + (k mean z + c - mean y)^2
        offset = self.mean_prediction(k, c) - self.y_mean
        mse = k * k * self.var_z - 2.0 * k * self.cov_zy + self.var_y + offset * offset
        n_below = int(np.searchsorted(self.z_sorted, (self.lo - c) / k, side="left"))  # p < lo  <=>  z < (lo - c) / k
        first_above = int(np.searchsorted(self.z_sorted, (self.hi - c) / k, side="right"))  # p > hi <=> z > (hi-c)/k
        n_above = n - first_above
        excess_below = n_below * (self.lo - c) - k * self.prefix[n_below]  # sum of lo - p over p < lo
        # sum of p - hi over p > hi
        excess_above = k * (self.prefix[n] - self.prefix[first_above]) - n_above * (self.hi - c)
        return RangeMetrics(
            n=n,
            rmse=math.sqrt(max(mse, 0.0)),
            mae=math.nan,
            n_below=n_below,
            n_above=n_above,
            mean_excess=max(excess_below + excess_above, 0.0) / n,
        )


def output_layer(model: nn.Module) -> nn.Linear:
    """The last `nn.Linear` of `model` in registration order (the output layer of every model in the registry)."""
    last = None
    for module in model.modules():
        if isinstance(module, nn.Linear):
            last = module
    if last is None:
        raise ValueError(f"model {type(model).__name__} has no nn.Linear layer")
    return last


def penultimate(model: nn.Module, x: np.ndarray | torch.Tensor, batch_size: int = 4096) -> np.ndarray:
    """(n, d) float64: the input of the output layer for windows x (n, T, F), in eval mode without gradients."""
    return _head_io(model, x, batch_size)[0]


def refine_model(model: nn.Module, x_val: np.ndarray, y_val: np.ndarray, config: QConfig = QConfig()) -> QResult:
    """Fits a QRefiner on the model's validation windows and writes the refined weights and bias into its output layer,
    in place. The result holds the trained (w_start, b_start) and refined (w, b) layers, and the metrics before and
    after."""
    h, z, predictions = _head_io(model, x_val)
    if not np.allclose(z, predictions, rtol=0.0, atol=1e-6):
        raise ValueError(
            f"model {type(model).__name__} transforms the output of its last nn.Linear (a bounded "
            "activation?); the Q refiner adjusts a linear output layer only"
        )
    layer = output_layer(model)
    result = QRefiner(config).fit(h, y_val, layer.weight.detach().cpu().numpy(), layer.bias.detach().cpu().numpy())
    with torch.no_grad():
        layer.weight.copy_(torch.as_tensor(result.w, dtype=layer.weight.dtype))
        layer.bias.copy_(torch.as_tensor(result.b, dtype=layer.bias.dtype))
    return result


def _head_io(model: nn.Module, x, batch_size: int = 4096) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(h (n, d), layer output (n,), model prediction (n,)), float64, from a forward hook on the output layer."""
    layer = output_layer(model)
    if layer.out_features != 1 or layer.bias is None:
        raise ValueError(
            f"the output layer of {type(model).__name__} must have 1 output and a bias, got "
            f"out_features={layer.out_features}, bias={layer.bias is not None}"
        )
    inputs, outputs = [], []

    def hook(module, args, output):
        inputs.append(args[0].detach())
        outputs.append(output.detach())

    x = torch.as_tensor(x, dtype=torch.float32)
    handle = layer.register_forward_hook(hook)
    was_training = model.training
    model.eval()
    try:
        with torch.no_grad():
            predictions = [model(x[i : i + batch_size]).reshape(-1) for i in range(0, len(x), batch_size)]
    finally:
        handle.remove()
        model.train(was_training)
    if not predictions:
        return np.zeros((0, layer.in_features)), np.zeros(0), np.zeros(0)
    h, z = torch.cat(inputs), torch.cat(outputs)
    if h.ndim != 2 or h.shape[0] != len(x):
        raise ValueError(
            f"the output layer of {type(model).__name__} must see one vector per window, got inputs of "
            f"shape {tuple(h.shape)} for {len(x)} windows"
        )
    return (
        h.cpu().numpy().astype(np.float64),
        z.reshape(-1).cpu().numpy().astype(np.float64),
        torch.cat(predictions).cpu().numpy().astype(np.float64),
    )


def _check_fit_inputs(h, y, w, b):
    h, y = np.asarray(h, dtype=np.float64), np.asarray(y, dtype=np.float64)
    w, b = np.asarray(w, dtype=np.float64), np.asarray(b, dtype=np.float64)
    if h.ndim != 2 or h.shape[0] == 0:
        raise ValueError(f"h_val must be (n, d) with n > 0, got shape {h.shape}")
    if y.shape != (h.shape[0],):
        raise ValueError(f"y_val must be ({h.shape[0]},) to match h_val, got shape {y.shape}")
    if w.shape != (1, h.shape[1]):
        raise ValueError(f"w must be (1, {h.shape[1]}) to match h_val, got shape {w.shape}")
    if b.shape != (1,):
        raise ValueError(f"b must be (1,), got shape {b.shape}")
    for name, value in (("h_val", h), ("y_val", y), ("w", w), ("b", b)):
        if not np.all(np.isfinite(value)):
            raise ValueError(f"{name} must be finite, got {np.count_nonzero(~np.isfinite(value))} non-finite value(s)")
    return h, y, w, b


__all__ = [
    "ACTIONS",
    "DEFAULT_ALLOWED_RANGE",
    "QConfig",
    "QRefiner",
    "QResult",
    "RangeMetrics",
    "clip",
    "output_layer",
    "penultimate",
    "q_update",
    "range_metrics",
    "refine_model",
]
