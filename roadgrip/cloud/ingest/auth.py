"""Credentials: who may call the cloud, and as what.

Four roles. A *vehicle* (login name = its vehicle_id) writes its own telemetry and reads its own estimates; a *station*
(a roadside road weather station, login name = its station_id: roadgrip/cloud/domain/stations.py) writes its own reports and
reads nothing else; a *reader* (a road operator, a dashboard) reads estimates of every vehicle, the stations' reports,
the map and the warnings; the *admin* registers vehicles, stations and readers and revokes credentials. The same name
and secret work over HTTP (Basic authentication) and MQTT.

Secrets are never stored, only hashed. The secrets the cloud issues are random (32 bytes, URL-safe: 256 bits), so a
plain SHA-256 of them cannot be reversed by guessing and costs microseconds, which a fleet registering and posting
every 100 ms needs (the practice of API tokens). The admin's secret may be chosen by a person, so it gets a slow,
salted scrypt hash (RFC 7914; n=2^14, r=8, p=1: ~40 ms a check). A verified secret is remembered in memory by its SHA-256
(never its clear text) until the credential is revoked or its secret changes, so scrypt runs once per admin session.

Several processes on one database (the cluster's API replicas, `Authenticator(storage, revalidate=True)`): a revocation
or a new secret made by another process must count at once, which an in-process cache cannot know of. There every call
reads the credential from storage (one primary-key query) and the cache only spares verifying again a secret whose
stored hash is unchanged (the admin's scrypt).
"""

from __future__ import annotations

import base64
import hashlib
import hmac
import secrets
import threading

from roadgrip.cloud.storage.database import Credential, Storage

ROLES = ("vehicle", "reader", "admin", "station")
ADMIN_NAME = "admin"
_SCRYPT_N, _SCRYPT_R, _SCRYPT_P = 2**14, 8, 1


class AuthError(Exception):
    """Authentication failed (unknown name, wrong secret, revoked): the message never says which, to an attacker."""


def new_secret() -> str:
    return secrets.token_urlsafe(32)


def hash_token(secret: str) -> str:
    """'sha256$hex' of an issued (random, 256-bit) secret."""
    return "sha256$" + hashlib.sha256(secret.encode()).hexdigest()


def hash_secret(secret: str, *, salt: bytes | None = None) -> str:
    """'scrypt$n$r$p$salt$hash' with base64 salt and hash, for secrets a person may have chosen."""
    salt = secrets.token_bytes(16) if salt is None else salt
    digest = hashlib.scrypt(secret.encode(), salt=salt, n=_SCRYPT_N, r=_SCRYPT_R, p=_SCRYPT_P, dklen=32)
    return "$".join(
        (
            "scrypt",
            str(_SCRYPT_N),
            str(_SCRYPT_R),
            str(_SCRYPT_P),
            base64.b64encode(salt).decode(),
            base64.b64encode(digest).decode(),
        )
    )


def verify_secret(secret: str, stored: str) -> bool:
    if stored.startswith("sha256$"):
        return hmac.compare_digest(hash_token(secret), stored)
    try:
        scheme, n, r, p, salt, digest = stored.split("$")
        if scheme != "scrypt":
            return False
        expected = base64.b64decode(digest)
        got = hashlib.scrypt(
            secret.encode(), salt=base64.b64decode(salt), n=int(n), r=int(r), p=int(p), dklen=len(expected)
        )
    except (ValueError, TypeError):
        return False
    return hmac.compare_digest(got, expected)


class Authenticator:
    """Checks name and secret against the stored credentials, with an in-memory cache of verified secrets; with
    `revalidate`, against storage on every call (the module docstring)."""

    def __init__(self, storage: Storage, revalidate: bool = False):
        self.storage = storage
        self.revalidate = revalidate
        self._verified: dict[str, tuple[Credential, bytes]] = {}
        self._lock = threading.Lock()

    def authenticate(self, name: str, secret: str) -> Credential:
        fingerprint = hashlib.sha256(secret.encode()).digest()
        with self._lock:
            cached = self._verified.get(name)
        if not self.revalidate and cached is not None and hmac.compare_digest(cached[1], fingerprint):
            return cached[0]
        credential = self.storage.credential(name)
        if credential is None or credential.revoked:
            raise AuthError("invalid credentials")
        if (
            cached is not None
            and cached[0].secret_hash == credential.secret_hash
            and hmac.compare_digest(cached[1], fingerprint)
        ):
            return credential
        if not verify_secret(secret, credential.secret_hash):
            raise AuthError("invalid credentials")
        with self._lock:
            self._verified[name] = (credential, fingerprint)
        return credential

    def create(self, name: str, role: str, vehicle_id: str | None = None) -> str:
        """A new credential; returns its secret (shown once, stored only hashed)."""
        if role not in ROLES:
            raise ValueError(f"role must be one of {ROLES}, got {role!r}")
        secret = new_secret()
        self.storage.add_credential(name, role, hash_token(secret), vehicle_id)
        return secret

    def revoke(self, name: str) -> bool:
        """Revoke at once: the cache forgets the name before the call returns."""
        with self._lock:
            self._verified.pop(name, None)
        revoked = self.storage.revoke_credential(name)
        with self._lock:
            self._verified.pop(name, None)
        return revoked

    def ensure_admin(self, secret: str) -> None:
        """Make the stored admin credential match the configured secret."""
        credential = self.storage.credential(ADMIN_NAME)
        if credential is None:
            self.storage.add_credential(ADMIN_NAME, "admin", hash_secret(secret), None)
        elif credential.revoked or not verify_secret(secret, credential.secret_hash):
            self.storage.set_secret_hash(ADMIN_NAME, hash_secret(secret))
        with self._lock:
            self._verified.pop(ADMIN_NAME, None)
