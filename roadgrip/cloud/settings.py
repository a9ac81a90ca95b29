"""The cloud's configuration: one typed class, read from environment variables (prefix `ROADGRIP_`), a YAML file, and
explicit arguments (highest first: arguments, environment, file, defaults).

    ROADGRIP_DATABASE_URL=postgresql://user@host/db ROADGRIP_MQTT=auto roadgrip serve
    roadgrip serve --config cloud.yaml

Unknown keys in the file are errors, as are values outside their ranges (the message names the key).
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

import yaml
from pydantic import Field, ValidationError, field_validator
from pydantic_settings import BaseSettings, PydanticBaseSettingsSource, SettingsConfigDict, YamlConfigSettingsSource

from roadgrip.cloud.domain import warnings as we
from roadgrip.cloud.formats.datex2 import check_country


class Settings(BaseSettings):
    model_config = SettingsConfigDict(env_prefix="ROADGRIP_", extra="forbid", frozen=True)

    # where things live
    data_dir: Path = Field(
        Path("roadgrip-data"), description="directory for the SQLite file, broker files and the generated admin secret"
    )
    database_url: str | None = Field(
        None, description="sqlite:///FILE or postgresql://...; default: SQLite in data_dir"
    )
    host: str = Field("127.0.0.1", description="HTTP listen address")
    port: int = Field(8000, ge=0, le=65535, description="HTTP port (0: pick a free one)")

    # MQTT: "off" (HTTP only), "auto" (start a Mosquitto when installed, else HTTP only), "managed" (start one, fail
    # without it), or a broker URL mqtt://host:port with mqtt_username/mqtt_password for the service's own login.
    mqtt: str = Field("off", description="off | auto | managed | mqtt://host:port")
    mqtt_port: int = Field(0, ge=0, le=65535, description="port of the managed broker (0: pick a free one)")
    mqtt_username: str | None = None
    mqtt_password: str | None = None

    # access
    admin_secret: str | None = Field(
        None, min_length=16, description="the admin's secret; generated into data_dir/admin-secret when absent"
    )

    # ingest and estimation
    estimator: str = Field(
        "pmf",
        description="estimator for every vehicle: pmf (the grid filter, docs/ESTIMATORS.md), "
        "ekf, ukf, default (the shipped learned model) or a model file",
    )
    max_payload_bytes: int = Field(1_048_576, ge=1024, description="largest accepted body or MQTT message")
    max_samples_per_payload: int = Field(10_000, ge=1)
    max_future_s: float = Field(60.0, gt=0, description="samples further ahead of the server clock are refused")
    max_gap_s: float = Field(0.25, gt=0, description="a longer gap between samples restarts the estimator")
    reorder_window_s: float = Field(
        0.3,
        ge=0,
        description="how long a vehicle's samples are held to put late arrivals back in order before estimation",
    )
    flush_interval_s: float = Field(0.1, gt=0, le=5, description="the pipeline's batching period")
    ingest_processes: int = Field(
        0,
        ge=0,
        le=64,
        description="processes that parse, estimate and store the "
        "vehicles' telemetry, each for its share of the vehicles "
        "(0: the service's own process; roadgrip/cloud/serve/shards.py)",
    )
    friction_publish_interval_s: float = Field(
        1.0,
        ge=0,
        le=60,
        description="each vehicle's estimates are published "
        "together on its friction topic at most "
        "this often (0: every round)",
    )
    rate_limit_samples_per_s: float = Field(
        50.0,
        ge=0,
        allow_inf_nan=False,
        description="samples a vehicle may send per second, HTTP and MQTT "
        "together (5x the 10 Hz of a terminal); 0: no limit "
        "(roadgrip/cloud/ingest/ratelimit.py)",
    )
    rate_limit_burst_s: float = Field(
        10.0,
        gt=0,
        allow_inf_nan=False,
        description="seconds of rate_limit_samples_per_s a vehicle may send at once "
        "after a quiet spell (the bucket's size)",
    )

    # map and warnings
    h3_resolution: int = Field(10, ge=0, le=15)
    map_half_life_s: float = Field(600.0, gt=0, description="an estimate's weight halves every half-life")
    map_max_age_s: float = Field(3600.0, gt=0, description="older evidence leaves the map")
    map_clock: Literal["wall", "data"] = Field(
        "wall", description="age against the server clock, or against the newest sample (replays of old logs)"
    )
    # the warning defaults live in one place, roadgrip/cloud/domain/warnings.py (THRESHOLD_MU, ...)
    warning_threshold_mu: float = Field(
        we.THRESHOLD_MU, gt=0, lt=2, description="a pass is low when its mu_upper lies below"
    )
    warning_min_low_passes: int = Field(
        we.MIN_LOW_PASSES, ge=1, description="low passes (vehicles or repeated passes) to raise"
    )
    warning_min_dry_passes: int = Field(we.MIN_DRY_PASSES, ge=1, description="dry passes after a warning to cancel it")
    warning_pass_gap_s: float = Field(
        we.PASS_GAP_S, gt=0, description="a vehicle back in a cell after this is a new pass"
    )
    warning_min_excited_per_pass: int = Field(we.MIN_EXCITED_PER_PASS, ge=1)
    warning_validity_s: float = Field(we.VALIDITY_S, gt=0, description="DENM validity; a warning not refreshed expires")
    station_id: int = Field(1, ge=0, le=4294967295, description="ITS station id of the cloud in DENMs")
    datex2_country: str = Field(
        "ZZ",
        description="ISO 3166-1 alpha-2 code of the operator's country, the DATEX II publicationCreator's country "
        "(roadgrip/cloud/formats/datex2.py); default ZZ, a user-assigned code (Unicode CLDR: unknown region) that "
        "claims no country: set your own, e.g. NO",
    )
    # cluster mode: the map and the warnings are kept per region, an H3 parent cell of the map's cells, by the worker
    # that owns the region's queue (roadgrip/cloud/cluster/regions.py); resolution 5 cells are about 250 km^2
    region_resolution: int = Field(
        5, ge=0, le=15, description="H3 resolution of the regions (at most h3_resolution; checked in cluster mode)"
    )
    region_queues: int = Field(
        4, ge=1, le=1024, description="queues the regions are spread over (fixed once declared, as the partitions)"
    )

    # dashboard
    map_tiles_url: str | None = Field(
        None,
        pattern=r"^(https?://|/)",
        description="base-map tile URL template (http, https or a path on this "
        "server) for the dashboard, e.g. "
        "https://tile.openstreetmap.org/{z}/{x}/{y}.png; none: no base map, "
        "the cells on a plain background",
    )

    @field_validator("mqtt")
    @classmethod
    def _mqtt_mode(cls, value: str) -> str:
        if value in ("off", "auto", "managed") or value.startswith(("mqtt://", "tcp://")):
            return value
        raise ValueError(f"mqtt must be off, auto, managed or mqtt://host:port, got {value!r}")

    @field_validator("datex2_country")
    @classmethod
    def _country(cls, value: str) -> str:
        return check_country(value)

    @classmethod
    def settings_customise_sources(
        cls,
        settings_cls: type[BaseSettings],
        init_settings: PydanticBaseSettingsSource,
        env_settings: PydanticBaseSettingsSource,
        dotenv_settings: PydanticBaseSettingsSource,
        file_secret_settings: PydanticBaseSettingsSource,
    ):
        return init_settings, env_settings, YamlConfigSettingsSource(settings_cls)

    @property
    def storage_url(self) -> str:
        return self.database_url or f"sqlite:///{self.data_dir / 'roadgrip.sqlite'}"


def load_settings(config_file: str | Path | None = None, **overrides) -> Settings:
    """Settings from explicit overrides (None values ignored), then the environment, then a YAML file, then defaults."""
    settings_cls = Settings
    if config_file is not None:
        path = Path(config_file)
        if not path.is_file():
            raise ValueError(f"config file {path} does not exist")
        loaded = yaml.safe_load(path.read_text())
        if loaded is not None and not isinstance(loaded, dict):
            raise ValueError(f"config file {path} must hold a mapping of settings, got {type(loaded).__name__}")
        settings_cls = type("FileSettings", (Settings,), {"model_config": {**Settings.model_config, "yaml_file": path}})
    try:
        return settings_cls(**{k: v for k, v in overrides.items() if v is not None})
    except ValidationError as exc:
        problems = "; ".join(
            f"{'.'.join(str(p) for p in e['loc'])}: {e['msg']} (got {e.get('input')!r})" for e in exc.errors()
        )
        raise ValueError(f"invalid settings: {problems}") from None
