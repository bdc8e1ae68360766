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
because the guest's own clock jumps while it waits on the host; with --limits-pace both grow
with the emulator's measured slowness, so a slower host is not a hang) the test that was running is
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
import re
import selectors
import shlex
import shutil
import signal
import socket
import stat
import struct
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable

# The modules the lane needs (with what they depend on, from the kernel's modules.dep): the
# 9p shares on virtio-pci, the overlay, vcan, CAN_RAW and CAN_BCM (python-can's periodic sends)
# sockets.
MODULES = ["virtio_pci", "9pnet_virtio", "9p", "overlay", "vcan", "can_raw", "can_bcm"]
# The host's programs the lane runs (tests/ and scripts/vcan-guest.sh), in the guest's memory
# with the libraries they load.
LANE_TOOLS = ["bash", "candump", "cansend", "canplayer", "ip", "chrt", "tmux", "dmesg", "kill"]
# The emulated CPU: QEMU's every feature, but for the fast string copies (ERMS, FSRM). With them
# the guest's kernel and C library copy with `rep movsb`, which QEMU's software emulation runs a
# byte at a time: unpacking the lane's trees (300 MiB) took 18 s of wall time, 7 s without.
CPU_MODEL = "max,-erms,-fsrm"
# How long the guest gets to print its dump after the time-out's SysRq keys.
DUMP_GRACE_S = 15.0
# The guest time in a progress line of tests/lane.py: `(guest 123.4 s)`.
GUEST_TIME = re.compile(r"\(guest (\d+(?:\.\d+)?) s\)")
# The guest time the finished tests must span before their pace scales the limits.
MIN_PACE_SPAN_S = 20.0


def scaled_limits(timeout: float, test_timeout: float, pace: float | None, limits_pace: float) -> tuple[float, float]:
    """The VM's and one test's limits (wall s) for an emulator measured at `pace` wall seconds per
    guest second, the limits having been set for one at `limits_pace` (0: fixed limits). A slower
    emulator stretches the guest's fixed work in proportion, so the limits grow with it, never
    below those set. A hung test prints nothing, so the pace of the tests before it bounds it."""
    if limits_pace <= 0 or pace is None or pace <= limits_pace:
        return timeout, test_timeout
    scale = pace / limits_pace
    return timeout * scale, test_timeout * scale


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
        out.extend(newc_header(name, mode, len(data), 0, ino))
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


def newc_header(name: str, mode: int, size: int, mtime: int, ino: int) -> bytes:
    """One `newc` entry's header and name, padded: the entry's data (`size` bytes) follows,
    then padding to 4 bytes."""
    fields = [ino, mode, 0, 0, 1, mtime, size, 0, 0, 0, 0, len(name) + 1, 0]
    head = b"070701" + b"".join(b"%08X" % f for f in fields) + name.encode() + b"\0"
    return head + b"\0" * (-len(head) % 4)


def elf_needed(path: pathlib.Path) -> list[str]:
    """The DT_NEEDED names of a 64-bit little-endian ELF file; [] for anything else. (Read here,
    not by ldd: that runs the loader once per file, 11 s for the .venv's 600 libraries.)"""
    try:
        with open(path, "rb") as f:
            head = f.read(64)
            if head[:6] != b"\x7fELF\x02\x01":
                return []
            phoff, = struct.unpack_from("<Q", head, 0x20)
            phentsize, phnum = struct.unpack_from("<HH", head, 0x36)
            f.seek(phoff)
            table = f.read(phentsize * phnum)
            segments = [struct.unpack_from("<IIQQQQ", table, i * phentsize) for i in range(phnum)]
            loads = [(vaddr, offset, filesz) for kind, _, offset, vaddr, _, filesz in segments if kind == 1]
            dynamic = next(((offset, filesz) for kind, _, offset, _, _, filesz in segments if kind == 2), None)
            if dynamic is None:
                return []
            f.seek(dynamic[0])
            raw = f.read(dynamic[1])
            tags = [struct.unpack_from("<QQ", raw, i) for i in range(0, len(raw) - 15, 16)]
            strtab = next((v for t, v in tags if t == 5), None)
            strsz = next((v for t, v in tags if t == 10), 0)
            at = next((offset + strtab - vaddr for vaddr, offset, filesz in loads
                       if strtab is not None and vaddr <= strtab < vaddr + filesz), None)
            if at is None:
                return []
            f.seek(at)
            strings = f.read(strsz)
    except (OSError, struct.error):
        return []
    return [strings[v:strings.index(b"\0", v)].decode(errors="replace") for t, v in tags if t == 1 and v < len(strings)]


