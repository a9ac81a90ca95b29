"""What the two Kalman filters (ekf.py, ukf.py) share beyond the model: the per-vehicle memory, the handling of a
sample (start, gaps, bad values, divergence), the estimate it yields (CONTRACTS 3.4), small dense linear algebra, and the
`Estimator` plumbing (streaming, save/restore, batch).

Per-vehicle memory `mem`, one flat float64 vector (so that a state saves as a list and a kernel call passes one array):

| slots            | meaning                                                                 |
|------------------|-------------------------------------------------------------------------|
| M_X .. +N_X      | x, the posterior state (vehicle_model: vx, vy, r, speed scale error, mu) |
| M_P .. +N_X^2    | P, its covariance, row-major                                            |
| M_U .. +N_U      | the previous sample's inputs u (vehicle_model.U_*)                      |
| M_T              | the previous sample's timestamp, ms                                     |
| M_STARTED        | 1 once the filter has started on this segment                          |
| M_REJECTED       | samples rejected (a non-finite value, time not increasing, an update that would break P) |
| M_RESTARTS       | restarts (a step longer than max_step_s, or a state that went non-finite) |
| M_SNR            | the last sample's mu signal-to-noise (vehicle_model.mu_snr)             |

A sample (one row) is the vector `SAMPLE_COLUMNS`, in wire format v1 units.
"""

from __future__ import annotations

import logging
from math import sqrt

import numpy as np
import pyarrow as pa
from numba import njit

from roadgrip.estimators.base import Estimate, Estimator, estimate_table, memory_state, profile_of_call
from roadgrip.estimators.vehicle_model import (
    INTERVAL_RANGE,
    INTERVAL_Z,
    MU,
    MU_MAX,
    MU_MIN,
    N_U,
    N_X,
    STATE_NAMES,
    T_MAX_STEP,
    T_SNR,
    U_AX,
    U_AY,
    U_DELTA,
    U_W0,
    Z_AX,
    Z_AY,
    Z_R,
    Z_V,
    FilterTuning,
    initial_state,
    pack_model,
)
from roadgrip.vehicle.dynamics import P_STEER_RATIO
from roadgrip.vehicle.params import VehicleParams

logger = logging.getLogger(__name__)

SAMPLE_COLUMNS = (
    "timestamp_ms",
    "wheel_speed_fl_radps",
    "wheel_speed_fr_radps",
    "wheel_speed_rl_radps",
    "wheel_speed_rr_radps",
    "steering_wheel_angle_rad",
    "accel_lon_mps2",
    "accel_lat_mps2",
    "yaw_rate_radps",
    "speed_mps",
)
S_T, S_W0, S_SWA, S_AX, S_AY, S_R, S_V = 0, 1, 5, 6, 7, 8, 9
N_S = len(SAMPLE_COLUMNS)

M_X = 0
M_P = M_X + N_X
M_U = M_P + N_X * N_X
M_T = M_U + N_U
M_STARTED, M_REJECTED, M_RESTARTS, M_SNR = M_T + 1, M_T + 2, M_T + 3, M_T + 4
N_MEM = M_T + 5
REJECT, START, STEP = 0, 1, 2  # what `begin` decided for a sample
O_MU, O_LOWER, O_UPPER, O_EXCITED, O_VALID = 0, 1, 2, 3, 4
N_OUT = 5


# --------------------------------------------------------------------------------------------- linear algebra


@njit(cache=True)
def cholesky(A, L):
    """L lower triangular with L L' = A; False (L unusable) unless A is symmetric positive definite."""
    n = A.shape[0]
    for i in range(n):
        for j in range(n):
            L[i, j] = 0.0
    for j in range(n):
        d = A[j, j]
        for k in range(j):
            d -= L[j, k] * L[j, k]
        if not d > 0.0:  # also catches NaN
            return False
        L[j, j] = sqrt(d)
        for i in range(j + 1, n):
            s = A[i, j]
            for k in range(j):
                s -= L[i, k] * L[j, k]
            L[i, j] = s / L[j, j]
    return True


