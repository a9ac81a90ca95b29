"""Credentials: hashing, verification, the cache that never outlives a revocation."""

from __future__ import annotations

import pytest

from roadgrip.cloud.ingest.auth import Authenticator, AuthError, hash_secret, hash_token, new_secret, verify_secret
from roadgrip.cloud.storage.database import open_storage

CALLS = 50  # calls timed per way of authenticating: the printed cost is a rough figure, no test checks it


@pytest.fixture
def auth(tmp_path):
    storage = open_storage(f"sqlite:///{tmp_path / 'auth.sqlite'}")
    yield Authenticator(storage)
    storage.close()


def test_hashes_verify_their_secret_only_and_never_contain_it():
    secret = new_secret()
    assert len(secret) >= 43  # 32 random bytes, URL-safe base64
    for stored in (hash_token(secret), hash_secret(secret)):
        assert secret not in stored
        assert verify_secret(secret, stored)
        assert not verify_secret(secret + "x", stored)
    assert hash_secret(secret) != hash_secret(secret)  # salted
    assert not verify_secret(secret, "md5$abc") and not verify_secret(secret, "garbage")


def test_a_created_credential_authenticates_with_its_role_and_vehicle(auth):
    secret = auth.create("car-1", "vehicle", "car-1")
    credential = auth.authenticate("car-1", secret)
    assert (credential.role, credential.vehicle_id) == ("vehicle", "car-1")
    with pytest.raises(AuthError):
        auth.authenticate("car-1", "wrong")
    with pytest.raises(AuthError):
        auth.authenticate("nobody", secret)
    with pytest.raises(ValueError, match="role"):
        auth.create("x", "superuser")


def test_revocation_beats_the_cache(auth):
    secret = auth.create("reader-1", "reader")
    auth.authenticate("reader-1", secret)  # now cached
    assert auth.revoke("reader-1")
    with pytest.raises(AuthError):
        auth.authenticate("reader-1", secret)
    assert not auth.revoke("reader-1")


def test_the_admin_secret_follows_the_settings(auth):
    auth.ensure_admin("first-admin-secret-0123")
    auth.authenticate("admin", "first-admin-secret-0123")
    auth.ensure_admin("second-admin-secret-0123")
    with pytest.raises(AuthError):
        auth.authenticate("admin", "first-admin-secret-0123")
    assert auth.authenticate("admin", "second-admin-secret-0123").role == "admin"


def test_a_revocation_through_one_replica_counts_at_once_on_another_that_verified_the_secret(postgres_database_url):
    """Two API replicas (two processes' worth: an Authenticator and a connection pool each) on one PostgreSQL: with
    `revalidate`, a secret verified (and cached) by one is refused by it on the next call after the other revoked
    it or changed it. Prints what a call costs, cached against checked in the database every time."""
    import time

    stores = [open_storage(postgres_database_url) for _ in range(2)]
    try:
        one, two = (Authenticator(s, revalidate=True) for s in stores)
        cached = Authenticator(stores[0])
        secret = two.create("car-1", "vehicle", "car-1")
        admin_secret = "a-person-chosen-admin-secret"
        one.ensure_admin(admin_secret)
        assert one.authenticate("car-1", secret).role == "vehicle"
        assert cached.authenticate("car-1", secret).role == "vehicle"

        costs = {}
        for name, auth_, login in (
            ("cached", cached, ("car-1", secret)),
            ("revalidate", one, ("car-1", secret)),
            ("revalidate, admin (scrypt skipped)", one, ("admin", admin_secret)),
        ):
            auth_.authenticate(*login)
            started = time.perf_counter()
            for _ in range(CALLS):
                auth_.authenticate(*login)
            costs[name] = (time.perf_counter() - started) / CALLS
        print("authentication per call: " + ", ".join(f"{k} {v * 1e6:.0f} us" for k, v in costs.items()))

        assert two.revoke("car-1")
        with pytest.raises(AuthError):
            one.authenticate("car-1", secret)
        assert cached.authenticate("car-1", secret).role == "vehicle"  # what one process's cache alone would do

        two.ensure_admin("another-admin-secret-of-the-settings")
        with pytest.raises(AuthError):
            one.authenticate("admin", admin_secret)
    finally:
        for s in stores:
            s.close()
