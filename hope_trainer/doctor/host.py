"""The doctor's checks of the machine: architecture, Python, memory cgroup, page size, thermal
sources, free memory and free disk. Read-only; nothing here imports torch."""
from __future__ import annotations

import os
import platform
import shutil
import sys
from dataclasses import fields
from pathlib import Path
from typing import Any

from hope_models.disk import FLOOR_MARGIN_MB, dispatch_floor_mb, free_mb
from hope_models.train.config import TrainConfig
from hope_models.train.thermal import ThermalGovernor
from hope_trainer.doctor.check import FAIL, OK, SKIP, WARN, Check

MB = 1024 * 1024
CGROUP_CONTROLLERS = Path("/sys/fs/cgroup/cgroup.controllers")
PROC_CGROUPS = Path("/proc/cgroups")  # cgroup v1 (and hybrid) hosts list their controllers here
DEVICE_MODEL = Path("/proc/device-tree/model")
CMDLINE_FIX = ("add 'cgroup_enable=memory cgroup_memory=1' to the end of the one line in "
               "/boot/firmware/cmdline.txt and reboot (docs/pi.md, 'Turn on the memory cgroup')")


def device_model() -> str | None:
    """'Raspberry Pi 5 Model B Rev 1.0' on a Pi (the device tree's model), None elsewhere."""
    try:
        return DEVICE_MODEL.read_text(encoding="ascii", errors="replace").strip("\x00\n ") or None
    except OSError:
        return None


def is_raspberry_pi() -> bool:
    return "raspberry pi" in (device_model() or "").lower()


def check_architecture(_settings: Any) -> Check:
    machine = platform.machine()
    model = device_model()
    where = f"{machine}" + (f" ({model})" if model else "")
    if machine in ("aarch64", "arm64"):
        return Check("architecture", OK, where)
    if machine in ("x86_64", "AMD64"):
        return Check("architecture", OK, f"{where}: a development machine (the robot is aarch64)")
    return Check("architecture", WARN, f"{where}: neither aarch64 (the robot) nor x86_64 (development); "
                 "no lock file or wheel set is proven here", "use a 64-bit OS (aarch64 Raspberry Pi OS)")


def check_python(_settings: Any) -> Check:
    version = ".".join(map(str, sys.version_info[:3]))
    detail = f"{version} ({sys.executable})"
    if sys.version_info[:2] not in ((3, 11), (3, 13)):
        return Check("python", WARN, f"{detail}: the aarch64 locks are for 3.11 (Bookworm) and 3.13 (Trixie)",
                     "install into a Python 3.11 or 3.13 venv")
    return Check("python", OK, detail)


def _memory_controller() -> tuple[bool | None, str]:
    """(enabled, where it was read); None when neither file exists (not Linux, a sandbox)."""
    try:
        return "memory" in CGROUP_CONTROLLERS.read_text().split(), str(CGROUP_CONTROLLERS)
    except OSError:
        pass
    try:
        for line in PROC_CGROUPS.read_text().splitlines():
            fields = line.split()
            if fields and fields[0] == "memory" and len(fields) >= 4:
                return fields[3] == "1", f"{PROC_CGROUPS} (cgroup v1)"
        return False, str(PROC_CGROUPS)
    except OSError:
        return None, "neither /sys/fs/cgroup/cgroup.controllers nor /proc/cgroups"


def check_memory_cgroup(_settings: Any) -> Check:
    enabled, where = _memory_controller()
    if enabled is None:
        return Check("memory-cgroup", WARN, f"cannot tell: {where} is readable", CMDLINE_FIX)
    if enabled:
        return Check("memory-cgroup", OK, f"the memory controller is enabled ({where})")
    return Check("memory-cgroup", WARN, f"the memory controller is off ({where}): systemd ignores the units' "
                 "MemoryHigh=/MemoryMax=, only the trainer's own budget guards memory", CMDLINE_FIX)


def check_page_size(settings: Any) -> Check:
    page = os.sysconf("SC_PAGE_SIZE")
    detail = f"{page // 1024} KiB pages"
    if page <= 4096:
        return Check("page-size", OK, detail)
    if not getattr(settings, "redis_url", None):
        return Check("page-size", OK, f"{detail}; the embedded broker needs no Redis")
    return Check("page-size", WARN, f"{detail} and redis_url is set: Redis builds using jemalloc crash on them "
                 "('Unsupported system page size')",
                 "use the embedded broker (remove redis_url / HOPE_REDIS_URL), or boot the 4 KiB kernel "
                 "('kernel=kernel8.img' in /boot/firmware/config.txt)")


def check_thermal(settings: Any) -> list[Check]:
    """The zone file's temperature and `vcgencmd get_throttled`'s flags, through the readers the
    trainer and the daemon use. Missing sources are a fail only on a Raspberry Pi, where they exist."""
    zone, vcgencmd = settings.thermal_zone_path, settings.vcgencmd_path
    reader = ThermalGovernor(zone, vcgencmd, settings.thermal_soft_c, settings.thermal_hard_c,
                             settings.thermal_resume_c)
    reading = reader.sample()
    missing = FAIL if is_raspberry_pi() else WARN
    return [_zone_line(settings, zone, reading.temp_c, missing),
            _vcgencmd_line(vcgencmd, reading.throttled_flags, missing)]


