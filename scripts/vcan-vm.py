#!/usr/bin/env python3
"""Boots the vcan lane's micro-VM and runs the lane in it (scripts/vcan.sh calls this; its --help
says when and why).

The guest is the host's own kernel and root file system, booted the shortest way there is under
software emulation: the kernel's ELF image (`vmlinux`, unpacked here from the bzImage once, and
entered through its PVH note: no decompressor, no BIOS disk probing), an initramfs of busybox,
the few modules the lane needs and scripts/vcan-init.sh as /init (no udev, no systemd), and the
host's root read-only over 9p with the guest's page cache on. The image is built once per kernel
and kept in LANE/guest/.

The console is the guest's serial port; every byte goes to stdout and to LANE/output.log, and
each line that starts with `lane:` or `vcan-guest:` (the pytest progress lines of
tests/conftest.py, the guest script's own) also goes to LANE/timeline.tsv with the host's wall
time since the VM started, so a run's guest and wall times can be set side by side
(scripts/lane-times.py). At the time-out (the whole VM's, or one test's: wall time, kept here
because the guest's own clock jumps while it waits on the host) the test that was running is
named, the guest is asked through its PS/2 keyboard (magic SysRq, over QMP) for its blocked
tasks and what its CPU runs, and only then is QEMU stopped (exit 124).
"""

from __future__ import annotations

import argparse
import contextlib
import gzip
import hashlib
import json
import lzma
import os
import pathlib
import selectors
import shlex
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time

# The modules the lane needs (with what they depend on, from the kernel's modules.dep): the
# 9p shares on virtio-pci, the overlay, vcan, CAN_RAW and CAN_BCM (python-can's periodic sends)
# sockets.
MODULES = ["virtio_pci", "9pnet_virtio", "9p", "overlay", "vcan", "can_raw", "can_bcm"]
# How long the guest gets to print its dump after the time-out's SysRq keys.
DUMP_GRACE_S = 15.0


def log(msg: str) -> None:
    print(f"vcan-vm: {msg}", file=sys.stderr, flush=True)


# --- the guest image ---------------------------------------------------------------------------


def write_whole(path: pathlib.Path, data: bytes) -> None:
    """`data` to `path` through `PATH.part` and a rename: a run that fails midway leaves no
    half-written file where QEMU or a later run would read one."""
    part = path.with_name(path.name + ".part")
    part.write_bytes(data)
    part.rename(path)


def unpack_vmlinux(bzimage: bytes) -> bytes | None:
    """The kernel's ELF image from a bzImage whose payload is xz or gzip (Debian's is xz), or
    None (the bzImage is booted as it is then: slower, the same guest)."""
    for magic, open_stream in ((b"\xfd7zXZ\x00", lambda d: lzma.LZMADecompressor().decompress(d)),
                               (b"\x1f\x8b\x08", lambda d: gzip.decompress(d))):
        at = bzimage.find(magic)
        while at >= 0:
            with contextlib.suppress(lzma.LZMAError, OSError, EOFError, gzip.BadGzipFile):
                elf = open_stream(bzimage[at:])
                if elf[:4] == b"\x7fELF":
                    return elf
            at = bzimage.find(magic, at + 1)
    return None


def module_paths(kver: str, names: list[str]) -> list[pathlib.Path]:
    """The .ko files of `names` and their dependencies, dependencies first (modules.dep)."""
    base = pathlib.Path("/lib/modules") / kver
    deps: dict[str, list[str]] = {}
    by_name: dict[str, str] = {}
    for line in (base / "modules.dep").read_text().splitlines():
        path, _, rest = line.partition(":")
        deps[path] = rest.split()
        name = pathlib.Path(path).name.split(".ko")[0].replace("-", "_")
        by_name[name] = path
    order: list[str] = []

    def visit(path: str) -> None:
        if path in order:
            return
        for dep in deps.get(path, []):
            visit(dep)
        order.append(path)

    for name in names:
        if name not in by_name:
            raise SystemExit(f"vcan-vm: kernel {kver} has no module {name} (modules.dep)")
        visit(by_name[name])
    return [base / p for p in order]


def ko_name(path: pathlib.Path) -> str:
    """The module's file name without a compression suffix (busybox's insmod takes plain .ko)."""
    return path.name.split(".ko")[0] + ".ko"


def ko_bytes(path: pathlib.Path) -> bytes:
    """The module, decompressed if the distribution compressed it (.ko.xz, .ko.gz)."""
    data = path.read_bytes()
    if path.name.endswith(".xz"):
        return lzma.decompress(data)
    if path.name.endswith(".gz"):
        return gzip.decompress(data)
    if not path.name.endswith(".ko"):
        raise SystemExit(f"vcan-vm: {path}: a compressed module this script cannot unpack")
    return data


