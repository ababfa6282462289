"""POST /api/episodes/upload and the inbox calls (webapp/api/episodes.py), in process (Flask's test client).

- a real Pi-runtime package (`run_trainer.py export --cloud` of a synthetic episode), as the raw
  body and as a multipart `file` part; a real XR-style zip (metadata.json + steps/000000.jsonl of a
  shared sample episode, with the XR app's headers): verdicts, what each can train, tags, the same
  package again changes nothing;
- unsafe archives: traversal, absolute and symlink members (tar and zip), a gzip bomb, a zip bomb,
  a zip whose header lies about a member's size, too many members, too much uncompressed, bad
  checksums, neither tar nor zip: each gets its status, the message names the member, and nothing
  at all is written anywhere under $HOPE_HOME (the whole tree compared before and after);
- the token is checked before the body is read; the app's list and tag calls.
"""
from __future__ import annotations

import hashlib
import io
import json
import stat
import subprocess
import sys
import tarfile
import zipfile
from pathlib import Path

import pytest
from test_app_handoff import make_client

REPO = Path(__file__).resolve().parents[1]
XR_SAMPLE = "history/continuonbrain/rlds/episodes/follow_user_mr_v2"
SAFETY = {"content_rating": {"audience": "general", "violence": "none", "language": "clean"},
          "pii_attestation": {"pii_present": False, "faces_present": False, "name_present": False,
                              "consent": True},
          "pii_cleared": True, "pending_review": False}


# -- packages ---------------------------------------------------------------------------------------

def pi_package(out: Path, episode_id: str = "ep_00000_10hz") -> Path:
    """A Pi-runtime upload package exactly as `export --cloud` writes it, of a trainable episode."""
    from hope_models.data.synthetic import generate_dataset

    generate_dataset(out / "src", 600, obs_dim=6, act_dim=2, rates_hz=(10,), episode_seconds=(30, 30))
    ep = out / "src" / episode_id
    md = json.loads((ep / "metadata.json").read_text())
    md["safety"] = SAFETY  # the cloud profile export checks wants it; the synthetic writer leaves it out
    (ep / "metadata.json").write_text(json.dumps(md))
    done = subprocess.run([sys.executable, str(REPO / "run_trainer.py"), "export", "--cloud", "--out",
                           str(out / "pkgs"), str(ep)], capture_output=True, text=True, cwd=REPO)
    assert done.returncode == 0, done.stdout + done.stderr
    return out / "pkgs" / f"{episode_id}.tar.gz"


def xr_zip(samples_dir: Path) -> bytes:
    """What HttpRldsUploader sends: the episode dir's files, names relative to it."""
    src = samples_dir / XR_SAMPLE
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as z:
        z.write(src / "metadata.json", "metadata.json")
        z.write(src / "steps" / "000000.jsonl", "steps/000000.jsonl")
    return buf.getvalue()


def tar_gz(members: list[tuple[tarfile.TarInfo, bytes | None]], level: int = 9) -> bytes:
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w:gz", compresslevel=level) as tar:
        for info, data in members:
            if data is not None:
                info.size = len(data)
            tar.addfile(info, io.BytesIO(data) if data is not None else None)
    return buf.getvalue()


def tar_file(name: str, data: bytes = b"{}") -> tuple[tarfile.TarInfo, bytes]:
    return tarfile.TarInfo(name), data


def tar_link(name: str, target: str) -> tuple[tarfile.TarInfo, None]:
    info = tarfile.TarInfo(name)
    info.type, info.linkname = tarfile.SYMTYPE, target
    return info, None


def zip_of(members: list[tuple[str, bytes]], *, symlink: str | None = None) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as z:
        for name, data in members:
            z.writestr(name, data)
        if symlink is not None:
            info = zipfile.ZipInfo(symlink)
            info.create_system = 3  # Unix: the mode is in the high bits of external_attr
            info.external_attr = (stat.S_IFLNK | 0o777) << 16
            z.writestr(info, "/etc/passwd")
    return buf.getvalue()


def lying_zip(real_size: int, declared: int) -> bytes:
    """metadata.json of `real_size` zeros whose local and central headers say `declared` bytes."""
    data = bytearray(zip_of([("metadata.json", b"\0" * real_size)]))
    local = data.index(b"PK\x03\x04")
    central = data.index(b"PK\x01\x02")
    data[local + 22:local + 26] = declared.to_bytes(4, "little")
    data[central + 24:central + 28] = declared.to_bytes(4, "little")
    return bytes(data)


