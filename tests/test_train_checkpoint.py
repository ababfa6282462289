"""Checkpoint files: atomic layout, manifest verification, keep-K, corrupt ones skipped, no pickle."""
from __future__ import annotations

import json
import os
import pickle
import subprocess
import sys
import warnings
from pathlib import Path

import pytest
import torch

from hope_models.durable import file_sha256
from hope_models import checkpoints as ckpt


def _save(run_dir: Path, step: int, keep_last: int = 3, value: float | None = None) -> Path:
    v = float(step) if value is None else value
    w = torch.full((3, 2), v)
    return ckpt.save_checkpoint(
        run_dir, step, model_state={"lin.weight": w, "lin.bias": torch.zeros(2), "tied": w},
        config={"component": "stand_in", "train": {"seed": 0}},
        state_tensors={"rng.torch": torch.get_rng_state(), "optim.0.exp_avg": torch.ones(3, 2) * v},
        state={"sampler": {"cursor": step}}, keep_last=keep_last)


def test_layout_manifest_and_pointer(tmp_path):
    path = _save(tmp_path, 7)
    assert path == tmp_path / "checkpoints" / "00000007"
    names = sorted(p.name for p in path.iterdir())
    assert names == ["config.json", "manifest.json", "model.safetensors", "training_state.json",
                     "training_state.safetensors"]
    manifest = json.loads((path / "manifest.json").read_text())
    assert set(manifest["files"]) == set(names) - {"manifest.json"}
    for name, entry in manifest["files"].items():
        assert (path / name).stat().st_size == entry["size"]
    assert (tmp_path / "checkpoints" / "last").read_text().strip() == "00000007"
    assert ckpt.verify(path) is None
    loaded = ckpt.load_checkpoint(path)
    assert loaded.step == 7 and loaded.state["sampler"] == {"cursor": 7}
    assert loaded.config["checkpoint"]["step"] == 7 and loaded.config["component"] == "stand_in"
    # shared storage (a tied weight) was written as two independent, equal tensors
    assert torch.equal(loaded.model["tied"], loaded.model["lin.weight"])
    rng = loaded.tensors["rng.torch"]
    assert rng.dtype == torch.uint8 and torch.equal(rng, torch.get_rng_state())  # nothing drew from it since
    assert not list((tmp_path / "checkpoints").glob(".tmp-*"))


def test_keep_last_k_deletes_older_only_after_new_one_is_durable(tmp_path):
    for step in (10, 20, 30, 40, 50):
        _save(tmp_path, step, keep_last=2)
    assert [s for s, _ in ckpt.list_step_dirs(tmp_path)] == [50, 40]
    assert ckpt.load_latest(tmp_path).step == 50


def test_truncated_newest_checkpoint_is_skipped_with_a_warning(tmp_path):
    _save(tmp_path, 10)
    newest = _save(tmp_path, 20)
    f = newest / "model.safetensors"
    f.write_bytes(f.read_bytes()[:-7])  # a torn write
    seen: list[str] = []
    loaded = ckpt.load_latest(tmp_path, warn=seen.append)
    assert loaded.step == 10 and float(loaded.model["lin.weight"][0, 0]) == 10.0
    assert len(seen) == 1 and str(newest) in seen[0] and "model.safetensors" in seen[0] and "truncated" in seen[0]
    # the default channel is a RuntimeWarning naming the dir
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        assert ckpt.latest_complete(tmp_path) == tmp_path / "checkpoints" / "00000010"
    assert any(str(newest) in str(x.message) for x in w)


def test_dir_without_manifest_is_not_a_checkpoint(tmp_path):
    _save(tmp_path, 10)
    half = _save(tmp_path, 20)
    (half / "manifest.json").unlink()
    seen: list[str] = []
    assert ckpt.load_latest(tmp_path, warn=seen.append).step == 10
    assert "no manifest.json" in seen[0]
    # the next save of step 20 replaces the damaged dir
    _save(tmp_path, 20)
    assert ckpt.load_latest(tmp_path).step == 20


def test_same_size_corruption_is_caught_by_the_hash(tmp_path):
    _save(tmp_path, 10)
    newest = _save(tmp_path, 20)
    f = newest / "training_state.json"
    data = bytearray(f.read_bytes())
    data[-3] ^= 0x01
    f.write_bytes(bytes(data))
    seen: list[str] = []
    assert ckpt.load_latest(tmp_path, warn=seen.append).step == 10
    assert "sha256" in seen[0]


