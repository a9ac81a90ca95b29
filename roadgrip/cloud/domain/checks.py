"""The domain's argument and record checks, one style for the map, the warning engine and the cells: a ValueError that
names the parameter (or the record), the constraint and the value received, as scikit-learn's do:

    half_life_s must be a positive finite number, got -1.0

A number is an int or a float, never a bool (True is no count and no threshold). Each check returns the value as the
caller keeps it (a float for a number, the int for an integer)."""

from __future__ import annotations

import json
import math


def _is_number(value) -> bool:
    return not isinstance(value, bool) and isinstance(value, (int, float))


def _is_integer(value) -> bool:
    return not isinstance(value, bool) and isinstance(value, int)


def _refuse(name: str, constraint: str, value) -> ValueError:
    return ValueError(f"{name} must be {constraint}, got {value!r}")


def positive_finite(name: str, value) -> float:
    """A number in (0, inf)."""
    if not _is_number(value) or not math.isfinite(value) or value <= 0:
        raise _refuse(name, "a positive finite number", value)
    return float(value)


def positive_at_most(name: str, value, upper: float = math.inf) -> float:
    """A number in (0, upper] (upper inf: any positive number, inf included)."""
    if not _is_number(value) or not 0 < value <= upper:
        raise _refuse(name, f"a number in (0, {upper}]", value)
    return float(value)


def probability(name: str, value) -> float:
    """A number in the open interval (0, 1)."""
    if not _is_number(value) or not 0 < value < 1:
        raise _refuse(name, "a number in (0, 1)", value)
    return float(value)


def count(name: str, value) -> int:
    """An integer >= 1."""
    if not _is_integer(value) or value < 1:
        raise _refuse(name, "an integer >= 1", value)
    return value


def integer_in(name: str, value, low: int, high: int, kind: str = "an integer") -> int:
    """An integer in low..high; `kind` names what it is ("an integer H3 resolution")."""
    if not _is_integer(value) or not low <= value <= high:
        raise _refuse(name, f"{kind} in {low}..{high}", value)
    return value


def interval(what: str, lower, upper, mu=None) -> None:
    """A record's 90 % interval (and its point value, when given): finite, with lower <= upper. `what` names the record
    ("estimate of vehicle 'v1' at 1768464000000")."""
    values = (lower, upper) if mu is None else (mu, lower, upper)
    if not all(math.isfinite(v) for v in values) or lower > upper:
        given = "" if mu is None else f"mu {mu!r}, "
        raise ValueError(
            f"{what}: {given}mu_lower {lower!r}, mu_upper {upper!r} must be finite with mu_lower <= mu_upper"
        )


def finite_bounds(what: str, lower, upper) -> None:
    """A record's bounds, finite (in either order)."""
    if not (math.isfinite(lower) and math.isfinite(upper)):
        raise ValueError(f"{what}: mu_lower {lower!r} and mu_upper {upper!r} must be finite")


class PayloadError(ValueError):
    """A payload of JSON messages refused: `index` (the message in an array; 0 for one object), `field` (None for the
    payload or the message as a whole) and the reason; `status` the HTTP status to answer. A subclass names its
    messages (NOUN: "report", "message")."""

    NOUN = "message"

    def __init__(self, reason: str, *, index: int | None = None, field: str | None = None, status: int = 422):
        where = " ".join(p for p in (f"{self.NOUN} {index}" if index is not None else "", field or "") if p)
        super().__init__(f"{where}: {reason}" if where else reason)
        self.index, self.field, self.reason, self.status = index, field, reason, status

    def to_dict(self) -> dict:
        return {"index": self.index, "field": self.field, "reason": self.reason}


def json_items(body: bytes, *, max_bytes: int, max_items: int, error: type[PayloadError]) -> list:
    """The messages of an HTTP body or MQTT message: a JSON object, or an array of 1..max_items; `error` (413 for a
    payload too large, 400 for one that is not JSON, 422 otherwise) for the first fault."""
    if len(body) > max_bytes:
        raise error(f"payload of {len(body)} bytes exceeds the limit of {max_bytes}", status=413)
    try:
        document = json.loads(body)
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise error(f"not JSON: {exc}", status=400) from None
    except RecursionError:
        raise error("not JSON: nested too deeply", status=400) from None
    items = document if isinstance(document, list) else [document]
    if not items:
        raise error(f"an empty array holds no {error.NOUN}")
    if len(items) > max_items:
        raise error(f"{len(items)} {error.NOUN}s in one payload, at most {max_items}", status=413)
    return items
