"""The inbox library (hope_models/data/inbox.py) and what an episode can train (data/trainable.py).

- ingest_into_inbox: tags, origin, trainable / not_trainable in the entries and the manifest;
  confined blobs (an absolute or file:// URI is never copied, a relative one inside the episode is);
  the same input again writes nothing;
- list_inbox: accepted and rejected episodes, with the statuses the API shows;
- tag_episode: kept once, in the manifest only (the content hash and dedupe do not move), 400/404;
- the flock: ingests from several processes at once lose no record;
- trainable: an episode called trainable for fast_loop builds a dataset cache and a fast_loop
  configuration; short, action-less and frame-only episodes say why not.
"""
from __future__ import annotations

import json
import multiprocessing
from pathlib import Path

import numpy as np
import pytest

from hope_models.intake.inbox import InboxError, ingest_into_inbox, ingest_record, list_inbox, tag_episode
from hope_models.intake.trainable import trainable, trainable_json
from hope_models.rlds.discover import read_path
from hope_models.rlds.ingest import MANIFEST


def steps(n: int, *, act: list | None = None, obs: bool = True, period_ns: int = 100_000_000, **extra) -> list:
    out = []
    for i in range(n):
        observation = {"robot_state": {"joint_positions": [0.1 * i, -0.1 * i, 0.3]}} if obs else {}
        observation.update(extra)
        out.append({"observation": observation,
                    "action": {"command": [0.2, -0.1] if act is None else act, "source": "human_teleop_xr"},
                    "timestamp_ns": 1_000_000_000 + i * period_ns, "is_terminal": i == n - 1})
    return out


def episode_file(path: Path, episode_id: str, step_list: list) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    meta = {"episode_id": episode_id, "xr_mode": "trainer", "control_role": "human_teleop",
            "environment_id": "lab", "tags": ["t"], "software": {"xr_app": "1"}}
    path.write_text(json.dumps({"metadata": meta, "steps": step_list}))
    return path


def manifest(inbox: Path) -> dict:
    return json.loads((inbox / MANIFEST).read_text())


def test_ingest_records_tags_origin_and_what_each_episode_trains(tmp_path: Path):
    long = episode_file(tmp_path / "src" / "long.json", "long", steps(40))  # 3.9 s at 10 Hz
    short = episode_file(tmp_path / "src" / "short.json", "short", steps(3))
    inbox = tmp_path / "inbox"
    result = ingest_into_inbox([long, short], inbox, tags=["kitchen"], origin="upload")
    by_id = {e["episode_id"]: e for e in result["episodes"]}
    assert by_id["long"]["trainable"] == ["vqvae", "fast_loop", "mid_loop"] and by_id["long"]["not_trainable"] == {}
    assert by_id["short"]["trainable"] == ["vqvae"]
    assert "3 steps" in by_id["short"]["not_trainable"]["fast_loop"]
    assert by_id["short"]["tags"] == ["kitchen"] and by_id["short"]["origin"] == "upload"
    records = {r["episode_id"]: r for r in manifest(inbox)["episodes"]}
    assert records["long"]["trainable"] == ["vqvae", "fast_loop", "mid_loop"]
    assert records["short"]["tags"] == ["kitchen"] and records["short"]["origin"] == "upload"
    # the same input again: nothing written, the first origin kept, the new tag added once
    again = ingest_into_inbox([long], inbox, tags=["kitchen", "again"], origin="cli:ingest")
    assert again["episodes"][0]["action"] == "unchanged" and again["summary"]["written"] == 0
    assert again["episodes"][0]["origin"] == "upload" and again["episodes"][0]["tags"] == ["kitchen", "again"]


