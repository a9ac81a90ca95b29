"""The estimator_states table: each vehicle's estimator state (its self-calibration) by estimator name, the
checkpoints of roadgrip/cloud/pipeline/checkpoints.py, fenced by partition in cluster mode."""

from __future__ import annotations

from collections.abc import Mapping

from sqlalchemy import select

from roadgrip.cloud.storage.base import Database, checked_rows, now_ms
from roadgrip.cloud.storage.partitions import check_fences
from roadgrip.cloud.storage.schema import estimator_states_table


class EstimatorStates:
    """Estimator states on one `Database` (the methods of `Storage` of the same names)."""

    def __init__(self, db: Database):
        self._db = db

    def put_estimator_states(self, rows: list[dict], fences: Mapping[int, int] | None = None) -> None:
        """Store (or replace) estimator states in one transaction: each row holds vehicle_id, estimator (its name),
        state (a JSON-able dict) and optionally updated_ms (default: now). Of rows with the same key the last wins.
        `fences` as in `write_batch`: Fenced, nothing stored, if another worker has taken one of those partitions
        since (a stale owner's checkpoint must not overwrite the new owner's)."""
        updated_ms = now_ms()
        latest = {}
        for row in rows:
            if not isinstance(row.get("state"), dict):
                raise TypeError(
                    f"state of vehicle {row.get('vehicle_id')!r} must be a dict, got {type(row.get('state')).__name__}"
                )
            latest[(row.get("vehicle_id"), row.get("estimator"))] = {"updated_ms": updated_ms, **row}
        if not latest:
            return
        rows = checked_rows("estimator state", list(latest.values()), estimator_states_table)
        insert = self._db.insert(estimator_states_table)
        upsert = insert.on_conflict_do_update(
            index_elements=["vehicle_id", "estimator"],
            set_={"state": insert.excluded.state, "updated_ms": insert.excluded.updated_ms},
        )
        with self._db.transaction() as conn:
            check_fences(conn, fences)
            conn.execute(upsert, rows)

    def estimator_states(self, vehicle_ids: list[str], estimator: str) -> dict[str, dict]:
        """vehicle_id -> the stored state of estimator `estimator`, for those of `vehicle_ids` that have one."""
        c = estimator_states_table.c
        states: dict[str, dict] = {}
        ids = sorted(set(vehicle_ids))
        for start in range(0, len(ids), 1000):  # well inside every database's limit on parameters
            query = select(c.vehicle_id, c.state).where(
                c.estimator == estimator, c.vehicle_id.in_(ids[start : start + 1000])
            )
            states.update((row["vehicle_id"], row["state"]) for row in self._db.all(query))
        return states

    def estimator_state_rows(self) -> list[dict]:
        """Every stored estimator state (vehicle_id, estimator, state, updated_ms), by vehicle and estimator."""
        c = estimator_states_table.c
        return self._db.all(select(estimator_states_table).order_by(c.vehicle_id, c.estimator))
