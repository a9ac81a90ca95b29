"""A trial, not kept in wire.py: checking a JSON payload's samples at once with numpy (one array of the payload's
numbers, the ranges compared in one go) against wire.py's `_Checker.check` one sample at a time, on a message of the
cluster bench (10 samples of simulated telemetry, the optional channels null). Prints microseconds per message, the
best of 7 repeats of 1,000 each:

    python results/rawpath/wire_check_at_once.py

At 10 samples a message the array costs more than the checks it replaces: turning 180 Python floats and nulls into a
float64 array alone takes about as long as `check` over the ten samples (docs/CLUSTER.md, issue 27).
"""

from __future__ import annotations

import json
import timeit
from itertools import chain
from operator import itemgetter

import numpy as np

from roadgrip.bench.cluster import sample_bodies
from roadgrip.cloud.ingest import wire

NUMBER_ROW = itemgetter(*(name for name, *_ in wire._NUMBERS))
LOW = np.array([low for _, low, _, _ in wire._NUMBERS])
HIGH = np.array([high for _, _, high, _ in wire._NUMBERS])
REQUIRED = np.array([required for *_, required in wire._NUMBERS])
BOOL_ROW = itemgetter(*(name for name, _ in wire._BOOLS))
BOOL_REQUIRED_AT = [k for k, (_, required) in enumerate(wire._BOOLS) if required]


def check_all(checker: wire._Checker, docs: list) -> list[dict] | None:
    """The samples `check` gives, when every doc is a usual sample that passes; else None (then `check` one by one)."""
    for doc in docs:
        if type(doc) is not dict or doc.keys() != wire._WIRE_KEYS:
            return None
    for vid in {doc["vehicle_id"] for doc in docs}:
        if type(vid) is not str or vid not in checker.accepted_ids:
            try:
                checker._vehicle(vid, None)
            except wire._Refused:
                return None
    stamps = [doc["timestamp_ms"] for doc in docs]
    if set(map(type, stamps)) != {int} or min(stamps) < 0 or max(stamps) > checker.latest_ms:
        return None
    rows = list(map(NUMBER_ROW, docs))
    values = list(chain.from_iterable(rows))
    if not set(map(type, values)) <= {float, type(None)}:
        return None
    numbers = np.array(rows, dtype=np.float64)  # null is NaN
    unset = np.isnan(numbers)
    if values.count(None) != int(unset.sum()) or (unset & REQUIRED).any():
        return None
    if not (((numbers >= LOW) & (numbers <= HIGH)) | unset).all():
        return None
    flags = list(map(BOOL_ROW, docs))
    if not set(map(type, chain.from_iterable(flags))) <= {bool, type(None)}:
        return None
    if any(row[k] is None for row in flags for k in BOOL_REQUIRED_AT):
        return None
    out = []
    for doc in docs:
        sample = wire._TEMPLATE.copy()
        sample.update(doc)
        out.append(sample)
    return out


def main() -> None:
    now_ms = 1_767_225_600_000
    rows = [json.loads("{" + f + "}") for f in sample_bodies()[0][:10]]
    docs = [{"vehicle_id": "bench00001", "timestamp_ms": now_ms - 1_000 + 100 * k, **r} for k, r in enumerate(rows)]
    checker = wire._Checker(now_ms, 60_000, "bench00001")
    one_by_one = [checker.check(d) for d in docs]
    assert check_all(checker, docs) == one_by_one
    for name, run in (
        ("check, one sample at a time", lambda: [checker.check(d) for d in docs]),
        ("numpy, the message at once", lambda: check_all(checker, docs)),
    ):
        best = min(timeit.repeat(run, number=1_000, repeat=7)) / 1_000
        print(json.dumps({"check": name, "samples": len(docs), "us_per_message": round(best * 1e6, 1)}))


if __name__ == "__main__":
    main()
