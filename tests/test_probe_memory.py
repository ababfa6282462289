"""A run request's dataset probe is remembered while the dataset's files are unchanged, so asking
again (every POST /api/runs does) costs a listing and stats, not a parse; any change is seen."""
from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from hope_models.data import dataset_spec
from hope_models.data.dataset_spec import probe_dataset_spec
from hope_models.data.features import FeatureSpecError
from hope_models.data.synthetic import generate_dataset


@pytest.fixture
def reads(monkeypatch):
    """Count the sources the probe parses; files written by the test count as settled at once."""
    calls: list[Path] = []
    real = dataset_spec.read_source

    def counting(src, *args, **kwargs):
        calls.append(Path(src))
        return real(src, *args, **kwargs)

    monkeypatch.setattr(dataset_spec, "read_source", counting)
    monkeypatch.setattr(dataset_spec, "CHANGED_LATELY_NS", 0)
    monkeypatch.setattr(dataset_spec, "_PROBES", dataset_spec._ProbeMemory(dataset_spec.PROBES_REMEMBERED))
    return calls


def _dataset(root: Path, obs_dim: int = 6, seed: int = 0, prefix: str = "ep") -> Path:
    generate_dataset(root, 300, obs_dim=obs_dim, act_dim=2, episode_seconds=(2, 4), seed=seed, id_prefix=prefix)
    return root


def test_the_same_dataset_is_parsed_once_and_each_caller_gets_its_own_spec(tmp_path, reads):
    data = _dataset(tmp_path / "ds")
    first = probe_dataset_spec(data)
    parsed = len(reads)
    assert parsed > 0
    first.notes.append("a caller's own note")
    second = probe_dataset_spec(data)
    assert len(reads) == parsed, "an unchanged dataset was parsed again"
    assert second.obs_dim == first.obs_dim == 6
    assert "a caller's own note" not in second.notes


def test_a_rewritten_episode_is_read_again(tmp_path, reads):
    data = _dataset(tmp_path / "ds", obs_dim=6)
    assert probe_dataset_spec(data).obs_dim == 6
    other = _dataset(tmp_path / "other", obs_dim=10)
    for src, dst in zip(sorted(other.iterdir()), sorted(data.iterdir())):
        shutil.rmtree(dst)
        shutil.copytree(src, dst)
    parsed = len(reads)
    assert probe_dataset_spec(data).obs_dim == 10
    assert len(reads) > parsed


def test_a_new_source_is_seen_when_the_probe_had_read_them_all(tmp_path, reads):
    data = tmp_path / "ds"
    data.mkdir()
    with pytest.raises(FeatureSpecError, match="no episode files"):
        probe_dataset_spec(data)
    with pytest.raises(FeatureSpecError, match="no episode files"):
        probe_dataset_spec(data)  # the refusal is remembered too
    _dataset(tmp_path / "src")
    first = sorted((tmp_path / "src").iterdir())[0]
    shutil.copytree(first, data / first.name)
    assert probe_dataset_spec(data).obs_dim == 6


def test_a_file_changed_while_it_was_read_is_not_remembered(tmp_path, reads, monkeypatch):
    monkeypatch.setattr(dataset_spec, "CHANGED_LATELY_NS", 2_000_000_000)
    data = _dataset(tmp_path / "ds")  # written just now: it may still be being written
    probe_dataset_spec(data)
    parsed = len(reads)
    probe_dataset_spec(data)
    assert len(reads) == 2 * parsed


def test_only_the_last_few_datasets_are_remembered(tmp_path, reads, monkeypatch):
    monkeypatch.setattr(dataset_spec, "_PROBES", dataset_spec._ProbeMemory(2))
    sets = [_dataset(tmp_path / f"ds{i}", seed=i) for i in range(3)]
    for data in sets:
        probe_dataset_spec(data)
    parsed = len(reads)
    probe_dataset_spec(sets[2])
    assert len(reads) == parsed
    probe_dataset_spec(sets[0])  # pushed out by the other two
    assert len(reads) > parsed
