import pytest
from telemetry_samples import drive, table_of


@pytest.fixture
def clean():
    """A clean synthetic drive (telemetry_samples.drive) as a table."""
    return table_of(drive())
