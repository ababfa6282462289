#!/usr/bin/env bash
# `make pi-smoke`: run the project on arm64 code under qemu-user, the way a Raspberry Pi 5 on
# Bookworm (Python 3.11) would install and run it.
#
#   1. a Debian bookworm arm64 root filesystem (debootstrap from the Debian mirror), cached under
#      $PI_SMOKE_CACHE so a second run reuses it (~4 min the first time);
#   2. a venv in it, installed from requirements/pi-aarch64-py311.txt (--require-hashes: every
#      dependency must come as an aarch64 wheel or sdist pinned there), then the project itself
#      from a copy of this checkout (--no-deps);
#   3. sim-demos --episodes 3 -> ingest -> train --component fast_loop --steps 50 -> promote ->
#      infer --local, each timed, with a summary table at the end.
#
# Needs root (debootstrap, chroot, mounts) and network to the Debian mirror and PyPI. Slow under
# emulation and not part of `make test`. Everything runs inside the root under `env -i` (the host's
# PIP_* settings point at x86 wheels), with QEMU_CPU=cortex-a76: qemu's default CPU advertises SVE,
# which the Pi 5 (Cortex-A76) lacks, and torch's oneDNN then takes SVE paths ~18x slower.
#
# Settings (environment): PI_SMOKE_CACHE (default /var/cache/hope-pi-smoke), PI_SMOKE_LOCK (default
# requirements/pi-aarch64-py311.txt), PI_SMOKE_MIRROR (default http://deb.debian.org/debian),
# PI_SMOKE_QEMU_CPU (default cortex-a76), PI_SMOKE_PIP_INDEX_URL (only if PyPI must be reached
# through a mirror), PI_SMOKE_KEEP_MOUNTS=1 to leave /proc etc. mounted for a look inside.
set -euo pipefail