def with_libraries(elves: list[pathlib.Path]) -> list[pathlib.Path]:
    """`elves` and the system libraries they load, transitively (by the loader's cache,
    `ldconfig -p`; a library a file carries beside itself is in the trees already)."""
    listing = subprocess.run(["ldconfig", "-p"], capture_output=True, text=True, check=False).stdout
    cache: dict[str, pathlib.Path] = {}
    for line in listing.splitlines():
        name, _, path = line.strip().partition(" => ")
        if path and "x86-64" in name:
            cache.setdefault(name.split(" (")[0], pathlib.Path(path))
    found, todo = set(elves), list(elves)
    while todo:
        for name in elf_needed(todo.pop()):
            library = cache.get(name)
            if library is not None and library not in found:
                found.add(library)
                todo.append(library)
                if library.is_symlink():  # the loader opens it by this name, reads its target
                    found.add(library.resolve())
    return sorted(found)


def tree_files(root: pathlib.Path, binaries: list[pathlib.Path]) -> list[pathlib.Path]:
    """What the lane runs from, to be in the guest's memory: the repository's tracked files,
    its Python bytecode (pytest's rewritten test modules among it) and `binaries`; its .venv
    but Ray; the interpreter the .venv was made from and its standard library (without its own
    tests, site-packages, build configuration and -O bytecode); the programs of LANE_TOOLS, and
    the system libraries all of those load. Everything else stays the host's, read through 9p
    when asked for."""
    files: list[pathlib.Path] = []
    tracked = subprocess.run(["git", "-C", str(root), "ls-files", "-z"], capture_output=True, check=False)
    if tracked.returncode == 0:
        files += [root / name for name in tracked.stdout.decode(errors="surrogateescape").split("\0") if name]
    for sub in ("tests", "python", "scripts"):
        files += (root / sub).rglob("__pycache__/*.pyc")
    files += binaries

    def walk(top: pathlib.Path, skip: tuple[str, ...] = ()) -> None:
        for dirpath, dirnames, filenames in os.walk(top):
            here = pathlib.Path(dirpath)
            dirnames[:] = [d for d in dirnames if not any((here / d).match(pattern) for pattern in skip)]
            files.extend(here / f for f in filenames if ".opt-" not in f)

    venv = root / ".venv"
    # Ray (the package's ray extra, 240 MB) is for `mecanum-drive sweep --ray`, not the lane.
    walk(venv, ("*/site-packages/ray",))
    python = (venv / "bin" / "python").resolve()
    if python.is_file() and venv not in python.parents:
        prefix = python.parent.parent
        files.append(python)
        files += prefix.glob("lib/libpython3*.so*")
        for stdlib in prefix.glob("lib/python3.*"):
            walk(stdlib, ("*/lib/python3.*/test", "*/lib/python3.*/site-packages", "*/lib/python3.*/dist-packages",
                          "*/lib/python3.*/config-*"))
    tools = [pathlib.Path(p) for p in map(shutil.which, LANE_TOOLS) if p]
    elves = [f for f in files + tools if f.suffix in ("", ".so") or ".so." in f.name]
    return files + tools + [p.resolve() for p in tools if p.is_symlink()] + with_libraries(elves)