def test_pickle_as_model_safetensors_is_refused_even_with_a_matching_manifest(tmp_path):
    path = _save(tmp_path, 10)
    f = path / "model.safetensors"
    f.write_bytes(pickle.dumps({"lin.weight": [[1.0]]}))
    # an attacker (or a confused tool) also rewrote the manifest to match
    manifest = json.loads((path / "manifest.json").read_text())
    from hope_models.durable import file_sha256
    manifest["files"]["model.safetensors"] = {"sha256": file_sha256(f), "size": f.stat().st_size}
    (path / "manifest.json").write_text(json.dumps(manifest))
    assert ckpt.verify(path) is None
    with pytest.raises(ckpt.CheckpointError, match="pickle"):
        ckpt.load_checkpoint(path)
    # torch.save output (a zip of pickles) likewise
    torch.save({"lin.weight": torch.zeros(1)}, f)
    with pytest.raises(ckpt.CheckpointError, match="pickle"):
        ckpt.load_tensors(f)
    # a garbage file is refused by header, not handed to a parser
    f.write_bytes(b"\x10\x00\x00\x00\x00\x00\x00\x00[not json")
    with pytest.raises(ckpt.CheckpointError, match="not a safetensors"):
        ckpt.load_tensors(f)


def _manifest_with(path: Path, name: str, target: Path) -> None:
    manifest = json.loads((path / "manifest.json").read_text())
    manifest["files"][name] = {"sha256": file_sha256(target), "size": target.stat().st_size}
    (path / "manifest.json").write_text(json.dumps(manifest))


def test_a_manifest_cannot_send_the_hash_outside_the_checkpoint_dir(tmp_path):
    """The manifest is untrusted: a name with a path, or a file that is a link (to /dev/zero, whose
    hash would never end), makes the dir not a checkpoint instead of being read."""
    outside = tmp_path / "secret.txt"
    outside.write_text("not a checkpoint file")
    path = _save(tmp_path / "a", 1)
    _manifest_with(path, "../../../secret.txt", outside)
    assert "not a file of a checkpoint dir" in ckpt.verify(path)
    path = _save(tmp_path / "b", 1)
    (path / "config.json").unlink()
    (path / "config.json").symlink_to(outside)
    _manifest_with(path, "config.json", outside)
    assert ckpt.verify(path) == "config.json is not a regular file"


@pytest.mark.parametrize("text,reason", [
    ("[" * 100_000 + "]" * 100_000, "nested too deeply"),
    ('{"step": NaN}', "not readable JSON: NaN is not JSON"),
    ("[1, 2]", "must be a JSON object, not list"),
    ("\udcff", "not UTF-8 text"),
])
def test_checkpoint_json_is_read_as_untrusted_input(tmp_path, text, reason):
    f = tmp_path / "config.json"
    f.write_text(text, errors="surrogateescape")
    with pytest.raises(ckpt.CheckpointError, match=reason) as err:
        ckpt.read_json_object(f)
    assert str(f) in str(err.value)
    size = f.stat().st_size
    with pytest.raises(ckpt.CheckpointError, match=f"{size} bytes, more than the {size - 1} a checkpoint's JSON"):
        ckpt.read_json_object(f, max_bytes=size - 1)
    os.mkfifo(tmp_path / "fifo")  # a read that would never end is refused, not waited on
    with pytest.raises(ckpt.CheckpointError, match="not a regular file"):
        ckpt.read_json_object(tmp_path / "fifo")


def test_module_never_calls_torch_load():
    src = Path(ckpt.__file__).read_text()
    loop_src = (Path(ckpt.__file__).parent / "train" / "loop.py").read_text()
    assert "torch.load" not in src and "torch.load" not in loop_src
    assert "import pickle" not in src and "import pickle" not in loop_src


def test_stale_temp_dirs_are_cleaned_and_ignored(tmp_path):
    _save(tmp_path, 10)
    stale = tmp_path / "checkpoints" / ".tmp-00000020-99999"
    stale.mkdir()
    (stale / "model.safetensors").write_bytes(b"partial")
    assert ckpt.load_latest(tmp_path).step == 10
    ckpt.clean_temp(tmp_path)
    assert not stale.exists()