@njit(cache=True)
def cholesky_solve(L, B):
    """Overwrite the columns of B with A^-1 B, where L L' = A."""
    n = L.shape[0]
    for c in range(B.shape[1]):
        for i in range(n):  # forward: L y = b
            s = B[i, c]
            for k in range(i):
                s -= L[i, k] * B[k, c]
            B[i, c] = s / L[i, i]
        for i in range(n - 1, -1, -1):  # back: L' x = y
            s = B[i, c]
            for k in range(i + 1, n):
                s -= L[k, i] * B[k, c]
            B[i, c] = s / L[i, i]


@njit(cache=True)
def matmul(A, B, C):
    """C = A B."""
    for i in range(A.shape[0]):
        for j in range(B.shape[1]):
            s = 0.0
            for k in range(A.shape[1]):
                s += A[i, k] * B[k, j]
            C[i, j] = s


@njit(cache=True)
def matmul_bt(A, B, C):
    """C = A B'."""
    for i in range(A.shape[0]):
        for j in range(B.shape[0]):
            s = 0.0
            for k in range(A.shape[1]):
                s += A[i, k] * B[j, k]
            C[i, j] = s


@njit(cache=True)
def symmetrize(A):
    """A = (A + A') / 2: rounding must not make a covariance drift from symmetric."""
    n = A.shape[0]
    for i in range(n):
        for j in range(i + 1, n):
            s = 0.5 * (A[i, j] + A[j, i])
            A[i, j] = s
            A[j, i] = s


@njit(cache=True)
def all_finite(a):
    for v in a.ravel():
        if not np.isfinite(v):
            return False
    return True


# ----------------------------------------------------------------------------------------- sample handling


@njit(cache=True)
def read_sample(prm, smp, u, z):
    """Inputs u and measurements z of a sample vector (SAMPLE_COLUMNS)."""
    for i in range(4):
        u[U_W0 + i] = smp[S_W0 + i]
    u[U_DELTA] = smp[S_SWA] / prm[P_STEER_RATIO]  # road-wheel angle
    u[U_AX] = smp[S_AX]
    u[U_AY] = smp[S_AY]
    z[Z_AX] = smp[S_AX]
    z[Z_AY] = smp[S_AY]
    z[Z_R] = smp[S_R]
    z[Z_V] = smp[S_V]


@njit(cache=True)
def start_filter(mem, prm, u, z):
    initial_state(prm, u, z[Z_V], z[Z_R], mem[M_X : M_X + N_X], mem[M_P : M_P + N_X * N_X].reshape(N_X, N_X))
    mem[M_STARTED] = 1.0


@njit(cache=True)
def begin(mem, prm, smp, u, z):
    """Decide what to do with a sample: REJECT it (a non-finite value, or time not after the last sample's), START the
    filter on it (first sample, or after a step longer than max_step_s: a gap), or STEP over dt seconds.
    Returns (decision, dt_s)."""
    if not all_finite(smp):
        mem[M_REJECTED] += 1.0
        return REJECT, 0.0
    read_sample(prm, smp, u, z)
    if mem[M_STARTED] == 0.0:
        start_filter(mem, prm, u, z)
        return START, 0.0
    dt = (smp[S_T] - mem[M_T]) / 1000.0
    if not dt > 0.0:
        mem[M_REJECTED] += 1.0
        return REJECT, 0.0
    if dt > prm[T_MAX_STEP]:
        mem[M_RESTARTS] += 1.0
        start_filter(mem, prm, u, z)
        return START, 0.0
    return STEP, dt


@njit(cache=True)
def accept_posterior(x_new, P_new, x_post, P_post):
    """Symmetrize P+ and keep (x+, P+) only if x+ is finite and P+ positive definite (a Cholesky factor exists)."""
    symmetrize(P_new)
    check = np.empty(P_new.shape)
    if not (np.isfinite(x_new).all() and cholesky(P_new, check)):
        return False
    x_post[:] = x_new
    P_post[:, :] = P_new
    return True


@njit(cache=True)
def finish_step(mem, prm, smp, u, z, x_post, P_post, accepted, snr, out):
    """After an update: count a rejected one, commit the state (the prior when rejected) and write the estimate."""
    if not accepted:
        mem[M_REJECTED] += 1.0
    commit(mem, prm, smp, u, z, x_post, P_post, snr)
    output(mem, prm, accepted, out)


