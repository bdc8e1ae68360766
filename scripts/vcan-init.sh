#!/bin/busybox sh
# PID 1 of the vcan lane's micro-VM (scripts/vcan.sh packs it into the guest's initramfs as
# /init, with busybox, the kernel modules it lists in /modules.list and the run's /lane.env).
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
. /lane.env # ROOT LANE IFACE TXQUEUELEN (scripts/vcan.sh writes it)
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
# The repository last: it may live under /tmp or /run, which the guest has of its own.
busybox mkdir -p "/newroot$ROOT"
busybox mount -t 9p -o "$opts" vcanrepo "/newroot$ROOT" || fail "mount the repository (9p vcanrepo) at $ROOT"
# The console as a plain byte stream: no \r added before each \n.
busybox stty -F /dev/console -opost 2>/dev/null

busybox chroot /newroot /bin/bash "$ROOT/scripts/vcan-guest.sh" "$LANE" "$ROOT" "$IFACE" "$TXQUEUELEN" \
    </dev/null >/dev/console 2>&1
busybox sync
busybox poweroff -f
