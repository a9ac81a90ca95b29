"""Importers of recorded logs: one plug-in point for every logger's format.

An importer turns one recorded log (a file, or a folder of files) into telemetry in wire format v1 (CONTRACTS 3.1): a
`pyarrow.Table` with the columns of `roadgrip.data.schema.TELEMETRY` (vehicle_id, timestamp_ms in ms since the Unix
epoch, SI units, ISO 8855 signs), sorted by (vehicle_id, timestamp_ms). It is any object with

| member                          | does                                                                          |
| ------------------------------- | ----------------------------------------------------------------------------- |
| `name: str`                     | the name users pick it by (`roadgrip import-log --importer NAME`)             |
| `detect(path) -> bool`          | whether `path` looks like its format (cheap: names and headers, not the data) |
| `load(path, **options) -> Table`| the log as wire-format telemetry; an unknown option is a `ValueError`         |

Every importer takes the options `vehicle_id` (default: its own, e.g. derived from the file) and `start_ms` (the
timestamp of the first sample; default: its own, documented there). The built-in ones are `wire` (any wire-format
file: `roadgrip.fleet.importers.wire`), `bmw-m8` (the real log in data/real/bmw_m8_braking:
`roadgrip.fleet.importers.bmw_m8`) and `can-dbc` (raw CAN logs with the car's DBC and a mapping file, such as the
Toyota RAV4's in data/real/toyota_rav4_street: `roadgrip.fleet.importers.can_dbc`).

Third-party packages add theirs through the entry-point group `roadgrip.importers`: in their pyproject.toml

    [project.entry-points."roadgrip.importers"]
    my-logger = "my_package.importer:MyLoggerImporter"

The entry point may name an importer object or a class (called without arguments); its `name` must be the entry
point's name. They are loaded the first time the registry is asked (`importers`, `get_importer`, `detect_importer`);
one that fails to load is skipped with a logged warning, and asking for it by name says why.
"""

from __future__ import annotations

import logging
from importlib.metadata import entry_points
from pathlib import Path
from typing import Protocol, runtime_checkable

import pyarrow as pa

logger = logging.getLogger(__name__)

ENTRY_POINT_GROUP = "roadgrip.importers"


@runtime_checkable
class Importer(Protocol):
    """A recorded log's format (see the module docstring). An importer that knows the logged vehicle may also have a
    `profile() -> VehicleParams` method: `roadgrip fleet --replay` then registers the vehicle with it."""

    name: str

    def detect(self, path: Path) -> bool:
        """Whether `path` looks like a log of this format."""

    def load(self, path: Path, **options) -> pa.Table:
        """The log as wire-format v1 telemetry (CONTRACTS 3.1)."""


_REGISTRY: dict[str, Importer] = {}
_FAILED: dict[str, str] = {}  # entry points that could not be loaded: name -> why
_entry_points_loaded = False


def register_importer(importer: Importer, *, replace: bool = False) -> Importer:
    """Add `importer` to the registry under its name (an importer object, not a class); returns it. A name already
    taken is a `ValueError` unless `replace`."""
    if isinstance(importer, type):
        raise TypeError(
            f"register_importer takes an importer object, got the class {importer.__name__}: "
            f"register {importer.__name__}() instead"
        )
    name = getattr(importer, "name", None)
    if not isinstance(name, str) or not name.strip():
        raise TypeError(f"an importer needs a non-empty string `name`, got {name!r} on {importer!r}")
    missing = [m for m in ("detect", "load") if not callable(getattr(importer, m, None))]
    if missing:
        raise TypeError(f"importer {name!r} lacks the method(s) {', '.join(missing)} (see roadgrip.fleet.importers)")
    if name in _REGISTRY and _REGISTRY[name] is not importer and not replace:
        raise ValueError(
            f"an importer named {name!r} is already registered ({_REGISTRY[name]!r}); pass replace=True to replace it"
        )
    _REGISTRY[name] = importer
    _FAILED.pop(name, None)
    return importer


def load_entry_points() -> list[str]:
    """Register the importers of the entry-point group `roadgrip.importers` that are not registered yet; returns their
    names. Called once, lazily, by the functions below; call it again after installing a package."""
    global _entry_points_loaded
    _entry_points_loaded = True
    added = []
    for ep in entry_points(group=ENTRY_POINT_GROUP):
        if ep.name in _REGISTRY:
            continue
        try:
            obj = ep.load()
            importer = obj() if isinstance(obj, type) else obj
            if getattr(importer, "name", None) != ep.name:
                raise ValueError(f"its importer is named {getattr(importer, 'name', None)!r}, not {ep.name!r}")
            register_importer(importer)
        except Exception as err:  # noqa: BLE001 - a broken plug-in, whatever its fault, must not break the others
            _FAILED[ep.name] = f"entry point {ep.name} = {ep.value} failed to load: {type(err).__name__}: {err}"
            logger.warning("skipped importer %s", _FAILED[ep.name])
            continue
        added.append(ep.name)
    return added


def _ensure_loaded() -> None:
    if not _entry_points_loaded:
        load_entry_points()


def importers() -> dict[str, Importer]:
    """The registered importers by name: the built-in ones first, then those of entry points."""
    _ensure_loaded()
    return dict(_REGISTRY)


def get_importer(name: str) -> Importer:
    """The importer called `name`; `ValueError` naming the known ones if there is none."""
    _ensure_loaded()
    if name in _REGISTRY:
        return _REGISTRY[name]
    if name in _FAILED:
        raise ValueError(f"importer {name!r} is not available: {_FAILED[name]}")
    raise ValueError(f"importer must be one of {sorted(_REGISTRY)}, got {name!r}")


def detect_importer(path: str | Path) -> Importer:
    """The first registered importer whose `detect` accepts `path` (built-in ones first); `ValueError` if none does."""
    _ensure_loaded()
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"log {path} does not exist")
    for importer in _REGISTRY.values():
        try:
            if importer.detect(path):
                return importer
        except OSError as err:  # an unreadable file is not this importer's format
            logger.debug("importer %s could not inspect %s: %s", importer.name, path, err)
    raise ValueError(f"no importer recognises {path}; name one with --importer (known: {sorted(_REGISTRY)})")


def resolve_importer(path: str | Path, importer: str | Importer | None = None) -> Importer:
    """`importer` itself, the registered one of that name, or (None) the one that detects `path`."""
    if importer is None:
        return detect_importer(path)
    if isinstance(importer, str):
        return get_importer(importer)
    return importer


def _register_builtins() -> None:
    from roadgrip.fleet.importers.bmw_m8 import BmwM8Importer
    from roadgrip.fleet.importers.can_dbc import CanDbcImporter
    from roadgrip.fleet.importers.wire import WireImporter

    register_importer(WireImporter())
    register_importer(BmwM8Importer())
    register_importer(CanDbcImporter())


_register_builtins()
