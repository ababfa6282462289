"""durable.atomic_write / atomic_open: the target is the old file or the new one, never half of one."""
from __future__ import annotations

import os
import stat

import pytest

from hope_models import durable


def _fsynced_paths(monkeypatch) -> list[str]:
    """Record what every os.fsync call synced, by the path its fd points at."""
    seen: list[str] = []
    real = os.fsync

    def spy(fd):
        seen.append(os.path.realpath(os.readlink(f"/proc/self/fd/{fd}")))
        return real(fd)

    monkeypatch.setattr(os, "fsync", spy)
    return seen


def test_atomic_write_replaces_the_file_and_leaves_no_temp(tmp_path):
    target = tmp_path / "pointer.json"
    target.write_bytes(b"old\n")
    durable.atomic_write(target, b"new\n")
    assert target.read_bytes() == b"new\n"
    durable.atomic_write(target, "text é\n")
    assert target.read_bytes() == "text é\n".encode("utf-8")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["pointer.json"]


def test_a_crash_inside_atomic_open_leaves_the_old_file_intact_and_no_temp(tmp_path):
    target = tmp_path / "episode.mcap"
    target.write_bytes(b"old complete file")
    with pytest.raises(RuntimeError, match="crash"):
        with durable.atomic_open(target, "wb") as f:
            f.write(b"half of the new")
            f.flush()
            raise RuntimeError("crash mid-write")
    assert target.read_bytes() == b"old complete file"
    assert [p.name for p in tmp_path.iterdir()] == ["episode.mcap"]


def test_a_crash_before_the_first_write_creates_nothing(tmp_path):
    target = tmp_path / "new.json"
    with pytest.raises(KeyboardInterrupt):
        with durable.atomic_open(target, "w"):
            raise KeyboardInterrupt
    assert list(tmp_path.iterdir()) == []


def test_a_failed_rename_leaves_the_old_file_and_removes_the_temp(tmp_path, monkeypatch):
    target = tmp_path / "last"
    target.write_bytes(b"00000010\n")

    def no_replace(src, dst):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "replace", no_replace)
    with pytest.raises(OSError):
        durable.atomic_write(target, b"00000020\n")
    assert target.read_bytes() == b"00000010\n"
    assert [p.name for p in tmp_path.iterdir()] == ["last"]


def test_the_file_and_then_its_directory_are_fsynced(tmp_path, monkeypatch):
    target = tmp_path / "manifest.json"
    seen = _fsynced_paths(monkeypatch)
    with durable.atomic_open(target, "w") as f:
        f.write("{}\n")
    assert target.read_text(encoding="utf-8") == "{}\n"
    assert len(seen) == 2
    temp, directory = seen
    assert os.path.dirname(temp) == str(tmp_path.resolve())  # the temp file sits beside the target
    assert os.path.basename(temp).startswith(".manifest.json.tmp-")
    assert directory == str(tmp_path.resolve())  # the dir fsync comes after the rename


def test_text_mode_writes_utf8_with_unix_newlines(tmp_path):
    target = tmp_path / "a.txt"
    with durable.atomic_open(target, "w") as f:
        f.write("ä\nb\n")
    assert target.read_bytes() == "ä\nb\n".encode("utf-8")
    with pytest.raises(ValueError):
        with durable.atomic_open(target, "ab"):
            pass


def test_modes_follow_the_umask_like_open_and_perms_narrow_them(tmp_path):
    old = os.umask(0o077)
    try:
        durable.atomic_write(tmp_path / "a", b"x")
        open(tmp_path / "b", "wb").close()
        durable.atomic_write(tmp_path / "c", b"x", perms=0o400)
    finally:
        os.umask(old)
    mode = lambda name: stat.S_IMODE((tmp_path / name).stat().st_mode)  # noqa: E731
    assert mode("a") == mode("b") == 0o600
    assert mode("c") == 0o400


def test_a_symlinked_temp_name_is_not_followed(tmp_path, monkeypatch):
    target = tmp_path / "t"
    victim = tmp_path / "victim"
    victim.write_bytes(b"keep")
    monkeypatch.setattr(durable, "_temp_name", lambda path: path.with_name(".t.tmp-fixed"))
    os.symlink(victim, tmp_path / ".t.tmp-fixed")
    with pytest.raises(OSError):
        durable.atomic_write(target, b"data")
    assert victim.read_bytes() == b"keep"
    assert not target.exists()


def test_many_files_are_made_durable_with_one_syncfs_or_one_fsync_each(tmp_path, monkeypatch):
    files = []
    for i in range(5):
        (tmp_path / f"f{i}").write_bytes(b"x")
        files.append(tmp_path / f"f{i}")
    calls: list[int] = []
    libc = durable._libc()
    assert libc is not None and hasattr(libc, "syncfs")  # Linux: the one-flush path is the one taken

    class Spy:
        def syncfs(self, fd):
            calls.append(fd)
            return libc.syncfs(fd)

    monkeypatch.setattr(durable, "_libc", lambda: Spy())
    fsynced = _fsynced_paths(monkeypatch)
    durable.fsync_files(files, tmp_path)
    assert len(calls) == 1 and fsynced == []

    class Failing:
        def syncfs(self, fd):
            return -1

    monkeypatch.setattr(durable, "_libc", lambda: Failing())
    durable.fsync_files(files, tmp_path)  # syncfs failed: every file is fsynced on its own
    assert sorted(fsynced) == sorted(str(f.resolve()) for f in files)