def test_blobs_are_confined_to_the_episode_dir(tmp_path: Path):
    secret = tmp_path / "secret.npy"
    np.save(secret, np.zeros((64, 64, 3), np.uint8))
    ep_dir = tmp_path / "src" / "ep"
    (ep_dir / "blobs").mkdir(parents=True)
    np.save(ep_dir / "blobs" / "f.npy", np.full((64, 64, 3), 7, np.uint8))
    step_list = steps(6)
    step_list[0]["observation"]["media"] = {"rgb": {"uri": str(secret)}}
    step_list[1]["observation"]["media"] = {"rgb": {"uri": f"file://{secret}"}}
    step_list[2]["observation"]["media"] = {"rgb": {"uri": "blobs/f.npy"}}
    step_list[3]["observation"]["media"] = {"rgb": {"uri": "../secret.npy"}}
    episode_file(ep_dir / "episode.json", "ep", step_list)
    inbox = tmp_path / "inbox"
    result = ingest_into_inbox([ep_dir / "episode.json"], inbox, origin="upload")
    (entry,) = result["episodes"]
    assert entry["action"] == "written"
    stored = sorted(p.relative_to(inbox / "ep").as_posix() for p in (inbox / "ep").rglob("*.npy"))
    assert stored == ["blobs/f.npy"]  # the relative one inside; neither the absolute nor the file://
    assert not any(str(secret) in w and "not found" in w for w in entry["warnings"])
    (ep,) = read_path(inbox / "ep")[0].episodes
    assert ep.steps[0].observation["media"]["rgb"]["uri"] == str(secret)  # kept, as text


def test_list_inbox_shows_accepted_and_rejected(tmp_path: Path):
    good = episode_file(tmp_path / "src" / "good.json", "good", steps(10))
    bad_steps = steps(10)
    bad_steps[4]["timestamp_ns"] = bad_steps[2]["timestamp_ns"]  # time runs backwards
    bad_steps[5]["action"]["command"] = [float("nan"), 0.0]
    bad = tmp_path / "src" / "bad.json"
    bad.write_text(json.dumps({"metadata": {"episode_id": "bad"}, "steps": bad_steps}))
    inbox = tmp_path / "inbox"
    ingest_into_inbox([good, bad], inbox, origin="upload")
    listed = {e["episode_id"]: e for e in list_inbox(inbox)}
    assert listed["good"]["status"] == "ok" and listed["good"]["steps"] == 10
    assert listed["good"]["source"] == str(good) and listed["good"]["origin"] == "upload"
    assert listed["bad"]["status"] == "rejected" and listed["bad"]["errors"]
    assert listed["bad"]["trainable"] == [] and listed["bad"]["origin"] == "upload"
    assert set(listed["good"]) == {"episode_id", "steps", "status", "errors", "warnings", "trainable",
                                   "not_trainable", "cameras", "reads", "tags", "source", "origin"}
    assert listed["good"]["cameras"] == [] and listed["good"]["reads"]["vqvae"].startswith("the observation vector")
    assert list_inbox(tmp_path / "nothing-here") == []


def test_tags_live_in_the_manifest_only(tmp_path: Path):
    src = episode_file(tmp_path / "src" / "ep.json", "ep", steps(10))
    inbox = tmp_path / "inbox"
    ingest_into_inbox([src], inbox, origin="upload")
    content = (inbox / "ep" / "metadata.json").read_bytes()
    digest = manifest(inbox)["episodes"][0]["content_sha256"]
    assert tag_episode(inbox, "ep", "wave")["tags"] == ["wave"]
    assert tag_episode(inbox, "ep", "wave")["tags"] == ["wave"]  # once
    assert (inbox / "ep" / "metadata.json").read_bytes() == content
    assert manifest(inbox)["episodes"][0]["content_sha256"] == digest
    assert ingest_into_inbox([src], inbox, origin="upload")["episodes"][0]["action"] == "unchanged"
    assert list_inbox(inbox)[0]["tags"] == ["wave"]
    # half an emoji, as Dart text may hold: kept, and the manifest stays valid UTF-8
    assert tag_episode(inbox, "ep", "hi \ud83d")["tags"] == ["wave", "hi \ud83d"]
    (inbox / "manifest.json").read_bytes().decode("utf-8")
    assert list_inbox(inbox)[0]["tags"] == ["wave", "hi \ud83d"]
    for bad in ("", "   ", "x" * 65, 7, None, "a\nb", "a\x7fb"):
        with pytest.raises(InboxError) as exc:
            tag_episode(inbox, "ep", bad)
        assert exc.value.status == 400
    with pytest.raises(InboxError) as exc:
        tag_episode(inbox, "nope", "wave")
    assert exc.value.status == 404
    with pytest.raises(InboxError) as exc:
        ingest_into_inbox([src], inbox, tags=[""], origin="upload")
    assert exc.value.status == 400