def newc(entries: list[tuple[str, int, bytes]]) -> bytes:
    """A cpio archive in the kernel's `newc` format: (path, mode, data) entries."""
    out = bytearray()

    def add(name: str, mode: int, data: bytes, ino: int) -> None:
        fields = [ino, mode, 0, 0, 1, 0, len(data), 0, 0, 0, 0, len(name) + 1, 0]
        out.extend(b"070701" + b"".join(b"%08X" % f for f in fields) + name.encode() + b"\0")
        out.extend(b"\0" * (-len(out) % 4))
        out.extend(data)
        out.extend(b"\0" * (-len(out) % 4))

    for ino, (name, mode, data) in enumerate(entries, start=1):
        add(name, mode, data, ino)
    add("TRAILER!!!", 0, b"", 0)
    return bytes(out)


def build_image(kernel: pathlib.Path, kver: str, init: pathlib.Path, guest_dir: pathlib.Path) -> tuple[pathlib.Path, pathlib.Path]:
    """(kernel to boot, the initramfs without the run's settings), built once per kernel, init
    script and busybox; kept in `guest_dir`."""
    busybox = pathlib.Path("/bin/busybox")
    stamp = hashlib.sha256()
    for path in (kernel, busybox):
        st = path.stat()
        stamp.update(f"{path}:{st.st_size}:{st.st_mtime_ns}\n".encode())
    stamp.update(init.read_bytes())
    stamp.update(" ".join(MODULES).encode())
    key = stamp.hexdigest()[:16]
    vmlinux, initramfs = guest_dir / f"vmlinux-{key}", guest_dir / f"initramfs-{key}.cpio"
    if initramfs.exists():
        return (vmlinux if vmlinux.exists() else kernel), initramfs
    guest_dir.mkdir(parents=True, exist_ok=True)
    for old in guest_dir.glob("*"):
        old.unlink()
    started = time.monotonic()
    elf = unpack_vmlinux(kernel.read_bytes())
    if elf is not None:
        write_whole(vmlinux, elf)
    modules = module_paths(kver, MODULES)
    entries: list[tuple[str, int, bytes]] = [
        (d, 0o40755, b"") for d in ("bin", "dev", "proc", "sys", "lib", "lib/modules")
    ]
    entries += [("bin/busybox", 0o100755, busybox.read_bytes()),
                ("bin/sh", 0o120777, b"busybox"),
                ("init", 0o100755, init.read_bytes()),
                ("modules.list", 0o100644, "".join(ko_name(m) + "\n" for m in modules).encode())]
    entries += [(f"lib/modules/{ko_name(m)}", 0o100644, ko_bytes(m)) for m in modules]
    write_whole(initramfs, newc(entries))
    log(f"guest image built in {time.monotonic() - started:.1f} s: "
        f"{'vmlinux (PVH entry)' if elf is not None else kernel.name + ' (no ELF payload found)'}, "
        f"initramfs {initramfs.stat().st_size >> 10} KiB, {len(modules)} modules")
    return (vmlinux if elf is not None else kernel), initramfs


def ram_plan(root: pathlib.Path, lane: pathlib.Path, binaries: list[pathlib.Path]) -> list[str]:
    """The lines of the guest's /ram.list (scripts/vcan-init.sh says what each kind means):
    the repository, but for .git and, under target/, all but `binaries` (the lane's runner,
    plant and codec) and the lane's own directory; and the Python the repository's .venv was
    made from, but for its tests, its own site-packages (the venv has its own) and its static
    libraries."""
    lines = [f"tree {root}", f"skip {root / '.git'}", f"empty {lane}"]
    target = root / "target"
    keep = [b for b in binaries if b.is_file() and target in b.parents] + [lane]
    # Every directory on the way from target/ to what is kept lists its other entries as skipped.
    ancestors = {a for k in keep for a in k.parents if target == a or target in a.parents}
    for directory in sorted(ancestors):
        for entry in directory.iterdir():
            if entry not in keep and entry not in ancestors:
                lines.append(f"skip {entry}")
    cfg = root / ".venv" / "pyvenv.cfg"
    home = next((line.split("=", 1)[1].strip() for line in cfg.read_text().splitlines()
                 if line.split("=", 1)[0].strip() == "home"), None) if cfg.is_file() else None
    if home:
        prefix = pathlib.Path(home).parent
        if prefix != pathlib.Path("/") and root not in prefix.parents and prefix != root:
            lines.append(f"tree {prefix}")
            for pattern in ("lib/python3*/test", "lib/python3*/site-packages", "lib/python3*/config-*", "lib/*.a"):
                lines += [f"skip {entry}" for entry in sorted(prefix.glob(pattern))]
    return lines


# --- the run -------------------------------------------------------------------------------------