# -- the app ----------------------------------------------------------------------------------------

@pytest.fixture
def client(tmp_path):
    c = make_client(tmp_path / "home", HOPE_UPLOAD_UNPACK_MAX_MB="4", HOPE_UPLOAD_MAX_MEMBERS="10000")
    yield c
    c.close()


@pytest.fixture(scope="module")
def package(tmp_path_factory) -> bytes:
    return pi_package(tmp_path_factory.mktemp("pi")).read_bytes()


def upload(client, body: bytes, *, headers: dict | None = None, content_type: str = "application/octet-stream"):
    return client.post("/api/episodes/upload", data=body, content_type=content_type,
                       headers={"Authorization": f"Bearer {client.token}", **(headers or {})})


def tree(home: Path) -> dict[str, str]:
    """Every path under $HOPE_HOME with its content's hash (dirs: "dir")."""
    return {str(p.relative_to(home)): "dir" if p.is_dir() else hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(home.rglob("*"))}


def assert_nothing_written(client, before: dict[str, str]) -> None:
    home = Path(client.settings.home)
    after = tree(home)
    changed = {k for k in before if after.get(k) != before[k]}
    added = set(after) - set(before)
    assert not changed, changed
    # received() may create $HOPE_HOME/tmp itself; what it held for the request is gone
    assert added <= {"tmp"}, sorted(added)
    assert not client.settings.inbox_dir.exists()


def only_episode(answer: dict) -> dict:
    (pkg,) = answer["packages"]
    (ep,) = pkg["episodes"]
    return ep


# -- the two package kinds --------------------------------------------------------------------------

def test_a_pi_runtime_package_lands_in_the_inbox_with_its_verdict(client, package):
    r = upload(client, package, content_type="application/gzip")
    assert r.status_code == 200, r.get_json()
    answer = r.get_json()
    assert answer["packages"][0]["kind"] == "pi"
    ep = only_episode(answer)
    assert ep["episode_id"] == "ep_00000_10hz" and ep["action"] == "written" and ep["status"] == "ok"
    assert ep["steps"] == 300 and ep["errors"] == []
    assert ep["trainable"] == ["vqvae", "fast_loop", "mid_loop"] and ep["not_trainable"] == {}
    assert ep["origin"] == "upload:pi"
    assert "tmp" not in ep["source"] and ep["source"].endswith("ep_00000_10hz/episode.json")
    inbox = client.settings.inbox_dir
    assert (inbox / "ep_00000_10hz" / "metadata.json").is_file()
    assert list((Path(client.settings.home) / "tmp").iterdir()) == []  # the extraction is gone

    # the same package again, this time as a browser drops it: nothing new
    r = client.post("/api/episodes/upload", data={"file": (io.BytesIO(package), "ep_00000_10hz.tar.gz")},
                    content_type="multipart/form-data", headers={"Authorization": f"Bearer {client.token}"})
    assert r.status_code == 200, r.get_json()
    again = only_episode(r.get_json())
    assert again["action"] == "unchanged" and again["episode_id"] == "ep_00000_10hz"
    assert r.get_json()["packages"][0]["name"] == "file 'ep_00000_10hz.tar.gz'"
    assert r.get_json()["summary"]["written"] == 0


def test_an_xr_zip_with_the_xr_apps_headers(client, samples_dir):
    body = xr_zip(samples_dir)
    headers = {"X-Continuon-Tag-xr_mode": "mixed_reality", "X-Continuon-Tag-control_role": "pilot",
               "X-Continuon-Tag-environment_id": "lab", "X-Continuon-Tag-list": "follow, user ,,demo"}
    r = upload(client, body, headers=headers, content_type="application/zip")
    assert r.status_code == 200, r.get_json()
    ep = only_episode(r.get_json())
    assert r.get_json()["packages"][0]["kind"] == "xr"
    assert ep["episode_id"] == "follow_user_mr_v2" and ep["action"] == "written"
    assert ep["status"] == "warnings" and any("mixed_reality" in w for w in ep["warnings"])
    assert ep["tags"] == ["follow", "user", "demo"]
    # three steps: frames-free VQ-VAE input is there, the loops' windows are not
    assert ep["trainable"] == ["vqvae"]
    assert set(ep["not_trainable"]) == {"fast_loop", "mid_loop"} and "steps" in ep["not_trainable"]["fast_loop"]
    stored = client.settings.inbox_dir / "follow_user_mr_v2"
    assert (stored / "metadata.json").is_file()
    r = upload(client, body, headers=headers, content_type="application/zip")
    assert only_episode(r.get_json())["action"] == "unchanged"

    listed = client.get("/api/v1/data/episodes", headers={"Authorization": f"Bearer {client.token}"})
    assert listed.status_code == 200
    (entry,) = listed.get_json()["episodes"]
    assert entry["episode_id"] == "follow_user_mr_v2" and entry["tags"] == ["follow", "user", "demo"]
    assert all("/tmp/" not in w for w in entry["warnings"])