@njit(cache=True)
def commit(mem, prm, smp, u, z, x, P, snr):
    """Store the posterior (mu projected onto [MU_MIN, MU_MAX]) and this sample's inputs and time. A posterior that is
    not finite (which the update guards should make impossible) restarts the filter on this sample instead."""
    if not (all_finite(x) and all_finite(P)):
        mem[M_RESTARTS] += 1.0
        start_filter(mem, prm, u, z)
        snr = 0.0
    else:
        for i in range(N_X):
            mem[M_X + i] = x[i]
            for j in range(N_X):
                mem[M_P + N_X * i + j] = P[i, j]
        mem[M_X + MU] = min(max(mem[M_X + MU], MU_MIN), MU_MAX)
    for i in range(N_U):
        mem[M_U + i] = u[i]
    mem[M_T] = smp[S_T]
    mem[M_SNR] = snr


@njit(cache=True)
def output(mem, prm, excited_ok, out):
    """The estimate: mu, the 90 % interval mu +- 1.645 sqrt(P_mumu) clipped to [0, 1.5], excited = mu_snr above its
    threshold (and `excited_ok`: False for a rejected sample)."""
    if mem[M_STARTED] == 0.0:
        out[O_VALID] = 0.0
        return
    mu = mem[M_X + MU]
    half = INTERVAL_Z * sqrt(mem[M_P + N_X * MU + MU])
    out[O_MU] = mu
    out[O_LOWER] = min(max(mu - half, INTERVAL_RANGE[0]), INTERVAL_RANGE[1])
    out[O_UPPER] = min(max(mu + half, INTERVAL_RANGE[0]), INTERVAL_RANGE[1])
    out[O_EXCITED] = 1.0 if (excited_ok and mem[M_SNR] >= prm[T_SNR]) else 0.0
    out[O_VALID] = 1.0


@njit(cache=True)
def new_segment(mem):
    """Forget the past: the next sample starts the filter afresh (the counters stay)."""
    mem[M_STARTED] = 0.0
    mem[M_SNR] = 0.0


@njit
def run_batch(step, prm, samples, segments, out, counters):
    """A filter's step kernel over the rows of one vehicle, restarting where the segment id changes.

    Not cached on disk: its cache key holds the step kernel's dispatcher, which a later process cannot pickle again
    when it adds the other filter's overload ("underlying object has vanished"); the kernels it calls are cached."""
    mem = np.zeros(N_MEM)
    for k in range(samples.shape[0]):
        if k > 0 and segments[k] != segments[k - 1]:
            new_segment(mem)
        step(mem, prm, samples[k], out[k])
    counters[0] = mem[M_REJECTED]
    counters[1] = mem[M_RESTARTS]


# ------------------------------------------------------------------------------------------ estimator plumbing


class FilterState:
    """One vehicle's filter: its profile, the packed model, and the memory the kernels update in place."""

    __slots__ = ("mem", "prm", "vehicle")

    def __init__(self, vehicle: VehicleParams, prm: np.ndarray, mem: np.ndarray):
        self.vehicle = vehicle
        self.prm = prm
        self.mem = mem