class Console:
    """The guest's serial console: to stdout and output.log as it comes; progress lines, with
    the host's wall time, to timeline.tsv."""

    PREFIXES = (b"lane: ", b"vcan-guest: ", b"vcan-init: ")

    def __init__(self, lane: pathlib.Path, t0: float) -> None:
        self.t0 = t0
        self.log = open(lane / "output.log", "wb")  # noqa: SIM115 (closed in close)
        self.timeline = open(lane / "timeline.tsv", "w")  # noqa: SIM115
        self.partial = b""
        self.last_start = ""  # the last `lane: start` line: the test now running
        self.test_started: float | None = None  # its wall time (monotonic); None between tests
        self.setup_failed = ""

    def feed(self, data: bytes) -> None:
        sys.stdout.buffer.write(data)
        sys.stdout.buffer.flush()
        self.log.write(data)
        self.log.flush()
        self.partial += data
        *lines, self.partial = self.partial.split(b"\n")
        for raw in lines:
            # pytest's progress dots may stand before a `lane:` line.
            at = min((i for i in (raw.find(p) for p in self.PREFIXES) if i >= 0), default=-1)
            if at >= 0:
                line = raw[at:].decode(errors="replace").rstrip("\r")
                self.timeline.write(f"{time.monotonic() - self.t0:.2f}\t{line}\n")
                self.timeline.flush()
                if line.startswith("lane: start "):
                    self.last_start = line
                    self.test_started = time.monotonic()
                elif line.startswith("lane: end "):
                    self.test_started = None
                elif line.startswith("vcan-init: setup failed: "):
                    self.setup_failed = line.removeprefix("vcan-init: setup failed: ")

    def close(self) -> None:
        self.log.close()
        self.timeline.close()


