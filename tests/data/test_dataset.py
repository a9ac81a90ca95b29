import json

import pytest

from roadgrip.data.dataset import MANIFEST_FILE, SAMPLES_FILE, read_dataset, read_manifest, write_dataset
from roadgrip.data.schema import DATASET_SCHEMA, TELEMETRY_COLUMNS
from roadgrip.sim.presets import paper_scenarios
from roadgrip.sim.simulate import simulate


@pytest.fixture(scope="module")
def table():
    return simulate(paper_scenarios()[:2])


def test_round_trip_keeps_schema_and_manifest(tmp_path, table):
    write_dataset(tmp_path / "ds", table, {"preset": "paper", "seed": 0})
    assert read_dataset(tmp_path / "ds").equals(table)
    assert read_manifest(tmp_path / "ds") == {"preset": "paper", "seed": 0, "rows": table.num_rows}
    assert set(TELEMETRY_COLUMNS) <= set(DATASET_SCHEMA.names)


def test_refuses_to_overwrite_and_leaves_nothing_half_written(tmp_path, table):
    target = tmp_path / "ds"
    write_dataset(target, table, {"preset": "paper"})
    with pytest.raises(FileExistsError, match="not empty"):
        write_dataset(target, table, {"preset": "other"})
    assert json.loads((target / MANIFEST_FILE).read_text())["preset"] == "paper"
    with pytest.raises(TypeError):
        write_dataset(tmp_path / "broken", table, {"unserialisable": object()})
    assert not (tmp_path / "broken").exists()
    assert [p.name for p in tmp_path.iterdir()] == ["ds"], "no staging folder is left behind"
    assert (target / SAMPLES_FILE).is_file()


def test_reading_a_folder_that_is_not_a_dataset_says_so(tmp_path):
    with pytest.raises(FileNotFoundError, match="not a roadgrip dataset"):
        read_dataset(tmp_path)