def test_errors_carry_their_status(tmp_path: Path):
    with pytest.raises(InboxError) as exc:
        ingest_into_inbox([tmp_path / "missing.json"], tmp_path / "inbox", origin="upload")
    assert exc.value.status == 400
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / MANIFEST).write_text('{"name": "someone else\'s"}')
    src = episode_file(tmp_path / "src" / "ep.json", "ep", steps(10))
    with pytest.raises(InboxError) as exc:
        ingest_into_inbox([src], foreign, origin="upload")
    assert exc.value.status == 409
    with pytest.raises(InboxError) as exc:
        ingest_record({"metadata": {}, "steps": "no"}, [], {}, tmp_path / "inbox")
    assert exc.value.status == 400 and "manifest.steps" in exc.value.message


def _ingest_one(args) -> str:
    src, inbox, tag = args
    return ingest_into_inbox([src], inbox, tags=[tag], origin="upload")["episodes"][0]["episode_id"]


def test_ingests_in_several_processes_at_once_lose_no_record(tmp_path: Path):
    inbox = tmp_path / "inbox"
    sources = [episode_file(tmp_path / "src" / f"e{i}.json", f"e{i}", steps(8, act=[0.1 * i, 0.0]))
               for i in range(6)]
    ctx = multiprocessing.get_context("spawn")
    with ctx.Pool(6) as pool:
        ids = pool.map(_ingest_one, [(s, inbox, f"tag{i}") for i, s in enumerate(sources)])
    assert sorted(ids) == [f"e{i}" for i in range(6)]
    records = {r["episode_id"]: r for r in manifest(inbox)["episodes"]}
    assert sorted(records) == sorted(ids)
    assert all(records[f"e{i}"]["tags"] == [f"tag{i}"] for i in range(6))


# -- what an episode can train --------------------------------------------------------------------

def test_an_episode_trainable_for_fast_loop_builds_a_cache_and_a_fast_loop_config(tmp_path: Path):
    from hope_models.data.cache import load_or_build
    from hope_models.components.resolve import resolve

    inbox = tmp_path / "inbox"
    src = episode_file(tmp_path / "src" / "ep.json", "ep", steps(30))
    (entry,) = ingest_into_inbox([src], inbox, origin="upload")["episodes"]
    assert "fast_loop" in entry["trainable"] and "vqvae" in entry["trainable"]
    cache, _ = load_or_build(inbox, tmp_path / "cache")
    assert cache.episode_ids == ["ep"] and cache.n_steps == 30
    fast = resolve("fast_loop", cache.spec, None)
    assert fast.cfg.obs_dim == 3 and fast.cfg.act_dim == 2
    resolve("vqvae", cache.spec, None)


def test_a_fast_loop_run_on_an_inbox_episode_called_trainable_completes(tmp_path: Path):
    pytest.importorskip("torch")
    from hope_models.train.loop import TrainConfig, train

    inbox = tmp_path / "inbox"
    src = episode_file(tmp_path / "src" / "ep.json", "ep", steps(5))  # the fewest it accepts
    (entry,) = ingest_into_inbox([src], inbox, origin="upload")["episodes"]
    assert "fast_loop" in entry["trainable"]
    cfg = TrainConfig(component="fast_loop", data=str(inbox), run_dir=str(tmp_path / "run"), steps=4, seed=1,
                      batch_size=4, threads=1, checkpoint_every_steps=4, log_every=1,
                      cache_dir=str(tmp_path / "cache"), thermal_zone=None, vcgencmd=None,
                      control_interval_s=0.0)
    assert train(cfg).outcome == "completed"


