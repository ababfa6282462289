"""Addresses that keep breaking the protocol are refused at the door for a while.

    strikes = Strikes()                      # one per listener (webapp/server.py GuardedServer)
    strike(environ, "a second long-poll")    # where a request is refused for something no client does
    strikes.banned(client) -> seconds left, or 0.0

Refusing a bad request is cheap, but not free: each one is a thread, a parsed request and a trip
through the WSGI stack, all in the interpreter that also answers the robot. A neighbour that sends
hundreds a second (long-polls on a session that already has one waiting, malformed Engine.IO
packets) costs serve what they cost however quickly they are refused. What a legitimate client never
sends counts as a strike against its address; STRIKES_TO_BAN strikes within WINDOW_S and the
address's new connections are refused at accept, before a thread or a parse, for BAN_S.
Only protocol errors no real client makes are strikes: never a 4xx a user's mistake causes (a bad
run request, a too-large upload), so a Robot Editor and a buggy script on one laptop are not cut
together for the script's upload errors.
"""
from __future__ import annotations

import logging
import threading
import time

log = logging.getLogger(__name__)

STRIKES_TO_BAN = 20
WINDOW_S = 10.0
BAN_S = 10.0
STRIKE_KEY = "hope.strike"  # the WSGI environ key of the callable that counts a strike for its client


class Strikes:
    def __init__(self, to_ban: int | None = None, window_s: float | None = None, ban_s: float | None = None):
        self.to_ban = STRIKES_TO_BAN if to_ban is None else to_ban
        self.window_s = WINDOW_S if window_s is None else window_s
        self.ban_s = BAN_S if ban_s is None else ban_s
        self._lock = threading.Lock()
        self._counts: dict[str, tuple[float, int]] = {}  # client -> (window start, strikes in it)
        self._bans: dict[str, float] = {}  # client -> banned until (monotonic)
        self.bans = 0

    def strike(self, client: str, why: str) -> None:
        if self.to_ban <= 0:
            return
        now = time.monotonic()
        with self._lock:
            start, n = self._counts.get(client, (now, 0))
            if now - start > self.window_s:
                start, n = now, 0
            n += 1
            self._counts[client] = (start, n)
            if n < self.to_ban or self._bans.get(client, 0.0) > now:
                return
            self._bans[client] = now + self.ban_s
            self._counts.pop(client, None)
            self.bans += 1
            if len(self._counts) > 4096:  # a spread of addresses cannot grow this without bound
                self._counts = {c: v for c, v in self._counts.items() if now - v[0] <= self.window_s}
        log.warning("%s refused for %.0f s: %d requests no client sends within %.0f s (the last: %s)",
                    client, self.ban_s, n, self.window_s, why)

    def banned(self, client: str) -> float:
        """Seconds left of `client`'s ban, 0.0 when it has none."""
        if not self._bans:
            return 0.0
        now = time.monotonic()
        with self._lock:
            until = self._bans.get(client)
            if until is None:
                return 0.0
            if until <= now:
                del self._bans[client]
                return 0.0
            return until - now


def strike(environ: dict | None, why: str) -> None:
    """Count a strike against the client of this request (nothing when the server keeps no count)."""
    count = (environ or {}).get(STRIKE_KEY)
    if count is not None:
        count(why)


__all__ = ["BAN_S", "STRIKES_TO_BAN", "STRIKE_KEY", "Strikes", "WINDOW_S", "strike"]
