"""The cloud upload package: its shape, reproducibility, and safe extraction with checksums."""
from __future__ import annotations

import hashlib
import io
import json
import tarfile
from pathlib import Path

import pytest

from hope_models.rlds.archive import ArchiveError, extract_package
from hope_models.rlds.export_cloud import export_episode

from test_rlds_validate import cloud_episode

CREATED_NS = 1_764_952_865_006_200_430


def episode_with_blob(tmp_path: Path):
    root = tmp_path / "src"
    (root / "frames").mkdir(parents=True)
    (root / "frames" / "step_0001_rgb.npy").write_bytes(b"\x93NUMPY fake frame")
    ep = cloud_episode()
    ep.blob_root = str(root)
    ep.steps[1].observation["media"] = {"rgb": {"uri": "frames/step_0001_rgb.npy", "width": 64}}
    return ep


def members_of(package: Path) -> dict[str, bytes | None]:
    with tarfile.open(package, "r:gz") as tar:
        return {m.name: (tar.extractfile(m).read() if m.isfile() else None) for m in tar.getmembers()}


def test_package_shape(tmp_path: Path):
    ep = episode_with_blob(tmp_path)
    package = export_episode(ep, tmp_path / "out", created_ns=CREATED_NS)
    assert package == tmp_path / "out" / "ep1.tar.gz"
    members = members_of(package)
    assert sorted(members) == ["ep1", "ep1/blobs", "ep1/blobs/frames", "ep1/blobs/frames/step_0001_rgb.npy",
                               "ep1/episode.json", "ep1/upload_manifest.json"]
    doc = json.loads(members["ep1/episode.json"])
    meta = doc["metadata"]
    assert (meta["episode_id"], meta["robot_type"], meta["xr_mode"], meta["action_source"],
            meta["total_steps"]) == ("ep1", "donkeycar", "trainer", "human_teleop_xr", 5)
    assert len(doc["steps"]) == 5
    assert doc["steps"][1]["observation"]["media"]["rgb"]["uri"] == "blobs/frames/step_0001_rgb.npy"
    assert doc["steps"][4]["timestamp_ns"] == ep.steps[4].timestamp_ns  # big ints stay exact

    manifest = json.loads(members["ep1/upload_manifest.json"])
    episode_sha = hashlib.sha256(members["ep1/episode.json"]).hexdigest()
    blob = members["ep1/blobs/frames/step_0001_rgb.npy"]
    assert manifest == {
        "episode_id": "ep1", "total_steps": 5, "robot_type": "donkeycar", "xr_mode": "trainer",
        "action_source": "human_teleop_xr", "created_timestamp_ns": CREATED_NS,
        "file_checksums": {"episode.json": episode_sha,
                           "blobs/frames/step_0001_rgb.npy": hashlib.sha256(blob).hexdigest()},
        "metadata_checksum": episode_sha,
        "total_size_bytes": len(members["ep1/episode.json"]) + len(blob),
        "version": "1.0.0",
    }


def test_package_is_byte_reproducible(tmp_path: Path):
    ep = episode_with_blob(tmp_path)
    first = export_episode(ep, tmp_path / "a", created_ns=CREATED_NS).read_bytes()
    second = export_episode(ep, tmp_path / "b", created_ns=CREATED_NS).read_bytes()
    assert first == second


def test_extract_verifies_and_returns_the_episode_dir(tmp_path: Path):
    package = export_episode(episode_with_blob(tmp_path), tmp_path / "out", created_ns=CREATED_NS)
    extracted = extract_package(package, tmp_path / "x")
    assert extracted == tmp_path / "x" / "ep1"
    assert (extracted / "blobs" / "frames" / "step_0001_rgb.npy").read_bytes() == b"\x93NUMPY fake frame"
    assert sorted(p.name for p in (tmp_path / "x").iterdir()) == ["ep1"]  # no staging left behind
    with pytest.raises(FileExistsError):
        extract_package(package, tmp_path / "x")


# -- hostile and damaged packages ---------------------------------------------------------------

def rebuild(package: Path, out: Path, replace: dict[str, bytes] | None = None,
            extra: list[tarfile.TarInfo] | None = None) -> Path:
    """A copy of `package` with some member contents replaced and extra members appended."""
    replace = replace or {}
    with tarfile.open(package, "r:gz") as src, tarfile.open(out, "w:gz") as dst:
        for member in src.getmembers():
            data = src.extractfile(member).read() if member.isfile() else None
            if member.name in replace:
                data = replace[member.name]
                member.size = len(data)
            dst.addfile(member, io.BytesIO(data) if data is not None else None)
        for info in extra or []:
            payload = b"x" * info.size if info.isfile() else None
            dst.addfile(info, io.BytesIO(payload) if payload is not None else None)
    return out