@pytest.mark.parametrize("make, component, why", [
    (lambda: steps(10, act=[]), "fast_loop", "action.command is always empty"),
    (lambda: steps(10, obs=False, pose={"label": "x"}), "vqvae", "no numeric observation"),
    (lambda: steps(4), "fast_loop", "4 steps; its window needs 5"),
    (lambda: steps(15), "mid_loop", "1.40 s long"),
])
def test_what_an_episode_cannot_train_says_why(tmp_path: Path, make, component, why):
    (ep,) = read_path(episode_file(tmp_path / "ep.json", "ep", make()))[0].episodes
    can, cannot = trainable(ep)
    assert component not in can
    assert why in cannot[component]


def test_frames_count_only_when_training_can_read_them(tmp_path: Path):
    ep_dir = tmp_path / "ep"
    (ep_dir / "blobs").mkdir(parents=True)
    np.save(ep_dir / "blobs" / "f.npy", np.full((64, 64, 3), 9, np.uint8))
    (ep_dir / "blobs" / "f.jpg").write_bytes(b"\xff\xd8 not a frame")
    frame = steps(10, media={"rgb": {"uri": "blobs/f.npy"}})
    (ep,) = read_path(episode_file(ep_dir / "episode.json", "ep", frame))[0].episodes
    assert "vqvae" in trainable(ep)[0]
    jpg = steps(10, act=[], obs=False, egocentric_video={"uri": "blobs/f.jpg", "timestamp_ms": 1})
    (ep,) = read_path(episode_file(ep_dir / "episode.json", "ep", jpg))[0].episodes
    can, cannot = trainable(ep)
    assert can == [] and "egocentric_video: 0/10 frames" in cannot["vqvae"]
    assert "not a known media file" in cannot["vqvae"]


def test_the_verdict_names_each_camera_and_what_the_tokenizer_reads(tmp_path: Path):
    from PIL import Image

    ep_dir = tmp_path / "ep"
    (ep_dir / "blobs").mkdir(parents=True)
    rng = np.random.default_rng(0)
    # the Continuon app writes a JPEG still into a .mp4-named file: the bytes decide, not the name
    Image.fromarray(rng.integers(0, 255, (480, 640, 3), np.uint8)).save(ep_dir / "blobs" / "ego.mp4", "JPEG")
    np.save(ep_dir / "blobs" / "d.npy", np.full((400, 640), 1500, np.uint16))
    (ep_dir / "blobs" / "empty.mp4").write_bytes(b"")
    cams = steps(40, egocentric_video={"uri": "blobs/ego.mp4"}, depth={"uri": "blobs/d.npy"},
                 wrist_rgb={"uri": "blobs/empty.mp4"})
    (ep,) = read_path(episode_file(ep_dir / "episode.json", "ep", cams))[0].episodes
    verdict = trainable_json(ep)
    assert verdict["trainable"] == ["vqvae", "fast_loop", "mid_loop"]
    assert verdict["cameras"] == ["depth: 40/40 frames, NPY 400x640 -> 64x64 (depth, metres)",
                                  "egocentric_video: 40/40 frames, JPEG 480x640 -> 64x64",
                                  "wrist_rgb: 0/40 frames; step 0: 'blobs/empty.mp4': empty file (0 bytes)"]
    reads = verdict["reads"]["vqvae"]
    assert reads.startswith("frame observation.egocentric_video (JPEG 480x640 -> 64x64); not usable: wrist_rgb")


def test_episodes_a_plain_ingest_put_in_the_inbox_still_get_a_verdict(tmp_path: Path):
    from hope_models.rlds.ingest import ingest_paths

    inbox = tmp_path / "inbox"
    ingest_paths([episode_file(tmp_path / "src" / "ep.json", "ep", steps(40))], inbox)  # the command line's way
    (entry,) = list_inbox(inbox)
    assert entry["trainable"] == ["vqvae", "fast_loop", "mid_loop"] and entry["origin"] is None
    other = episode_file(tmp_path / "src" / "other.json", "other", steps(3))
    ingest_into_inbox([other], inbox, origin="upload")
    assert manifest(inbox)["episodes"][0]["episode_id"] == "ep"
    assert "trainable" not in manifest(inbox)["episodes"][0]  # only what this ingest brought is annotated
