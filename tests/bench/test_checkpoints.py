"""The checkpoint cost benchmark (roadgrip/bench/checkpoints.py): every state stored is restored, and packing
shrinks a pmf state."""

import json

from roadgrip.bench.checkpoints import main, measure_cost
from roadgrip.cloud.pipeline.checkpoints import MAX_CHECKPOINTS_PER_ROUND


def test_measure_cost_restores_every_state_and_packs_a_pmf_state_smaller(tmp_path):
    result = measure_cost(vehicles=MAX_CHECKPOINTS_PER_ROUND + 5, estimator_name="pmf", seconds=20.0)
    assert result["vehicles"] == MAX_CHECKPOINTS_PER_ROUND + 5 and result["rounds"] == 2
    assert result["estimator"] == "pmf" and result["database"] == "sqlite"
    assert 0 < result["state_bytes_packed"] < result["state_bytes_plain_json"]
    assert result["sqlite_file_bytes"] > 0  # the temporary database's main file (SQLite keeps recent pages in its WAL)
    assert all(v > 0 for v in result["per_vehicle_us"].values())


def test_main_prints_the_cost_as_json(tmp_path, capsys):
    main(["--vehicles", "3", "--estimator", "ekf", "--database-url", f"sqlite:///{tmp_path / 'states.sqlite'}"])
    result = json.loads(capsys.readouterr().out)
    assert result["vehicles"] == 3 and result["estimator"] == "ekf" and result["sqlite_file_bytes"] is None