def _zone_line(settings: Any, zone: str, temp: float | None, missing: str) -> Check:
    if temp is None:
        return Check("thermal-zone", missing, f"{zone or '(none configured)'} gives no temperature: jobs train "
                     "without a thermal guard", "point thermal_zone_path / HOPE_THERMAL_ZONE at a readable "
                     "zone (/sys/class/thermal/thermal_zone0/temp on a Pi)")
    detail = f"{temp:.1f} C from {zone}"
    if temp >= settings.thermal_hard_c:
        return Check("thermal-zone", FAIL, f"{detail}: at or above the hard limit {settings.thermal_hard_c:g} C, "
                     "jobs pause", "cool the board: fan or heatsink (the Pi 5 Active Cooler), airflow")
    if temp >= settings.thermal_soft_c:
        return Check("thermal-zone", WARN, f"{detail}: above the soft limit {settings.thermal_soft_c:g} C, jobs "
                     "slow down", "improve the cooling (the Pi 5 Active Cooler)")
    return Check("thermal-zone", OK, detail)


def _vcgencmd_line(vcgencmd: str, flags: Any, missing: str) -> Check:
    if flags is None:
        if not vcgencmd or not shutil.which(vcgencmd):
            return Check("vcgencmd", missing if is_raspberry_pi() else SKIP,
                         f"{vcgencmd or '(none configured)'} is not found", "sudo apt install raspi-utils "
                         "(libraspberrypi-bin on Bookworm)" if is_raspberry_pi() else "")
        return Check("vcgencmd", missing, f"{vcgencmd} get_throttled failed or printed no flags",
                     "add the service user to the video group (/dev/vcio): sudo usermod -aG video $USER")
    now = [n for n in ("under_voltage", "arm_freq_capped", "throttled", "soft_temp_limit") if getattr(flags, n)]
    past = [n for n in ("under_voltage_occurred", "arm_freq_capped_occurred", "throttled_occurred",
                        "soft_temp_limit_occurred") if getattr(flags, n)]
    detail = f"throttled={hex(flags.raw)}" + (f", now: {', '.join(now)}" if now else "") + \
        (f", since boot: {', '.join(past)}" if past else "")
    if flags.under_voltage or flags.under_voltage_occurred:
        return Check("vcgencmd", WARN, detail, "use a 5 V / 5 A supply (the official 27 W USB-C one)")
    if now or past:
        return Check("vcgencmd", WARN, detail, "improve the cooling (the Pi 5 Active Cooler)")
    return Check("vcgencmd", OK, detail)


def check_memory(settings: Any) -> Check:
    import psutil  # lazy: loads psutil

    vm = psutil.virtual_memory()
    budget = int(settings.memory_budget_mb)
    detail = f"{vm.available // MB} MB available of {vm.total // MB} MB; job budget {budget} MB"
    if vm.total // MB < budget:
        return Check("memory", FAIL, f"{detail}: the budget is more than this machine has",
                     "lower memory_budget_mb / HOPE_MEMORY_BUDGET_MB (docs/pi.md, 'Memory and CPU budget')")
    if vm.available // MB < budget:
        return Check("memory", WARN, f"{detail}: a job at its budget would not fit now",
                     "stop what else is using memory, or lower memory_budget_mb")
    return Check("memory", OK, detail)


def checkpoints_mb(home: Path) -> float:
    """The largest checkpoint step dir under $HOPE_HOME/runs, in MB (0 with none): with no job at
    hand, the biggest one a job here has written stands in for the next job's."""
    largest = 0
    for step_dir in (home / "runs").glob("*/checkpoints/*"):
        if step_dir.is_dir() and not step_dir.is_symlink():
            size = sum(f.stat().st_size for f in step_dir.rglob("*") if f.is_file() and not f.is_symlink())
            largest = max(largest, size)
    return largest / MB


def _default_keep() -> int:
    defaults: dict[str, Any] = {f.name: f.default for f in fields(TrainConfig)}  # keep_last has one
    return int(defaults["keep_last"])


def disk_floor_mb(settings: Any) -> tuple[float, str]:
    """(floor, how it was chosen), by the daemon's rule (hope_models/disk.py): disk_floor_mb when
    set (> 0), else a checkpoint x (keep_last + 2) + 200 MB."""
    setting = float(getattr(settings, "disk_floor_mb", 0) or 0)
    if setting > 0:
        return dispatch_floor_mb(0.0, 1, setting), "disk_floor_mb"
    ckpt, keep = checkpoints_mb(Path(settings.home)), _default_keep()
    return dispatch_floor_mb(ckpt, keep), \
        f"{FLOOR_MARGIN_MB:.0f} MB + the largest checkpoint here ({ckpt:.0f} MB) x {keep + 2}"


def check_disk(settings: Any) -> Check:
    free = free_mb(settings.home)
    floor, how = disk_floor_mb(settings)
    if free is None:
        return Check("disk", FAIL, f"the free space under {settings.home} cannot be read",
                     "check that $HOPE_HOME's filesystem is mounted")
    detail = f"{free:.0f} MB free under {settings.home}; floor {floor:.0f} MB ({how})"
    if free < floor:
        return Check("disk", FAIL, f"{detail}: the daemon will not start a job",
                     "free space: delete old runs under $HOPE_HOME/runs (or lower keep_runs), or use a larger card")
    return Check("disk", OK, detail)