def test_the_kind_comes_from_the_bytes_not_the_name_or_type(client, package, samples_dir):
    r = upload(client, package, content_type="application/zip")  # a tar.gz sent as a zip
    assert r.status_code == 200 and r.get_json()["packages"][0]["kind"] == "pi"
    r = client.post("/api/episodes/upload", data={"file": (io.BytesIO(xr_zip(samples_dir)), "x.tar.gz")},
                    content_type="multipart/form-data", headers={"Authorization": f"Bearer {client.token}"})
    assert r.status_code == 200 and r.get_json()["packages"][0]["kind"] == "xr"


# -- refused archives: the status, the member named, nothing written ---------------------------------

def _corrupt_checksum(package: bytes) -> bytes:
    members = []
    with tarfile.open(fileobj=io.BytesIO(package), mode="r:gz") as tar:
        for m in tar.getmembers():
            data = tar.extractfile(m).read() if m.isfile() else None
            if m.name.endswith("/episode.json"):
                data = data.replace(b'"steps"', b'"steps" ', 1)
            members.append((m, data))
    return tar_gz(members)


BAD = {
    "tar-traversal": (lambda p: tar_gz([tar_file("ep/episode.json"), tar_file("ep/../../evil.json")]),
                      400, "'ep/../../evil.json'"),
    "tar-absolute": (lambda p: tar_gz([tar_file("/tmp/evil.json")]), 400, "'/tmp/evil.json'"),
    "tar-symlink": (lambda p: tar_gz([tar_file("ep/episode.json"), tar_link("ep/blobs", "/etc")]),
                    400, "'ep/blobs': symlink"),
    "tar-bad-checksum": (_corrupt_checksum, 400, "episode.json: sha256"),
    "gzip-bomb": (lambda p: tar_gz([tar_file("ep/episode.json", b"\0" * (8 << 20))]), 413,
                  "more than 4194304 bytes uncompressed (upload_unpack_max_mb=4)"),
    "zip-traversal": (lambda p: zip_of([("metadata.json", b"{}"), ("steps/../../evil.jsonl", b"{}")]),
                      400, "'steps/../../evil.jsonl'"),
    "zip-absolute": (lambda p: zip_of([("/etc/evil.json", b"{}")]), 400, "'/etc/evil.json'"),
    "zip-symlink": (lambda p: zip_of([("metadata.json", b"{}")], symlink="steps"), 400, "'steps': symlink"),
    "zip-bomb": (lambda p: zip_of([("steps/000000.jsonl", b"\0" * (8 << 20))]), 413,
                 "8388608 bytes uncompressed, more than 4194304 (upload_unpack_max_mb=4)"),
    "zip-lying-header": (lambda p: lying_zip(3 << 20, 1000), 400, "'metadata.json'"),
    "zip-too-many-members": (lambda p: zip_of([(f"{i}", b"") for i in range(10_001)]),
                             413, "more than 10000 members (upload_max_members=10000)"),
    "zip-too-large-uncompressed": (lambda p: zip_of([("blobs/a.bin", _low_entropy(5 << 20))]),
                                   413, "uncompressed, more than 4194304"),
    # level 4: zlib's level 9 takes 16 s over two-symbol data; the unpacked size is what is tested
    "tar-too-large-uncompressed": (lambda p: tar_gz([tar_file("ep/blobs/a.bin", _low_entropy(5 << 20))], level=4),
                                   413, "more than 4194304 bytes uncompressed"),
    "not-a-package": (lambda p: b'{"metadata": {}, "steps": []}', 400, "not a package"),
}


def _low_entropy(n: int) -> bytes:
    """Random bits, one per byte: compresses ~8x, so n bytes cross no ratio limit but do fill a disk."""
    import numpy as np

    return (np.random.default_rng(0).integers(0, 2, n, dtype=np.uint8) + ord("a")).astype(np.uint8).tobytes()


