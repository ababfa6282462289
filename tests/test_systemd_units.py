"""systemd/: the unit files say what docs/pi.md promises, and install.sh renders them to valid units."""
from __future__ import annotations

import configparser
import re
import shutil
import stat
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
UNITS = ("hope-daemon.service", "hope-worker.service", "hope-webapp.service")


def unit(path: Path) -> configparser.ConfigParser:
    # systemd allows repeated keys (Environment=); keep the last for the checks, read all with multi()
    cp = configparser.ConfigParser(strict=False, interpolation=None, comment_prefixes=("#", ";"))
    cp.optionxform = str
    cp.read_string(path.read_text())
    return cp


def multi(path: Path, key: str) -> list[str]:
    return [line.split("=", 1)[1] for line in path.read_text().splitlines() if line.startswith(f"{key}=")]


def render(tmp_path: Path) -> Path:
    units = tmp_path / "units"
    proc = subprocess.run(["sh", str(REPO / "systemd" / "install.sh"), "--no-systemctl", "--no-user",
                           "--python", sys.executable, "--unit-dir", str(units), "--state-dir", str(tmp_path / "state"),
                           "--defaults-file", str(tmp_path / "default")],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    return units


def test_units_carry_the_promised_settings():
    d, w, a = (REPO / "systemd" / name for name in UNITS)
    for path in (d, w, a):
        u = unit(path)
        assert u["Service"]["Restart"] == "on-failure"
        assert u["Service"]["User"] == "hope"
        assert "redis-server.service" in u["Unit"]["After"] and "redis-server.service" in u["Unit"]["Wants"]
        env = multi(path, "Environment")
        assert "HOPE_HOME=/var/lib/hope-trainer" in env
        assert "HOPE_REDIS_URL=redis://127.0.0.1:6379/0" in env
        assert u["Install"]["WantedBy"] == "multi-user.target"
        # the state dir (registry, broker, token, runs) is the service user's alone, so are its files
        assert u["Service"]["UMask"] == "0077", path.name
        assert u["Service"]["StateDirectory"] == "hope-trainer" and u["Service"]["StateDirectoryMode"] == "0700"
        assert 1024 < int(u["Service"]["LimitNOFILE"]) <= 65536, path.name
    daemon, worker, webapp = unit(d)["Service"], unit(w)["Service"], unit(a)["Service"]
    assert daemon["Type"] == "notify" and daemon["WatchdogSec"] == "30"
    assert daemon["ExecStart"].endswith("run_trainer.py daemon")
    assert webapp["Type"] == "notify" and webapp["ExecStart"].endswith("run_trainer.py webapp")
    assert worker["ExecStart"].endswith("run_trainer.py worker -Q pi")
    assert worker["KillMode"] == "control-group" and worker["TimeoutStopSec"] == "60"
    assert int(worker["Nice"]) >= 10 and int(worker["CPUWeight"]) < 100
    assert worker["MemoryHigh"] and worker["MemoryMax"]


def test_install_script_renders_units(tmp_path):
    units = render(tmp_path)
    for name in UNITS:
        text = (units / name).read_text()
        assert "@REPO@" not in text and "@PYTHON@" not in text
        assert f"ExecStart={sys.executable} {REPO}/run_trainer.py" in text
        assert f"HOPE_HOME={tmp_path / 'state'}" in text
    assert (tmp_path / "state").is_dir() and stat.S_IMODE((tmp_path / "state").stat().st_mode) == 0o700
    assert "HOPE_REDIS_URL" in (tmp_path / "default").read_text()
    # re-running keeps the site's overrides file
    (tmp_path / "default").write_text("HOPE_MEMORY_BUDGET_MB=2048\n")
    render(tmp_path)
    assert (tmp_path / "default").read_text() == "HOPE_MEMORY_BUDGET_MB=2048\n"


def test_install_script_refuses_a_missing_python(tmp_path):
    proc = subprocess.run(["sh", str(REPO / "systemd" / "install.sh"), "--no-systemctl", "--no-user",
                           "--python", str(tmp_path / "nope" / "python"), "--unit-dir", str(tmp_path / "u")],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode != 0 and "not found" in proc.stderr
    assert not (tmp_path / "u").exists()


def analyze() -> str:
    exe = shutil.which("systemd-analyze")
    # no skip: `make test` runs `make system-deps`, which installs systemd where it is missing
    assert exe is not None, "systemd-analyze is missing: make system-deps (apt-get install systemd)"
    return exe


def test_rendered_units_pass_systemd_analyze(tmp_path):
    exe = analyze()
    units = render(tmp_path)
    proc = subprocess.run([exe, "verify", *(str(units / n) for n in UNITS)], capture_output=True, text=True,
                          timeout=60)
    # verify exits 0 even for unknown keys and bad values; it reports them on stderr naming the file
    complaints = [line for line in (proc.stdout + proc.stderr).splitlines() if str(units) in line]
    assert not complaints, "\n".join(complaints)


MAX_EXPOSURE = 3.0  # systemd-analyze security rates up to 3.9 "OK"; the issue asks for 3.0 at most
EXPOSURE_RE = re.compile(r"Overall exposure level for (\S+): (\d+(?:\.\d+)?) (\w+)")


def test_rendered_units_are_hardened(tmp_path):
    exe = analyze()
    units = render(tmp_path)
    levels = {}
    for name in UNITS:
        proc = subprocess.run([exe, "security", "--offline=true", "--no-pager", str(units / name)],
                              capture_output=True, text=True, timeout=60)
        out = proc.stdout + proc.stderr
        found = EXPOSURE_RE.findall(out)
        assert found and found[-1][0] == name, out
        levels[name] = float(found[-1][1])
    assert all(level <= MAX_EXPOSURE for level in levels.values()), levels


def test_units_carry_the_hardening():
    """What the exposure figure cannot show: these keys must be exactly so for the services to work
    (and to stop on a configuration error instead of restarting forever)."""
    for name in UNITS:
        path = REPO / "systemd" / name
        s = unit(path)["Service"]
        assert s["RestartPreventExitStatus"] == "2", name
        assert s["SyslogIdentifier"] == name.removesuffix(".service"), name
        assert s["ProtectSystem"] == "strict" and s["NoNewPrivileges"] == "true", name
        # $HOPE_HOME is the one writable path (install.sh rewrites it with --state-dir)
        assert multi(path, "ReadWritePaths") == ["/var/lib/hope-trainer"], name
        assert s["CapabilityBoundingSet"] == "" and s["PrivateTmp"] == "true", name
        assert multi(path, "SystemCallFilter")[0] == "@system-service", name
        assert s["SystemCallErrorNumber"] == "EPERM", name
        families = set(s["RestrictAddressFamilies"].split())
        assert {"AF_UNIX", "AF_INET", "AF_INET6"} <= families <= {"AF_UNIX", "AF_INET", "AF_INET6", "AF_NETLINK"}, name
        # torch's CPU kernels are JIT-compiled (oneDNN) in the job child and the promotion gate children
        assert "MemoryDenyWriteExecute" not in s, name
        # psutil's memory and CPU figures come from /proc/meminfo and /proc/stat
        assert s.get("ProcSubset", "all") == "all", name
    # only the daemon and the webapp read the throttle flags through vcgencmd (/dev/vcio)
    for name in ("hope-daemon.service", "hope-webapp.service"):
        s = unit(REPO / "systemd" / name)["Service"]
        assert s["DevicePolicy"] == "closed" and multi(REPO / "systemd" / name, "DeviceAllow") == ["/dev/vcio rw"]
    assert unit(REPO / "systemd" / "hope-worker.service")["Service"]["PrivateDevices"] == "true"


def test_install_script_points_the_writable_path_at_the_state_dir(tmp_path):
    units = render(tmp_path)
    for name in UNITS:
        assert f"ReadWritePaths={tmp_path / 'state'}\n" in (units / name).read_text(), name
