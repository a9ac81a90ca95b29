"""The one settings class: defaults, environment, file, explicit values, and errors that name the key."""

from __future__ import annotations

import pytest

from roadgrip.cloud.settings import load_settings


def test_precedence_is_explicit_then_environment_then_file(tmp_path, monkeypatch):
    config = tmp_path / "cloud.yaml"
    config.write_text("port: 9000\nh3_resolution: 9\nmqtt: auto\n")
    monkeypatch.setenv("ROADGRIP_PORT", "7000")
    settings = load_settings(config)
    assert (settings.port, settings.h3_resolution, settings.mqtt) == (7000, 9, "auto")
    assert load_settings(config, port=1234).port == 1234
    monkeypatch.delenv("ROADGRIP_PORT")
    assert load_settings(config).port == 9000
    assert load_settings().port == 8000


def test_the_default_storage_is_sqlite_in_the_data_dir(tmp_path):
    settings = load_settings(data_dir=tmp_path)
    assert settings.storage_url == f"sqlite:///{tmp_path / 'roadgrip.sqlite'}"
    assert load_settings(database_url="postgresql://u@h/db").storage_url == "postgresql://u@h/db"


@pytest.mark.parametrize(
    "text, key",
    [
        ("prt: 1\n", "prt"),
        ("h3_resolution: 16\n", "h3_resolution"),
        ("mqtt: carrier-pigeon\n", "mqtt"),
        ("- a list\n", "mapping"),
    ],
)
def test_bad_files_name_the_key(tmp_path, text, key):
    config = tmp_path / "bad.yaml"
    config.write_text(text)
    with pytest.raises(ValueError, match=key):
        load_settings(config)


def test_a_missing_file_is_an_error(tmp_path):
    with pytest.raises(ValueError, match="does not exist"):
        load_settings(tmp_path / "nope.yaml")