def trees_archive(root: pathlib.Path, binaries: list[pathlib.Path], out: pathlib.Path) -> tuple[int, int]:
    """Writes `tree_files` as a `newc` archive whose entries sit under /trees (the guest's
    /init lays it over the host's root), with their modes and modification times (Python
    checks its bytecode against its source's); (files, bytes). Rebuilt only when a file's
    size or time changed."""
    entries: dict[str, os.stat_result] = {}
    for listed in tree_files(root, binaries):
        # At the path with no link on its way (/lib/x/libc.so.6 is /usr/lib/x/libc.so.6 where
        # /lib links to usr/lib): a directory of the trees where the host has a link would
        # hide the link's target in the guest.
        path = listed.parent.resolve() / listed.name
        try:
            st = path.lstat()
        except OSError:
            continue
        if stat.S_ISREG(st.st_mode) or stat.S_ISLNK(st.st_mode):
            entries[str(path)] = st
    stamp = hashlib.sha256()
    for name in sorted(entries):
        st = entries[name]
        stamp.update(f"{name}:{st.st_mode}:{st.st_size}:{st.st_mtime_ns}\n".encode())
    key = out.with_name(out.name + ".key")
    size = sum(st.st_size for st in entries.values())
    if out.is_file() and key.is_file() and key.read_text() == stamp.hexdigest():
        return len(entries), size
    part = out.with_name(out.name + ".part")
    made: set[str] = set()
    ino = 0
    with open(part, "wb") as f:
        for name in sorted(entries):
            st = entries[name]
            parents = pathlib.PurePosixPath("trees" + name).parents
            for directory in reversed(parents[:-1]):  # the archive's own directories, outermost first
                if str(directory) not in made:
                    made.add(str(directory))
                    ino += 1
                    f.write(newc_header(str(directory), 0o40755, 0, 0, ino))
            if stat.S_ISLNK(st.st_mode):
                data = os.readlink(name).encode()
            else:
                try:
                    data = pathlib.Path(name).read_bytes()
                except OSError:
                    continue
            ino += 1
            f.write(newc_header("trees" + name, st.st_mode, len(data), int(st.st_mtime), ino))
            f.write(data + b"\0" * (-len(data) % 4))
        f.write(newc_header("TRAILER!!!", 0, 0, 0, 0))
    part.rename(out)
    key.write_text(stamp.hexdigest())
    return len(entries), size


# --- the run -------------------------------------------------------------------------------------


class Console:
    """The guest's serial console: to stdout and output.log as it comes; progress lines, with
    the host's wall time, to timeline.tsv."""

    PREFIXES = (b"lane: ", b"vcan-guest: ", b"vcan-init: ")

    def __init__(self, lane: pathlib.Path, t0: float, clock: Callable[[], float] = time.monotonic) -> None:
        self.t0 = t0
        self.clock = clock
        self.log = open(lane / "output.log", "wb")  # noqa: SIM115 (closed in close)
        self.timeline = open(lane / "timeline.tsv", "w")  # noqa: SIM115
        self.partial = b""
        self.last_start = ""  # the last `lane: start` line: the test now running
        self.test_started: float | None = None  # its wall time (monotonic); None between tests
        self.setup_failed = ""
        # (wall s since t0, guest s) at the first test's start and at the last progress line.
        self.first: tuple[float, float] | None = None
        self.last: tuple[float, float] | None = None

    def pace(self) -> float | None:
        """Wall seconds per guest second over the tests so far (from the first test's start to
        the last progress line), once they span MIN_PACE_SPAN_S of guest time; else None. The
        boot is left out: its waits on the host make the guest's clock leap (85 s in 0.5 s)."""
        if self.first is None or self.last is None:
            return None
        guest = self.last[1] - self.first[1]
        return (self.last[0] - self.first[0]) / guest if guest >= MIN_PACE_SPAN_S else None

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
                now = self.clock()
                wall = now - self.t0
                self.timeline.write(f"{wall:.2f}\t{line}\n")
                self.timeline.flush()
                guest = GUEST_TIME.search(line) if line.startswith("lane: ") else None
                if guest:
                    self.last = (wall, float(guest.group(1)))
                    if self.first is None and line.startswith("lane: start "):
                        self.first = self.last
                if line.startswith("lane: start "):
                    self.last_start = line
                    self.test_started = now
                elif line.startswith("lane: end "):
                    self.test_started = None
                elif line.startswith("vcan-init: setup failed: "):
                    self.setup_failed = line.removeprefix("vcan-init: setup failed: ")

    def close(self) -> None:
        self.log.close()
        self.timeline.close()


