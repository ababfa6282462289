#!/bin/sh
# Install the HOPE Seed Trainer as three systemd services (daemon, worker, webapp) on a Pi.
#
#   sudo systemd/install.sh                      # repo = this checkout; `make install` -> /opt/hope-trainer/venv
#   sudo systemd/install.sh --python /opt/hope/venv/bin/python --no-start   # an existing venv, no install
#
# What it does (docs/pi.md explains each step):
#   0. unless --python is given, `make install` (runtime + sim from the lock, no dev tools) into --venv;
#   1. checks the venv's python can import the services without torch in the parents;
#   2. creates the system user `hope` (in the video group for vcgencmd) and /var/lib/hope-trainer (0700);
#   3. writes the unit files to /etc/systemd/system with the repo and python paths filled in;
#   4. writes /etc/default/hope-trainer (site overrides) if it does not exist;
#   5. systemctl daemon-reload, enable (and start unless --no-start) the three services;
#   6. warns when the memory cgroup controller is off (MemoryMax would be silently ignored).
# Re-running it is safe: units are rewritten, the user, state dir and overrides file are kept.
#
# Options: --repo DIR, --venv DIR, --python PATH, --user NAME, --state-dir DIR, --unit-dir DIR (default
# /etc/systemd/system), --defaults-file FILE (default /etc/default/hope-trainer), --no-start,
# --no-systemctl (only write files: for images and tests), --no-user (do not create the user).
set -eu

here=$(cd "$(dirname "$0")" && pwd)
repo=$(dirname "$here")
python=""
venv=/opt/hope-trainer/venv
user=hope
state_dir=/var/lib/hope-trainer
unit_dir=/etc/systemd/system
defaults_file=/etc/default/hope-trainer
start=1
use_systemctl=1
make_user=1

die() { echo "install.sh: $*" >&2; exit 1; }

while [ $# -gt 0 ]; do
  case "$1" in
    --repo) repo=$2; shift 2 ;;
    --python) python=$2; shift 2 ;;
    --venv) venv=$2; shift 2 ;;
    --user) user=$2; shift 2 ;;
    --state-dir) state_dir=$2; shift 2 ;;
    --unit-dir) unit_dir=$2; shift 2 ;;
    --defaults-file) defaults_file=$2; shift 2 ;;
    --no-start) start=0; shift ;;
    --no-systemctl) use_systemctl=0; start=0; shift ;;
    --no-user) make_user=0; shift ;;
    -h|--help) sed -n '2,19p' "$0"; exit 0 ;;
    *) die "unknown option $1 (see --help)" ;;
  esac
done

repo=$(cd "$repo" 2>/dev/null && pwd) || die "--repo: no such directory"
[ -f "$repo/run_trainer.py" ] || die "$repo has no run_trainer.py: pass --repo <the hope-seed-trainer checkout>"
# 0. the production venv: exact pins for this arch and Python (make install; docs/pi.md "Install")
if [ -z "$python" ]; then
  make -C "$repo" install INSTALL_VENV="$venv" || die "make install into $venv failed (see above)"
  python="$venv/bin/python"
fi
[ -x "$python" ] || die "python $python not found: run make install or pass --python"

# 1. the services must import, and their parents must not load torch (memory budget)
"$python" - "$repo" <<'PY' || die "the venv at $python cannot run the services (see the error above)"
import sys
sys.path.insert(0, sys.argv[1])
import daemon, workers, webapp, run_trainer  # noqa: F401
run_trainer.build_parser()
assert "torch" not in sys.modules, "a service parent imported torch"
PY

# 2. user and state directory
if [ "$make_user" = 1 ]; then
  [ "$(id -u)" = 0 ] || die "run as root (sudo) to create the user $user, or pass --no-user"
  if ! id "$user" >/dev/null 2>&1; then
    useradd --system --home-dir "$state_dir" --no-create-home --shell /usr/sbin/nologin "$user"
    echo "created system user $user"
  fi
  if getent group video >/dev/null 2>&1; then
    usermod -a -G video "$user"
  fi
  # the registry and the API token live here: the service user's alone (the units set UMask=0077)
  install -d -m 0700 -o "$user" -g "$user" "$state_dir"
  install -d -m 0700 -o "$user" -g "$user" "$state_dir/logs"
else
  install -d -m 0700 "$state_dir"
fi

# 3. unit files with the paths filled in
install -d "$unit_dir"
for unit in hope-daemon.service hope-worker.service hope-webapp.service; do
  sed -e "s|@REPO@|$repo|g" -e "s|@PYTHON@|$python|g" \
      -e "s|^User=hope$|User=$user|" -e "s|^Group=hope$|Group=$user|" \
      -e "s|^Environment=HOPE_HOME=/var/lib/hope-trainer$|Environment=HOPE_HOME=$state_dir|" \
      -e "s|^ReadWritePaths=/var/lib/hope-trainer$|ReadWritePaths=$state_dir|" \
      "$here/$unit" > "$unit_dir/$unit.tmp"
  chmod 0644 "$unit_dir/$unit.tmp"
  mv "$unit_dir/$unit.tmp" "$unit_dir/$unit"
  echo "wrote $unit_dir/$unit"
done

# 4. site overrides, never overwritten (it may hold the Redis password)
if [ ! -e "$defaults_file" ]; then
  install -d "$(dirname "$defaults_file")"
  cat > "$defaults_file" <<'EOF'
# Overrides for hope-daemon, hope-worker and hope-webapp (read by systemd; KEY=value lines).
# HOPE_REDIS_URL=redis://:PASSWORD@127.0.0.1:6379/0
# HOPE_MEMORY_BUDGET_MB=3072
# HOPE_HOST=127.0.0.1
# HOPE_PORT=8765
# HOPE_INFERENCE_PORT=8766
EOF
  chmod 0640 "$defaults_file"
  echo "wrote $defaults_file"
fi

# 5. systemd
if [ "$use_systemctl" = 1 ]; then
  command -v redis-server >/dev/null 2>&1 || \
    echo "warning: redis-server is not installed; the services expect it: apt-get install redis-server" >&2
  systemctl daemon-reload
  systemctl enable hope-daemon.service hope-worker.service hope-webapp.service
  if [ "$start" = 1 ]; then
    systemctl restart hope-daemon.service hope-worker.service hope-webapp.service
    echo "started; check with: systemctl status 'hope-*'  and  journalctl -u hope-daemon -f"
  else
    echo "enabled; start with: systemctl start hope-daemon hope-worker hope-webapp"
  fi
fi

# 6. the memory cgroup (off by default on Raspberry Pi OS)
controllers=/sys/fs/cgroup/cgroup.controllers
if [ -r "$controllers" ] && ! grep -qw memory "$controllers"; then
  echo "warning: the memory cgroup controller is off, so MemoryHigh/MemoryMax are ignored." >&2
  echo "  add 'cgroup_enable=memory cgroup_memory=1' to /boot/firmware/cmdline.txt and reboot (docs/pi.md)" >&2
fi
exit 0
