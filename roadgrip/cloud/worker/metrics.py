"""Prometheus metrics of a cluster worker (`roadgrip worker --metrics-port N`, docs/CLUSTER.md "Workers"): the
families every pipeline process exposes (roadgrip/cloud/metrics.py `pipeline_metrics`: samples received, rejected,
stored, duplicate, estimator time, checkpoints, ...), the latency from a sample's time to its stored estimate, and
the worker's own: which partitions it holds, the partition queues' depth, the live workers and the partitions moved.

Read at each scrape from the running Worker (plain counters it keeps anyway; the queues' depth and the live workers
as its watcher last read them, at most WATCH_S old), on a registry of its own, served by prometheus_client's own
HTTP server in a thread.
"""

from __future__ import annotations

from collections.abc import Iterator
from wsgiref.simple_server import WSGIServer

from prometheus_client import start_http_server
from prometheus_client.core import Metric
from prometheus_client.registry import Collector

from roadgrip.cloud.metrics import counter, estimate_latency, gauge, pipeline_metrics, registry_with
from roadgrip.cloud.worker.consumer import Worker


class WorkerCollector(Collector):
    def __init__(self, worker: Worker):
        self.worker = worker

    def collect(self) -> Iterator[Metric]:
        worker = self.worker
        if worker.ingest is not None:
            yield from pipeline_metrics(worker.ingest.views())
        yield estimate_latency(worker.latency_histogram)
        partitions = range(worker.partitions)
        held = set(worker.held_partitions())
        yield gauge("roadgrip_partition_active", "1 while this worker is the active consumer of the partition queue "
                    "(it took the partition at its first delivery and has not released it), else 0",
                    [([str(p)], float(p in held)) for p in partitions], ["partition"])
        yield gauge("roadgrip_partition_messages_ready", "Messages in the partition queue waiting to be delivered "
                    "(the broker's count, read every few seconds)",
                    [([str(p)], n) for p, n in zip(partitions, worker.messages_ready) if n is not None], ["partition"])
        yield gauge("roadgrip_partition_messages_unacknowledged", "Messages of the partition queue delivered to this "
                    "worker and not yet acknowledged (being stored, or left for the next owner)",
                    [([str(p)], worker.unacknowledged(p)) for p in partitions], ["partition"])
        if worker.live_workers is not None:
            yield gauge("roadgrip_workers_live", "Workers consuming the partitions, as the broker counts them",
                        [([], worker.live_workers)])
        yield counter("roadgrip_partition_moves", "Partitions this worker released to spread them over the workers",
                      [([], worker.moves)])
        yield counter("roadgrip_partition_fenced_writes", "Writes that found a partition taken by another worker",
                      [([], worker.fenced)])
        yield counter("roadgrip_partition_connections_lost", "Partition connections lost (a broker node, the "
                      "network)", [([], worker.lost)])


def serve_metrics(worker: Worker, port: int, host: str) -> WSGIServer:
    """Serve `worker`'s metrics at http://host:port/metrics (any path) from a thread; `shutdown()` stops it."""
    server, _thread = start_http_server(port, host, registry_with(WorkerCollector(worker)))
    return server