def test_resolve_checkpoint_dir_accepts_run_dir_or_checkpoint_dir(tmp_path):
    _save(tmp_path, 10)
    p20 = _save(tmp_path, 20)
    assert ckpt.resolve_checkpoint_dir(tmp_path) == p20
    assert ckpt.resolve_checkpoint_dir(tmp_path / "checkpoints") == p20
    assert ckpt.resolve_checkpoint_dir(p20) == p20
    with pytest.raises(ckpt.CheckpointError, match="no complete checkpoint"):
        ckpt.resolve_checkpoint_dir(tmp_path / "elsewhere")


def test_optimizer_state_round_trips_exactly():
    torch.manual_seed(0)
    model = torch.nn.Linear(4, 3)
    opt = torch.optim.AdamW(model.parameters(), lr=1e-2, betas=(0.9, 0.95))
    for _ in range(3):
        opt.zero_grad()
        model(torch.randn(5, 4)).pow(2).sum().backward()
        opt.step()
    tensors, meta = ckpt.flatten_optimizer(opt.state_dict())
    tensors = {k: v.clone() for k, v in tensors.items()}  # as if written and read back
    meta = json.loads(json.dumps(meta))
    model2 = torch.nn.Linear(4, 3)
    model2.load_state_dict(model.state_dict())
    opt2 = torch.optim.AdamW(model2.parameters(), lr=5.0)
    opt2.load_state_dict(ckpt.unflatten_optimizer(tensors, meta))
    assert opt2.param_groups[0]["betas"] == (0.9, 0.95)
    x = torch.randn(5, 4)
    for m, o in ((model, opt), (model2, opt2)):
        o.zero_grad()
        m(x).pow(2).sum().backward()
        o.step()
    for a, b in zip(model.parameters(), model2.parameters()):
        assert torch.equal(a, b)


def test_kill_during_checkpoint_writes_never_leave_a_bad_newest(tmp_path):
    """SIGKILL a process that writes checkpoints in a tight loop at random moments; after each
    kill the newest loadable checkpoint is complete and no step dir without a manifest loads."""
    code = (
        "import sys, torch\n"
        "from hope_models import checkpoints as c\n"
        "run = sys.argv[1]\n"
        "w = torch.arange(200_000, dtype=torch.float32)\n"
        "for step in range(1, 10_000):\n"
        "    c.save_checkpoint(run, step, model_state={'w': w + step}, config={}, "
        "state_tensors={'x': torch.zeros(1)}, state={}, keep_last=2)\n"
        "    print(step, flush=True)\n"
    )
    import random
    import time
    rnd = random.Random(1)
    mid_write = 0
    # At least 6 kills, every one checked; more (up to 20) until one has landed inside a write: about
    # half do on an idle machine, a third when another process (a second pytest worker) is busy too.
    for attempt in range(20):
        if attempt >= 6 and mid_write:
            break
        run = tmp_path / f"r{attempt}"
        proc = subprocess.Popen([sys.executable, "-c", code, str(run)], stdout=subprocess.PIPE, text=True,
                                cwd=Path(__file__).resolve().parents[1])
        target = rnd.randint(3, 12)
        for line in proc.stdout:
            if int(line) >= target:
                break
        time.sleep(rnd.uniform(0, 0.01))  # land somewhere inside the next write
        os.kill(proc.pid, 9)
        proc.wait()
        proc.stdout.close()
        mid_write += any(p.name.startswith((".tmp-", ".del-")) for p in (run / "checkpoints").iterdir())
        loaded = ckpt.load_latest(run)
        assert loaded is not None and loaded.step >= target
        assert float(loaded.model["w"][0]) == loaded.step
        pointed = (run / "checkpoints" / (run / "checkpoints" / "last").read_text().strip())
        assert ckpt.verify(pointed) is None
    assert mid_write >= 1, "no kill landed inside a checkpoint write; the test exercised nothing"


def test_equal_weights_make_equal_files(tmp_path):
    """A checkpoint's bytes depend only on what it holds: the same weights saved twice (or by two
    identical runs) hash the same, so their version names match too."""
    import hashlib

    import torch

    state = {"w": torch.arange(12, dtype=torch.float32).reshape(3, 4), "b": torch.ones(4)}
    digests = set()
    for i in range(12):
        path = ckpt.save_checkpoint(tmp_path / f"r{i}", 7, model_state=state, config={"component": "x"},
                                    state_tensors={"t": torch.zeros(2)}, state={"k": 1})
        digests.add(hashlib.sha256((path / ckpt.MODEL_FILE).read_bytes()).hexdigest())
    assert len(digests) == 1
