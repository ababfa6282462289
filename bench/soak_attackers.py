"""The attackers of bench/soak.py, each run as its own process for the soak's length.

No token (a LAN neighbour), each from a loopback address of its own (127.0.0.x, as another host):
- `hostile`: Engine.IO handshakes each followed by a bad POST, half-sent headers, silent WebSockets;
- `longpoll`: one polling handshake, then 200 concurrent long-poll GETs on its session id;
- `logflood`: malformed Engine.IO / Socket.IO packets as fast as the server answers them.
With the token (it travels in clear on the LAN and sits in the phone app):
- `binary`: a Socket.IO binary event declaring 999,999,999 attachments, then MBs of messages;
- `uploads`: decompression bombs inside members (MCAP, gzip TFRecord, npz), 99,991 directories,
  odd archive entries, several at once;
- `runs`: runs created on a queue no worker serves and cancelled, queue fills past the cap, forced
  promotions without the admin credential, handoffs naming host paths.
Each returns counts of what the server answered, so the soak can say what the attack met.
"""
from __future__ import annotations

import json
import threading
import time

from hostile_clients import HostileRound, LongPollFlood, binary_attachment_bomb, http_request, log_flood, run_flood

NEIGHBOUR = {"hostile": "127.0.0.3", "longpoll": "127.0.0.2", "logflood": "127.0.0.4"}


def _count(counts: dict, key) -> None:
    counts[str(key)] = counts.get(str(key), 0) + 1


def attack_hostile(port: int, token: str, seconds: float) -> dict:
    end = time.monotonic() + seconds
    rounds, statuses, refused = 0, {}, 0
    while time.monotonic() < end - 6:
        r = HostileRound(port, pairs_per_body=20, half_headers=50, silent_websockets=100,
                         source=NEIGHBOUR["hostile"]).run()
        time.sleep(4.0)  # hold the sockets a while, as a patient attacker does
        r.release()
        rounds += 1
        refused += r.refused
        for k, v in r.statuses.items():
            statuses[str(k)] = statuses.get(str(k), 0) + v
        time.sleep(1.0)
    return {"rounds": rounds, "bad_post_statuses": statuses, "held_refused": refused}


def attack_longpoll(port: int, token: str, seconds: float) -> dict:
    flood = LongPollFlood(port, concurrency=200, refresh_s=8.0, source=NEIGHBOUR["longpoll"]).start()
    time.sleep(seconds)
    flood.stop()
    return {"handshakes": flood.handshakes, "get_statuses": {str(k): v for k, v in flood.statuses.items()}}