class KalmanEstimator(Estimator):
    """A Kalman filter on vehicle_model behind the estimator interface. A subclass names itself and gives its compiled
    `step_kernel(mem, prm, smp, out)`, which `run_batch` also drives over a whole table.

    Every sample gets an estimate, from the first one on (there the prior: mu_initial with a wide interval, not
    excited); a sample with a missing or non-finite value is rejected (counted in the state) and repeats the previous
    estimate, not excited."""

    name: str
    step_kernel = None

    def __init__(self, tuning: FilterTuning | None = None, vehicle: VehicleParams | None = None):
        if tuning is not None and not isinstance(tuning, FilterTuning):
            raise TypeError(f"{self.name}: tuning must be a FilterTuning, got {type(tuning).__name__}")
        if vehicle is not None and not isinstance(vehicle, VehicleParams):
            raise TypeError(f"{self.name}: vehicle must be a VehicleParams, got {type(vehicle).__name__}")
        self.tuning = FilterTuning() if tuning is None else tuning
        self.vehicle = vehicle

    def _vehicle(self, vehicle: VehicleParams | None) -> VehicleParams:
        return profile_of_call(vehicle, self.vehicle)

    # streaming
    def start(self, vehicle: VehicleParams | None = None) -> FilterState:
        vehicle = self._vehicle(vehicle)
        return FilterState(vehicle, pack_model(vehicle, self.tuning), np.zeros(N_MEM))

    def update(self, state: FilterState, sample: dict) -> Estimate | None:
        smp = np.empty(N_S)
        for k, column in enumerate(("vehicle_id",) + SAMPLE_COLUMNS):
            if column not in sample:
                raise ValueError(f"{self.name}: telemetry sample lacks the field {column!r}")
            if k:
                value = sample[column]
                smp[k - 1] = np.nan if value is None else float(value)
        out = np.zeros(N_OUT)
        type(self).step_kernel(state.mem, state.prm, smp, out)
        if out[O_VALID] == 0.0 or not np.isfinite(smp[S_T]):  # nothing to say yet, or no time to say it at
            return None
        return Estimate(
            str(sample["vehicle_id"]),
            int(smp[S_T]),
            float(out[O_MU]),
            float(out[O_LOWER]),
            float(out[O_UPPER]),
            bool(out[O_EXCITED]),
            self.name,
        )

    def reset(self, state: FilterState) -> None:
        new_segment(state.mem)

    def state_to_dict(self, state: FilterState) -> dict:
        return {"estimator": self.name, "vehicle": state.vehicle.to_dict(), "memory": state.mem.tolist()}

    def state_from_dict(self, data: dict) -> FilterState:
        vehicle, memory = memory_state(data, self.name, N_MEM)
        return FilterState(vehicle, pack_model(vehicle, self.tuning), memory)

    def diagnostics(self, state: FilterState) -> dict:
        """The filter's inner estimates (what the terminal does not send: lateral speed) and its counters."""
        mem = state.mem
        return {
            **{name: float(mem[M_X + i]) for i, name in enumerate(STATE_NAMES)},
            "covariance": mem[M_P : M_P + N_X * N_X].reshape(N_X, N_X).copy(),
            "mu_snr": float(mem[M_SNR]),
            "rejected": int(mem[M_REJECTED]),
            "restarts": int(mem[M_RESTARTS]),
        }

    # batch
    def run_batch(self, table: pa.Table, segments, vehicle: VehicleParams | None = None) -> tuple[np.ndarray, dict]:
        """The kernel's raw output (rows x N_OUT) for a table of one vehicle, and the counters."""
        vehicle = self._vehicle(vehicle)
        missing = [c for c in SAMPLE_COLUMNS if c not in table.column_names]
        if missing:
            raise ValueError(f"{self.name}: telemetry table lacks the column(s) {missing}")
        samples = np.empty((table.num_rows, N_S))
        for k, column in enumerate(SAMPLE_COLUMNS):
            samples[:, k] = table[column].to_numpy(zero_copy_only=False).astype(np.float64)
        segments = np.asarray(segments)
        if segments.shape != (table.num_rows,):
            raise ValueError(f"segments must give one id per row ({table.num_rows}), got shape {segments.shape}")
        out = np.zeros((table.num_rows, N_OUT))
        counters = np.zeros(2)
        run_batch(
            type(self).step_kernel, pack_model(vehicle, self.tuning), samples, segments.astype(np.int64), out, counters
        )
        return out, {"rejected": int(counters[0]), "restarts": int(counters[1])}

    def estimate_batch(self, table: pa.Table, segments, vehicle: VehicleParams | None = None) -> pa.Table:
        out, counters = self.run_batch(table, segments, vehicle)
        if counters["rejected"] or counters["restarts"]:
            logger.warning(
                "%s: %d sample(s) rejected, %d restart(s) (non-finite values, time not increasing, steps "
                "longer than %.2f s, or an update that would have broken the covariance)",
                self.name,
                counters["rejected"],
                counters["restarts"],
                self.tuning.max_step_s,
            )
        valid = out[:, O_VALID] > 0.5
        return estimate_table(
            {
                "vehicle_id": pa.array(table["vehicle_id"].to_numpy(zero_copy_only=False)[valid], pa.string()),
                "timestamp_ms": table["timestamp_ms"].to_numpy()[valid].astype(np.int64),
                "mu": out[valid, O_MU],
                "mu_lower": out[valid, O_LOWER],
                "mu_upper": out[valid, O_UPPER],
                "excited": out[valid, O_EXCITED] > 0.5,
                "estimator": pa.array([self.name] * int(valid.sum()), pa.string()),
            }
        )