@pytest.mark.parametrize("name", sorted(BAD))
def test_an_unsafe_or_corrupt_archive_is_refused_and_writes_nothing(client, package, name):
    make, status, needle = BAD[name]
    body = make(package)
    assert len(body) < 1 << 20  # under the body limit: the archive itself is what is refused
    before = tree(Path(client.settings.home))
    r = upload(client, body)
    assert r.status_code == status, r.get_json()
    assert needle in r.get_json()["error"]
    assert "tmp/upload-" not in r.get_json()["error"]  # named as the client sent it
    assert_nothing_written(client, before)


def test_one_refused_package_of_a_drop_means_none_is_ingested(client, package):
    before = tree(Path(client.settings.home))
    r = client.post("/api/episodes/upload", content_type="multipart/form-data",
                    data={"file": [(io.BytesIO(package), "good.tar.gz"),
                                   (io.BytesIO(zip_of([("../evil", b"x")])), "bad.zip")]},
                    headers={"Authorization": f"Bearer {client.token}"})
    assert r.status_code == 400 and "file 'bad.zip'" in r.get_json()["error"]
    assert_nothing_written(client, before)


def test_a_body_over_upload_max_mb_is_413(client):
    before = tree(Path(client.settings.home))
    r = upload(client, b"PK\x03\x04" + b"\0" * (1 << 20))
    assert r.status_code == 413
    assert_nothing_written(client, before)


class _Tattletale(io.BytesIO):
    read_at_all = False

    def read(self, *args):
        _Tattletale.read_at_all = True
        return super().read(*args)


@pytest.mark.parametrize("token", [None, "wrong-token-xxxxxxxxxxxxxxxx"])
def test_the_token_is_checked_before_any_body_is_read(client, package, token):
    before = tree(Path(client.settings.home))
    stream = _Tattletale(package)
    headers = {"Content-Length": str(len(package))}
    if token:
        headers["Authorization"] = f"Bearer {token}"
    r = client.post("/api/episodes/upload", input_stream=stream, content_type="application/gzip", headers=headers)
    assert r.status_code == 401
    assert not _Tattletale.read_at_all
    assert_nothing_written(client, before)


def test_bad_tags_are_refused_before_the_body(client, package):
    r = upload(client, package, headers={"X-Continuon-Tag-list": "ok," + "x" * 65})
    assert r.status_code == 400 and "X-Continuon-Tag-list[1]" in r.get_json()["error"]
    assert not client.settings.inbox_dir.exists()


def test_multipart_needs_file_parts(client, package):
    auth = {"Authorization": f"Bearer {client.token}"}
    r = client.post("/api/episodes/upload", data={"other": (io.BytesIO(package), "a.tar.gz")},
                    content_type="multipart/form-data", headers=auth)
    assert r.status_code == 400 and "'other'" in r.get_json()["error"]
    r = client.post("/api/episodes/upload", data={"tags": "x"}, content_type="multipart/form-data", headers=auth)
    assert r.status_code == 400 and "no file part named 'file'" in r.get_json()["error"]
    r = upload(client, b"")
    assert r.status_code == 400 and "empty body" in r.get_json()["error"]


def test_a_zip_with_no_episode_is_a_400(client):
    r = upload(client, zip_of([("readme.txt", b"hello")]))
    assert r.status_code == 400 and "no episode" in r.get_json()["error"]


# -- the app's list and tag calls -------------------------------------------------------------------

