"""A PostgreSQL 15 server of our own, for a local cluster (`roadgrip cluster`), benchmarks and tests: initdb in a
directory, started on 127.0.0.1 at a free port with trust authentication on the unix socket (in that directory, private
to the server's user) and on 127.0.0.1 only, stopped and removed on `close`. Needs the Debian package postgresql-15
(`bash scripts/install_system_deps.sh`). initdb refuses to run as root, so as root the server runs as the user
`postgres` the package creates.

    with LocalPostgres() as pg:
        url = pg.create_database("roadgrip")   # postgresql+psycopg://postgres@127.0.0.1:PORT/roadgrip
    # pg.stop(); pg.start(): the same server again (a restart); leaving the block stops it and deletes its files
"""

from __future__ import annotations

import os
import pwd
import shutil
import subprocess
import tempfile
from pathlib import Path
from typing import Self

import psycopg
from sqlalchemy.engine import make_url

from roadgrip.cloud.localhost import free_port

PG_BIN = Path("/usr/lib/postgresql/15/bin")


class PostgresUnavailable(RuntimeError):
    """PostgreSQL is not installed, or the server did not start (the message holds its log)."""


def admin_conninfo(url: str) -> str:
    """libpq conninfo for the maintenance database `postgres` of the server that `url` points at."""
    u = make_url(url)
    return f"host={u.host} port={u.port} user={u.username} dbname=postgres"


def create_database(url: str, name: str) -> str:
    """Create database `name` on the server of `url` (a PostgreSQL URL); return the URL of the new database."""
    with psycopg.connect(admin_conninfo(url), autocommit=True) as conn:
        conn.execute(f'CREATE DATABASE "{name}"')
    return make_url(url).set(database=name).render_as_string(hide_password=False)


def drop_database(url: str, name: str) -> None:
    with psycopg.connect(admin_conninfo(url), autocommit=True) as conn:
        conn.execute(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)')


PORT_ATTEMPTS = 3  # starts on a freshly chosen port when the previous one was taken meanwhile


class LocalPostgres:
    """`start()` creates the server's files (initdb) the first time and starts it; `stop()` stops it (`pg_ctl stop -m
    fast`: clients are disconnected at once) and keeps its files, so that `start()` starts it again on the same port;
    `close()` stops it if it runs and deletes its files.

    `root`: the folder of the server's files (`data/`, `server.log`), created if missing; default a new temporary
    folder. As root, the server runs as `postgres`, which must be able to reach it: every folder above it searchable
    by others (o+x)."""

    def __init__(self, port: int | None = None, root: Path | None = None):
        self.port = port or free_port()
        self._port_free_to_change = port is None  # until the first start: a port taken meanwhile is chosen again
        self.root: Path | None = None
        self._given_root = root
        self._as_postgres: list[str] = []

    @property
    def server_url(self) -> str:
        """The URL of the server's maintenance database `postgres`."""
        return f"postgresql+psycopg://postgres@127.0.0.1:{self.port}/postgres"

    def create_database(self, name: str) -> str:
        return create_database(self.server_url, name)

    def _pg(self, *args: str | Path) -> None:
        done = subprocess.run([*self._as_postgres, *map(str, args)], check=False, capture_output=True, text=True)
        if done.returncode != 0:
            log = self.root / "server.log"
            server_log = log.read_text()[-2000:] if log.exists() else ""
            raise PostgresUnavailable(f"{Path(str(args[0])).name} failed: {done.stderr}\n{server_log}")

    def _init(self) -> None:
        missing = [p.name for p in (PG_BIN / "initdb", PG_BIN / "pg_ctl") if not p.exists()]
        if missing:
            raise PostgresUnavailable(
                f"PostgreSQL 15 not installed ({', '.join(missing)} missing in {PG_BIN}): "
                "run `bash scripts/install_system_deps.sh`"
            )
        if self._given_root is None:
            self.root = Path(tempfile.mkdtemp(prefix="roadgrip-pg-"))  # its parents must be reachable by postgres
        else:
            self.root = Path(self._given_root).resolve()
            self.root.mkdir(mode=0o700, parents=True, exist_ok=True)
        if os.geteuid() == 0:
            pw = pwd.getpwnam("postgres")
            os.chown(self.root, pw.pw_uid, pw.pw_gid)
            self._as_postgres = ["runuser", "-u", "postgres", "--"]
            reach = subprocess.run([*self._as_postgres, "test", "-w", str(self.root)], check=False)
            if reach.returncode != 0:
                raise PostgresUnavailable(
                    f"the user postgres, as which root runs the server, cannot reach {self.root}: "
                    "make every folder above it searchable by others (chmod o+x)"
                )
        self._pg(
            PG_BIN / "initdb", "-D", self.root / "data", "-U", "postgres", "-A", "trust", "-E", "UTF8", "--locale=C"
        )
        (self.root / "data" / "pg_hba.conf").write_text("local all all trust\nhost all all 127.0.0.1/32 trust\n")

    def start(self) -> None:
        """Start the server; on its first start on a port it chose itself, a port another process bound between the
        choice and the start is replaced by a new free one (up to PORT_ATTEMPTS times); later starts keep the port."""
        if self.root is None:
            self._init()
        for attempt in range(1, PORT_ATTEMPTS + 1):
            options = f"-c listen_addresses=127.0.0.1 -c port={self.port} -k {self.root} -c fsync=on"
            try:
                self._pg(
                    PG_BIN / "pg_ctl",
                    "start",
                    "-w",
                    "-D",
                    self.root / "data",
                    "-l",
                    self.root / "server.log",
                    "-o",
                    options,
                )
                break
            except PostgresUnavailable as exc:
                if (
                    not self._port_free_to_change
                    or "Address already in use" not in str(exc)
                    or attempt == PORT_ATTEMPTS
                ):
                    raise
                self.port = free_port()
        self._port_free_to_change = False

    def stop(self) -> None:
        self._pg(PG_BIN / "pg_ctl", "stop", "-w", "-m", "fast", "-D", self.root / "data")

    def close(self) -> None:
        if self.root is None:
            return
        subprocess.run(
            [
                *self._as_postgres,
                str(PG_BIN / "pg_ctl"),
                "stop",
                "-w",
                "-m",
                "immediate",
                "-D",
                str(self.root / "data"),
            ],
            check=False,
            capture_output=True,
        )
        shutil.rmtree(self.root, ignore_errors=True)
        self.root = None

    def __enter__(self) -> Self:
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.close()
