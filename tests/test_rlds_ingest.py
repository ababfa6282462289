"""Canonical episode dirs and ingest: atomic writes, blobs, ids, the manifest and idempotency."""
from __future__ import annotations

import hashlib
import json
import math
from pathlib import Path

import pytest

from hope_models.rlds.ingest import MANIFEST, IngestError, ingest_paths
from hope_models.rlds.read_episode_dir import read_episode_dir
from hope_models.rlds.validation_report import validate_paths
from hope_models.rlds.write_episode_dir import prepare_episode, safe_episode_id, write_episode_dir

from test_rlds_validate import clean_episode


def tree(root: Path) -> dict[str, tuple[str, int]]:
    """Every file under root: its sha256 and mtime_ns, so a rewrite with equal bytes shows too."""
    return {p.relative_to(root).as_posix(): (hashlib.sha256(p.read_bytes()).hexdigest(), p.stat().st_mtime_ns)
            for p in sorted(root.rglob("*")) if p.is_file()}


def single_json(path: Path, ep_id: str, steps: list[dict], metadata: dict | None = None) -> Path:
    meta = {"episode_id": ep_id, "xr_mode": "trainer", "control_role": "human_teleop",
            "environment_id": "lab", "tags": ["t"], "software": {"xr_app": "1"}}
    meta.update(metadata or {})
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({"metadata": meta, "steps": steps}), encoding="utf-8")
    return path


def steps_10hz(n: int, command: list[float] | None = None, **extra) -> list[dict]:
    return [{"observation": {"robot_state": {"timestamp_nanos": i * 100_000_000,
                                             "joint_positions": [0.1 * i, 0.0]}, **extra},
             "action": {"command": command or [0.1, 0.2], "source": "human_teleop_xr"},
             "reward": 0.0, "is_terminal": i == n - 1} for i in range(n)]


# -- write_episode_dir --------------------------------------------------------------------------

def test_write_episode_dir_is_canonical_and_reads_back_losslessly(tmp_path: Path):
    ep = clean_episode()
    ep.metadata.pop("schema_version")
    ep.metadata.pop("provenance")
    out = write_episode_dir(ep, tmp_path / "ds")
    assert out == tmp_path / "ds" / "ep1"
    assert sorted(tree(out)) == ["metadata.json", "steps/000000.jsonl"]
    meta = json.loads((out / "metadata.json").read_text())
    assert (meta["schema_version"], meta["episode_id"], meta["provenance"]) == \
        ("1.1", "ep1", {"origin": "import:single_json"})
    lines = (out / "steps" / "000000.jsonl").read_text().splitlines()
    assert [json.loads(line)["step_index"] for line in lines] == [0, 1, 2, 3, 4]

    [back] = read_episode_dir(out).episodes
    assert back.layout == "canonical_dir" and back.problems == []
    assert back.steps == ep.steps  # every value, including epoch-ns timestamps beyond 2**53
    assert prepare_episode(back).content_sha256 == prepare_episode(ep).content_sha256
    assert [p.name for p in (tmp_path / "ds").iterdir()] == ["ep1"]  # no temp dir left


def test_write_refuses_an_existing_dir_and_non_finite_content(tmp_path: Path):
    write_episode_dir(clean_episode(), tmp_path)
    with pytest.raises(FileExistsError, match="ep1"):
        write_episode_dir(clean_episode(), tmp_path)
    bad = clean_episode()
    bad.episode_id = "bad"
    bad.steps[2].reward = math.nan
    with pytest.raises(ValueError, match="Out of range float"):
        write_episode_dir(bad, tmp_path)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ep1"]