def test_the_apps_list_and_tag_calls(client, package):
    auth = {"Authorization": f"Bearer {client.token}"}
    r = client.get("/api/v1/data/episodes", headers=auth)
    assert r.status_code == 200 and r.get_json() == {"episodes": []}
    assert upload(client, package, headers={"X-Continuon-Tag-list": "pi"}).status_code == 200
    r = client.post("/api/v1/data/tag", json={"episode_id": "ep_00000_10hz", "tag": "good grasp"}, headers=auth)
    assert r.status_code == 200, r.get_json()
    answer = r.get_json()
    assert answer["success"] is True and answer["episode"]["tags"] == ["pi", "good grasp"]
    (entry,) = client.get("/api/v1/data/episodes", headers=auth).get_json()["episodes"]
    assert entry["tags"] == ["pi", "good grasp"] and entry["status"] == "ok"
    editor = client.get("/api/episodes", headers=auth).get_json()
    assert editor["episodes"] == [entry] and editor["upload_max_mb"] == 1

    r = client.post("/api/v1/data/tag", json={"episode_id": "nope", "tag": "x"}, headers=auth)
    assert r.status_code == 404 and "nope" in r.get_json()["error"]
    for body, needle in [({"episode_id": "ep_00000_10hz"}, "tag: required"),
                         ({"episode_id": "ep_00000_10hz", "tag": ""}, "tag"),
                         ({"episode_id": "ep_00000_10hz", "tag": "x" * 65}, "tag"),
                         ({"episode_id": 3, "tag": "x"}, "episode_id"),
                         ({"episode_id": "ep_00000_10hz", "tag": "x", "more": 1}, "more")]:
        r = client.post("/api/v1/data/tag", json=body, headers=auth)
        assert r.status_code == 400 and needle in r.get_json()["error"], (body, r.get_json())
    assert client.get("/api/v1/data/episodes").status_code == 401
    assert client.post("/api/v1/data/tag", json={"episode_id": "ep_00000_10hz", "tag": "x"}).status_code == 401


def test_a_pi_package_with_a_blob_keeps_it_beside_the_episode(client, tmp_path):
    from test_rlds_export import CREATED_NS, episode_with_blob

    from hope_models.rlds.export_cloud import export_episode

    package = export_episode(episode_with_blob(tmp_path), tmp_path / "out", created_ns=CREATED_NS)
    r = upload(client, package.read_bytes())
    assert r.status_code == 200, r.get_json()
    ep = only_episode(r.get_json())
    assert ep["episode_id"] == "ep1" and ep["action"] == "written", ep
    stored = [p for p in (client.settings.inbox_dir / "ep1").rglob("*.npy")]
    assert [p.read_bytes() for p in stored] == [b"\x93NUMPY fake frame"]


def test_a_rejected_episode_is_listed_with_its_reasons_once_however_often_it_comes(client):
    body = zip_of([("metadata.json", b'{"episode_id": "bad1"}'),
                   ("steps/000000.jsonl", b'{"observation": {"x": [1]}, "action": {"command": [NaN]}, "timestamp_ns": 1}\n')])
    for _ in range(2):
        r = upload(client, body)
        assert r.status_code == 200, r.get_json()
        ep = only_episode(r.get_json())
        assert ep["action"] == "rejected" and ep["status"] == "rejected" and ep["trainable"] == []
        assert any("not a finite number" in e for e in ep["errors"])
    (entry,) = client.get("/api/episodes", headers={"Authorization": f"Bearer {client.token}"}).get_json()["episodes"]
    assert entry["episode_id"] == "bad1" and entry["status"] == "rejected"
    assert entry["source"].startswith("upload:xr-") and "/tmp/" not in entry["errors"][0]
    # the manifest names the package too, not the extraction dir that is gone
    manifest = (client.settings.inbox_dir / "manifest.json").read_text()
    assert '"upload:xr-' in manifest and "package-" not in manifest and "/tmp/" not in manifest
    assert list((Path(client.settings.home) / "tmp").iterdir()) == []


def test_zip_members_are_counted_before_zipfile_parses_them(tmp_path):
    """A central directory that claims more than the limit is refused by the walk, not by zipfile."""
    from hope_models.rlds.zip_package import ZipPackageError, extract_zip

    z = tmp_path / "many.zip"
    z.write_bytes(zip_of([(f"{i}", b"") for i in range(30)]))
    with pytest.raises(ZipPackageError, match="more than 20 members"):
        extract_zip(z, tmp_path / "out", max_members=20)
    assert not (tmp_path / "out").exists()
    assert extract_zip(z, tmp_path / "ok", max_members=30) == tmp_path / "ok"
    assert len(list((tmp_path / "ok").iterdir())) == 30


def test_the_app_calls_as_dart_sends_them(client, package):
    """package:http: lower-case header names, a String body gets `; charset=utf-8`."""
    assert upload(client, package).status_code == 200
    auth = {"authorization": f"Bearer {client.token}"}
    r = client.post("/api/v1/data/tag", data=json.dumps({"episode_id": "ep_00000_10hz", "tag": "dart"}),
                    headers={**auth, "content-type": "application/json; charset=utf-8"})
    assert r.status_code == 200 and r.get_json()["success"] is True, r.get_json()
    episodes = client.get("/api/v1/data/episodes", headers=auth).get_json()["episodes"]
    assert isinstance(episodes, list) and episodes[0]["tags"] == ["dart"]
