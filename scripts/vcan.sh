#!/usr/bin/env bash
# The vcan lane: runs a command where a real SocketCAN interface vcan0 is up.
# Natively where the kernel has vcan, else in a QEMU micro-VM (scripts/vcan-vm.py) that boots
# Debian's own kernel on the host's file system. `scripts/vcan.sh --help` says more.
set -euo pipefail

SCRIPT_DIR=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd -P)
ROOT=$(cd "$SCRIPT_DIR/.." && pwd -P)
IFACE=vcan0
LANE=$ROOT/target/vcan-lane
TXQUEUELEN=10000
DEB_PACKAGES=(qemu-system-x86 linux-image-amd64 busybox-static can-utils iproute2 tmux)
MODE=${VCAN_MODE:-auto}
VM_TIMEOUT=${VCAN_VM_TIMEOUT:-1800}
TEST_TIMEOUT=${VCAN_TEST_TIMEOUT:-0}
LIMITS_PACE=${VCAN_LIMITS_PACE:-0}
VM_MEMORY=${VCAN_VM_MEMORY:-4G}
VM_CLOCK=${VCAN_VM_CLOCK:-icount}
VM_CPUS=${VCAN_VM_CPUS:-}
usage() {
    cat <<EOF
Usage: scripts/vcan.sh [--native | --vm] -- COMMAND [ARG...]

Runs COMMAND, in the repository's root directory, where a real SocketCAN interface
$IFACE is up, with MECANUM_VCAN_REQUIRED=1 in its environment (so tests marked \`vcan\`
fail rather than skip without $IFACE) and MECANUM_VCAN_MODE=native or vm. Exits with
COMMAND's exit status. Example:

    scripts/vcan.sh -- .venv/bin/python -m pytest tests -m vcan -q

How $IFACE comes up, first that works:
  1. native: $IFACE exists already (used as it is), or \`modprobe vcan\` and
     \`ip link add dev $IFACE type vcan\` work (root or CAP_NET_ADMIN); a $IFACE this script
     created gets txqueuelen $TXQUEUELEN and is deleted afterwards.
  2. vm: the kernel has no vcan (\`ip link add ... type vcan\` says "Unknown device type").
     A QEMU micro-VM (software emulation; scripts/vcan-vm.py) boots Debian's kernel, which has
     vcan, on the host's file system: COMMAND runs there as root, on the same repository,
     .venv, toolchains and host-built binaries (read-only but for $LANE; the guest's writes
     elsewhere stay in its memory). What the lane runs from (the repository's tracked files
     and bytecode, the binaries, the .venv and its Python) is in the guest's memory from its
     boot, unpacked from the initramfs; every other file is read through 9p when asked for. Needs Debian ${DEB_PACKAGES[*]}
     (installed with apt-get when run as root and missing) and python3. The guest boots its
     kernel's ELF image straight into an initramfs of busybox and the modules vcan needs
     (scripts/vcan-init.sh), built once per kernel into $LANE/guest: vcan0 is up some 15 s
     after QEMU starts.
     The guest's clock (VCAN_VM_CLOCK=icount, the default) is QEMU's -icount shift=0,sleep=off:
     guest time is the count of instructions the guest executed (1 ns each), and when every
     guest process waits it jumps to the next timer at once. A host that is busy, or that
     deschedules QEMU for 100 ms, slows the whole guest down in wall time but cannot stall
     its timeline: the guest's 1 kHz loops and their latencies, as the guest's clocks measure
     them, are the same on an idle and a busy host. One vCPU (QEMU runs icount guests on one
     host thread in any case, and this QEMU hangs bringing up a second vCPU under icount), so
     the lane takes one host core and leaves the rest free. Guest time also runs on while
     the guest waits on the host (a first read of a file through 9p, which the trees in
     memory keep out of the tests). VCAN_VM_CLOCK=host:
     the guest's clock follows the host's wall clock (a vCPU per host CPU, up to 4), as the
     lane ran before; for comparisons.
     The environment variables the tools need are passed on (paths, locale, toolchains,
     Python, CI, MECANUM_*; none whose name says token, secret, password or key), no
     others. Output is also kept in target/vcan-lane/output.log, the VM's exit code in
     target/vcan-lane/exit-code, and the progress lines (\`lane: ...\`, one as each test
     starts and ends, with its guest time) with the host's wall time in
     target/vcan-lane/timeline.tsv (scripts/lane-times.py makes the table of both).
     At the time-out (VCAN_VM_TIMEOUT, or one test's VCAN_TEST_TIMEOUT) the script names the
     test that was running, has the guest print its blocked tasks and its CPU's backtrace
     (magic SysRq), then stops the VM.
  3. neither: in CI (CI set to anything but empty, 0 or false) that is a failure (exit 1,
     saying why); elsewhere the script prints "SKIP: <why>" and exits 0 without running
     COMMAND.

Ctrl-C (or SIGTERM, SIGHUP) stops COMMAND, or the VM, and the script exits 130.

Options:
  --native     only try the native way      (or VCAN_MODE=native)
  --vm         go straight to the VM        (or VCAN_MODE=vm)
  -h, --help   this text

Environment: VCAN_VM_TIMEOUT (wall seconds, default 1800; bounds a native COMMAND too),
VCAN_TEST_TIMEOUT (wall seconds one test may take in the VM, from its \`lane: start\` line to
its \`lane: end\`; default 0, none), VCAN_LIMITS_PACE (the emulator's pace, wall seconds per
guest second, those two were set for: when the tests so far ran slower, the VM's limits grow
in proportion, and the time-out line says so; default 0, fixed),
VCAN_VM_MEMORY (default 4G), VCAN_VM_CLOCK (icount or host; see above),
VCAN_VM_CPUS (default 1 with icount, else host CPUs up to 4), VCAN_KERNEL (a vmlinuz to boot
instead of the one linux-image-amd64 installed; its modules must be in /lib/modules),
VCAN_NO_INSTALL=1 (install nothing: what is missing makes the lane unavailable),
VCAN_VM_APPEND (more kernel command-line arguments for the VM), VCAN_VM_CPU (QEMU's -cpu;
default max,-erms,-fsrm: scripts/vcan-vm.py says why). With one vCPU, QEMU is kept to one host
CPU (the last this script may use): the guest's every wake-up then stays on that CPU.
EOF
}

log() { printf 'vcan.sh: %s\n' "$*" >&2; }
now() { date +%s.%N; }
elapsed() { awk -v a="$1" -v b="$2" 'BEGIN { printf "%.1f", b - a }'; }

# The lane cannot run here: a failure in CI, else a skip that says why.
unavailable() {
    case ${CI:-} in
    "" | 0 | false | False | FALSE) ;;
    *)
        log "FAIL: the vcan lane cannot run: $*"
        log "(CI=${CI}: in CI a lane that cannot run is a failure, not a skip)"
        exit 1
        ;;
    esac
    printf 'SKIP: vcan lane: %s\n' "$*"
    exit 0
}

# Runs COMMAND... in the background and returns its status, passing SIGINT, SIGTERM and SIGHUP
# on to it (a CI runner's signal to this script alone, or test.sh stopping the lane, must reach
# it). On such a signal the script exits 130 once COMMAND has ended (exit_if_interrupted).
INTERRUPTED=0
run_forwarding() {
    local pid rc
    # 9>&-: COMMAND must not hold the lane's lock (a stray child would keep it).
    "$@" 9>&- &
    pid=$!
    trap 'INTERRUPTED=1; kill -TERM "$pid" 2>/dev/null || true' INT TERM HUP
    while :; do
        rc=0
        wait "$pid" || rc=$?
        # A trapped signal ends `wait` early; the process (or its zombie) is still there.
        kill -0 "$pid" 2>/dev/null || break
    done
    trap - INT TERM HUP
    return "$rc"
}

# Runs `timeout -k KILL_AFTER VM_TIMEOUT COMMAND...` (run_forwarding: `timeout` runs in a
# process group of its own, so a Ctrl-C at the terminal would not reach COMMAND otherwise).
run_bounded() {
    local kill_after=$1 rc=0
    shift
    run_forwarding timeout -k "$kill_after" "$VM_TIMEOUT" "$@" || rc=$?
    [ "$rc" = 124 ] && log "COMMAND did not finish within $VM_TIMEOUT s (VCAN_VM_TIMEOUT)"
    return "$rc"
}

# After run_bounded: exit as interrupted if a signal came.
exit_if_interrupted() {
    if [ "$INTERRUPTED" = 1 ]; then
        log "interrupted; COMMAND stopped"
        exit 130
    fi
}

while [ $# -gt 0 ]; do
    case $1 in
    -h | --help) usage; exit 0 ;;
    --native) MODE=native; shift ;;
    --vm) MODE=vm; shift ;;
    --) shift; break ;;
    *) log "unknown argument: $1 (a command goes after --; see --help)"; exit 2 ;;
    esac
done
if [ $# -eq 0 ]; then
    log "no command given (scripts/vcan.sh -- COMMAND [ARG...]; see --help)"
    exit 2
fi
case $MODE in auto | native | vm) ;; *) log "VCAN_MODE must be auto, native or vm, not '$MODE'"; exit 2 ;; esac
case $VM_CLOCK in
icount) VM_CPUS=${VM_CPUS:-1} ;;
host) VM_CPUS=${VM_CPUS:-$(n=$(nproc 2>/dev/null || echo 2); echo $((n > 4 ? 4 : n)))} ;;
*) log "VCAN_VM_CLOCK must be icount or host, not '$VM_CLOCK'"; exit 2 ;;
esac

# One lane at a time per repository: they share vcan0 and target/vcan-lane.
mkdir -p "$LANE"
if command -v flock >/dev/null; then
    exec 9>"$LANE/lock"
    if ! flock -n 9; then
        log "another vcan lane is running in this repository; waiting for it (at most ${VM_TIMEOUT} s)"
        flock -w "$VM_TIMEOUT" 9 || unavailable "another vcan lane held $LANE/lock for ${VM_TIMEOUT} s"
    fi
fi

can_install() {
    [ "${VCAN_NO_INSTALL:-}" != "1" ] && [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null
}

APT_UPDATED=0
apt_install() {
    log "installing Debian packages: $*"
    if [ "$APT_UPDATED" = 0 ]; then
        apt-get update -qq >&2
        APT_UPDATED=1
    fi
    # INITRD=No: the kernel's own initramfs is never used (the lane boots one of its own), and
    # generating it is most of the install time.
    DEBIAN_FRONTEND=noninteractive INITRD=No apt-get install -y -qq --no-install-recommends "$@" >&2
}

# Debian packages (of those given) that are not installed.
missing_debs() {
    local pkg
    for pkg in "$@"; do
        if ! dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q 'install ok installed'; then
            printf '%s\n' "$pkg"
        fi
    done
}

# ---------------------------------------------------------------------------------------------
# 1. native

NATIVE_WHY=
CREATED_IFACE=0

teardown_native() {
    if [ "$CREATED_IFACE" = 1 ]; then
        ip link del dev "$IFACE" 2>/dev/null || true
        CREATED_IFACE=0
    fi
}

native_up() {
    local err
    if ! command -v ip >/dev/null; then
        NATIVE_WHY="ip (iproute2) not found"
        return 1
    fi
    if [ -e "/sys/class/net/$IFACE" ]; then
        if [ "$(cat "/sys/class/net/$IFACE/type")" != 280 ]; then
            NATIVE_WHY="$IFACE exists but is not a CAN interface"
            return 1
        fi
        # IFF_UP (bit 0 of flags): already up, which needs no privilege to use; bringing it
        # up needs CAP_NET_ADMIN.
        if (($(cat "/sys/class/net/$IFACE/flags") & 1)); then
            log "native: using the existing $IFACE (up)"
        elif ! err=$(ip link set up dev "$IFACE" 2>&1); then
            NATIVE_WHY="$IFACE exists but cannot be brought up: $err"
            return 1
        else
            log "native: using the existing $IFACE (brought up)"
        fi
        local qlen
        qlen=$(cat "/sys/class/net/$IFACE/tx_queue_len")
        if [ "$qlen" -lt "$TXQUEUELEN" ] &&
            ! ip link set dev "$IFACE" txqueuelen "$TXQUEUELEN" 2>/dev/null; then
            log "native: warning: $IFACE has txqueuelen $qlen (< $TXQUEUELEN): a burst may be dropped"
        fi
        return 0
    fi
    if command -v modprobe >/dev/null; then
        modprobe vcan 2>/dev/null || true
    fi
    if ! err=$(ip link add dev "$IFACE" type vcan 2>&1); then
        NATIVE_WHY="this kernel cannot create $IFACE (ip link add dev $IFACE type vcan: $err)"
        return 1
    fi
    CREATED_IFACE=1
    trap teardown_native EXIT
    if ! err=$({ ip link set dev "$IFACE" txqueuelen "$TXQUEUELEN" && ip link set up dev "$IFACE"; } 2>&1); then
        NATIVE_WHY="created $IFACE but cannot bring it up: $err"
        teardown_native
        return 1
    fi
    log "native: created $IFACE (txqueuelen $TXQUEUELEN)"
    return 0
}

run_native() {
    local rc
    if ! command -v cansend >/dev/null && can_install; then
        apt_install can-utils || log "native: installing can-utils failed"
    fi
    cd "$ROOT"
    rc=0
    MECANUM_VCAN_REQUIRED=1 MECANUM_VCAN_MODE=native run_bounded 10 "$@" || rc=$?
    teardown_native
    exit_if_interrupted
    exit "$rc"
}

if [ "$MODE" != vm ]; then
    if native_up; then
        run_native "$@"
    fi
    log "native: $NATIVE_WHY"
    if [ "$MODE" = native ]; then
        unavailable "native: $NATIVE_WHY"
    fi
fi

# ---------------------------------------------------------------------------------------------
# 2. the micro-VM

T_START=$(now)
VM_WHY=

# The kernel to boot: the one the linux-image-amd64 metapackage depends on, else the newest
# /boot/vmlinuz-* whose modules include vcan.
find_kernel() {
    local dep version candidates=()
    if [ -n "${VCAN_KERNEL:-}" ]; then
        printf '%s\n' "$VCAN_KERNEL"
        return
    fi
    dep=$(dpkg-query -W -f='${Depends}' linux-image-amd64 2>/dev/null || true)
    version=${dep%%[ ,|]*}
    version=${version#linux-image-}
    if [ -n "$version" ] && [ -e "/boot/vmlinuz-$version" ]; then
        printf '%s\n' "/boot/vmlinuz-$version"
        return
    fi
    for version in $(find /lib/modules -mindepth 1 -maxdepth 1 -printf '%f\n' 2>/dev/null | sort -rV); do
        if compgen -G "/lib/modules/$version/kernel/drivers/net/can/vcan.ko*" >/dev/null &&
            [ -e "/boot/vmlinuz-$version" ]; then
            candidates+=("/boot/vmlinuz-$version")
        fi
    done
    if [ ${#candidates[@]} -gt 0 ]; then
        printf '%s\n' "${candidates[0]}"
    fi
}

vm_prepare() {
    local missing=() tool
    mapfile -t missing < <(command -v dpkg-query >/dev/null && missing_debs "${DEB_PACKAGES[@]}")
    if [ ${#missing[@]} -gt 0 ]; then
        if can_install; then
            apt_install "${missing[@]}" || { VM_WHY="apt-get install ${missing[*]} failed"; return 1; }
        elif ! command -v dpkg-query >/dev/null; then
            : # not Debian: the checks below say what is missing
        else
            VM_WHY="missing Debian packages ${missing[*]} (install them as root: apt-get install ${missing[*]})"
            return 1
        fi
    fi
    for tool in qemu-system-x86_64 busybox ip python3; do
        if ! command -v "$tool" >/dev/null; then
            VM_WHY="$tool not found (Debian: apt-get install ${DEB_PACKAGES[*]})"
            return 1
        fi
    done
    KERNEL=$(find_kernel)
    if [ -z "$KERNEL" ] || [ ! -e "$KERNEL" ]; then
        VM_WHY="no kernel with vcan to boot (Debian: apt-get install linux-image-amd64; or set VCAN_KERNEL)"
        return 1
    fi
    if [ ! -r "$KERNEL" ]; then
        VM_WHY="$KERNEL is not readable (Debian installs kernels mode 0600: run as root)"
        return 1
    fi
    KVER=$(basename "$KERNEL")
    KVER=${KVER#vmlinuz-}
    if ! compgen -G "/lib/modules/$KVER/kernel/drivers/net/can/vcan.ko*" >/dev/null; then
        VM_WHY="$KERNEL has no vcan module under /lib/modules/$KVER"
        return 1
    fi
    return 0
}

# The environment for the command in the guest: the caller's variables that the tests and the
# tools need (paths, locale, toolchains, Python, the project's own), and nothing else: the file
# stays in target/vcan-lane for a look after a failure, so no credential may end up in it.
write_guest_env() {
    local name
    for name in $(compgen -e); do
        case $name in
        *TOKEN* | *SECRET* | *PASSWORD* | *CREDENTIAL* | *_KEY) ;;
        PATH | HOME | USER | LOGNAME | LANG | LC_* | TZ | TMPDIR | CI | HOSTSIM | MECANUM_* | VCAN_* | \
            RUST* | CARGO* | PYTHON* | PYTEST_* | VIRTUAL_ENV)
            printf 'export %s=%q\n' "$name" "${!name}" ;;
        esac
    done
    printf 'export MECANUM_VCAN_REQUIRED=1 MECANUM_VCAN_MODE=vm MECANUM_VCAN_CLOCK=%s\n' "$VM_CLOCK"
}

if ! vm_prepare; then
    unavailable "VM: $VM_WHY${NATIVE_WHY:+ (native: $NATIVE_WHY)}"
fi

rm -f "$LANE/exit-code" "$LANE/started" "$LANE/setup-failed" "$LANE/timing" "$LANE/output.log" "$LANE/timeline.tsv"
printf '%q ' "$@" >"$LANE/command.sh"
printf '\n' >>"$LANE/command.sh"
(umask 077 && write_guest_env >"$LANE/env.sh")

log "vm: booting $KERNEL (software emulation, $VM_CPUS CPU(s), $VM_MEMORY, guest clock: $VM_CLOCK; timeout ${VM_TIMEOUT}s)"
T_BOOT=$(now)
cd "$ROOT"
vm_rc=0
run_forwarding python3 "$SCRIPT_DIR/vcan-vm.py" --kernel "$KERNEL" --lane "$LANE" --root "$ROOT" \
    --iface "$IFACE" --txqueuelen "$TXQUEUELEN" --memory "$VM_MEMORY" --clock "$VM_CLOCK" \
    --cpus "$VM_CPUS" --timeout "$VM_TIMEOUT" --test-timeout "$TEST_TIMEOUT" --limits-pace "$LIMITS_PACE" \
    --append "${VCAN_VM_APPEND:-}" || vm_rc=$?
exit_if_interrupted
T_END=$(now)

timing=
if [ -s "$LANE/timing" ]; then
    read -r up_start up_ready up_end <"$LANE/timing" || true
    timing="; in the guest: boot ${up_start} s, set-up $(elapsed "$up_start" "$up_ready") s, command $(elapsed "$up_ready" "$up_end") s"
fi
log "vm: prepare $(elapsed "$T_START" "$T_BOOT") s, VM $(elapsed "$T_BOOT" "$T_END") s$timing"

if [ "$vm_rc" = 124 ]; then
    log "FAIL: a time-out (VCAN_VM_TIMEOUT=$VM_TIMEOUT s for the VM, VCAN_TEST_TIMEOUT=$TEST_TIMEOUT s a test, VCAN_LIMITS_PACE=$LIMITS_PACE); the TIME-OUT line above names the test and the limit it met"
    exit 124
fi
if [ -s "$LANE/exit-code" ]; then
    rc=$(cat "$LANE/exit-code")
    log "vm: command exited with $rc"
    exit "$rc"
fi
if [ -e "$LANE/setup-failed" ]; then
    unavailable "VM: $(cat "$LANE/setup-failed")${NATIVE_WHY:+ (native: $NATIVE_WHY)}"
fi
if [ -e "$LANE/started" ]; then
    log "FAIL: the command started in the VM but reported no exit code (the VM exited with $vm_rc)"
    exit 1
fi
unavailable "VM: the guest did not start the command (the VM exited with $vm_rc; output in $LANE/output.log)${NATIVE_WHY:+ (native: $NATIVE_WHY)}"
