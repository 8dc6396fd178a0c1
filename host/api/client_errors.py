"""Errors of the API client: what a caller catches (each mixes in the matching built-in).

Kept apart from :mod:`host.api.client` so the connection opener and the client share them
without importing each other.
"""

from __future__ import annotations


class ApiError(Exception):
    """The daemon refused a request; ``code`` is one of ``host.api.schema.ERROR_CODES``."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(f"{code}: {message}")
        self.code = code
        self.message = message


class ApiConnectionError(ApiError, ConnectionError):
    """The daemon cannot be reached or the connection broke."""

    def __init__(self, message: str, code: str = "connection") -> None:
        super().__init__(code, message)

    def __str__(self) -> str:
        return self.message


class ApiAuthError(ApiConnectionError, PermissionError):
    """The daemon refused the token (or wanted one and got none)."""

    def __init__(self, message: str) -> None:
        super().__init__(message, "unauthorized")


class ApiTimeoutError(ApiError, TimeoutError):
    """No reply in time."""

    def __init__(self, message: str) -> None:
        super().__init__("timeout", message)
