#!/bin/busybox sh
# PID 1 of the vcan lane's micro-VM (scripts/vcan-vm.py packs it into the guest's initramfs as
# /init, with busybox, the kernel modules it lists in /modules.list, the run's /lane.env and
# /ram.list).
# It loads the modules from the initramfs, mounts the host's root read-only over 9p with the
# guest's page cache on, under an overlay whose upper layer is the guest's memory (the guest may
# write anywhere; nothing reaches the host), mounts the repository read-write at its own path,
# then runs scripts/vcan-guest.sh there and powers the machine off. No udev, no systemd, no
# module probing: under software emulation every instruction of a boot costs wall time.
export PATH=/bin
busybox mount -t proc proc /proc
busybox mount -t sysfs sys /sys
busybox mount -t devtmpfs dev /dev
# shellcheck source=/dev/null
. /lane.env # ROOT LANE IFACE TXQUEUELEN (scripts/vcan-vm.py writes it)
# Magic SysRq on (the host's time-out asks for the blocked tasks through the PS/2 keyboard).
echo 1 >/proc/sys/kernel/sysrq

fail() {
    echo "vcan-init: $*" >&2
    # The host names this line's text as why the lane could not run.
    echo "vcan-init: setup failed: $*"
    busybox poweroff -f
}

while read -r module; do
    busybox insmod "/lib/modules/$module" || fail "insmod $module"
done </modules.list

opts=trans=virtio,version=9p2000.L,access=any,msize=512000,cache=loose
busybox mkdir -p /host /upper /newroot
busybox mount -t 9p -o "$opts,ro" vcanroot /host || fail "mount the host's root (9p vcanroot)"
busybox mount -t tmpfs -o mode=0755 upper /upper || fail "tmpfs for the overlay"
busybox mkdir -p /upper/data /upper/work
busybox mount -t overlay -o lowerdir=/host,upperdir=/upper/data,workdir=/upper/work root /newroot ||
    fail "the overlay over the host's root"
for fs in proc:proc sysfs:sys devtmpfs:dev tmpfs:tmp tmpfs:run; do
    busybox mount -t "${fs%%:*}" "${fs%%:*}" "/newroot/${fs#*:}" || fail "mount ${fs#*:}"
done
busybox mkdir -p /newroot/dev/pts /newroot/dev/shm
busybox mount -t devpts devpts /newroot/dev/pts
busybox mount -t tmpfs shm /newroot/dev/shm
busybox chmod 1777 /newroot/tmp /newroot/dev/shm

# The trees the lane runs from, copied into the guest's memory (/ram.list, written by
# scripts/vcan-vm.py): `tree PATH` is a tmpfs at PATH holding a copy of the host's PATH, but
# for the `skip PATH` entries under it, which stay the host's (symbolic links into its root,
# at /run/vcan-host), and the `empty PATH` ones, made as empty directories. The guest's clock
# runs on while every guest process waits on the host (QEMU -icount sleep=off jumps to the
# next timer), so a file read or opened through 9p mid-test could let another process's timer
# fire first: a 60 s time-out while `ip` waited for its own binary, a plant's loop stalled
# behind a page fault while the runner's went on.
busybox mkdir -p /newroot/run/vcan-host
busybox mount --bind /host /newroot/run/vcan-host
listed() { busybox grep -qxF "$1 $2" /ram.list; }
listed_below() { busybox grep -qF " $1/" /ram.list; }
copy_children() { # PATH: the host's PATH's entries into the new root's PATH
    local entry name
    for entry in "/host$1"/* "/host$1"/.[!.]* "/host$1"/..?*; do
        [ -e "$entry" ] || [ -L "$entry" ] || continue
        name=${entry##*/}
        if listed skip "$1/$name"; then
            busybox ln -s "/run/vcan-host$1/$name" "/newroot$1/$name"
        elif listed empty "$1/$name"; then
            busybox mkdir -p "/newroot$1/$name"
        elif [ -d "$entry" ] && [ ! -L "$entry" ] && listed_below "$1/$name"; then
            busybox mkdir -p "/newroot$1/$name"
            copy_children "$1/$name"
        else
            busybox cp -a "$entry" "/newroot$1/" || fail "copy $1/$name into memory"
        fi
    done
}
while read -r kind path; do
    if [ "$kind" = tree ]; then
        busybox mkdir -p "/newroot$path"
        busybox mount -t tmpfs -o mode=0755 ram "/newroot$path" || fail "tmpfs at $path"
        copy_children "$path"
    fi
done </ram.list
# The repository, shared read-write, at its place (mounted after the guest's own /tmp and /run,
# where it may live); when its copy in memory is there instead, the lane's directory alone is
# bound from it at its place: it stays the host's (the exit code, the timing).
if listed tree "$ROOT"; then
    busybox mkdir -p /newroot/run/vcan-repo "/newroot$LANE"
    busybox mount -t 9p -o "$opts" vcanrepo /newroot/run/vcan-repo || fail "mount the repository (9p vcanrepo)"
    busybox mount --bind "/newroot/run/vcan-repo${LANE#"$ROOT"}" "/newroot$LANE" ||
        fail "bind the lane's directory $LANE"
else
    busybox mkdir -p "/newroot$ROOT"
    busybox mount -t 9p -o "$opts" vcanrepo "/newroot$ROOT" || fail "mount the repository (9p vcanrepo) at $ROOT"
fi
# The console as a plain byte stream: no \r added before each \n.
busybox stty -F /dev/console -opost 2>/dev/null

busybox chroot /newroot /bin/bash "$ROOT/scripts/vcan-guest.sh" "$LANE" "$ROOT" "$IFACE" "$TXQUEUELEN" \
    </dev/null >/dev/console 2>&1
busybox sync
busybox poweroff -f
