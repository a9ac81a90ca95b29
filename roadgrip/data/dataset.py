"""Simulation datasets on disk (CONTRACTS 3.3): `samples.parquet`, one row per sample, and `manifest.json`.

A dataset is written into a temporary folder beside the target and renamed into place only when complete, so a failed or
interrupted run never leaves half a dataset behind.
"""

from __future__ import annotations

import json
import shutil
import tempfile
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq

SAMPLES_FILE = "samples.parquet"
MANIFEST_FILE = "manifest.json"


def write_dataset(out_dir: str | Path, table: pa.Table, manifest: dict, overwrite: bool = False) -> Path:
    out = Path(out_dir)
    if out.exists() and any(out.iterdir()) and not overwrite:
        raise FileExistsError(f"output folder {out} exists and is not empty; choose another or pass overwrite")
    out.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    try:
        pq.write_table(table, staging / SAMPLES_FILE, compression="zstd")
        (staging / MANIFEST_FILE).write_text(json.dumps(manifest | {"rows": table.num_rows}, indent=2))
        if out.exists():
            shutil.rmtree(out)
        staging.rename(out)
    finally:
        if staging.exists():
            shutil.rmtree(staging)
    return out


def read_manifest(dataset_dir: str | Path) -> dict:
    path = Path(dataset_dir) / MANIFEST_FILE
    if not path.is_file():
        raise FileNotFoundError(f"{dataset_dir} is not a roadgrip dataset: {MANIFEST_FILE} is missing")
    return json.loads(path.read_text())


def read_dataset(dataset_dir: str | Path, columns: list[str] | None = None) -> pa.Table:
    read_manifest(dataset_dir)
    return pq.read_table(Path(dataset_dir) / SAMPLES_FILE, columns=columns)


def vehicles_from_manifest(manifest: dict) -> dict:
    """{vehicle name: VehicleParams} of every run of a simulated dataset (for features that use the vehicle profile)."""
    from roadgrip.vehicle.params import VehicleParams

    return {s["vehicle"]["name"]: VehicleParams.from_dict(s["vehicle"]) for s in manifest.get("scenarios", [])}