REPO=$(cd "$(dirname "$0")/.." && pwd)
CACHE=${PI_SMOKE_CACHE:-/var/cache/hope-pi-smoke}
LOCK=${PI_SMOKE_LOCK:-$REPO/requirements/pi-aarch64-py311.txt}
MIRROR=${PI_SMOKE_MIRROR:-http://deb.debian.org/debian}
QEMU_CPU_MODEL=${PI_SMOKE_QEMU_CPU:-cortex-a76}
ROOT=$CACHE/bookworm-arm64
VENV=/opt/hope-venv          # inside the root
SRC=/opt/hope-src            # inside the root
HOME_IN=/root/hope-smoke     # HOPE_HOME inside the root, emptied on every run
# A reacher observation in the fast_loop's feature order (2 joint positions, 2 velocities, the
# 2-D target offset); `infer` lists the fields if the model ever wants others.
OBSERVATION='[0.1,-0.2,0.0,0.0,0.05,0.03]'

log() { printf '[pi-smoke %s] %s\n' "$(date -u +%H:%M:%S)" "$*"; }
die() { printf 'pi-smoke: %s\n' "$*" >&2; exit 1; }

[ "$(id -u)" = 0 ] || die "needs root (debootstrap, chroot, binfmt_misc): sudo make pi-smoke"
[ -f "$LOCK" ] || die "no lock file $LOCK (PI_SMOKE_LOCK=... to use another)"

STEPS=()      # "name|seconds|exit code" in the order they ran
timed() {     # timed NAME COMMAND...: run, print and record its wall time; stop on failure
  local name=$1; shift
  local t0 t1 rc
  log "== $name"
  t0=$(date +%s.%N)
  set +e; "$@"; rc=$?; set -e
  t1=$(date +%s.%N)
  local secs; secs=$(awk -v a="$t0" -v b="$t1" 'BEGIN{printf "%.1f", b-a}')
  STEPS+=("$name|$secs|$rc")
  log "-- $name: exit $rc in ${secs}s"
  if [ "$rc" != 0 ]; then summary; die "$name failed (exit $rc)"; fi
}
summary() {
  printf '\n%-52s %9s %5s\n' "step (arm64 under qemu-user, QEMU_CPU=$QEMU_CPU_MODEL)" "seconds" "exit"
  local s; for s in "${STEPS[@]}"; do
    IFS='|' read -r n t r <<<"$s"; printf '%-52s %9s %5s\n' "$n" "$t" "$r"
  done
}

# --- host tools: qemu-user-static, debootstrap, binfmt_misc ------------------------------------
if ! command -v qemu-aarch64-static >/dev/null || ! command -v debootstrap >/dev/null \
   || ! command -v update-binfmts >/dev/null; then
  log "apt-get install qemu-user-static debootstrap binfmt-support"
  apt-get install -y -q qemu-user-static debootstrap binfmt-support >/dev/null \
    || { apt-get update -q >/dev/null && apt-get install -y -q qemu-user-static debootstrap binfmt-support >/dev/null; }
fi
if [ ! -e /proc/sys/fs/binfmt_misc/register ]; then
  mount -t binfmt_misc binfmt_misc /proc/sys/fs/binfmt_misc
fi
if [ ! -e /proc/sys/fs/binfmt_misc/qemu-aarch64 ]; then
  update-binfmts --enable qemu-aarch64 || update-binfmts --import qemu-aarch64
fi
[ -e /proc/sys/fs/binfmt_misc/qemu-aarch64 ] || die "qemu-aarch64 is not registered in binfmt_misc"

# --- the root filesystem (cached) -------------------------------------------------------------
mkdir -p "$CACHE"
if [ ! -f "$ROOT/.debootstrap-done" ]; then
  rm -rf "$ROOT.tmp"
  timed "debootstrap bookworm arm64 (first run only)" \
    debootstrap --arch=arm64 --variant=minbase --include=python3-venv,python3-pip,ca-certificates \
      bookworm "$ROOT.tmp" "$MIRROR"
  rm -rf "$ROOT"; mv "$ROOT.tmp" "$ROOT"; touch "$ROOT/.debootstrap-done"
else
  log "reusing the root filesystem $ROOT"
fi

MOUNTS=()
cleanup() {
  [ "${PI_SMOKE_KEEP_MOUNTS:-0}" = 1 ] && return 0
  local i; for ((i=${#MOUNTS[@]}-1; i>=0; i--)); do umount -l "${MOUNTS[$i]}" 2>/dev/null || true; done
}
trap cleanup EXIT
mnt() { local where=$ROOT$1; shift; mountpoint -q "$where" && return 0; mount "$@" "$where"; MOUNTS+=("$where"); }
mnt /proc -t proc proc
mnt /sys -t sysfs sysfs
mnt /dev --bind /dev
mnt /dev/shm -t tmpfs -o size=512m tmpfs
cp /etc/resolv.conf "$ROOT/etc/resolv.conf"

# Everything inside runs with a clean environment: nothing of the host's PIP_*, only the CA bundle
# (the host's local CAs are copied in below) and, if set, an index mirror.
PIP_ENV=(PIP_CERT=/etc/ssl/certs/ca-certificates.crt PIP_DISABLE_PIP_VERSION_CHECK=1 PIP_DEFAULT_TIMEOUT=180)
[ -n "${PI_SMOKE_PIP_INDEX_URL:-}" ] && PIP_ENV+=(PIP_INDEX_URL="$PI_SMOKE_PIP_INDEX_URL")
inside() {
  chroot "$ROOT" /usr/bin/env -i HOME=/root LANG=C.UTF-8 PATH=$VENV/bin:/usr/sbin:/usr/bin:/sbin:/bin \
    QEMU_CPU="$QEMU_CPU_MODEL" HOPE_HOME=$HOME_IN MUJOCO_GL=disabled "${PIP_ENV[@]}" "$@"
}

# The host's local CA certificates (a TLS-inspecting proxy's, say), so pip reaches the registry.
if compgen -G "/usr/local/share/ca-certificates/*" >/dev/null; then
  mkdir -p "$ROOT/usr/local/share/ca-certificates"
  cp -r /usr/local/share/ca-certificates/. "$ROOT/usr/local/share/ca-certificates/"
fi
inside update-ca-certificates >/dev/null 2>&1 || die "update-ca-certificates failed inside the root"

inside /bin/sh -c 'echo "inside: $(uname -m), $(python3 --version), Debian $(cat /etc/debian_version)"'

# --- the venv from the lock (rebuilt when the lock changes) -----------------------------------
lock_sum=$(sha256sum "$LOCK" | cut -d' ' -f1)
if [ "$(cat "$ROOT$VENV/.lock-sha256" 2>/dev/null)" != "$lock_sum" ]; then
  rm -rf "$ROOT$VENV"
  cp "$LOCK" "$ROOT/opt/lock.txt"
  timed "venv + pip install --require-hashes -r $(basename "$LOCK")" \
    inside /bin/sh -c "python3 -m venv $VENV && $VENV/bin/pip install -q --only-binary=:all: --require-hashes -r /opt/lock.txt"
  echo "$lock_sum" >"$ROOT$VENV/.lock-sha256"
else
  log "reusing the venv (lock unchanged: $(basename "$LOCK"))"
fi

# --- the project from this checkout (tracked and new files, not the ignored ones) --------------
rm -rf "$ROOT$SRC"; mkdir -p "$ROOT$SRC"
(cd "$REPO" && git ls-files -z --cached --others --exclude-standard \
   | while IFS= read -r -d '' f; do [ -f "$f" ] && printf '%s\0' "$f"; done \
   | tar --null -T - -cf -) \
  | tar -C "$ROOT$SRC" -xf -
timed "pip install --no-deps the project" inside pip install -q --no-deps $SRC

inside python -c 'import platform, torch, mujoco, dm_control; print("arm64 check:", platform.machine(), "torch", torch.__version__, "cpu capability", torch.backends.cpu.get_cpu_capability(), "mujoco", mujoco.__version__)'

# --- the pipeline --------------------------------------------------------------------------------
rm -rf "$ROOT$HOME_IN"; mkdir -p "$ROOT$HOME_IN"
hope() { inside python -m hope_trainer "$@"; }
timed "sim-demos --episodes 3" hope sim-demos --episodes 3 --out $HOME_IN/demos
timed "ingest" hope ingest --into $HOME_IN/data $HOME_IN/demos
timed "train --component fast_loop --steps 50" \
  hope train --component fast_loop --data $HOME_IN/data --run-dir $HOME_IN/runs/smoke --steps 50
timed "promote (gate: finite, val_loss, reflex)" hope promote --checkpoint $HOME_IN/runs/smoke
timed "infer --local" hope infer --local --observation "$OBSERVATION"

summary
log "pi-smoke passed: every step exited 0 on aarch64"
