"""Which `Host` names the webapp answers, and which browser origins may open a Socket.IO connection.

A web page the robot's browser opens can reach the loopback server through DNS rebinding: its own
domain resolves first to the attacker, then to 127.0.0.1, so the page's requests arrive here with
`Host: evil.example`. The token still guards the API, but a page must not get as far as the
Socket.IO handshake or the login page. The rule is therefore on the *name*:

- loopback names and addresses (`localhost`, `*.localhost`, 127.0.0.0/8, ::1);
- this machine's own names (`hostname`, `hostname.local` for mDNS on the LAN) and the addresses
  of its interfaces (an IP literal cannot be rebound: no DNS lookup is involved);
- the address the server listens on, when it is not a wildcard;
- `allowed_hosts` from the settings (`config.toml` or `HOPE_ALLOWED_HOSTS`), for LAN names.

Anything else gets 421 with a message saying how to allow it; a request without `Host` gets 400.
Socket.IO origins are tied to the same rule: an `Origin` header (browsers always send one) must name
an allowed host and the same host:port the request was sent to; clients without an Origin (the
Continuon app, scripts) are judged by Host alone.
"""
from __future__ import annotations

import ipaddress
import json
import logging
import socket
from typing import TYPE_CHECKING, Callable, Iterable
from urllib.parse import urlsplit

if TYPE_CHECKING:
    from hope_models.settings import Settings

log = logging.getLogger(__name__)

LOOPBACK_NAMES = ("localhost", "localhost.localdomain", "ip6-localhost", "ip6-loopback")
WILDCARDS = ("", "0.0.0.0", "::", "*")


def split_host(value: str) -> tuple[str, str | None] | None:
    """'name:port' / '[v6]:port' / 'name' -> (lower-case name, port or None); None if malformed."""
    value = value.strip()
    if not value or any(c in value for c in "/\\@?# \t") or len(value) > 300:
        return None
    if value.startswith("["):
        end = value.find("]")
        if end < 0:
            return None
        name, rest = value[1:end], value[end + 1:]
        if rest and not (rest.startswith(":") and rest[1:].isdigit()):
            return None
        return name.lower(), rest[1:] or None
    if value.count(":") > 1:  # a bare IPv6 address (not valid in Host, but harmless to read)
        return value.lower(), None
    name, _, port = value.partition(":")
    if port and not port.isdigit():
        return None
    return name.rstrip(".").lower(), port or None


def _ip(name: str):
    try:
        return ipaddress.ip_address(name.split("%", 1)[0])
    except ValueError:
        return None


def _own_addresses() -> set[str]:
    """The addresses of this machine's interfaces (psutil; empty if it cannot tell)."""
    try:
        import psutil  # lazy: loads psutil

        return {a.address.split("%", 1)[0].lower() for addrs in psutil.net_if_addrs().values() for a in addrs
                if a.family in (socket.AF_INET, socket.AF_INET6)}
    except Exception:  # noqa: BLE001 - without the list, LAN addresses must be configured by name
        log.warning("cannot list this machine's addresses; add LAN addresses to allowed_hosts")
        return set()


class HostPolicy:
    """Decides whether a Host (or an Origin's host) names this server."""

    def __init__(self, names: Iterable[str] = (), addresses: Iterable[str] = ()):
        self.names = {n.rstrip(".").lower() for n in names if n}
        self.addresses = {a.lower() for a in addresses if a}

    @classmethod
    def from_settings(cls, settings: Settings) -> "HostPolicy":
        names = set(LOOPBACK_NAMES)
        hostname = socket.gethostname().lower()
        if hostname:
            names |= {hostname, f"{hostname}.local"}  # no getfqdn(): a DNS lookup can stall offline
        listen = str(getattr(settings, "host", "") or "").strip("[]").lower()
        extra = [str(h) for h in getattr(settings, "allowed_hosts", []) or []]
        addresses = _own_addresses()
        for item in [listen, *extra]:
            if item in WILDCARDS:
                continue
            parsed = split_host(item)
            if parsed is None:
                continue
            if _ip(parsed[0]) is not None:
                addresses.add(str(_ip(parsed[0])))
            else:
                names.add(parsed[0])
        return cls(names, addresses)

    def allows_name(self, name: str) -> bool:
        ip = _ip(name)
        if ip is not None:
            return ip.is_loopback or str(ip) in self.addresses
        return name in self.names or name.endswith(".localhost")

    def allows(self, host_header: str | None) -> bool:
        if not host_header:
            return False
        parsed = split_host(host_header)
        return parsed is not None and self.allows_name(parsed[0])

    def origin_allowed(self, origin: str | None, environ: dict) -> bool:
        """Socket.IO's cors_allowed_origins: the Origin must be this very host:port, and allowed."""
        if origin is None:
            return True  # not a browser: Host (checked before) is the whole rule
        try:
            parts = urlsplit(origin)
        except ValueError:
            return False
        if parts.scheme not in ("http", "https") or not parts.netloc:
            return False
        return parts.netloc.lower() == str(environ.get("HTTP_HOST", "")).lower() and self.allows(parts.netloc)


class HostAllowlist:
    """WSGI middleware: refuse every request whose Host is not allowed, before any route runs."""

    def __init__(self, app: Callable, policy: HostPolicy):
        self.app = app
        self.policy = policy

    def __call__(self, environ, start_response):
        host = environ.get("HTTP_HOST")
        if self.policy.allows(host):
            return self.app(environ, start_response)
        if not host:
            status, message = "400 Bad Request", "missing Host header"
        else:
            status = "421 Misdirected Request"
            message = (f"this server does not answer to the host name {host[:100]!r}; if it is this robot's "
                       "LAN name, add it to allowed_hosts in $HOPE_HOME/config.toml (or HOPE_ALLOWED_HOSTS)")
        body = json.dumps({"error": message}).encode()
        start_response(status, [("Content-Type", "application/json"), ("Content-Length", str(len(body))),
                                ("Connection", "close")])
        return [body]


__all__ = ["HostAllowlist", "HostPolicy", "split_host"]