class Fence:
    """Keeps the other processes of this process group (scripts/test.sh and its stages, not
    QEMU, which has a session of its own) to `cpus`, and those they start, which inherit it;
    `lift` gives them `cpus_after`. Affinity only: nothing else of theirs changes."""

    def __init__(self, cpus: set[int]) -> None:
        self.group = os.getpgrp()
        for _ in range(2):  # again, for a process started from one not yet fenced
            for pid in self.members():
                with contextlib.suppress(OSError):
                    for task in os.listdir(f"/proc/{pid}/task"):
                        os.sched_setaffinity(int(task), cpus)

    def members(self) -> list[int]:
        pids = []
        for entry in os.listdir("/proc"):
            if entry.isdigit() and int(entry) != os.getpid():
                with contextlib.suppress(OSError, ValueError, IndexError):
                    with open(f"/proc/{entry}/stat") as f:
                        fields = f.read().rsplit(")", 1)[1].split()
                    if int(fields[2]) == self.group:  # field 5 of stat: the process group
                        pids.append(int(entry))
        return pids

    def lift(self, cpus_after: set[int]) -> None:
        for pid in self.members():
            with contextlib.suppress(OSError):
                for task in os.listdir(f"/proc/{pid}/task"):
                    os.sched_setaffinity(int(task), cpus_after)


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
    ap.add_argument("--cpu-model", default=os.environ.get("VCAN_VM_CPU", CPU_MODEL),
                    help=f"QEMU's -cpu (default {CPU_MODEL}, or VCAN_VM_CPU)")
    ap.add_argument("--timeout", type=float, required=True, help="wall seconds for the whole VM")
    ap.add_argument("--test-timeout", type=float, default=0.0,
                    help="wall seconds for one test (its `lane: start` to its `lane: end`); 0: none")
    ap.add_argument("--limits-pace", type=float, default=0.0,
                    help="the emulator's pace (wall s per guest s) the two limits were set for: when "
                         "the tests so far ran slower, both grow in proportion; 0: fixed limits")
    ap.add_argument("--append", default="", help="more kernel command-line arguments")
    args = ap.parse_args()
    if not 1 <= args.cpus <= 64:
        ap.error(f"--cpus {args.cpus}: must be 1..64")
    if not 0 < args.timeout < 1e7 or not 0 <= args.test_timeout < 1e7:
        ap.error(f"--timeout {args.timeout} must be positive and --test-timeout {args.test_timeout} "
                 "zero (none) or positive, both below 1e7 s")
    if not 0 <= args.limits_pace < 1e3:
        ap.error(f"--limits-pace {args.limits_pace}: must be 0 (fixed limits) or positive, below 1000")
    lane, root = args.lane.resolve(), args.root.resolve()
    kver = args.kernel.name.removeprefix("vmlinuz-")
    here = pathlib.Path(__file__).resolve().parent
    boot, initramfs = build_image(args.kernel, kver, here / "vcan-init.sh", lane / "guest")

    # The run's settings as a second archive after the first: the kernel unpacks both.
    env = "".join(f"{k}={shlex.quote(str(v))}\n" for k, v in
                  (("ROOT", root), ("LANE", lane), ("IFACE", args.iface), ("TXQUEUELEN", args.txqueuelen)))
    binaries = [pathlib.Path(os.environ[v]).resolve() for v in ("HOSTSIM", "MECANUM_RUNNER", "MECANUM_CODEC")
                if os.environ.get(v)]
    # The trees the lane runs from, in the guest's memory from its boot: the kernel unpacks
    # them from the initramfs, so no file the tests read waits on the host (scripts/vcan-init.sh).
    started = time.monotonic()
    trees = lane / "trees.cpio"
    count, size = trees_archive(root, binaries, trees)
    log(f"the lane's trees in the guest's memory: {count} files, {size >> 20} MiB "
        f"(archive ready in {time.monotonic() - started:.1f} s)")
    initrd = lane / "initrd.cpio"
    with open(initrd.with_name(initrd.name + ".part"), "wb") as f:
        f.write(initramfs.read_bytes() + newc([("lane.env", 0o100644, env.encode())]))
        with open(trees, "rb") as src:
            shutil.copyfileobj(src, f, 1 << 20)
    initrd.with_name(initrd.name + ".part").rename(initrd)

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
    cmd = ["qemu-system-x86_64", "-machine", "pc", "-cpu", args.cpu_model, "-smp", str(args.cpus), "-m", args.memory,
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
    # One vCPU under -icount runs on one host thread, but every wake-up of the guest from idle
    # (its 1 kHz loops make thousands a second) passes between that thread and QEMU's main loop:
    # on one host CPU that is a switch, across two a wake-up of the other CPU, a fifth of the
    # wall time of the 8,000 frames/s test. So QEMU keeps to the last CPU this script may use,
    # and while it runs the rest of this process group (scripts/test.sh's stages) keeps to the
    # others: a build beside QEMU on its CPU, even at niceness 10, made that test 2.5 times
    # slower (every wake-up waits for the build's time slice).
    allowed = sorted(os.sched_getaffinity(0))
    pin = {allowed[-1]} if args.cpus == 1 and len(allowed) > 1 else None

    def place() -> None:
        if pin:
            os.sched_setaffinity(0, pin)

    proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            start_new_session=True, preexec_fn=place)
    fence = Fence(set(allowed) - pin) if pin else None
    if pin:
        log(f"QEMU kept to host CPU {allowed[-1]} of {len(allowed)}, the rest of its process group "
            f"to the others until it ends")
    stop = {"signal": 0}

    def on_signal(signum: int, _frame: object) -> None:
        stop["signal"] = signum

    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, on_signal)
    sel = selectors.DefaultSelector()
    assert proc.stdout is not None
    os.set_blocking(proc.stdout.fileno(), False)
    sel.register(proc.stdout, selectors.EVENT_READ)
    dump_until = None
    fd = proc.stdout.fileno()
    told_scale = 1.0
    while True:
        now = time.monotonic()
        if stop["signal"] and proc.poll() is None:
            proc.terminate()
        pace = console.pace()
        vm_limit, test_limit = scaled_limits(args.timeout, args.test_timeout, pace, args.limits_pace)
        if pace is not None and vm_limit >= told_scale * 1.1 * args.timeout:
            told_scale = vm_limit / args.timeout
            per_test = f", a test's {test_limit:.0f} s" if test_limit > 0 else ""
            log(f"the tests so far ran {pace:.2f} wall s per guest s, slower than the {args.limits_pace:g} "
                f"the limits were set for: the VM's limit is now {vm_limit:.0f} s{per_test}")
        test_over = (test_limit > 0 and console.test_started is not None
                     and now - console.test_started >= test_limit)
        if dump_until is None and (now >= t0 + vm_limit or test_over) and proc.poll() is None:
            running = console.last_start.removeprefix("lane: start ") or "no test had started"
            measured = f" (the tests' pace {pace:.2f} wall s per guest s)" if pace is not None else ""
            if test_over:
                log(f"TIME-OUT: a test ran longer than its limit of {test_limit:.0f} s{measured}: {running}")
            else:
                log(f"TIME-OUT: the VM's limit of {vm_limit:.0f} s is reached{measured}; running: {running}")
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
    if fence is not None:
        fence.lift(set(allowed))
    # QEMU has read it; trees.cpio, the bulk of it, stays for the next run.
    initrd.unlink(missing_ok=True)
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
