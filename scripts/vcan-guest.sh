#!/usr/bin/env bash
# Runs inside the vcan lane's micro-VM (scripts/vcan.sh starts it there; not meant to be run by
# hand): brings vcan0 up, then runs the lane's command with the caller's environment and
# leaves its exit code where the host reads it. Process starts are slow under software
# emulation (~0.3 s each), so this script keeps to builtins where it can.
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

# can_raw too: the command's sockets need it, and it is loaded before the mounts change.
if ! err=$({ modprobe -a vcan can_raw &&
    printf 'link add dev %s type vcan\nlink set dev %s txqueuelen %s\nlink set up dev %s\n' \
        "$IFACE" "$IFACE" "$TXQUEUELEN" "$IFACE" | ip -batch -; } 2>&1); then
    printf 'cannot bring %s up in the guest (kernel %s): %s\n' "$IFACE" "$KERNEL_RELEASE" "$err" >"$LANE/setup-failed"
    cat "$LANE/setup-failed" >&2
    exit 97
fi

# The host's file system again, with the guest's page cache on (virtme-ng's own 9p mounts have
# none, so every file read and page fault is a round trip to the host, and Python takes ~10 s to
# start instead of ~1 s): scripts/vcan.sh adds two 9p shares, the host's root (tag vcanroot,
# read-only) and the repository (tag vcanrepo, read-write). Each non-empty top-level directory
# of the root becomes an overlay of the cached share under a tmpfs (the guest can write there;
# nothing reaches the host), then the repository is mounted over its place, read-write. The
# guest's own /etc, /var, /tmp, /run, /dev, /proc, /sys stay. If anything fails, everything is
# undone and virtme-ng's uncached mounts serve: slower, same result.
fast_mounts() {
    local opts=trans=virtio,version=9p2000.L,access=any,msize=512000,cache=loose
    local stage=/run/vcan-lane dir name names=() dirs=() entries mounted=() i
    mkdir -p "$stage/root" "$stage/repo" || return 1
    mount -t 9p -o "$opts,ro" vcanroot "$stage/root" || return 1
    if ! mount -t 9p -o "$opts" vcanrepo "$stage/repo"; then
        umount "$stage/root"
        return 1
    fi
    shopt -s nullglob dotglob
    for dir in "$stage"/root/*/; do
        name=${dir%/}
        name=${name##*/}
        case $name in proc | sys | dev | run | tmp | etc | var | boot | lost+found) continue ;; esac
        entries=("$dir"*)
        if [ ${#entries[@]} -eq 0 ] || [ -L "$stage/root/$name" ] || [ ! -d "/$name" ] || [ -L "/$name" ]; then
            continue
        fi
        names+=("$name")
        dirs+=("$stage/upper/$name/upper" "$stage/upper/$name/work")
    done
    shopt -u nullglob dotglob
    if [ ${#dirs[@]} -gt 0 ] && mkdir -p "${dirs[@]}"; then
        for name in "${names[@]}"; do
            if mount -t overlay -o "lowerdir=$stage/root/$name,upperdir=$stage/upper/$name/upper,workdir=$stage/upper/$name/work" \
                "vcan-$name" "/$name"; then
                mounted+=("/$name")
            fi
        done
    fi
    if mount --move "$stage/repo" "$ROOT"; then
        return 0
    fi
    # An overlay may now hide virtme-ng's read-write mount of the repository: undo them all.
    for ((i = ${#mounted[@]} - 1; i >= 0; i--)); do
        umount "${mounted[$i]}"
    done
    umount "$stage/repo" "$stage/root"
    return 1
}

if ! fast_mounts; then
    echo "vcan-guest: page-cached mounts failed; using virtme-ng's uncached ones (slower)" >&2
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
