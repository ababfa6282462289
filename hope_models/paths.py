"""The data roots: the one rule for a path that arrives from outside (an API request, a
checkpoint's config.json) and is then read or written by a service.

    roots = data_roots(settings)                  # $HOPE_HOME + settings.data_roots
    path = confine_path("train.spec_path", value, allowed_roots=roots)

`POST /api/runs` and `/api/brain/promote` (through registry/run_request.py) and the promotion gate
(hope_models/promote/gate.py, for the paths a candidate's config.json names) all check here, so
that a path refused at one door is refused at every door. The path is resolved (symlinks
followed) before it is compared, so a link inside a root that points outside is outside; callers
use the resolved path this returns, not the text they were given. Text no filesystem call should
see (a NUL, a segment over NAME_MAX, a lone surrogate) and a leading '~' of a confined path are
refused before any lookup, and what the filesystem still refuses (a symlink loop, a directory this
user may not enter) is a PathError too: bad input is a 400 naming the field, never a 500.
"""
from __future__ import annotations

import reprlib
from pathlib import Path
from typing import Any


class PathError(ValueError):
    """A path that cannot be used; the message names the field."""


def data_roots(settings: Any) -> list[Path]:
    """Where services may read data and write caches: $HOPE_HOME and settings.data_roots."""
    return [Path(settings.home)] + [Path(r) for r in settings.data_roots]


def confine_path(field_name: str, value: Any, *, base: Path | None = None, allowed_roots: list[Path] | None = None,
                 must_exist: bool = True) -> Path:
    """`value` as an absolute, resolved path (relative to `base`, default the working directory).
    With `allowed_roots`, it must lie inside one of them; with `must_exist`, it must exist."""
    if not isinstance(value, str) or not value.strip():
        raise PathError(f"{field_name}: expected a path, got {reprlib.repr(value)}")
    if "\x00" in value:  # the OS would refuse it later with a less helpful message
        raise PathError(f"{field_name}: {reprlib.repr(value)} is not a path (it holds a NUL character)")
    _check_lengths(field_name, value)
    if value.startswith("~"):
        if allowed_roots is not None:
            # Expanding it would look the user up: "no such user" against "outside the roots" tells
            # a client which local accounts exist. Refused before any lookup, the same for every name.
            raise PathError(f"{field_name}: a path starting with '~' is not expanded here; give it relative "
                            f"to {base or 'the data root'} or absolute")
        try:
            value = str(Path(value).expanduser())
        except RuntimeError:  # ~name of no local user (the command line: its own user may know that)
            raise PathError(f"{field_name}: {value}: no such user's home directory") from None
    path = Path(value)
    if not path.is_absolute():
        path = (base or Path.cwd()) / path
    _check_lengths(field_name, str(path))
    try:
        path = path.resolve()
    except (OSError, RuntimeError) as exc:  # RuntimeError: a symlink loop (Python < 3.13)
        raise PathError(f"{field_name}: {value}: {getattr(exc, 'strerror', None) or exc}") from None
    if allowed_roots is not None:
        roots = [Path(r).expanduser().resolve() for r in allowed_roots]
        if not any(path == r or r in path.parents for r in roots):
            raise PathError(f"{field_name}: {value} is outside the allowed data roots "
                            f"({', '.join(str(r) for r in roots)}; add one with data_roots in config.toml)")
    try:
        exists = path.exists()
    except OSError as exc:  # e.g. a directory on the way that this user may not enter
        raise PathError(f"{field_name}: {path}: {exc.strerror or exc}") from None
    if must_exist and not exists:
        raise PathError(f"{field_name}: {path} does not exist")
    return path


NAME_MAX = 255  # bytes in one path segment (Linux filesystems)
PATH_MAX = 4096  # bytes in a whole path


def _check_lengths(field_name: str, value: str) -> None:
    """What the filesystem would refuse with ENAMETOOLONG (a 500 where it surfaced) or cannot
    encode (a lone UTF-16 surrogate that JSON's \\ud800 escape lets through)."""
    try:
        raw = value.encode("utf-8")
    except UnicodeEncodeError:
        raise PathError(f"{field_name}: not a path (it is not valid Unicode text)") from None
    if len(raw) > PATH_MAX:
        raise PathError(f"{field_name}: the path is longer than {PATH_MAX} bytes")
    longest = max(raw.split(b"/"), key=len)
    if len(longest) > NAME_MAX:
        raise PathError(f"{field_name}: a path segment is longer than {NAME_MAX} bytes "
                        f"({longest[:40].decode('utf-8', 'replace')}...)")


__all__ = ["PathError", "confine_path", "data_roots"]
