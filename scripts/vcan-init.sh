#!/bin/busybox sh
# PID 1 of the vcan lane's micro-VM (scripts/vcan-vm.py packs it into the guest's initramfs as
# /init, with busybox, the kernel modules it lists in /modules.list, the run's /lane.env and
# the trees the lane runs from under /trees).
# It loads the modules from the initramfs, mounts the host's root read-only over 9p with the
# guest's page cache on, under an overlay whose upper layer is the guest's memory (the guest may
# write anywhere; nothing reaches the host) and whose top lower layer is /trees; the repository
# likewise at its own path, with the lane's directory alone written through to the host; then
# runs scripts/vcan-guest.sh there and powers the machine off. No udev, no systemd, no module
# probing: under software emulation every instruction of a boot costs wall time.
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

# /trees holds, at their own paths, the files the lane runs from (its .venv, its Python, the
# repository and the binaries; scripts/vcan-vm.py lists them), unpacked by the kernel from the
# initramfs. It is the top lower layer of both overlays: those files are read from memory, any
# other file from the host through 9p. The guest's clock runs on while every guest process
# waits on the host (QEMU -icount sleep=off jumps to the next timer), so a file read through 9p
# mid-test could let another process's timer fire first: a 60 s time-out while `ip` waited for
# its own binary, a plant's loop stalled behind a page fault while the runner's went on.
opts=trans=virtio,version=9p2000.L,access=any,msize=512000,cache=loose
busybox mkdir -p /host /upper /newroot /trees
busybox mount -t 9p -o "$opts,ro" vcanroot /host || fail "mount the host's root (9p vcanroot)"
busybox mount -t tmpfs -o mode=0755 upper /upper || fail "tmpfs for the overlay"
busybox mkdir -p /upper/data /upper/work /upper/repo-data /upper/repo-work
busybox mount -t overlay -o lowerdir=/trees:/host,upperdir=/upper/data,workdir=/upper/work root /newroot ||
    fail "the overlay over the host's root"
for fs in proc:proc sysfs:sys devtmpfs:dev tmpfs:tmp tmpfs:run; do
    busybox mount -t "${fs%%:*}" "${fs%%:*}" "/newroot/${fs#*:}" || fail "mount ${fs#*:}"
done
busybox mkdir -p /newroot/dev/pts /newroot/dev/shm
busybox mount -t devpts devpts /newroot/dev/pts
busybox mount -t tmpfs shm /newroot/dev/shm
busybox chmod 1777 /newroot/tmp /newroot/dev/shm

# The repository at its place (after the guest's own /tmp and /run, where it may live): the
# host's, shared read-write over 9p, under an overlay with its files from /trees on top; the
# lane's directory alone is bound from the share at its place, so what the lane writes there
# (the exit code, the timing) reaches the host.
busybox mkdir -p /newroot/run/vcan-repo "/newroot$ROOT" "/trees$ROOT"
busybox mount -t 9p -o "$opts" vcanrepo /newroot/run/vcan-repo || fail "mount the repository (9p vcanrepo)"
busybox mount -t overlay -o "lowerdir=/trees$ROOT:/newroot/run/vcan-repo,upperdir=/upper/repo-data,workdir=/upper/repo-work" \
    repo "/newroot$ROOT" || fail "the overlay over the repository at $ROOT"
busybox mkdir -p "/newroot$LANE"
busybox mount --bind "/newroot/run/vcan-repo${LANE#"$ROOT"}" "/newroot$LANE" ||
    fail "bind the lane's directory $LANE"
# The console as a plain byte stream: no \r added before each \n.
busybox stty -F /dev/console -opost 2>/dev/null

busybox chroot /newroot /bin/bash "$ROOT/scripts/vcan-guest.sh" "$LANE" "$ROOT" "$IFACE" "$TXQUEUELEN" \
    </dev/null >/dev/console 2>&1
busybox sync
busybox poweroff -f
