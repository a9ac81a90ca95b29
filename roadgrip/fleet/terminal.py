"""What a vehicle's terminal sends: simulated runs turned into wire-format v1 samples (CONTRACTS 3.1)."""

from __future__ import annotations

import pyarrow as pa

from roadgrip.data.schema import TELEMETRY_COLUMNS


def wire_samples(run: pa.Table, vehicle_id: str, start_ms: int) -> list[dict]:
    """The samples of one simulated run as its terminal would send them: the telemetry columns only (no ground
    truth), under `vehicle_id`, with timestamps moved so that the run starts at `start_ms`."""
    if run.num_rows == 0:
        raise ValueError("wire_samples needs a run with at least one sample")
    samples = run.select([c for c in TELEMETRY_COLUMNS if c in run.column_names]).to_pylist()
    shift = start_ms - samples[0]["timestamp_ms"]
    for sample in samples:
        sample["vehicle_id"] = vehicle_id
        sample["timestamp_ms"] += shift
    return samples