def file_member(name: str) -> tarfile.TarInfo:
    info = tarfile.TarInfo(name)
    info.size = 4
    return info


def link_member(name: str, target: str, kind: bytes) -> tarfile.TarInfo:
    info = tarfile.TarInfo(name)
    info.type = kind
    info.linkname = target
    return info


def special_member(name: str, kind: bytes) -> tarfile.TarInfo:
    info = tarfile.TarInfo(name)
    info.type = kind
    return info


HOSTILE = [
    pytest.param([file_member("ep1/../../evil.txt")], "'..' component refused", id="dotdot"),
    pytest.param([file_member("../evil.txt")], "'..' component refused", id="dotdot-top"),
    pytest.param([file_member("/tmp/evil.txt")], "absolute path refused", id="absolute"),
    pytest.param([link_member("ep1/escape", "../../../etc/passwd", tarfile.SYMTYPE)],
                 "symlink to '../../../etc/passwd' leaves the target dir", id="symlink-escapes"),
    pytest.param([link_member("ep1/abs", "/etc/passwd", tarfile.SYMTYPE)],
                 "symlink to '/etc/passwd' leaves the target dir", id="symlink-absolute"),
    pytest.param([link_member("ep1/hard", "../outside", tarfile.LNKTYPE)],
                 "hardlink to '../outside' leaves the target dir", id="hardlink-escapes"),
    pytest.param([link_member("ep1/inner", "episode.json", tarfile.SYMTYPE)],
                 "not allowed in an upload package", id="symlink-inside"),
    pytest.param([special_member("ep1/null", tarfile.CHRTYPE)], "device, FIFO or special file", id="device"),
    pytest.param([special_member("ep1/pipe", tarfile.FIFOTYPE)], "device, FIFO or special file", id="fifo"),
    pytest.param([file_member("other/x.txt")], "expected one top-level episode dir", id="two-tops"),
    pytest.param([file_member("ep1/unlisted.bin")], "files not listed in file_checksums: unlisted.bin",
                 id="unlisted-file"),
]


@pytest.mark.parametrize("extra, words", HOSTILE)
def test_hostile_packages_are_refused(tmp_path: Path, extra, words):
    package = export_episode(cloud_episode(), tmp_path / "out", created_ns=CREATED_NS)
    hostile = rebuild(package, tmp_path / "hostile.tar.gz", extra=extra)
    dest = tmp_path / "dest" / "inner"
    before = sorted(tmp_path.rglob("*"))
    with pytest.raises(ArchiveError, match=words.replace("(", r"\(").replace(".", r"\.")) as info:
        extract_package(hostile, dest)
    assert str(hostile) in str(info.value)
    # Nothing was written anywhere: not in dest, not beside it (dest itself may have been made).
    after = [p for p in sorted(tmp_path.rglob("*")) if p not in (tmp_path / "dest", dest)]
    assert after == before


def test_tampered_episode_json_fails_its_checksum(tmp_path: Path):
    package = export_episode(cloud_episode(), tmp_path / "out", created_ns=CREATED_NS)
    original = members_of(package)["ep1/episode.json"]
    tampered = rebuild(package, tmp_path / "t.tar.gz",
                       replace={"ep1/episode.json": original.replace(b'"reward": 0.0', b'"reward": 1.0')})
    with pytest.raises(ArchiveError, match=r"episode\.json: sha256 [0-9a-f]{64} does not match"):
        extract_package(tampered, tmp_path / "dest")
    assert not (tmp_path / "dest" / "ep1").exists()


def test_missing_listed_file_and_wrong_size_are_refused(tmp_path: Path):
    package = export_episode(episode_with_blob(tmp_path), tmp_path / "out", created_ns=CREATED_NS)
    manifest = json.loads(members_of(package)["ep1/upload_manifest.json"])
    manifest["total_size_bytes"] += 1
    wrong_size = rebuild(package, tmp_path / "s.tar.gz",
                         replace={"ep1/upload_manifest.json": json.dumps(manifest).encode()})
    with pytest.raises(ArchiveError, match="total_size_bytes"):
        extract_package(wrong_size, tmp_path / "d1")
    manifest["file_checksums"]["blobs/gone.npy"] = "0" * 64
    listed_missing = rebuild(package, tmp_path / "m.tar.gz",
                             replace={"ep1/upload_manifest.json": json.dumps(manifest).encode()})
    with pytest.raises(ArchiveError, match="blobs/gone.npy: listed in file_checksums but missing"):
        extract_package(listed_missing, tmp_path / "d2")