def test_blobs_are_copied_and_uris_point_into_blobs(tmp_path: Path):
    src = tmp_path / "src"
    (src / "cam").mkdir(parents=True)
    (src / "cam" / "f1.png").write_bytes(b"png-bytes")
    (src / "blobs").mkdir()
    (src / "blobs" / "d1.npy").write_bytes(b"npy-bytes")
    ep = clean_episode(blob_root=str(src))
    ep.steps[1].observation["media"] = {"rgb": {"uri": "cam/f1.png"}, "depth": {"uri": "blobs/d1.npy"},
                                        "audio": {"uri": "mock://audio/1.wav"}}
    ep.steps[2].observation["media"] = {"rgb": {"uri": "cam/missing.png"}}
    out = write_episode_dir(ep, tmp_path / "ds")
    assert (out / "blobs" / "cam" / "f1.png").read_bytes() == b"png-bytes"
    assert (out / "blobs" / "d1.npy").read_bytes() == b"npy-bytes"
    [back] = read_episode_dir(out).episodes
    media = back.steps[1].observation["media"]
    assert (media["rgb"]["uri"], media["depth"]["uri"], media["audio"]["uri"]) == \
        ("blobs/cam/f1.png", "blobs/d1.npy", "mock://audio/1.wav")
    assert back.steps[2].observation["media"]["rgb"]["uri"] == "cam/missing.png"  # left as it was


@pytest.mark.parametrize("raw, safe", [("ep_1.a-b", "ep_1.a-b"), ("0", "0")])
def test_safe_ids_are_kept(raw, safe):
    assert safe_episode_id(raw) == safe


@pytest.mark.parametrize("raw", ["../escape", "a/b", ".hidden", "..", "", "x" * 300, "caf\u00e9 1"])
def test_unsafe_ids_become_distinct_safe_names(raw):
    safe = safe_episode_id(raw)
    assert safe == safe_episode_id(raw)  # deterministic
    assert "/" not in safe and not safe.startswith(".") and len(safe) <= 128
    assert safe.endswith(hashlib.sha256(raw.encode()).hexdigest()[:8])


# -- ingest -------------------------------------------------------------------------------------

def test_ingest_writes_rejects_and_reruns_without_changes(tmp_path: Path):
    src = tmp_path / "src"
    single_json(src / "good.json", "good", steps_10hz(4))
    nan_steps = steps_10hz(3)
    (src / "bad.jsonl").write_text("\n".join(json.dumps(s) for s in nan_steps[:1]) + "\n" +
                                   json.dumps(nan_steps[1]).replace("0.2]", "NaN]") + "\n")
    ds = tmp_path / "ds"
    result = ingest_paths([src], ds)
    actions = {e["source"]: (e["action"], e["episode_id"]) for e in result["episodes"]}
    assert actions == {str(src / "good.json"): ("written", "good"),
                       str(src / "bad.jsonl"): ("rejected", "bad")}
    assert result["summary"]["ok"] is False

    manifest = json.loads((ds / MANIFEST).read_text())
    [entry] = manifest["episodes"]
    assert entry["episode_id"] == "good" and entry["steps"] == 4 and entry["imagined"] is False
    assert entry["source"] == str(src / "good.json") and len(entry["content_sha256"]) == 64
    [rejected] = manifest["rejected"]
    assert rejected["source"] == str(src / "bad.jsonl")
    assert any("step 1: action.command[1]: nan is not a finite number" in r for r in rejected["reasons"])
    assert manifest["counts"] == {"episodes": 1, "steps": 4, "imagined": 0, "rejected": 1, "skipped": 0}
    assert sorted(p.name for p in ds.iterdir()) == ["good", MANIFEST]

    before = tree(ds)
    again = ingest_paths([src], ds)
    assert [e["action"] for e in again["episodes"] if e["episode_id"] == "good"] == ["unchanged"]
    assert again["summary"]["manifest_written"] is False
    assert tree(ds) == before


