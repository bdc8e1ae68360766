#!/usr/bin/env bash
# Runs inside the vcan lane's micro-VM (scripts/vcan-init.sh starts it there, in the host's root
# with the repository mounted; not meant to be run by hand): brings vcan0 up, then runs the
# lane's command with the caller's environment and leaves its exit code where the host reads
# it. Process starts are slow under software emulation, so this script keeps to builtins.
# Usage: vcan-guest.sh LANE_DIR REPO_ROOT IFACE TXQUEUELEN
set -uo pipefail
LANE=$1 ROOT=$2 IFACE=$3 TXQUEUELEN=$4

uptime_s() {
    local up _
    read -r up _ </proc/uptime
    printf '%s' "$up"
}
read -r KERNEL_RELEASE </proc/sys/kernel/osrelease
UP_START=$(uptime_s)
echo "vcan-guest: kernel $KERNEL_RELEASE, up after ${UP_START} s"

# The modules (vcan, can_raw) are loaded already: scripts/vcan-init.sh did, from the initramfs.
# Loopback too: the live server's tests connect to 127.0.0.1.
if ! err=$(printf 'link set lo up\nlink add dev %s type vcan\nlink set dev %s txqueuelen %s\nlink set up dev %s\n' \
    "$IFACE" "$IFACE" "$TXQUEUELEN" "$IFACE" | ip -batch - 2>&1); then
    printf 'cannot bring %s up in the guest (kernel %s): %s\n' "$IFACE" "$KERNEL_RELEASE" "$err" >"$LANE/setup-failed"
    cat "$LANE/setup-failed" >&2
    exit 97
fi

# shellcheck source=/dev/null
. "$LANE/env.sh"
# A TMPDIR of the host's that the guest does not have (under /run, say) would break mktemp.
if [ -n "${TMPDIR:-}" ] && [ ! -d "$TMPDIR" ]; then
    unset TMPDIR
fi

# Socket receive buffers of 32 MiB by default: a process the emulated CPU runs slowly
# (Python's can.logger, say) falls behind a 1 kHz bus for a while and catches up instead of
# losing frames. (The guest is ours: its settings go with it.)
printf '%s\n' 33554432 >/proc/sys/net/core/rmem_default
printf '%s\n' 33554432 >/proc/sys/net/core/rmem_max

# The scheduler's counts of idle entries (/proc/schedstat), which tests/lane.py reports per test.
printf '1\n' >/proc/sys/kernel/sched_schedstats 2>/dev/null || true

cd "$ROOT" || exit 98
UP_READY=$(uptime_s)
echo "vcan-guest: $IFACE up, running the command after ${UP_READY} s"
: >"$LANE/started"
bash "$LANE/command.sh"
rc=$?
printf '%s %s %s\n' "$UP_START" "$UP_READY" "$(uptime_s)" >"$LANE/timing"
printf '%s\n' "$rc" >"$LANE/exit-code"
sync
exit "$rc"
