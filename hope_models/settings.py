"""Deployment settings: one state directory ($HOPE_HOME) plus optional config.toml and env overrides.

Every command and service builds its Settings the same way, so `serve`, `enqueue` and `status`
run with the same HOPE_HOME see the same state. Settings are passed in, never imported as a global.

$HOPE_HOME holds the registry, the API token, the broker's messages, datasets and checkpoints, so
it is its user's alone: loading the settings creates it 0700 (or takes group/other access away
from one we own, saying so), and every entry point sets PRIVATE_UMASK, so what is written in it
is 0600 (directories 0700).
"""
from __future__ import annotations

import logging
import os
import re
import stat
import tomllib
from dataclasses import dataclass, field, fields
from pathlib import Path
from urllib.parse import urlsplit

from hope_models.numbers import NumberError, as_float, as_int, float_from_text, int_from_text, short

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
    # Host names the webapp answers besides loopback and this machine's own names/addresses
    # (webapp/hosts.py): a browser reaching it through any other name may be DNS rebinding.
    allowed_hosts: list[str] = field(default_factory=list)
    # browser origins (scheme://host[:port]) whose pages may call /api/ on the Robot Editor's port: a
    # web build of the Continuon app served from elsewhere (webapp/cors.py); empty = no CORS at all
    cors_origins: list[str] = field(default_factory=list)
    max_connections: int = 200  # open HTTP/WebSocket connections at once; more get 503 (webapp/server.py)
    # open connections from one client address at once (a browser's six, its editor tabs' WebSockets
    # and the phone app stay far below); one neighbour cannot take the whole server (webapp/server.py)
    max_connections_per_client: int = 32
    # protocol errors no real client makes (a second long-poll on one session, malformed Engine.IO
    # packets) from one address within 10 s before its connections are refused at accept for 10 s;
    # 0 = never (webapp/strikes.py)
    strikes_to_ban: int = 20
    # the robot's door: POST /api/brain/infer, GET /api/brain, /api/ping and /api/health on a
    # listener of their own, which nothing on the Robot Editor's side can fill (0 = any free port)
    inference_port: int = 8766
    # the same door on a Unix socket too (0600; relative = under $HOPE_HOME; "" = none)
    inference_socket: str = ""
    # Engine.IO's ping interval for Socket.IO sessions (python-engineio's default): how often the
    # server pings a browser, and how long a closed session's ping thread lingers (webapp/socket_guard.py)
    socketio_ping_interval_s: float = 25.0
    max_file_mb: int = 512  # reader guard: larger episode files are refused
    max_line_kb: int = 64 * 1024  # reader guard: a JSONL line longer than this is refused
    # promotion (hope_models/promote/gate.py, daemon/autopromote.py)
    auto_promote: bool = True  # gate (and promote when it passes) every run that completes
    # POST /api/brain/promote with force: true (past a refusing gate) only when this is on AND the
    # request carries X-Hope-Admin = $HOPE_HOME/admin_token (webapp/admin.py); the CLI on the robot
    # (`promote --force`) can always force
    allow_http_force: bool = False
    gate_val_tolerance: float = 0.05  # candidate val loss may be at most this fraction above the promoted one's
    gate_reflex_tolerance: float = 50.0  # sim reflex: mean return may be at most this many points below
    gate_reflex_episodes: int = 5  # held-out reacher seeds the reflex check runs
    # the reflex check runs after the candidate is served and rolls it back when it fails
    # (registry/gating.py): a new model answers seconds after its run, not after the episodes
    gate_reflex_after_serving: bool = True
    # baselines (gate.py, check 3): a vqvae keeps at least 1 - this share of the held-out variance;
    # a mid_loop's predicted observation has at least this much lower error than copy-last
    gate_vqvae_max_nmse: float = 0.05
    gate_mid_loop_min_gain: float = 0.30
    # a full disk (hope_models/disk.py, daemon/disk_guard.py): free MB under home a job needs before
    # the daemon dispatches it (0 = its checkpoint size x (keep_last + 2) + 200 MB), and how many
    # finished runs keep their run dirs (0 = keep all; promoted and pinned runs are always kept)
    disk_floor_mb: int = 0
    keep_runs: int = 20
    # runs one queue may hold waiting to start (queued or starting); one more is refused with 429
    # (registry/run_request.py check_queue_room; the daemon's auto chain is not counted against it)
    max_queued_runs: int = 20
    # the Continuon app's episodes (webapp/api/handoff.py, webapp/api/episodes.py): the dataset they
    # are ingested into (relative: under datasets_dir) and the largest request body one may send
    inbox_dataset: str = "inbox"
    upload_max_mb: int = 512
    # all uploads in progress together hold at most upload_tmp_max_mb in $HOPE_HOME/tmp (bodies and
    # what they unpack to) and leave disk_floor_mb (else 200 MB) free; one upload's unpacking and
    # reading may take upload_extract_s, plus 0.5 s per MB it sent (webapp/uploads.py, webapp/api/episodes.py)
    upload_tmp_max_mb: int = 3072
    upload_extract_s: float = 30.0
    # one multipart body holds at most upload_max_parts parts (the app's handoff sends 3-4 files per
    # tap, each streamed to its own file: a 2,000-tap session with depth is 8,002 parts); one package
    # unpacks to at most upload_unpack_max_mb (and never past the room in $HOPE_HOME/tmp) and holds at
    # most upload_max_members members (the Pi writes an rgb and a depth .npy per step)
    # (webapp/uploads.py, hope_models/rlds/upload_package.py)
    upload_max_parts: int = 20_000
    upload_unpack_max_mb: int = 3072
    upload_max_members: int = 20_000
    # continuous learning (daemon/continuous.py): when at least auto_train_min_new_episodes new
    # trainable episodes reached the inbox and the robot is idle, cool and has memory and disk to
    # spare, queue a chain of auto_train_components on it (auto_train_steps each; 0 = TrainConfig's default)
    auto_train: bool = False
    auto_train_min_new_episodes: int = 20
    auto_train_components: list[str] = field(default_factory=lambda: ["vqvae", "fast_loop", "mid_loop"])
    auto_train_steps: int = 0
    # what the Robot Editor's System and Workers pages show: the daemon samples the host every
    # system_sample_s into its history (daemon/system_history.py); a Celery worker beats every
    # worker_heartbeat_s (workers/heartbeat.py) and is offline after 3 missed beats
    system_sample_s: float = 5.0
    worker_heartbeat_s: float = 5.0
    # the log files under $HOPE_HOME/logs (daemon.log, worker.log, promote.log) are rotated at
    # log_max_mb, keeping log_backups older ones: at most (log_backups + 1) * log_max_mb each
    # (hope_models/log_limits.py); an SD card must not fill with log
    log_max_mb: int = 10
    log_backups: int = 3

    @property
    def datasets_dir(self) -> Path:
        return self.home / "datasets"

    @property
    def runs_dir(self) -> Path:
        return self.home / "runs"

    @property
    def cache_dir(self) -> Path:
        return self.home / "cache"

    @property
    def inbox_dir(self) -> Path:
        """Where handed-off and uploaded episodes are ingested (an absolute inbox_dataset as is)."""
        return self.datasets_dir / self.inbox_dataset  # an absolute right-hand side wins