def test_sources_under_a_temporary_dir_are_recorded_under_its_name(tmp_path: Path):
    # an upload is extracted to a temp dir that is gone afterwards: the manifest and the answer
    # name the package instead, and a prefix-sharing dir is left alone
    src = tmp_path / "tmp" / "package-ab12"
    single_json(src / "good.json", "good", steps_10hz(4))
    nan_steps = steps_10hz(3)
    (src / "bad.jsonl").write_text("\n".join(json.dumps(s) for s in nan_steps[:1]) + "\n" +
                                   json.dumps(nan_steps[1]).replace("0.2]", "NaN]") + "\n")
    single_json(tmp_path / "tmp" / "package-ab123" / "other.json", "other", steps_10hz(5))
    ds = tmp_path / "ds"
    result = ingest_paths([src, tmp_path / "tmp" / "package-ab123"], ds, sources_as=(str(src), "upload:ep.zip"))
    sources = sorted(e["source"] for e in result["episodes"])
    assert sources == sorted(["upload:ep.zip/good.json", "upload:ep.zip/bad.jsonl",
                              str(tmp_path / "tmp" / "package-ab123" / "other.json")])
    manifest = json.loads((ds / MANIFEST).read_text())
    assert {e["source"] for e in manifest["episodes"]} == {"upload:ep.zip/good.json",
                                                            str(tmp_path / "tmp" / "package-ab123" / "other.json")}
    [rejected] = manifest["rejected"]
    assert rejected["source"] == "upload:ep.zip/bad.jsonl"
    for text in (json.dumps(manifest), json.dumps(result)):
        assert str(src) + "/" not in text and str(src) + ":" not in text


def test_clashing_ids_get_a_content_hash_suffix(tmp_path: Path):
    first = single_json(tmp_path / "a" / "run.json", "run", steps_10hz(3))
    second = single_json(tmp_path / "b" / "run.json", "run", steps_10hz(3, command=[0.5, 0.5]))
    ds = tmp_path / "ds"
    result = ingest_paths([first, second], ds)
    ids = [e["episode_id"] for e in result["episodes"]]
    manifest = json.loads((ds / MANIFEST).read_text())
    digest = {e["source"]: e["content_sha256"] for e in manifest["episodes"]}[str(second)]
    assert ids == ["run", f"run-{digest[:8]}"]
    assert json.loads((ds / ids[1] / "metadata.json").read_text())["episode_id"] == ids[1]
    assert {e["episode_id"]: e.get("source_episode_id") for e in manifest["episodes"]} == \
        {"run": None, ids[1]: "run"}

    # The same input again, in either order, finds both by content and writes nothing.
    before = tree(ds)
    again = ingest_paths([second, first], ds)
    assert [(e["episode_id"], e["action"]) for e in again["episodes"]] == \
        [(ids[1], "unchanged"), ("run", "unchanged")]
    assert tree(ds) == before


def test_same_content_under_another_id_or_from_the_dataset_itself_is_not_duplicated(tmp_path: Path):
    first = single_json(tmp_path / "a" / "run.json", "run", steps_10hz(3))
    second = single_json(tmp_path / "b" / "run.json", "run", steps_10hz(3, command=[0.5, 0.5]))
    copy = tmp_path / "c" / "renamed.json"
    copy.parent.mkdir()
    copy.write_text(first.read_text().replace('"episode_id": "run"', '"episode_id": "renamed"'))
    ds = tmp_path / "ds"
    result = ingest_paths([first, second, copy], ds)
    assert [e["action"] for e in result["episodes"]] == ["written", "written", "duplicate"]
    assert result["episodes"][2]["episode_id"] == "run"
    before = tree(ds)
    # Reading the dataset's own dirs back (suffixed id included) finds every episode already there.
    again = ingest_paths([ds], ds)
    assert {e["action"] for e in again["episodes"]} <= {"unchanged", "duplicate"}
    assert len(again["episodes"]) == 2
    assert tree(ds) == before


def test_a_lost_manifest_does_not_duplicate_episodes(tmp_path: Path):
    first = single_json(tmp_path / "a" / "run.json", "run", steps_10hz(3))
    second = single_json(tmp_path / "b" / "run.json", "run", steps_10hz(3, command=[0.5, 0.5]))
    ds = tmp_path / "ds"
    ingest_paths([first, second], ds)
    manifest_text = (ds / MANIFEST).read_text()
    dirs = sorted(p.name for p in ds.iterdir() if p.is_dir())
    (ds / MANIFEST).unlink()  # as if the previous run died after its episodes, before its manifest
    (ds / ".tmp-run-deadbeef").mkdir()  # and a half-written dir of a crashed write
    result = ingest_paths([first, second], ds)
    assert [e["action"] for e in result["episodes"]] == ["unchanged", "unchanged"]
    assert sorted(p.name for p in ds.iterdir() if p.is_dir()) == dirs
    assert (ds / MANIFEST).read_text() == manifest_text


