"""Odd archive entries and tags, sent by a client holding the token to the real server:

- entries that once made the upload answer 500 (a name over 255 bytes, a path over 4 KB, a file
  then a directory below it and the reverse, a name twice), tar and zip, and more directories than
  a package has: a 400 naming the entry, nothing left in $HOPE_HOME/tmp;
- generated archives (tests/hostile_packages.random_archives): extraction and reading raise only
  their own errors, and the server never answers 5xx;
- tags: at most 16 per request (400), at most 64 on an episode (an upload's extra ones left out
  with a warning; POST /api/v1/data/tag past it: 413), so the inbox manifest stays small.
"""
from __future__ import annotations

import io
import json
import shutil
import zipfile
from pathlib import Path


import hostile_packages as hp
from test_upload_bombs import served, server  # noqa: F401 - the real server the uploads go to


ODD = {  # entry -> the words of the refusal
    "tar-name-over-255-bytes": "a name of 300 bytes; at most 255",
    "tar-path-over-4kb": "a path of 5034 bytes; at most 1024",
    "tar-file-then-dir-below-it": "'ep/a' is both a file and a directory",
    "tar-file-then-file-below-it": "'ep/a' is both a file and a directory",
    "tar-dir-then-file-of-its-name": "'ep/a' appears twice",
    "tar-duplicate-file": "'ep/a' appears twice",
    "zip-name-over-255-bytes": "a name of 300 bytes; at most 255",
    "zip-path-over-4kb": "a path of 5031 bytes; at most 1024",
    "zip-file-then-dir-below-it": "'a' is both a file and a directory",
    "zip-dir-then-file-of-its-name": "'a' appears twice",
    "tar-dir-name-over-255-bytes": "a name of 300 bytes; at most 255",
    "tar-dir-path-over-4kb": "a path of 5027 bytes; at most 1024",
    "zip-dir-name-over-255-bytes": "a name of 300 bytes; at most 255",
    "zip-dir-path-over-4kb": "a path of 5024 bytes; at most 1024",
    "zip-1001-implied-directories": "1001 directories, more than 1000",
    "tar-1001-implied-directories": "1001 directories, more than 1000",
}


def test_odd_entries_are_a_400_naming_the_entry(server):
    s = server()
    bodies = hp.odd_entries()
    assert set(bodies) == set(ODD)
    wrong = {}
    for name, body in sorted(bodies.items()):
        status, answer = s.upload(body)
        error = answer.get("error", "")
        if status != 400 or ODD[name] not in error or not error.startswith("request body: "):
            wrong[name] = (status, error or answer)
    assert not wrong, wrong
    assert s.tmp_entries() == []


def test_generated_archives_raise_only_their_own_errors(tmp_path):
    from hope_models.rlds.discover import read_path
    from hope_models.rlds.inflate import Budget, InflateError
    from hope_models.rlds.upload_package import PackageError, extract_upload

    for i, body in hp.random_archives(seed=7, count=300):
        case = tmp_path / f"case{i}"
        (case / "out").mkdir(parents=True)
        (case / "pkg").write_bytes(body)
        try:
            _, where = extract_upload(case / "pkg", case / "out", label="body", max_total_bytes=1 << 20,
                                      budget=Budget(1 << 20, 30.0))
            read_path(where)
        except (PackageError, InflateError):
            pass
        shutil.rmtree(case)


def test_generated_archives_never_get_a_5xx(server):
    s = server()
    for i, body in hp.random_archives(seed=11, count=40):
        status, answer = s.upload(body)
        assert status in (200, 400, 413), (i, status, answer)
    assert s.tmp_entries() == []


def _episode_zip(episode_id: str) -> bytes:
    from test_inbox import steps

    meta = {"episode_id": episode_id, "xr_mode": "trainer", "control_role": "human_teleop", "environment_id": "lab"}
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as z:
        z.writestr("episode.json", json.dumps({"metadata": meta, "steps": steps(30)}))
    return buf.getvalue()


def test_tags_are_capped_per_request_and_per_episode(server):
    from hope_models.rlds.ingest import MANIFEST
    from hostile_clients import http_request

    per_request, per_episode = 16, 64
    s = server()
    body = _episode_zip("ep_tags")
    too_many = ",".join(f"t{i}" for i in range(per_request + 1))
    status, answer = s.upload(body, headers={"X-Continuon-Tag-list": too_many})
    assert status == 400 and f"more than {per_request} tags" in answer["error"], answer
    for round_ in range(per_episode // per_request + 1):
        tags = ",".join(f"r{round_}-{i}" for i in range(per_request))
        status, answer = s.upload(body, headers={"X-Continuon-Tag-list": tags})
        assert status == 200, answer
    (episode,) = answer["packages"][0]["episodes"]
    assert len(episode["tags"]) == per_episode
    assert any("not added" in w and "r4-0" in w for w in episode["warnings"]), episode["warnings"]
    status, raw = http_request(s.port, "POST", "/api/v1/data/tag",
                               json.dumps({"episode_id": "ep_tags", "tag": "one more"}).encode(),
                               {"Authorization": f"Bearer {s.token}", "Content-Type": "application/json"})
    assert status == 413 and "already holds 64 tags" in json.loads(raw)["error"], raw
    manifest = Path(s.settings.inbox_dir) / MANIFEST
    assert manifest.stat().st_size < 64 << 10