# env var -> settings field; environment wins over config.toml
_ENV = {
    "HOPE_HOST": "host",
    "HOPE_PORT": "port",
    "HOPE_REDIS_URL": "redis_url",
    "HOPE_MEMORY_BUDGET_MB": "memory_budget_mb",
    "HOPE_ALLOWED_HOSTS": "allowed_hosts",
    "HOPE_CORS_ORIGINS": "cors_origins",
    "HOPE_MAX_CONNECTIONS": "max_connections",
    "HOPE_MAX_CONNECTIONS_PER_CLIENT": "max_connections_per_client",
    "HOPE_STRIKES_TO_BAN": "strikes_to_ban",
    "HOPE_INFERENCE_PORT": "inference_port",
    "HOPE_INFERENCE_SOCKET": "inference_socket",
    "HOPE_SOCKETIO_PING_INTERVAL_S": "socketio_ping_interval_s",
    "HOPE_THERMAL_ZONE": "thermal_zone_path",
    "HOPE_VCGENCMD": "vcgencmd_path",
    "HOPE_THERMAL_SOFT_C": "thermal_soft_c",
    "HOPE_THERMAL_HARD_C": "thermal_hard_c",
    "HOPE_THERMAL_RESUME_C": "thermal_resume_c",
    "HOPE_AUTO_PROMOTE": "auto_promote",
    "HOPE_ALLOW_HTTP_FORCE": "allow_http_force",
    "HOPE_GATE_VAL_TOLERANCE": "gate_val_tolerance",
    "HOPE_GATE_REFLEX_TOLERANCE": "gate_reflex_tolerance",
    "HOPE_GATE_REFLEX_EPISODES": "gate_reflex_episodes",
    "HOPE_GATE_REFLEX_AFTER_SERVING": "gate_reflex_after_serving",
    "HOPE_GATE_VQVAE_MAX_NMSE": "gate_vqvae_max_nmse",
    "HOPE_GATE_MID_LOOP_MIN_GAIN": "gate_mid_loop_min_gain",
    "HOPE_DISK_FLOOR_MB": "disk_floor_mb",
    "HOPE_KEEP_RUNS": "keep_runs",
    "HOPE_MAX_QUEUED_RUNS": "max_queued_runs",
    "HOPE_INBOX": "inbox_dataset",
    "HOPE_UPLOAD_MAX_MB": "upload_max_mb",
    "HOPE_UPLOAD_TMP_MAX_MB": "upload_tmp_max_mb",
    "HOPE_UPLOAD_EXTRACT_S": "upload_extract_s",
    "HOPE_UPLOAD_MAX_PARTS": "upload_max_parts",
    "HOPE_UPLOAD_UNPACK_MAX_MB": "upload_unpack_max_mb",
    "HOPE_UPLOAD_MAX_MEMBERS": "upload_max_members",
    "HOPE_AUTO_TRAIN": "auto_train",
    "HOPE_AUTO_TRAIN_MIN_NEW_EPISODES": "auto_train_min_new_episodes",
    "HOPE_AUTO_TRAIN_COMPONENTS": "auto_train_components",
    "HOPE_AUTO_TRAIN_STEPS": "auto_train_steps",
    "HOPE_SYSTEM_SAMPLE_S": "system_sample_s",
    "HOPE_WORKER_HEARTBEAT_S": "worker_heartbeat_s",
    "HOPE_LOG_MAX_MB": "log_max_mb",
    "HOPE_LOG_BACKUPS": "log_backups",
}
# the promotion gate's part of _ENV: the daemon passes these to the gate it spawns
GATE_ENV = {var: name for var, name in _ENV.items() if name.startswith("gate_")}
_TRUE = {"1", "true", "yes", "on"}
_FALSE = {"0", "false", "no", "off"}
# field -> (lowest allowed value, inclusive): a negative tolerance or zero episodes is a mistake
_MINIMUM = {"gate_val_tolerance": 0.0, "gate_reflex_tolerance": 0.0, "gate_reflex_episodes": 1,
            "gate_vqvae_max_nmse": 0.0, "gate_mid_loop_min_gain": 0.0,
            "max_connections": 8, "max_connections_per_client": 2, "strikes_to_ban": 0,
            "inference_port": 0,
            "socketio_ping_interval_s": 1.0, "disk_floor_mb": 0, "keep_runs": 0, "max_queued_runs": 1,
            "upload_max_mb": 1, "upload_tmp_max_mb": 1,
            "upload_max_parts": 3, "upload_unpack_max_mb": 1, "upload_max_members": 2, "auto_train_min_new_episodes": 1, "auto_train_steps": 0,
            "log_max_mb": 1, "log_backups": 0}