def test_ingested_dataset_validates_and_keeps_blobs_and_imagined_flag(tmp_path: Path):
    src = tmp_path / "src"
    (src / "frames").mkdir(parents=True)
    (src / "frames" / "0.png").write_bytes(b"frame")
    steps = steps_10hz(3, media={"rgb": {"uri": "frames/0.png"}})
    single_json(src / "dream.json", "dream", steps,
                {"provenance": {"origin": "imagined:mid_loop"}, "tags": ["continuon.imagined"]})
    ds = tmp_path / "ds"
    ingest_paths([src], ds)
    assert (ds / "dream" / "blobs" / "frames" / "0.png").read_bytes() == b"frame"
    assert json.loads((ds / MANIFEST).read_text())["episodes"][0]["imagined"] is True
    report = validate_paths([ds], "train")
    [entry] = report["episodes"]
    assert (entry["episode_id"], entry["status"], entry["errors"], entry["warnings"]) == \
        ("dream", "accepted", [], [])


def test_a_foreign_manifest_is_not_overwritten(tmp_path: Path):
    ds = tmp_path / "ds"
    ds.mkdir()
    (ds / MANIFEST).write_text('{"name": "someone else\'s"}')
    single_json(tmp_path / "a.json", "a", steps_10hz(2))
    with pytest.raises(IngestError, match="not a dataset manifest"):
        ingest_paths([tmp_path / "a.json"], ds)
    assert (ds / MANIFEST).read_text() == '{"name": "someone else\'s"}'


def test_missing_source_is_a_usage_error(tmp_path: Path):
    with pytest.raises(FileNotFoundError, match="nope"):
        ingest_paths([tmp_path / "nope"], tmp_path / "ds")
    assert not (tmp_path / "ds").exists()


# -- the real samples ---------------------------------------------------------------------------

def test_ingesting_the_samples_twice_changes_nothing(samples_dir: Path, tmp_path: Path):
    ds = tmp_path / "ds"
    first = ingest_paths([samples_dir], ds)
    actions = [e["action"] for e in first["episodes"]]
    assert actions.count("rejected") == 0, [e for e in first["episodes"] if e["action"] == "rejected"]
    written = [e for e in first["episodes"] if e["action"] == "written"]
    manifest = json.loads((ds / MANIFEST).read_text())
    assert manifest["counts"]["episodes"] == len(written) == len({e["episode_id"] for e in written})
    assert manifest["counts"]["skipped"] == actions.count("skipped")
    assert len([s for s in manifest["skipped"] if "autonomous_learning" in s["source"]]) == 16
    before = tree(ds)

    second = ingest_paths([samples_dir], ds)
    assert {e["action"] for e in second["episodes"]} <= {"unchanged", "skipped"}
    assert [e["episode_id"] for e in second["episodes"]] == [e["episode_id"] for e in first["episodes"]]
    assert tree(ds) == before

    # What ingest wrote passes the train profile (warnings allowed) and reads back as canonical.
    report = validate_paths([ds], "train")
    assert report["summary"]["ok"] is True and report["summary"]["rejected"] == 0
    assert report["summary"]["episodes"] == len(written)
    assert {e["episode_id"] for e in report["episodes"]} == {e["episode_id"] for e in written}
    steps = {e["episode_id"]: e["steps"] for e in written}
    assert {e["episode_id"]: e["steps"] for e in report["episodes"]} == steps
    # The corrupt .tfrecord.gz episodes remember, in the canonical copy, that steps were lost.
    recovered = {e["episode_id"] for e in written if e["source"].endswith(".tfrecord.gz")}
    assert len(recovered) == 3
    for entry in report["episodes"]:
        lost_warning = any("metadata.provenance.steps_lost: 1 step(s)" in w for w in entry["warnings"])
        assert lost_warning == (entry["episode_id"] in recovered), entry


# -- key order, and manifests written before hashes sorted keys -----------------------------------

