"""The `roadgrip` command line: thin commands over the package's parts.

This module holds the typer `app` and lists its commands in the order `roadgrip --help` shows them; the commands
live by what they drive: data.py (simulate, train, evaluate, estimate), fleet.py (fleet, import-log, demo),
cloud.py (serve, worker, api), edge.py (edge), bench.py (`bench ...`) and cluster.py (`cluster up`); common.py has what they share.
"""

from __future__ import annotations

import typer

from roadgrip.cli import bench, cloud, cluster, data, edge, fleet

app = typer.Typer(
    help="roadgrip: tire-road adhesion (mu) estimation from connected-vehicle telemetry.",
    no_args_is_help=True,
    add_completion=False,
)
bench_app = typer.Typer(help="Performance benchmarks.", no_args_is_help=True)
app.add_typer(bench_app, name="bench")
cluster_app = typer.Typer(help="The cluster mode on one machine (docs/CLUSTER.md).", no_args_is_help=True)
app.add_typer(cluster_app, name="cluster")

# the order of these lines is the order `roadgrip --help` lists the commands in
app.command("simulate")(data.simulate)
app.command("train")(data.train)
app.command("evaluate")(data.evaluate)
app.command("estimate")(data.estimate)
app.command("fleet")(fleet.fleet)
app.command("import-log")(fleet.import_log)
app.command("serve")(cloud.serve)
app.command("worker")(cloud.worker)
app.command("api")(cloud.api)
app.command("demo")(fleet.demo)
app.command("edge")(edge.edge)
bench_app.command("estimate")(bench.estimate)
bench_app.command("ingest")(bench.ingest)
bench_app.command("cluster")(bench.cluster)
bench_app.command("failover")(bench.failover)
bench_app.command("sim")(bench.sim)
bench_app.command("uplink")(bench.uplink)
cluster_app.command("up")(cluster.up)