def send_sysrq(qmp_path: pathlib.Path, keys: str) -> str | None:
    """Presses Alt+SysRq+KEY for each key through QEMU's QMP socket; None, or what failed."""
    try:
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
            sock.settimeout(5.0)
            sock.connect(str(qmp_path))
            stream = sock.makefile("rwb")
            stream.readline()  # the greeting
            for command in [{"execute": "qmp_capabilities"}] + [
                {"execute": "send-key", "arguments": {"keys": [
                    {"type": "qcode", "data": "alt"}, {"type": "qcode", "data": "sysrq"},
                    {"type": "qcode", "data": key}]}} for key in keys]:
                stream.write(json.dumps(command).encode() + b"\n")
                stream.flush()
                while True:  # skip events up to the command's answer
                    answer = json.loads(stream.readline() or b"{}")
                    if "return" in answer or "error" in answer or not answer:
                        break
                if "error" in answer:
                    return f"QMP {command['execute']}: {answer['error']}"
    except (OSError, ValueError) as err:
        return f"QMP: {err}"
    return None


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--kernel", type=pathlib.Path, required=True)
    ap.add_argument("--lane", type=pathlib.Path, required=True, help="the lane's directory (target/vcan-lane)")
    ap.add_argument("--root", type=pathlib.Path, required=True, help="the repository, mounted read-write")
    ap.add_argument("--iface", default="vcan0")
    ap.add_argument("--txqueuelen", type=int, default=10000)
    ap.add_argument("--memory", default="4G")
    ap.add_argument("--clock", choices=["icount", "host"], default="icount")
    ap.add_argument("--cpus", type=int, default=1)
    ap.add_argument("--timeout", type=float, required=True, help="wall seconds for the whole VM")
    ap.add_argument("--test-timeout", type=float, default=0.0,
                    help="wall seconds for one test (its `lane: start` to its `lane: end`); 0: none")
    ap.add_argument("--append", default="", help="more kernel command-line arguments")
    args = ap.parse_args()
    if not 1 <= args.cpus <= 64:
        ap.error(f"--cpus {args.cpus}: must be 1..64")
    if not 0 < args.timeout < 1e7 or not 0 <= args.test_timeout < 1e7:
        ap.error(f"--timeout {args.timeout} must be positive and --test-timeout {args.test_timeout} "
                 "zero (none) or positive, both below 1e7 s")
    lane, root = args.lane.resolve(), args.root.resolve()
    kver = args.kernel.name.removeprefix("vmlinuz-")
    here = pathlib.Path(__file__).resolve().parent
    boot, initramfs = build_image(args.kernel, kver, here / "vcan-init.sh", lane / "guest")

    # The run's settings as a second archive after the first: the kernel unpacks both.
    env = "".join(f"{k}={shlex.quote(str(v))}\n" for k, v in
                  (("ROOT", root), ("LANE", lane), ("IFACE", args.iface), ("TXQUEUELEN", args.txqueuelen)))
    binaries = [pathlib.Path(os.environ[v]).resolve() for v in ("HOSTSIM", "MECANUM_RUNNER", "MECANUM_CODEC")
                if os.environ.get(v)]
    # Opt-in (VCAN_VM_RAM=1) until it costs less: the copy through 9p took 139 s of wall time
    # with the host busy (docs/reliability.md, "Where the suite's time goes").
    plan = ram_plan(root, lane, binaries) if os.environ.get("VCAN_VM_RAM") == "1" else []
    ram = "".join(line + "\n" for line in plan)
    write_whole(lane / "ram.list", ram.encode())  # for a look after a run
    initrd = lane / "initrd.cpio"
    write_whole(initrd, initramfs.read_bytes() + newc([("lane.env", 0o100644, env.encode()),
                                                       ("ram.list", 0o100644, ram.encode())]))

    def share(tag: str, path: pathlib.Path, readonly: bool) -> list[str]:
        quoted = str(path).replace(",", ",,")  # QEMU doubles a comma in an option's value
        return ["-fsdev", f"local,id={tag},path={quoted},security_model=none,multidevs=remap"
                + (",readonly=on" if readonly else ""),
                "-device", f"virtio-9p-pci,fsdev={tag},mount_tag={tag}"]

    # QEMU's monitor socket, in a directory of its own under the temporary directory: a socket's
    # path has at most 107 bytes, and the repository's may be longer.
    qmp_dir = pathlib.Path(tempfile.mkdtemp(prefix="vcan-qmp-"))
    qmp = qmp_dir / "qmp.sock"
    # `no_timer_check`: the IO-APIC timer check's busy waits poll emulated timers, seconds of
    # wall time for milliseconds of guest time. The TSC is the guest's clock: with -icount it
    # counts the guest's instructions. `preempt=full`, as a robot's real-time computer runs: the
    # kernel's work for another process (a page fault on a 9p file, an exit freeing 200 MB)
    # yields to the plant's and the runner's SCHED_FIFO loops at once, not at its next
    # voluntary preemption point (Debian's default).
    cmdline = (f"console=ttyS0 quiet panic=-1 no_timer_check clocksource=tsc tsc=reliable preempt=full "
               f"{args.append}").strip()
    cmd = ["qemu-system-x86_64", "-machine", "pc", "-cpu", "max", "-smp", str(args.cpus), "-m", args.memory,
           "-nodefaults", "-no-user-config", "-display", "none", "-no-reboot",
           "-serial", "stdio", "-qmp", f"unix:{qmp},server=on,wait=off",
           "-kernel", str(boot), "-initrd", str(initrd), "-append", cmdline,
           *share("vcanroot", pathlib.Path("/"), True), *share("vcanrepo", root, False)]
    if args.clock == "icount":
        cmd += ["-icount", "shift=0,sleep=off"]

    t0 = time.monotonic()
    console = Console(lane, t0)
    # stdin: /dev/null (QEMU would take over a terminal). Its own process group: a Ctrl-C at
    # the terminal reaches this script, which stops QEMU.
    proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            start_new_session=True)
    stop = {"signal": 0}

    def on_signal(signum: int, _frame: object) -> None:
        stop["signal"] = signum

    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, on_signal)
    sel = selectors.DefaultSelector()
    assert proc.stdout is not None
    os.set_blocking(proc.stdout.fileno(), False)
    sel.register(proc.stdout, selectors.EVENT_READ)
    deadline = t0 + args.timeout
    dump_until = None
    fd = proc.stdout.fileno()
    while True:
        now = time.monotonic()
        if stop["signal"] and proc.poll() is None:
            proc.terminate()
        test_over = (args.test_timeout > 0 and console.test_started is not None
                     and now - console.test_started >= args.test_timeout)
        if dump_until is None and (now >= deadline or test_over) and proc.poll() is None:
            running = console.last_start.removeprefix("lane: start ") or "no test had started"
            if test_over:
                log(f"TIME-OUT: a test ran longer than its limit of {args.test_timeout:.0f} s: {running}")
            else:
                log(f"TIME-OUT: the VM's limit of {args.timeout:.0f} s is reached; running: {running}")
            log("asking the guest for its blocked tasks and its CPU's backtrace (SysRq w, l)")
            problem = send_sysrq(qmp, "wl")
            if problem:
                log(f"could not ask the guest: {problem}")
            dump_until = now + DUMP_GRACE_S
        if dump_until is not None and now >= dump_until and proc.poll() is None:
            proc.kill()
        if not sel.select(timeout=1.0):
            continue
        try:
            data = os.read(fd, 65536)
        except BlockingIOError:
            continue
        if not data:  # QEMU has exited (or closed its output)
            break
        console.feed(data)
    rc = proc.wait()
    shutil.rmtree(qmp_dir, ignore_errors=True)
    console.close()
    if console.setup_failed:
        (lane / "setup-failed").write_text(console.setup_failed + "\n")
    if stop["signal"]:
        return 130
    if dump_until is not None:
        return 124
    return rc or 0


if __name__ == "__main__":
    sys.exit(main())