def test_not_a_tar_is_an_archive_error(tmp_path: Path):
    junk = tmp_path / "junk.tar.gz"
    junk.write_bytes(b"\x1f\x8b not really gzip")
    with pytest.raises(ArchiveError, match="junk.tar.gz"):
        extract_package(junk, tmp_path / "dest")


# -- round trip through the readers -------------------------------------------------------------

def test_export_extract_read_round_trip(tmp_path: Path):
    from hope_models.rlds.discover import read_path
    from hope_models.rlds.export_cloud import export_paths
    from hope_models.rlds.validate import validate_episode

    src = tmp_path / "src"
    (src / "frames").mkdir(parents=True)
    (src / "frames" / "step_0001_rgb.npy").write_bytes(b"\x93NUMPY fake frame")
    original = cloud_episode()
    original.steps[1].observation["media"] = {"rgb": {"uri": "frames/step_0001_rgb.npy"}}
    doc = {"metadata": original.metadata,
           "steps": [s.to_json_obj(i) for i, s in enumerate(original.steps)]}
    (src / "ep1.json").write_text(json.dumps(doc), encoding="utf-8")

    [read] = [ep for report in read_path(src / "ep1.json") for ep in report.episodes]
    result = export_paths([src / "ep1.json"], tmp_path / "out")
    assert result["summary"] == {"exported": 1, "refused": 0, "skipped": 0, "ok": True}
    extracted = extract_package(result["episodes"][0]["package"], tmp_path / "x")
    [back] = [ep for report in read_path(extracted) for ep in report.episodes]

    assert back.episode_id == read.episode_id == "ep1"
    assert back.errors == []
    assert validate_episode(back, "cloud") == []  # the blob resolves inside the extracted package
    assert [s.timestamp_ns for s in back.steps] == [s.timestamp_ns for s in read.steps]
    for a, b in zip(read.steps, back.steps):
        assert (a.action, a.reward, a.is_terminal, a.step_metadata) == (b.action, b.reward, b.is_terminal,
                                                                          b.step_metadata)
    # Only the blob URI moved, into the package's blobs/ dir, where the file now is.
    assert back.steps[1].observation.pop("media") == {"rgb": {"uri": "blobs/frames/step_0001_rgb.npy"}}
    assert read.steps[1].observation.pop("media") == {"rgb": {"uri": "frames/step_0001_rgb.npy"}}
    assert [s.observation for s in back.steps] == [s.observation for s in read.steps]
    assert (Path(back.blob_root) / "blobs/frames/step_0001_rgb.npy").read_bytes() == b"\x93NUMPY fake frame"
    added = {"robot_type": "donkeycar", "action_source": "human_teleop_xr", "total_steps": 5}
    assert back.metadata == {**read.metadata, **added}


def test_two_sources_with_one_id_get_two_packages(tmp_path: Path):
    from hope_models.rlds.export_cloud import export_paths

    for name, reward in (("a", 0.0), ("b", 1.0)):
        ep = cloud_episode()
        doc = {"metadata": ep.metadata, "steps": [dict(s.to_json_obj(i), reward=reward)
                                                  for i, s in enumerate(ep.steps)]}
        (tmp_path / name).mkdir()
        (tmp_path / name / "ep1.json").write_text(json.dumps(doc), encoding="utf-8")
    result = export_paths([tmp_path / "a" / "ep1.json", tmp_path / "b" / "ep1.json"], tmp_path / "out")
    packages = [Path(e["package"]).name for e in result["episodes"]]
    assert packages[0] == "ep1.tar.gz" and packages[1].startswith("ep1-") and len(packages[1]) == len("ep1-12345678.tar.gz")
    assert any("already exported in this run" in w for w in result["episodes"][1]["warnings"])
    second = extract_package(tmp_path / "out" / packages[1], tmp_path / "x")
    assert json.loads((second / "episode.json").read_text())["metadata"]["episode_id"] == second.name
