"""hope_models/checkpoint_format.py: one set of names and rules for a checkpoint dir, and a model
load that hashes each file once (the manifest check, the pointer's sha256 and the version string
all read the same digest)."""
from __future__ import annotations

import hashlib
import pickle
import subprocess
import sys
from pathlib import Path

import pytest

from brain_fixtures import brain_runs, promote_pointer
from hope_models import checkpoint_format as fmt
from hope_models.runtime.brain_service import BrainService

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    return brain_runs(tmp_path_factory)


class _HashCount:
    """Every sha256 computed while installed: how many bytes went through hashlib.sha256, and which
    checkpoint files went through checkpoint_format.file_digest."""

    def __init__(self, monkeypatch):
        self.bytes = 0
        self.files: list[str] = []
        real_sha256, real_digest = hashlib.sha256, fmt.file_digest
        count = self

        class Counting:
            def __init__(self, data: bytes = b"", **kw):
                count.bytes += len(data)
                self._h = real_sha256(data, **kw)

            def update(self, data: bytes) -> None:
                count.bytes += len(data)
                self._h.update(data)

            def hexdigest(self) -> str:
                return self._h.hexdigest()

        def digest(path: Path, keep: bool = False):
            count.files.append(Path(path).name)
            return real_digest(path, keep)

        monkeypatch.setattr(hashlib, "sha256", Counting)
        monkeypatch.setattr(fmt, "file_digest", digest)


def test_a_brain_service_load_hashes_each_checkpoint_file_once(runs, tmp_path, monkeypatch):
    ckpt = runs["alpha30"]
    home = tmp_path / "home"
    promote_pointer(home, ckpt)
    count = _HashCount(monkeypatch)
    brain = BrainService(home)
    brain.check_now()  # the load, on this thread
    assert brain.status()["fast_loop"]["last_error"] is None and brain.version("fast_loop")
    assert sorted(count.files) == sorted(fmt.CHECKPOINT_FILES)  # each once: no second pass over any
    assert count.bytes == sum((ckpt / name).stat().st_size for name in fmt.CHECKPOINT_FILES)


def test_the_version_names_the_run_the_step_and_the_weights(tmp_path):
    sha = "ab" * 32
    run_ckpt = tmp_path / "reach" / "checkpoints" / "00002500"
    assert fmt.version_name(run_ckpt, sha, {"checkpoint": {"step": 2500}}) == f"reach@2500:{sha[:12]}"
    assert fmt.version_name(run_ckpt, sha, None) == f"reach@2500:{sha[:12]}"  # the dir name's step
    # an untrusted config of any shape only loses the step
    for bad in ({"checkpoint": "x"}, {"checkpoint": {"step": True}}, [1], "s"):
        assert fmt.version_name(tmp_path / "bare", sha, bad) == f"bare@0:{sha[:12]}"


def test_sniffing_refuses_pickles_by_their_first_bytes(tmp_path):
    f = tmp_path / "model.safetensors"
    f.write_bytes(pickle.dumps({"w": [1.0]}))
    assert fmt.looks_like_pickle(f.read_bytes()[:fmt.SNIFF_BYTES])
    with pytest.raises(fmt.CheckpointError, match="is a pickle"):
        fmt.refuse_non_safetensors(f)
    f.write_bytes(b"PK\x03\x04" + b"\x00" * 20)  # torch.save's zip
    assert "pickle" in fmt.safetensors_problem(f.read_bytes()[:fmt.SNIFF_BYTES])
    header = b'{"__metadata__":{}}'
    assert fmt.safetensors_problem(len(header).to_bytes(8, "little") + header) is None


def test_weights_misfit_names_what_differs():
    assert fmt.weights_misfit({"a": [2]}, {"a": [2]}) is None
    text = fmt.weights_misfit({"a": [2], "b": [3]}, {"a": [4], "c": [1]}, described_by="model")
    assert "a: file [4], model [2]" in text and "missing: ['b']" in text and "unexpected: ['c']" in text
    assert fmt.weights_misfit({"a": [2]}, {"a": [2], "vq.x": [1]}, ignore=["vq.x"]) is None


def test_read_verified_keeps_the_bytes_it_hashed(runs):
    ckpt = runs["alpha30"]
    v = fmt.read_verified(ckpt, keep=(fmt.MODEL_FILE,))
    assert v.data[fmt.MODEL_FILE] == (ckpt / fmt.MODEL_FILE).read_bytes()
    assert v.sha256[fmt.MODEL_FILE] == hashlib.sha256(v.data[fmt.MODEL_FILE]).hexdigest()
    assert set(v.sha256) == set(fmt.CHECKPOINT_FILES) and set(v.data) == {fmt.MODEL_FILE}


def test_the_format_module_stands_at_the_bottom():
    """Importable by the daemon and the webapp: nothing of hope_models' sub-packages, no torch."""
    code = ("import sys; import hope_models.checkpoint_format, hope_models.promoted; "
            "bad = sorted(m for m in sys.modules if m == 'torch' or m.startswith(('hope_models.train', "
            "'hope_models.data', 'hope_models.runtime', 'hope_models.promote.'))); print(bad); "
            "sys.exit(1 if bad else 0)")
    proc = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stdout + proc.stderr
