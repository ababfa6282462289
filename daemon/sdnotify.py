"""A minimal sd_notify(3): READY=1, WATCHDOG=1, STATUS=..., STOPPING=1 over $NOTIFY_SOCKET.

systemd (Type=notify) sets NOTIFY_SOCKET to a unix datagram socket path, or an abstract one
written with a leading "@". With WatchdogSec= it also sets WATCHDOG_USEC (and WATCHDOG_PID, the
process it expects pings from); we ping at half that interval, as sd_watchdog_enabled(3) advises.
Outside systemd (no NOTIFY_SOCKET) every call is a cheap no-op that returns False.
No dependency on python-systemd.
"""
from __future__ import annotations

import logging
import os
import socket
import time
from collections.abc import Mapping

log = logging.getLogger(__name__)


class SdNotifier:
    def __init__(self, env: Mapping[str, str] | None = None):
        environ: Mapping[str, str] = os.environ if env is None else env
        self.address = self._address(environ.get("NOTIFY_SOCKET") or "")
        self.watchdog_s = self._watchdog_s(environ)
        self._sock: socket.socket | None = None
        self._last_ping: float | None = None
        self._warned = False

    @staticmethod
    def _address(raw: str) -> str | bytes | None:
        if not raw:
            return None
        if raw.startswith("@"):  # abstract namespace: a leading NUL byte instead of "@"
            return "\0" + raw[1:]
        if raw.startswith("/"):
            return raw
        log.warning("NOTIFY_SOCKET=%r is neither a path nor an abstract '@' name; not notifying systemd", raw)
        return None

    @staticmethod
    def _watchdog_s(env) -> float | None:
        usec = env.get("WATCHDOG_USEC")
        if not usec:
            return None
        pid = env.get("WATCHDOG_PID")
        if pid and pid.strip() != str(os.getpid()):  # the watchdog is meant for another process
            return None
        try:
            value = int(usec)
        except ValueError:
            log.warning("WATCHDOG_USEC=%r is not a number; not sending watchdog pings", usec)
            return None
        return value / 1e6 if value > 0 else None

    @property
    def enabled(self) -> bool:
        return self.address is not None

    def notify(self, message: str) -> bool:
        """Send one datagram ("KEY=value" lines). False when not under systemd or the send failed."""
        if self.address is None:
            return False
        try:
            if self._sock is None:
                self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
            self._sock.sendto(message.encode("utf-8"), self.address)
            return True
        except OSError as exc:
            if not self._warned:  # systemd gone (or restarting): say so once, keep running
                self._warned = True
                log.warning("sd_notify to %r failed: %s", self.address, exc)
            return False

    def ready(self, status: str | None = None) -> bool:
        return self.notify("READY=1" + (f"\nSTATUS={status}" if status else ""))

    def status(self, text: str) -> bool:
        return self.notify(f"STATUS={text}")

    def stopping(self, status: str | None = None) -> bool:
        return self.notify("STOPPING=1" + (f"\nSTATUS={status}" if status else ""))

    def watchdog(self) -> bool:
        return self.notify("WATCHDOG=1")

    def watchdog_due(self, now: float | None = None) -> bool:
        """True (and counts as sent) when a watchdog ping is due: every half WATCHDOG_USEC."""
        if self.watchdog_s is None or self.address is None:
            return False
        now = time.monotonic() if now is None else now
        if self._last_ping is not None and now - self._last_ping < self.watchdog_s / 2:
            return False
        self._last_ping = now
        return True

    def maybe_watchdog(self, now: float | None = None) -> bool:
        return self.watchdog() if self.watchdog_due(now) else False

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None


__all__ = ["SdNotifier"]


_default: SdNotifier | None = None


def notify(message: str) -> bool:
    """sd_notify(0, message) with the process's environment, e.g. notify("READY=1")."""
    global _default
    if _default is None:
        _default = SdNotifier()
    return _default.notify(message)


__all__ += ["notify"]
