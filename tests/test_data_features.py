"""Feature spec inference, overrides and per-episode exclusion (hope_models.data.features)."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from hope_models.data.cache import CacheError, load_or_build
from hope_models.data.features import FeatureSpec, FeatureSpecError
from hope_models.data.spec_request import SpecRequest, spec_from_json_obj
from hope_models.rlds.discover import read_path

REPO = Path(__file__).resolve().parents[1]


from hope_models.data import synthetic as gen  # noqa: E402


def _raw_steps(dataset: Path) -> list[dict]:
    steps = []
    for f in sorted(dataset.glob("*/steps/*.jsonl")):
        steps += [json.loads(line) for line in f.read_text().splitlines() if line.strip()]
    return steps


def test_inferred_spec_on_generated_data(tmp_path):
    ds = tmp_path / "ds"
    gen.generate_dataset(ds, 3000, obs_dim=8, act_dim=3, seed=3, episode_seconds=(5, 10))
    cache, _ = load_or_build(ds, tmp_path / "cache")
    spec = cache.spec
    assert [(f.path, f.size) for f in spec.observation.fields] == [
        ("observation.robot_state.joint_positions", 4), ("observation.robot_state.joint_velocities", 4)]
    assert [(f.path, f.size) for f in spec.action.fields] == [("action.command", 3)]
    assert spec.frame is None
    # the clock inside robot_state is a number but must never become a feature
    assert not any("timestamp" in f.path for f in spec.all_fields())
    raw = _raw_steps(ds)
    obs = np.array([s["observation"]["robot_state"]["joint_positions"] + s["observation"]["robot_state"]["joint_velocities"]
                    for s in raw])
    act = np.array([s["action"]["command"] for s in raw])
    np.testing.assert_allclose(spec.observation.mean, obs.mean(axis=0), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(spec.observation.std, np.maximum(obs.std(axis=0), spec.std_floor), rtol=1e-4)
    np.testing.assert_allclose(spec.action.mean, act.mean(axis=0), rtol=1e-5, atol=1e-6)


def _step(t_ns: int, joints: list, command, **obs_extra) -> dict:
    return {"timestamp_ns": t_ns, "observation": {"robot_state": {"joint_positions": joints}, **obs_extra},
            "action": {"command": command}}


def test_mixed_sizes_are_excluded_with_reason(tmp_path):
    ds = tmp_path / "ds"
    for e in range(19):
        gen.write_episode(ds, f"good_{e:02d}", [_step(i * 10**8, [0.1 * i, e, 1.0, 2.0], [0.5, -0.5]) for i in range(5)])
    gen.write_episode(ds, "odd_joints", [_step(i * 10**8, [0.0, 1.0, 2.0], [0.5, -0.5]) for i in range(5)])
    cache, _ = load_or_build(ds, tmp_path / "cache")
    assert [(f.path, f.size) for f in cache.spec.observation.fields] == [("observation.robot_state.joint_positions", 4)]
    assert cache.n_episodes == 19 and "odd_joints" not in cache.episode_ids
    (excluded,) = cache.manifest["excluded"]
    assert excluded["episode_id"] == "odd_joints"
    assert excluded["reason"] == "step 0: observation.robot_state.joint_positions: has 3 values, the spec needs 4"


def test_field_missing_from_too_many_episodes_is_left_out_with_a_note(tmp_path):
    ds = tmp_path / "ds"
    for e in range(10):
        extra = {"gaze": {"confidence": 0.9}} if e < 5 else {}
        gen.write_episode(ds, f"ep{e}", [_step(i * 10**8, [1.0, 2.0], [0.1], **extra) for i in range(3)])
    cache, _ = load_or_build(ds, tmp_path / "cache")
    assert [f.path for f in cache.spec.observation.fields] == ["observation.robot_state.joint_positions"]
    assert any(n.startswith("observation.gaze.confidence: left out, present with one length in 5 of 10")
               for n in cache.spec.notes)


def test_nan_and_missing_fields_exclude_the_episode_naming_step_and_field(tmp_path):
    ds = tmp_path / "ds"
    for e in range(20):
        gen.write_episode(ds, f"ep{e:02d}", [_step(i * 10**8, [1.0, float(i)], [0.1]) for i in range(4)])
    bad = tmp_path / "ds" / "ep03" / "steps" / "000000.jsonl"
    lines = bad.read_text().splitlines()
    lines[2] = lines[2].replace('"joint_positions": [1.0, 2.0]', '"joint_positions": [1.0, NaN]')
    bad.write_text("\n".join(lines) + "\n")
    gone = tmp_path / "ds" / "ep07" / "steps" / "000000.jsonl"
    lines = gone.read_text().splitlines()
    obj = json.loads(lines[3])
    del obj["observation"]["robot_state"]["joint_positions"]
    obj["observation"]["robot_state"]["other"] = 1  # the first and last steps must still differ only here
    lines[3] = json.dumps(obj)
    gone.write_text("\n".join(lines) + "\n")
    cache, _ = load_or_build(ds, tmp_path / "cache")
    reasons = {e["episode_id"]: e["reason"] for e in cache.manifest["excluded"]}
    assert reasons == {
        "ep03": "step 2: observation.robot_state.joint_positions: value is NaN or infinite",
        "ep07": "step 3: observation.robot_state.joint_positions: missing",
    }
    assert cache.n_episodes == 18 and np.isfinite(cache.x).all()


def test_legacy_named_scalars_and_tagged_actions(tmp_path):
    legacy = tmp_path / "legacy"
    for e in range(3):
        gen.write_episode(legacy, f"car{e}", [{"timestamp_ns": i * 10**8, "observation": {"pose": [0.0, 1.0, 2.0]},
                                                "action": {"steering": 0.1 * i, "throttle": 0.5, "source": "pilot"}}
                                               for i in range(4)])
    cache, _ = load_or_build(legacy, tmp_path / "c1")
    assert [(f.path, f.size) for f in cache.spec.action.fields] == [("action.steering", 1), ("action.throttle", 1)]
    np.testing.assert_allclose(cache.act[:4], [[0.0, 0.5], [0.1, 0.5], [0.2, 0.5], [0.3, 0.5]], rtol=1e-6)

    tagged = tmp_path / "tagged"
    for e in range(3):
        gen.write_episode(tagged, f"xr{e}", [{
            "timestamp_ns": i * 5 * 10**7, "observation": {"robot_state": {"joint_positions": [0.0, 0.2]}},
            "action": {"type": "EndEffectorVelocity", "linear_mps": {"x": 0.1, "y": 0.0, "z": -0.1},
                       "angular_rad_s": {"x": 0.0, "y": 0.0, "z": 0.3}}} for i in range(3)])
    cache, _ = load_or_build(tagged, tmp_path / "c2")
    assert [f.path for f in cache.spec.action.fields] == [
        "action.angular_rad_s.x", "action.angular_rad_s.y", "action.angular_rad_s.z",
        "action.linear_mps.x", "action.linear_mps.y", "action.linear_mps.z"]


SAMPLE_TFRECORDS = "rlds"  # vlm_tfrecord (7 joints, image_rgb) + wiki_tfrecord (128 joints)


def test_sample_tfrecords_with_override_exclude_other_sizes(tmp_path, samples_dir):
    # Real producer files: 20 one-step VLM episodes (7 joints) and 50 wiki episodes (128 joints).
    with pytest.raises(FeatureSpecError, match="no numeric observation field .* best candidates: "
                                               r"observation.robot_state.joint_positions \(128 values in 50"):
        load_or_build(samples_dir / SAMPLE_TFRECORDS, tmp_path / "cache")
    override = tmp_path / "spec.json"
    override.write_text(json.dumps({"observation": {"fields": ["observation.robot_state.joint_positions"]},
                                    "action": {"fields": ["action.command"]}}))
    cache, _ = load_or_build(samples_dir / SAMPLE_TFRECORDS, tmp_path / "cache", spec_path=override)
    assert (cache.spec.obs_dim, cache.spec.act_dim) == (128, 32)
    assert cache.n_episodes == 50
    assert len(cache.manifest["excluded"]) == 20
    assert all(e["episode_id"].startswith("vlm_")
               and e["reason"] == "step 0: observation.robot_state.joint_positions: has 7 values, the spec needs 128"
               for e in cache.manifest["excluded"])
    assert any(n.startswith("observation.image_rgb: no frame feature") for n in cache.spec.notes)


def test_sample_vlm_frames_become_a_uint8_frame_feature(tmp_path, samples_dir):
    src = samples_dir / "rlds" / "vlm_tfrecord"
    cache, _ = load_or_build(src, tmp_path / "cache")
    assert cache.spec.frame is not None and cache.spec.frame.path == "observation.image_rgb"
    assert cache.frames.shape == (20, 64, 64, 3) and cache.frames.dtype == np.uint8
    assert [f.path for f in cache.spec.observation.fields] == ["observation.robot_state.joint_positions"]
    episodes = {ep.episode_id: ep for r in read_path(src) for ep in r.episodes}
    for i, eid in enumerate(cache.episode_ids):
        image = np.asarray(episodes[eid].steps[0].observation["image_rgb"], dtype=np.float32)
        expected = np.rint(image * 255).astype(np.uint8).reshape(64, 64, 3)
        assert np.array_equal(cache.frames[cache.offsets[i]], expected)


def test_spec_json_roundtrip_and_given_stats_are_kept(tmp_path):
    ds = tmp_path / "ds"
    gen.generate_dataset(ds, 400, obs_dim=4, act_dim=2, episode_seconds=(5, 10))
    cache, _ = load_or_build(ds, tmp_path / "c")
    again = spec_from_json_obj(json.loads(cache.spec.to_json()))
    assert again.to_json_obj() == cache.spec.to_json_obj()
    override = tmp_path / "spec.json"
    override.write_text(json.dumps({
        "observation": {"fields": [{"path": "observation.robot_state.joint_positions", "size": 2}],
                        "mean": [1.0, -1.0], "std": [2.0, 0.0000001]},
        "action": {"fields": [{"path": "action.command", "size": 2}]},
        "frame": None}))
    assert not SpecRequest.load(override).needs_inference
    c2, info = load_or_build(ds, tmp_path / "c", spec_path=override)
    assert not info.reused and info.fingerprint != cache.fingerprint
    assert c2.spec.observation.mean == [1.0, -1.0]
    assert c2.spec.observation.std == [2.0, c2.spec.std_floor]  # floored
    assert c2.spec.action.mean == pytest.approx(cache.spec.action.mean)  # recomputed


@pytest.mark.parametrize("content, message", [
    ("{not json", "not valid JSON"),
    ('{"observation": {"fields": []}}', "observation: needs a non-empty 'fields' list"),
    ('{"observation": {"fields": ["action.command"]}}', "must start with 'observation.'"),
    ('{"observation": {"fields": [{"path": "observation.a", "size": 2}], "mean": [0], "std": [1]}}',
     "mean has 1 values, the fields make 2"),
    ('{"std_floor": 0}', "std_floor must be a positive number"),
    ('{"colour": "red"}', "unknown keys"),
])
def test_bad_spec_files_are_named_in_the_error(tmp_path, content, message):
    bad = tmp_path / "bad_spec.json"
    bad.write_text(content)
    with pytest.raises(FeatureSpecError) as info:
        SpecRequest.load(bad)
    assert str(bad) in str(info.value) and message in str(info.value)


def test_episode_without_clock_is_excluded(tmp_path):
    ds = tmp_path / "ds"
    for e in range(10):
        gen.write_episode(ds, f"ep{e}", [_step(i * 10**8, [1.0], [0.1]) for i in range(3)])
    gen.write_episode(ds, "no_clock", [{"observation": {"robot_state": {"joint_positions": [1.0]}},
                                        "action": {"command": [0.1]}} for _ in range(3)])
    cache, _ = load_or_build(ds, tmp_path / "c")
    reasons = {e["episode_id"]: e["reason"] for e in cache.manifest["excluded"]}
    assert "no_clock" in reasons and "timestamp" in reasons["no_clock"]
    assert cache.n_episodes == 10


def test_nothing_fits_is_a_clear_error(tmp_path):
    ds = tmp_path / "ds"
    gen.write_episode(ds, "only", [{"timestamp_ns": 0, "observation": {"note": "text only"}, "action": {"command": [1.0]}}])
    with pytest.raises(FeatureSpecError, match="no numeric observation field"):
        load_or_build(ds, tmp_path / "c")
    with pytest.raises(CacheError, match="dataset dir not found"):
        load_or_build(tmp_path / "missing", tmp_path / "c")