# fields that must be above zero (an interval of 0 s would spin)
_POSITIVE = {"system_sample_s", "worker_heartbeat_s", "upload_extract_s"}
# list settings whose items never contain a path separator are split on commas and blanks instead
# (an IPv6 address holds ':', os.pathsep)
_WORD_LISTS = {"allowed_hosts", "auto_train_components", "cors_origins"}
_DEFAULT_PORTS = {"http": "80", "https": "443"}


def check_origin(value: str, where: str) -> str:
    """A browser origin as the Origin header spells it: `http(s)://host[:port]`, lower case, the
    scheme's default port left out. Never `*` nor `null`: each allowed origin is named."""
    text = value.strip()
    usage = "an origin is scheme://host[:port], e.g. https://app.example.com or http://192.168.1.20:8081"
    if text in ("*", "null"):
        raise SettingsError(f"{where}: setting 'cors_origins': {text!r} is not allowed; name each origin ({usage})")
    try:
        parts = urlsplit(text)
        port = parts.port
    except ValueError:
        raise SettingsError(f"{where}: setting 'cors_origins': {text!r} is not an origin ({usage})") from None
    if (parts.scheme.lower() not in _DEFAULT_PORTS or not parts.hostname or "@" in parts.netloc
            or parts.path or parts.query or parts.fragment or text.endswith(("?", "#"))):
        raise SettingsError(f"{where}: setting 'cors_origins': {text!r} is not an origin ({usage}; no path, not "
                            "even a trailing /)")
    scheme, host = parts.scheme.lower(), parts.hostname.lower()
    if ":" in host:
        host = f"[{host}]"
    shown = "" if port is None or str(port) == _DEFAULT_PORTS[scheme] else f":{port}"
    return f"{scheme}://{host}{shown}"


