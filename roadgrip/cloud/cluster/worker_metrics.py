"""Prometheus metrics of a cluster worker (`roadgrip worker --metrics-port N`, docs/CLUSTER.md "Workers"): the
families every pipeline process exposes (roadgrip/cloud/metrics.py `pipeline_metrics`: samples received, rejected,
stored, duplicate, estimator time, checkpoints, ...), the latency from a sample's time to its stored estimate, and
the worker's own: which partitions it holds, the partition queues' depth, the live workers and the partitions moved;
and the region fan-out's (roadgrip/cloud/cluster/regions.py): which region queues it holds, the region messages it
published and applied, the map cells it saved, its regions' warning changes (serve's family, roadgrip_warnings), the
publishes tried again and the longest crash window.

Read at each scrape from the running Worker (plain counters it keeps anyway; the queues' depth and the live workers
as its watcher last read them, at most WATCH_S old), on a registry of its own, served by prometheus_client's own
HTTP server in a thread. The worker is read through `WorkerView` (what this module needs of
roadgrip/cloud/cluster/worker.py `Worker`), so that the worker's module, which serves these metrics, is not imported
back here.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Protocol
from wsgiref.simple_server import WSGIServer

from prometheus_client import start_http_server
from prometheus_client.core import Metric
from prometheus_client.registry import Collector

from roadgrip.cloud.cluster.regions import RegionOwners, WorkerFanout
from roadgrip.cloud.cluster.spread import Spread
from roadgrip.cloud.ingest.admission import Ingest
from roadgrip.cloud.metrics import BatchHistogram, counter, estimate_latency, gauge, pipeline_metrics, registry_with


class WorkerView(Protocol):
    """What the metrics read of a running worker (roadgrip/cloud/cluster/worker.py `Worker`)."""

    ingest: Ingest | None  # each None until the worker started
    fanout: WorkerFanout | None
    regions: RegionOwners | None
    latency_histogram: BatchHistogram
    partitions: int
    messages_ready: list[int | None]
    live_workers: int | None
    spread: Spread
    fenced: int
    lost: int

    def held_partitions(self) -> list[int]:
        """The partitions it is the active consumer of."""

    def unacknowledged(self, partition: int) -> int:
        """Messages of the partition delivered to it and not yet acknowledged."""


class WorkerCollector(Collector):
    def __init__(self, worker: WorkerView):
        self.worker = worker

    def collect(self) -> Iterator[Metric]:
        worker = self.worker
        if worker.ingest is not None:
            yield from pipeline_metrics(worker.ingest.views())
        yield estimate_latency(worker.latency_histogram)
        partitions = range(worker.partitions)
        held = set(worker.held_partitions())
        yield gauge(
            "roadgrip_partition_active",
            "1 while this worker is the active consumer of the partition queue "
            "(it took the partition at its first delivery and has not released it), else 0",
            [([str(p)], float(p in held)) for p in partitions],
            ["partition"],
        )
        yield gauge(
            "roadgrip_partition_messages_ready",
            "Messages in the partition queue waiting to be delivered (the broker's count, read every few seconds)",
            [([str(p)], n) for p, n in zip(partitions, worker.messages_ready) if n is not None],
            ["partition"],
        )
        yield gauge(
            "roadgrip_partition_messages_unacknowledged",
            "Messages of the partition queue delivered to this "
            "worker and not yet acknowledged (being stored, or left for the next owner)",
            [([str(p)], worker.unacknowledged(p)) for p in partitions],
            ["partition"],
        )
        if worker.live_workers is not None:
            yield gauge(
                "roadgrip_workers_live",
                "Live workers, as their heartbeats in PostgreSQL count them",
                [([], worker.live_workers)],
            )
        yield counter(
            "roadgrip_partition_moves",
            "Partitions this worker released to spread them over the workers",
            [([], worker.spread.moves)],
        )
        yield counter(
            "roadgrip_partition_fenced_writes",
            "Writes that found a partition taken by another worker",
            [([], worker.fenced)],
        )
        yield counter(
            "roadgrip_partition_connections_lost",
            "Partition connections lost (a broker node, the network)",
            [([], worker.lost)],
        )
        yield from region_metrics(worker)


def region_metrics(worker: WorkerView) -> Iterator[Metric]:
    """The region fan-out's families: the worker's side (`WorkerFanout.stats`) and the region owner's
    (`RegionOwners.stats`), once started."""
    if worker.fanout is not None:
        fanout = worker.fanout.stats()
        yield counter(
            "roadgrip_region_messages_published",
            "Region messages (a round's estimates of one region) this worker published and the broker confirmed",
            [([], fanout["region_messages_published"])],
        )
        yield counter(
            "roadgrip_region_publish_failures",
            "Region publishes not confirmed (a nack, a lost connection) and tried again through the next broker",
            [([], fanout["region_publish_failures"])],
        )
        yield gauge(
            "roadgrip_region_publish_window_max_seconds",
            "Longest time from a round's commit to its region "
            "messages' last confirm since the worker started (the crash window)",
            [([], fanout["region_publish_window_s_max"])],
        )
    if worker.regions is not None:
        regions = worker.regions.stats()
        held = set(regions["region_queues_held"])
        queues = range(len(regions["region_messages_applied"]))
        yield gauge(
            "roadgrip_region_queue_active",
            "1 while this worker is the active consumer of the region queue "
            "(it took the queue at its first delivery and has not given it up), else 0",
            [([str(q)], float(q in held)) for q in queues],
            ["region_queue"],
        )
        yield gauge(
            "roadgrip_regions_held", "Regions whose map and warnings this worker keeps", [([], regions["regions_held"])]
        )
        yield counter(
            "roadgrip_region_messages_applied",
            "Region messages (estimates, station evidence) this worker applied to its regions' map and warnings",
            [([str(q)], n) for q, n in zip(queues, regions["region_messages_applied"])],
            ["region_queue"],
        )
        yield counter(
            "roadgrip_map_cells_saved",
            "Map cells this worker's regions stored (each changed cell about once a second)",
            [([], regions["map_cells_saved"])],
        )
        yield counter(
            "roadgrip_warnings",
            "Warning changes of this worker's regions: raised, refreshed, cancelled, expired",
            [([change], n) for change, n in regions["warning_changes"].items()],
            ["change"],
        )
        yield counter(
            "roadgrip_region_queue_moves",
            "Region queues this worker released to spread them over the workers",
            [([], regions["region_queue_moves"])],
        )
        yield counter(
            "roadgrip_region_queue_connections_lost",
            "Region queue connections lost or given up (a broker node, the network, a fenced write)",
            [([], regions["region_connections_lost"])],
        )


def serve_metrics(worker: WorkerView, port: int, host: str) -> WSGIServer:
    """Serve `worker`'s metrics at http://host:port/metrics (any path) from a thread; `shutdown()` stops it."""
    server, _thread = start_http_server(port, host, registry_with(WorkerCollector(worker)))
    return server
