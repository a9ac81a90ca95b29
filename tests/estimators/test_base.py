"""The estimate record of CONTRACTS 3.4."""

import dataclasses

from roadgrip.estimators.base import ESTIMATE_SCHEMA, Estimate


def test_to_dict_holds_every_field_in_order_as_asdict_would():
    estimate = Estimate("car-1", 1_700_000_000_000, 0.52, 0.31, 0.78, True, "ekf")
    assert list(estimate.to_dict().items()) == list(dataclasses.asdict(estimate).items())
    assert list(estimate.to_dict()) == ESTIMATE_SCHEMA.names