def _coerce(name: str, value, where: str, from_env: bool = False):
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
        if kind in ("int", "float"):
            # the one rule for numbers (numbers.py): text only where everything is text
            if kind == "int":
                checked = int_from_text(name, value) if from_env else as_int(name, value)
            else:
                checked = float_from_text(name, value) if from_env else as_float(name, value)
            return _at_least(name, checked, where)
        if kind == "list[str]":
            if isinstance(value, str):
                if name in _WORD_LISTS:
                    items = [v for v in re.split(r"[,\s]+", value) if v]
                else:
                    items = [v for v in value.split(os.pathsep) if v]
            else:
                items = [str(v) for v in value]
            return [check_origin(v, where) for v in items] if name == "cors_origins" else items
        if kind == "str | None":
            return str(value) if value not in (None, "") else None
        return str(value)
    except SettingsError:
        raise
    except NumberError as exc:
        raise SettingsError(f"{where}: setting {name!r} = {short(value)} is not a valid {kind}: {exc.reason}") from None
    except (TypeError, ValueError):
        raise SettingsError(f"{where}: setting {name!r} = {value!r} is not a valid {kind}") from None


def _at_least(name: str, value, where: str):
    if name in _POSITIVE and not value > 0:
        raise SettingsError(f"{where}: setting {name!r} = {value!r} must be > 0")
    low = _MINIMUM.get(name)
    if low is not None and value < low:
        raise SettingsError(f"{where}: setting {name!r} = {value!r} must be >= {low}")
    return value


