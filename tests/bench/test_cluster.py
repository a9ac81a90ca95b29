"""`roadgrip bench cluster` at a tiny size (roadgrip/bench/cluster.py): it starts its own 3 RabbitMQ nodes and
PostgreSQL, runs every case and reports what the vehicles got PUBACKed and what the workers stored. A behaviour test:
the figures' values are this machine's and not checked, only that each case measured something real."""

from __future__ import annotations

import pytest

from roadgrip.bench.cluster import ClusterBench, format_cluster_bench, run_cluster_bench
from roadgrip.cloud.transport.amqp import RabbitCluster

pytestmark = [pytest.mark.cluster, pytest.mark.timeout(900)]  # needs a local RabbitMQ cluster


def test_cluster_bench_measures_every_case():
    if not (RabbitCluster.bin_dir / "rabbitmq-server").exists():
        pytest.fail("rabbitmq-server is not installed: run `bash scripts/install_system_deps.sh`", pytrace=False)
    # 8 vehicles (bench00000..07) reach all 4 partitions, so the partitions spread
    bench = ClusterBench(vehicles=8, seconds=3.0, workers=(1, 2), partitions=4, rate=5.0)
    steps = []
    result = run_cluster_bench(bench, lambda message, fraction: steps.append((message, fraction)))
    assert list(result["config"]["workers"]) == [1, 2]
    assert result["broker"]["pubacked_messages_per_s"] > 0
    assert result["broker"]["consumed_messages_per_s"] > 0
    assert [case["workers"] for case in result["workers"]] == [1, 2]
    for case in result["workers"]:
        assert case["stored_total"] > 0 and case["stored_samples_per_s"] > 0, case
        assert case["offered_samples_per_s"] == 8 * 5.0 * 10
        assert case["pubacked_samples_per_s"] > 0
        assert case["spread_s"] is not None, case
        assert sum(case["partitions_held"]) == 4 and len(case["partitions_held"]) == case["workers"], case
    assert result["workers"][1]["partitions_held"] == [2, 2]
    assert steps[-1] == ("stopping the cluster", 1.0)
    assert [f for _, f in steps] == sorted(f for _, f in steps)  # the progress only moves forward
    assert format_cluster_bench(result).row_count == 3
