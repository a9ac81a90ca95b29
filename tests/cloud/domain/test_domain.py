"""The domain's own ground: it imports no format and no simulator, and the range of mu it owns holds every road the
simulator can build."""

import subprocess
import sys

import numpy as np
import pytest

from roadgrip.cloud.domain.friction_map import MU_GRID, MU_MAX
from roadgrip.cloud.domain.warnings import MAX_VALIDITY_S
from roadgrip.fleet.network import SURFACE_MU
from roadgrip.sim import roads


def test_the_domain_imports_no_format_and_no_simulator():
    probe = (
        "import sys\n"
        "import roadgrip.cloud.domain.friction_map, roadgrip.cloud.domain.warnings, roadgrip.cloud.domain.stations\n"
        "print(' '.join(sorted(m for m in sys.modules if m.startswith('roadgrip.'))))"
    )
    loaded = subprocess.run([sys.executable, "-c", probe], check=True, capture_output=True, text=True).stdout.split()
    assert "roadgrip.cloud.domain.warnings" in loaded
    forbidden = ("roadgrip.cloud.formats", "roadgrip.sim", "roadgrip.fleet", "roadgrip.evaluation", "roadgrip.bench")
    assert [m for m in loaded if m.startswith(forbidden)] == []


def test_the_simulator_s_roads_never_exceed_the_map_s_mu_range():
    assert roads.MU_MAX <= MU_MAX == MU_GRID[-1]
    assert max(SURFACE_MU.values()) <= MU_MAX
    with pytest.raises(ValueError, match="mu_left"):  # the simulator refuses a road above its own bound
        roads.MuProfile(np.array([0.0]), np.array([roads.MU_MAX + 0.01]), np.array([0.5]))


def test_the_denm_validity_bound_is_the_engine_s():
    from roadgrip.cloud.formats import denm

    assert denm.MAX_VALIDITY_S is MAX_VALIDITY_S == 86_400
