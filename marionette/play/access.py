"""Who may reach the play server: this machine through loopback, or, on another interface, whoever holds its token.
Importable without the server (``marionette play --help`` parses with it)."""

from __future__ import annotations

import argparse
import re
import secrets

LOOPBACK_NAMES = ("127.0.0.1", "localhost")  # the names a server that only this machine reaches answers to


def serve_host(s: str) -> str:
    """An argparse type: an interface to bind, a host name or an IP address."""
    if not s or any(c.isspace() for c in s) or "/" in s or s.count(":") == 1:
        raise argparse.ArgumentTypeError(f"expected a host name or an IP address (no scheme, port or path), not {s!r}")
    return s


TOKEN = re.compile(r"[A-Za-z0-9_-]{16,256}")


def token_value(s: str) -> str:
    """An argparse type: a server token (``TOKEN``), or ``auto``."""
    if s != "auto" and not TOKEN.fullmatch(s):
        raise argparse.ArgumentTypeError("a token is 16 to 256 of A-Z a-z 0-9 _ -, or 'auto' to draw one")
    return s


def access(host: str, token: str | None) -> str | None:
    """The token a server on ``host`` runs with: None on loopback unless one is given; elsewhere the one given, drawn
    for ``auto``; a ValueError naming ``--token`` where a non-loopback host has none."""
    if token is None and host not in LOOPBACK_NAMES:
        raise ValueError(
            f"--host {host} serves other machines: give --token SECRET (or --token auto to draw one); every request "
            "must then carry it"
        )
    return secrets.token_urlsafe(24) if token == "auto" else token
