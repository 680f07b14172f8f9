"""Password hashing (argon2) and signed access tokens.

A token names its login session, user and expiry and is signed with HMAC-SHA256, so it can be checked
without the database: the emergency stop relies on that to reach the worker before any DB round trip.
Every other route also checks the login-session row, so logout and deactivation revoke a token at once.
"""

from __future__ import annotations

import base64
import hashlib
import hmac
import secrets
import time
from dataclasses import dataclass
from functools import lru_cache

from argon2 import PasswordHasher
from argon2.exceptions import InvalidHashError, VerificationError, VerifyMismatchError

_hasher = PasswordHasher()


def hash_password(password: str) -> str:
    return _hasher.hash(password)


@lru_cache(maxsize=1)
def _dummy_hash() -> str:
    return _hasher.hash(secrets.token_urlsafe(16))


def verify_password(password_hash: str | None, password: str) -> bool:
    """True when `password` matches; an unknown user costs the same time (`password_hash=None`)."""
    try:
        return _hasher.verify(password_hash or _dummy_hash(), password) and password_hash is not None
    except (VerifyMismatchError, VerificationError, InvalidHashError):
        return False


def new_session_id() -> str:
    return secrets.token_hex(16)


@dataclass(frozen=True)
class TokenClaims:
    session_id: str
    user_id: int
    expires_at_epoch_s: int

    @property
    def expired(self) -> bool:
        return time.time() >= self.expires_at_epoch_s


class TokenSigner:
    def __init__(self, key: bytes) -> None:
        if len(key) < 16:
            raise ValueError("secret_key: must be at least 16 bytes")
        self._key = key

    def _signature(self, payload: str) -> str:
        digest = hmac.new(self._key, payload.encode(), hashlib.sha256).digest()
        return base64.urlsafe_b64encode(digest).rstrip(b"=").decode()

    def issue(self, claims: TokenClaims) -> str:
        payload = f"{claims.session_id}.{claims.user_id}.{claims.expires_at_epoch_s}"
        return f"{payload}.{self._signature(payload)}"

    def verify(self, token: str) -> TokenClaims | None:
        """The claims of a genuine, unexpired token; None otherwise."""
        parts = token.split(".")
        if len(parts) != 4:
            return None
        payload, signature = ".".join(parts[:3]), parts[3]
        if not hmac.compare_digest(signature, self._signature(payload)):
            return None
        try:
            claims = TokenClaims(parts[0], int(parts[1]), int(parts[2]))
        except ValueError:
            return None
        return None if claims.expired else claims
