"""Unpaired UTF-16 surrogates (Dart strings; undecodable file names) are kept everywhere.

Dart's jsonEncode writes a lone surrogate as `\\udXXX`; json.loads hands back a str holding it,
which UTF-8 cannot encode. Every writer goes through json_text.json_dumps, which writes it back as
the same escape: the file is valid UTF-8 and reads back to the same str. One test per path:
validate, ingest (write + hash + manifest), export, MCAP, TFRecord, the webapp's JSON answers and
the commands' `--json` output.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import tarfile
from pathlib import Path

import pytest

from hope_models.rlds.discover import read_path
from hope_models.rlds.export_cloud import export_paths
from hope_models.rlds.ingest import MANIFEST, ingest_paths
from hope_models.rlds.json_text import escape_surrogates, json_dumps
from hope_models.rlds.read_mcap import read_mcap
from hope_models.rlds.read_tfrecord import read_tfrecord
from hope_models.rlds.validation_report import validate_paths
from hope_models.rlds.write_mcap import write_episode_mcap
from hope_models.rlds.write_tfrecord import episode_to_examples, write_tfrecord

REPO = Path(__file__).resolve().parents[1]
NOTE = "half an emoji \ud83d and a low half \udc00"
KEY = "k\udfff"


def episode_doc(n: int = 4) -> dict:
    return {"metadata": {"episode_id": "sur", "xr_mode": "trainer", "control_role": "human_teleop",
                         "environment_id": "lab", "tags": [NOTE], "software": {"xr_app": "1"}},
            "steps": [{"observation": {"robot_state": {"joint_positions": [0.1 * i, 0.2]}, "note": NOTE,
                                       KEY: "v"},
                       "action": {"command": [0.5, -0.5], "source": "human_teleop_xr"},
                       "timestamp_ns": 1_000_000_000 + i * 100_000_000, "is_terminal": i == n - 1}
                      for i in range(n)]}


@pytest.fixture
def source(tmp_path: Path) -> Path:
    """An episode file with lone surrogates in values and a key, under a name that is not UTF-8."""
    src = tmp_path / "src"
    src.mkdir()
    name = os.fsdecode(b"ep\xff.json")  # "ep\udcff.json": the file system's bytes, surrogate-escaped
    path = src / name
    path.write_text(json.dumps(episode_doc()), encoding="ascii")  # \udXXX escapes, as Dart writes them
    return path


def test_the_one_function_escapes_lone_surrogates_and_keeps_pairs():
    obj = {KEY: [NOTE, "😀"]}
    text = json_dumps(obj)
    assert "\\ud83d" in text and "\\udfff" in text and "😀" in text
    text.encode("utf-8")
    assert json.loads(text) == obj
    assert escape_surrogates("a\ud800b") == "a\\ud800b" and escape_surrogates("plain") == "plain"


def test_validate_keeps_the_episode(source: Path):
    report = validate_paths([source])
    (entry,) = report["episodes"]
    assert entry["ok"] and entry["source"] == str(source)
    (ep,) = read_path(source)[0].episodes
    assert ep.steps[0].observation["note"] == NOTE and ep.steps[0].observation[KEY] == "v"


def test_ingest_writes_valid_utf8_hashes_stably_and_records_the_source(source: Path, tmp_path: Path):
    ds = tmp_path / "ds"
    first = ingest_paths([source], ds)
    assert first["summary"]["written"] == 1, first
    ep_dir = ds / first["episodes"][0]["episode_id"]
    for f in (ep_dir / "metadata.json", ep_dir / "steps" / "000000.jsonl", ds / MANIFEST):
        f.read_bytes().decode("utf-8")  # strict: raises on a raw surrogate
    (back,) = read_path(ep_dir)[0].episodes
    assert back.steps[2].observation["note"] == NOTE and back.metadata["tags"] == [NOTE]
    manifest = json.loads((ds / MANIFEST).read_text(encoding="utf-8"))
    assert manifest["episodes"][0]["source"] == str(source)  # the surrogate-escaped name, kept
    again = ingest_paths([source], ds)
    assert again["summary"]["unchanged"] == 1 and again["summary"]["written"] == 0
    assert ingest_paths([ep_dir], ds)["summary"]["written"] == 0  # the written dir hashes the same


def test_export_package_is_valid_utf8(source: Path, tmp_path: Path):
    result = export_paths([source], tmp_path / "out", allow_invalid=True)
    (entry,) = result["episodes"]
    assert entry["action"] == "exported", entry
    with tarfile.open(entry["package"]) as tar:
        member = next(m for m in tar.getmembers() if m.name.endswith("episode.json"))
        doc = json.loads(tar.extractfile(member).read().decode("utf-8"))
    assert doc["steps"][0]["observation"]["note"] == NOTE


def test_mcap_round_trip(source: Path, tmp_path: Path):
    (ep,) = read_path(source)[0].episodes
    out = write_episode_mcap(ep, tmp_path / "ep.mcap")
    (back,) = read_mcap(out).episodes
    assert back.steps[1].observation["note"] == NOTE and back.steps[1].observation[KEY] == "v"
    assert back.metadata["tags"] == [NOTE]


def test_tfrecord_round_trip(source: Path, tmp_path: Path):
    (ep,) = read_path(source)[0].episodes
    ep.episode_id = "id\ud800"
    out = write_tfrecord(tmp_path / "ep.tfrecord", episode_to_examples(ep))
    (back,) = read_tfrecord(out).episodes
    assert back.steps[3].observation["note"] == NOTE
    assert back.episode_id == "id\\ud800"  # a plain-text feature keeps it as its escape


def test_webapp_json_answers_are_valid_utf8():
    from flask import Flask

    from webapp.json_provider import FiniteJSONProvider

    app = Flask("t")
    app.json = FiniteJSONProvider(app)
    for ensure_ascii in (True, False):
        app.json.ensure_ascii = ensure_ascii
        with app.app_context():
            body = app.json.response({"note": NOTE, KEY: 1}).get_data()
        assert json.loads(body.decode("utf-8")) == {"note": NOTE, KEY: 1}


@pytest.mark.parametrize("command", ["validate", "ingest", "export"])
def test_json_output_of_the_commands_is_valid_utf8(source: Path, tmp_path: Path, command: str):
    extra = {"validate": [], "ingest": ["--into", str(tmp_path / "ds")],
             "export": ["--cloud", "--out", str(tmp_path / "out"), "--allow-invalid"]}[command]
    args = [str(source)] if command != "export" else []
    argv = [sys.executable, "-m", "hope_trainer", command, *args, *extra, "--json"]
    if command == "export":
        argv.insert(argv.index("--out"), str(source))
    env = dict(os.environ, HOPE_HOME=str(tmp_path / "home"), PYTHONIOENCODING="utf-8")
    done = subprocess.run(argv, cwd=REPO, env=env, capture_output=True, timeout=120)
    assert done.returncode == 0, done.stderr.decode("utf-8", "replace")
    doc = json.loads(done.stdout.decode("utf-8"))
    assert str(source) in json.dumps(doc, ensure_ascii=False)



def test_a_file_holding_a_lone_surrogates_own_bytes_is_read(tmp_path: Path):
    # ED A0 BD is how older Dart, Java's modified UTF-8 or CESU-8 write U+D83D: not valid UTF-8,
    # but one lost character must not cost the episode
    path = tmp_path / "raw.json"
    path.write_bytes(json.dumps(episode_doc(), ensure_ascii=False).encode("utf-8", "surrogatepass"))
    assert b"\xed\xa0\xbd" in path.read_bytes()
    [report] = read_path(path)
    assert len(report.episodes) == 1, [p.message for p in report.problems]
    assert report.episodes[0].steps[0].observation["note"] == NOTE
    # still refused: bytes that are no text at all, with the offset named
    bad = tmp_path / "bad.json"
    bad.write_bytes(b'{"metadata": {"episode_id": "\xff\xfe"}, "steps": []}')
    [refused] = read_path(bad)
    assert not refused.episodes and any("offset" in p.message for p in refused.problems)