def attack_logflood(port: int, token: str, seconds: float, clients: int = 4) -> dict:
    end = time.monotonic() + seconds
    statuses: dict = {}
    packets = [0]
    lock = threading.Lock()

    def one() -> None:
        while time.monotonic() < end:
            got = log_flood(port, packets=50, source=NEIGHBOUR["logflood"])
            with lock:
                packets[0] += 50
                for k, v in got.items():
                    statuses[str(k)] = statuses.get(str(k), 0) + v

    threads = [threading.Thread(target=one) for _ in range(clients)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return {"packets": packets[0], "statuses": statuses}


def attack_binary(port: int, token: str, seconds: float) -> dict:
    end = time.monotonic() + seconds
    tries, closed, sent = 0, 0, 0
    while time.monotonic() < end - 5:
        try:
            out = binary_attachment_bomb(port, token, megabytes=8.0)
        except Exception:  # noqa: BLE001 - refused or cut before it logged in: the next bomb tries again
            out = {"closed": True, "sent": 0, "client": None}
        tries += 1
        closed += bool(out["closed"])
        sent += out["sent"]
        if out.get("client") is not None:
            out["client"].close()
        time.sleep(2.0)
    return {"bombs": tries, "closed_by_server": closed, "mb_sent": round(sent / 2**20, 1)}


def _bombs() -> list[tuple[str, bytes, str]]:
    import hostile_packages as hp

    bombs = [("mcap", hp.xr_mcap_bomb(), "application/zip"), ("tfrecord", hp.xr_tfrecord_bomb(), "application/zip"),
             ("npz", hp.xr_npz_bomb(), "application/zip"),
             ("dirs", hp.many_dirs_tar_gz(), "application/gzip")]
    bombs += [(f"odd:{name}", body, "application/octet-stream") for name, body in hp.odd_entries().items()]
    return bombs


def attack_uploads(port: int, token: str, seconds: float) -> dict:
    bombs = _bombs()
    end = time.monotonic() + seconds
    statuses: dict = {}
    slowest = [0.0]
    lock = threading.Lock()

    def one(worker: int) -> None:
        i = worker
        while time.monotonic() < end:
            name, body, kind = bombs[i % len(bombs)]
            i += 3
            started = time.monotonic()
            try:
                status, _ = http_request(port, "POST", "/api/episodes/upload", body,
                                         {"Authorization": f"Bearer {token}", "Content-Type": kind}, timeout=120)
            except OSError:
                status = 0
            with lock:
                _count(statuses, f"{name.split(':')[0]} {status}")
                slowest[0] = max(slowest[0], time.monotonic() - started)
            time.sleep(0.5)

    threads = [threading.Thread(target=one, args=(i,)) for i in range(3)]  # several at once
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return {"statuses": statuses, "slowest_s": round(slowest[0], 2)}


def _handoffs() -> dict[str, tuple[bytes, str]]:
    """The app's episode handoff naming host paths, and with an integer of 5,000 digits."""
    from test_app_handoff import ASSETS, multipart, record

    out = {}
    for target in ("/etc/passwd", "/etc/nope"):
        rec = record()
        rec["steps"][0]["observation"]["egocentric_video"]["uri"] = target
        assets = [dict(ASSETS[0], uri=target), dict(ASSETS[1], local_uri=target)]
        out[target] = multipart({"manifest": json.dumps(rec), "assets": json.dumps(assets)}, [])
    huge = json.dumps(record()).replace('"frame_id": "ego-2"', '"frame_id": ' + "9" * 5000, 1)
    out["huge-int"] = multipart({"manifest": huge, "assets": json.dumps(ASSETS)}, [])
    return out


def attack_runs(port: int, token: str, seconds: float, data: str = "soak") -> dict:
    end = time.monotonic() + seconds
    auth = {"Authorization": f"Bearer {token}", "Content-Type": "application/json"}
    out: dict = {"flood_created": {}, "fill_created": {}, "force": {}, "handoff": {}}
    handoffs = _handoffs()
    while time.monotonic() < end - 5:
        for key, cancel in (("flood_created", True), ("fill_created", False)):
            got = run_flood(port, token, data, runs=25, cancel=cancel)
            for k, v in got["created"].items():
                out[key][str(k)] = out[key].get(str(k), 0) + v
            if not cancel:  # let the queue go again, so the next round floods it afresh
                for run_id in got["ids"]:
                    http_request(port, "POST", f"/api/runs/{run_id}/cancel", headers=auth, timeout=30.0)
        status, _ = http_request(port, "POST", "/api/brain/promote",
                                 json.dumps({"run_id": "r-none", "force": True}).encode(), auth, timeout=30.0)
        _count(out["force"], status)
        for name, (body, ctype) in handoffs.items():
            status, _ = http_request(port, "POST", "/api/training/episode_handoff", body,
                                     {"Authorization": f"Bearer {token}", "Content-Type": ctype}, timeout=30.0)
            _count(out["handoff"], f"{name} {status}")
        time.sleep(3.0)
    return out


ATTACKERS = {"hostile": attack_hostile, "longpoll": attack_longpoll, "logflood": attack_logflood,
             "binary": attack_binary, "uploads": attack_uploads, "runs": attack_runs}
