"""LocalPostgres (roadgrip/cloud/storage/local_postgres.py): a real PostgreSQL 15 server in a folder of one's choosing,
as the local cluster keeps it in its data directory."""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

import psycopg
import pytest

from roadgrip.cloud.storage.local_postgres import LocalPostgres, PostgresUnavailable


def test_a_server_in_a_given_folder_keeps_its_files_there_across_a_restart():
    parent = Path(tempfile.mkdtemp(prefix="roadgrip-pg-test-"))
    parent.chmod(0o711)  # as root the server runs as postgres, which must reach the folder below
    server = LocalPostgres(root=parent / "pg")
    try:
        server.start()
        url = server.create_database("kept")
        assert (parent / "pg" / "data" / "PG_VERSION").exists() and (parent / "pg" / "server.log").exists()
        server.stop()
        server.start()  # the same files, the same port
        with psycopg.connect(f"host=127.0.0.1 port={server.port} user=postgres dbname=kept") as conn:
            assert conn.execute("SELECT current_database()").fetchone() == ("kept",)
        assert url.endswith(f":{server.port}/kept")
    finally:
        server.close()
        shutil.rmtree(parent, ignore_errors=True)
    assert not (parent / "pg").exists()


@pytest.mark.skipif(os.geteuid() != 0, reason="only root hands the server to the user postgres")
def test_as_root_a_folder_postgres_cannot_reach_is_named(tmp_path):
    closed = tmp_path / "closed"
    closed.mkdir(mode=0o700)
    with pytest.raises(PostgresUnavailable, match="cannot reach .*closed/pg"):
        LocalPostgres(root=closed / "pg").start()


def test_a_chosen_port_taken_before_the_start_is_chosen_again(monkeypatch):
    """Another process binds the port LocalPostgres chose before its server starts (servers of parallel tests): the
    first start moves to a new free port instead of failing."""
    import socket

    from roadgrip.cloud.localhost import free_port
    from roadgrip.cloud.storage import local_postgres

    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        taken_port = taken.getsockname()[1]
        monkeypatch.setattr(local_postgres, "free_port", lambda: taken_port)
        server = LocalPostgres()
        monkeypatch.setattr(local_postgres, "free_port", free_port)
        try:
            server.start()
            assert server.port != taken_port
            with psycopg.connect(f"host=127.0.0.1 port={server.port} user=postgres dbname=postgres") as conn:
                assert conn.execute("SELECT 1").fetchone() == (1,)
        finally:
            server.close()
