"""The domain's checks (roadgrip/cloud/domain/checks.py): a ValueError names the parameter, the constraint and the
value received; bools are no numbers; what passes comes back as the caller keeps it."""

import math

import pytest

from roadgrip.cloud.domain import checks


@pytest.mark.parametrize(
    ("check", "args", "bad", "constraint"),
    [
        (checks.positive_finite, (), [0, -1.0, math.inf, math.nan, True, "1", None], "a positive finite number"),
        (checks.positive_at_most, (10.0,), [0, -1, 10.5, math.nan, False, "1"], "a number in (0, 10.0]"),
        (checks.probability, (), [0, 1, 1.5, -0.1, math.nan, True], "a number in (0, 1)"),
        (checks.count, (), [0, -3, 1.0, 2.5, True, "2"], "an integer >= 1"),
        (checks.integer_in, (0, 15), [-1, 16, 10.5, "10", True, None], "an integer in 0..15"),
    ],
)
def test_a_refusal_names_the_parameter_the_constraint_and_the_value(check, args, bad, constraint):
    for value in bad:
        with pytest.raises(ValueError) as refused:
            check("some_parameter", value, *args)
        assert str(refused.value) == f"some_parameter must be {constraint}, got {value!r}"


def test_what_passes_comes_back_as_kept():
    assert checks.positive_finite("x", 3) == 3.0 and isinstance(checks.positive_finite("x", 3), float)
    assert checks.positive_at_most("x", math.inf) == math.inf  # no upper bound: inf is positive
    assert checks.probability("x", 0.5) == 0.5 and checks.count("x", 2) == 2
    assert checks.integer_in("station_id", 7, 0, 9, "an integer StationID") == 7
    with pytest.raises(ValueError, match="station_id must be an integer StationID in 0..9, got 10"):
        checks.integer_in("station_id", 10, 0, 9, "an integer StationID")


def test_a_record_s_interval_is_finite_and_ordered():
    checks.interval("estimate of vehicle 'v' at 1", 0.2, 0.4, mu=0.3)
    checks.finite_bounds("estimate of vehicle 'v' at 1", 0.4, 0.2)  # bounds alone: in either order
    with pytest.raises(ValueError, match=r"^estimate of vehicle 'v' at 1: mu 0\.3, mu_lower 0\.7, mu_upper 0\.2 "):
        checks.interval("estimate of vehicle 'v' at 1", 0.7, 0.2, mu=0.3)
    with pytest.raises(ValueError, match=r"report: mu nan"):
        checks.interval("report", 0.2, 0.4, mu=math.nan)
    with pytest.raises(ValueError, match=r"^evidence: mu_lower 0\.2, mu_upper inf must be finite"):
        checks.interval("evidence", 0.2, math.inf)
    with pytest.raises(ValueError, match=r"mu_lower nan and mu_upper 0\.4 must be finite"):
        checks.finite_bounds("estimate", math.nan, 0.4)
