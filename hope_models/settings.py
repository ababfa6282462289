"""Deployment settings: one state directory ($HOPE_HOME) plus optional config.toml and env overrides.

Every command and service builds its Settings the same way, so `serve`, `enqueue` and `status`
run with the same HOPE_HOME see the same state. Settings are passed in, never imported as a global.
"""
from __future__ import annotations

import os
import tomllib
from dataclasses import dataclass, field, fields
from pathlib import Path

DEFAULT_HOME = "~/.local/share/hope-trainer"


class SettingsError(ValueError):
    """A setting has a value that cannot be used; the message names it and where it came from."""


@dataclass
class Settings:
    home: Path
    host: str = "127.0.0.1"
    port: int = 8765
    redis_url: str | None = None  # None = embedded sqla+sqlite broker
    memory_budget_mb: int = 3072
    thermal_zone_path: str = "/sys/class/thermal/thermal_zone0/temp"
    vcgencmd_path: str = "vcgencmd"
    thermal_soft_c: float = 75.0
    thermal_hard_c: float = 82.0
    thermal_resume_c: float = 70.0
    data_roots: list[str] = field(default_factory=list)  # extra roots API requests may read from
    max_file_mb: int = 512  # reader guard: larger episode files are refused
    max_line_kb: int = 64 * 1024  # reader guard: a JSONL line longer than this is refused
    # promotion (hope_models/promote/gate.py, daemon/autopromote.py)
    auto_promote: bool = True  # gate (and promote when it passes) every run that completes
    gate_val_tolerance: float = 0.05  # candidate val loss may be at most this fraction above the promoted one's
    gate_reflex_tolerance: float = 50.0  # sim reflex: mean return may be at most this many points below
    gate_reflex_episodes: int = 5  # held-out reacher seeds the reflex check runs

    @property
    def datasets_dir(self) -> Path:
        return self.home / "datasets"

    @property
    def runs_dir(self) -> Path:
        return self.home / "runs"

    @property
    def cache_dir(self) -> Path:
        return self.home / "cache"


# env var -> settings field; environment wins over config.toml
_ENV = {
    "HOPE_HOST": "host",
    "HOPE_PORT": "port",
    "HOPE_REDIS_URL": "redis_url",
    "HOPE_MEMORY_BUDGET_MB": "memory_budget_mb",
    "HOPE_THERMAL_ZONE": "thermal_zone_path",
    "HOPE_VCGENCMD": "vcgencmd_path",
    "HOPE_THERMAL_SOFT_C": "thermal_soft_c",
    "HOPE_THERMAL_HARD_C": "thermal_hard_c",
    "HOPE_THERMAL_RESUME_C": "thermal_resume_c",
    "HOPE_AUTO_PROMOTE": "auto_promote",
    "HOPE_GATE_VAL_TOLERANCE": "gate_val_tolerance",
    "HOPE_GATE_REFLEX_TOLERANCE": "gate_reflex_tolerance",
    "HOPE_GATE_REFLEX_EPISODES": "gate_reflex_episodes",
}
_TRUE = {"1", "true", "yes", "on"}
_FALSE = {"0", "false", "no", "off"}
# field -> (lowest allowed value, inclusive): a negative tolerance or zero episodes is a mistake
_MINIMUM = {"gate_val_tolerance": 0.0, "gate_reflex_tolerance": 0.0, "gate_reflex_episodes": 1}


def _coerce(name: str, value, where: str):
    types = {f.name: f.type for f in fields(Settings)}
    kind = types[name]
    try:
        if kind == "bool":
            if isinstance(value, bool):
                return value
            text = str(value).strip().lower()
            if text in _TRUE or text in _FALSE:
                return text in _TRUE
            raise ValueError(value)
        if kind == "int":
            if isinstance(value, bool):
                raise ValueError(value)
            return _at_least(name, int(value), where)
        if kind == "float":
            if isinstance(value, bool):
                raise ValueError(value)
            v = float(value)
            if v != v or v in (float("inf"), float("-inf")):
                raise ValueError(value)
            return _at_least(name, v, where)
        if kind == "list[str]":
            if isinstance(value, str):
                return [v for v in value.split(os.pathsep) if v]
            return [str(v) for v in value]
        if kind == "str | None":
            return str(value) if value not in (None, "") else None
        return str(value)
    except SettingsError:
        raise
    except (TypeError, ValueError):
        raise SettingsError(f"{where}: setting {name!r} = {value!r} is not a valid {kind}") from None


def _at_least(name: str, value, where: str):
    low = _MINIMUM.get(name)
    if low is not None and value < low:
        raise SettingsError(f"{where}: setting {name!r} = {value!r} must be >= {low}")
    return value


def load_settings(home: str | os.PathLike | None = None, env: dict[str, str] | None = None) -> Settings:
    env = dict(os.environ if env is None else env)
    home_path = Path(home or env.get("HOPE_HOME") or DEFAULT_HOME).expanduser()
    values: dict = {}
    config_file = home_path / "config.toml"
    if config_file.exists():
        try:
            raw = tomllib.loads(config_file.read_text(encoding="utf-8"))
        except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
            raise SettingsError(f"{config_file}: not valid TOML: {exc}") from None
        known = {f.name for f in fields(Settings)} - {"home"}
        for key, value in raw.items():
            if key not in known:
                raise SettingsError(f"{config_file}: unknown setting {key!r} (known: {', '.join(sorted(known))})")
            values[key] = _coerce(key, value, str(config_file))
    for var, name in _ENV.items():
        if var in env and env[var] != "":
            values[name] = _coerce(name, env[var], f"environment variable {var}")
    if "HOPE_DATA_ROOTS" in env:
        values["data_roots"] = _coerce("data_roots", env["HOPE_DATA_ROOTS"], "environment variable HOPE_DATA_ROOTS")
    return Settings(home=home_path, **values)