def test_key_order_and_camel_case_do_not_make_another_episode(tmp_path: Path):
    first = single_json(tmp_path / "a" / "run.json", "run", steps_10hz(4))
    doc = json.loads(first.read_text())

    def shuffled(obj):  # every object's keys reversed; step keys camelCased where they have a '_'
        if isinstance(obj, dict):
            return {k: shuffled(v) for k, v in reversed(list(obj.items()))}
        return [shuffled(v) for v in obj] if isinstance(obj, list) else obj

    other = shuffled(doc)
    for step in other["steps"]:
        step["isTerminal"] = step.pop("is_terminal")
        step["observation"]["robotState"] = step["observation"].pop("robot_state")
    second = tmp_path / "b" / "run.json"
    second.parent.mkdir()
    second.write_text(json.dumps(other))
    ds = tmp_path / "ds"
    result = ingest_paths([first, second], ds)
    assert [e["action"] for e in result["episodes"]] == ["written", "unchanged"]
    assert sorted(p.name for p in ds.iterdir() if p.is_dir()) == ["run"]


def legacy_hash(ep) -> str:
    """The content hash as ingest computed it before keys were sorted (the old code, verbatim)."""
    prepared = prepare_episode(ep)
    digest = hashlib.sha256()
    anonymous = {k: v for k, v in prepared.metadata.items() if k != "episode_id"}
    digest.update(json.dumps(anonymous, indent=2, ensure_ascii=False, allow_nan=False).encode("utf-8"))
    digest.update("".join(json.dumps(s, ensure_ascii=False, allow_nan=False, separators=(",", ":")) + "\n"
                          for s in prepared.steps).encode("utf-8"))
    digest.update(json.dumps(prepared.blob_sha256, sort_keys=True).encode("utf-8"))
    return digest.hexdigest()


def test_a_manifest_with_legacy_hashes_still_finds_its_episodes(tmp_path: Path):
    from hope_models.rlds.discover import read_path

    first = single_json(tmp_path / "a" / "run.json", "run", steps_10hz(3))
    second = single_json(tmp_path / "b" / "run.json", "run", steps_10hz(3, command=[0.5, 0.5]))
    ds = tmp_path / "ds"
    ingest_paths([first, second], ds)
    manifest = json.loads((ds / MANIFEST).read_text())
    new = {}
    for record in manifest["episodes"]:  # as an earlier version wrote it
        (ep,) = read_path(record["source"])[0].episodes
        new[record["episode_id"]] = record["content_sha256"]
        record["content_sha256"] = legacy_hash(ep)
        assert record.pop("hash_version") == 2 and record["content_sha256"] != new[record["episode_id"]]
    (ds / MANIFEST).write_text(json.dumps(manifest))
    dirs = sorted(p.name for p in ds.iterdir() if p.is_dir())

    again = ingest_paths([second, first], ds)
    assert [e["action"] for e in again["episodes"]] == ["unchanged", "unchanged"]
    assert sorted(p.name for p in ds.iterdir() if p.is_dir()) == dirs  # no -<hash> copy
    upgraded = {r["episode_id"]: r for r in json.loads((ds / MANIFEST).read_text())["episodes"]}
    assert {k: (r["content_sha256"], r["hash_version"]) for k, r in upgraded.items()} == \
        {k: (h, 2) for k, h in new.items()}


def test_extra_record_keys_survive_a_rewrite_of_the_manifest(tmp_path: Path):
    first = single_json(tmp_path / "a" / "run.json", "run", steps_10hz(3))
    ds = tmp_path / "ds"
    ingest_paths([first], ds)
    manifest = json.loads((ds / MANIFEST).read_text())
    manifest["episodes"][0].update(tags=["kept"], trainable=["vqvae"])
    (ds / MANIFEST).write_text(json.dumps(manifest))
    second = single_json(tmp_path / "b" / "other.json", "other", steps_10hz(3, command=[0.5, 0.5]))
    assert ingest_paths([second, first], ds)["summary"]["written"] == 1
    records = {r["episode_id"]: r for r in json.loads((ds / MANIFEST).read_text())["episodes"]}
    assert records["run"]["tags"] == ["kept"] and records["run"]["trainable"] == ["vqvae"]