def _huge_integer(config_file: Path) -> str:
    """What a config.toml tomllib refused with a plain ValueError says: the setting whose value is an
    integer of more digits than Python converts."""
    for line in config_file.read_text(encoding="utf-8").splitlines():
        m = re.match(r"\s*([A-Za-z0-9_-]+)\s*=\s*[+-]?([0-9_]+)", line)
        if m and len(m.group(2).replace("_", "")) > 400:
            return f"setting {m.group(1)!r} is an integer of {len(m.group(2).replace('_', ''))} digits; no setting " \
                   "takes one that long"
    return "an integer too long to read (more digits than Python converts)"


PRIVATE_UMASK = 0o077  # files 0600, directories 0700
HOME_MODE = 0o700

log = logging.getLogger(__name__)


def use_private_umask() -> int:
    """Files and directories this process creates from now on are its user's alone (0600/0700),
    and so are those of its children, which inherit the umask (the Celery worker and its job
    children, the gate's child, serve's worker). Called first thing by every entry point
    (run_trainer.main, a Celery worker's start). Returns the previous umask."""
    return os.umask(PRIVATE_UMASK)


def secure_home(home: Path) -> None:
    """Create `home` 0700, or take group/other access away from an existing one that we own
    (logged: the registry and the token were readable by other local users). One owned by
    someone else is left alone, with a warning. Never raises: a home that cannot be created is
    reported by whatever writes to it first, with its own path in the error."""
    try:
        home.mkdir(mode=HOME_MODE, parents=True, exist_ok=True)  # parents keep the default mode, like mkdir -p
        st = home.stat()
    except OSError as exc:
        log.warning("HOPE_HOME %s cannot be created or read: %s", home, exc.strerror or exc)
        return
    mode = stat.S_IMODE(st.st_mode)
    if not mode & 0o077:
        return
    if st.st_uid != os.geteuid():
        log.warning("HOPE_HOME %s is mode %04o and belongs to uid %d, not to us: other local users may read "
                    "the registry; ask its owner to chmod 700 it", home, mode, st.st_uid)
        return
    try:
        os.chmod(home, mode & HOME_MODE)
    except OSError as exc:
        log.warning("HOPE_HOME %s is mode %04o (other local users can read the registry and the API token) "
                    "and could not be changed: %s", home, mode, exc.strerror or exc)
        return
    log.warning("HOPE_HOME %s was mode %04o (other local users could read the registry and the API token); "
                "changed to %04o", home, mode, mode & HOME_MODE)


def load_settings(home: str | os.PathLike | None = None, env: dict[str, str] | None = None, *,
                  secure: bool = True) -> Settings:
    """The settings of `home` ($HOPE_HOME, else the default), from config.toml and HOPE_*. With
    `secure` (every service and command), the home is created 0700 or tightened first; `doctor`
    passes secure=False, since it reports the home as it is and changes nothing."""
    env = dict(os.environ if env is None else env)
    home_path = Path(home or env.get("HOPE_HOME") or DEFAULT_HOME).expanduser()
    if secure:
        secure_home(home_path)
    values: dict = {}
    config_file = home_path / "config.toml"
    if config_file.exists():
        try:
            raw = tomllib.loads(config_file.read_text(encoding="utf-8"))
        except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
            raise SettingsError(f"{config_file}: not valid TOML: {exc}") from None
        except ValueError:  # tomllib's int() of a digit string longer than Python converts
            raise SettingsError(f"{config_file}: {_huge_integer(config_file)}") from None
        known = {f.name for f in fields(Settings)} - {"home"}
        for key, value in raw.items():
            if key not in known:
                raise SettingsError(f"{config_file}: unknown setting {key!r} (known: {', '.join(sorted(known))})")
            values[key] = _coerce(key, value, str(config_file))
    for var, name in _ENV.items():
        if var in env and env[var] != "":
            values[name] = _coerce(name, env[var], f"environment variable {var}", from_env=True)
    if "HOPE_DATA_ROOTS" in env:
        values["data_roots"] = _coerce("data_roots", env["HOPE_DATA_ROOTS"], "environment variable HOPE_DATA_ROOTS")
    return Settings(home=home_path, **values)
