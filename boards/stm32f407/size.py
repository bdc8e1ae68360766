#!/usr/bin/env python3
"""Flash and RAM use of the board firmware, read from the ELF's section headers.

Standard library only, so the test script runs it on a fresh machine. The memory regions come
from memory.x beside this file, so the figures follow the linker's view of the chip.

    flash = every allocated section placed in FLASH (.vector_table, .text, .rodata, ...)
            + the load image of initialised RAM data (.data)
    RAM   = every allocated section placed in RAM (.data, .bss, .uninit); the stack is not a
            section: cortex-m-rt starts it at the top of RAM, so it has what is left.

Usage: size.py ELF [--max-flash BYTES] [--max-ram BYTES]
Exits 1 if a budget is exceeded, 2 on a malformed ELF or memory.x.
"""

import argparse
import pathlib
import re
import struct
import sys

SHF_ALLOC = 0x2
SHT_NOBITS = 8


def regions(memory_x: pathlib.Path) -> dict[str, tuple[int, int]]:
    """`NAME : ORIGIN = 0x..., LENGTH = 123K` lines of a linker MEMORY block."""
    units = {"": 1, "K": 1024, "M": 1024 * 1024}
    found = {}
    pattern = re.compile(
        r"^\s*(\w+)\s*(?:\([^)]*\))?\s*:\s*ORIGIN\s*=\s*(0x[0-9A-Fa-f]+|\d+)\s*,"
        r"\s*LENGTH\s*=\s*(0x[0-9A-Fa-f]+|\d+)\s*([KM]?)",
        re.MULTILINE,
    )
    for name, origin, length, unit in pattern.findall(memory_x.read_text()):
        found[name] = (int(origin, 0), int(length, 0) * units[unit])
    for needed in ("FLASH", "RAM"):
        if needed not in found:
            sys.exit(f"size.py: no {needed} region in {memory_x}")
    return found


def sections(elf: bytes):
    """(name, type, flags, addr, size) of every section of a 32-bit little-endian ELF."""
    if elf[:4] != b"\x7fELF" or elf[4] != 1 or elf[5] != 1:
        print("size.py: not a 32-bit little-endian ELF", file=sys.stderr)
        sys.exit(2)
    (shoff,) = struct.unpack_from("<I", elf, 0x20)
    shentsize, shnum, shstrndx = struct.unpack_from("<HHH", elf, 0x2E)
    headers = [struct.unpack_from("<10I", elf, shoff + i * shentsize) for i in range(shnum)]
    strtab_off = headers[shstrndx][4]

    def name(off: int) -> str:
        end = elf.index(b"\0", strtab_off + off)
        return elf[strtab_off + off : end].decode()

    for sh_name, sh_type, sh_flags, sh_addr, _off, sh_size, *_ in headers:
        yield name(sh_name), sh_type, sh_flags, sh_addr, sh_size


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("elf", type=pathlib.Path)
    parser.add_argument("--max-flash", type=int, help="fail above this many bytes of flash")
    parser.add_argument("--max-ram", type=int, help="fail above this many bytes of static RAM")
    args = parser.parse_args()

    mem = regions(pathlib.Path(__file__).with_name("memory.x"))
    flash_origin, flash_len = mem["FLASH"]
    ram_origin, ram_len = mem["RAM"]

    flash = ram = 0
    rows = []
    for name, sh_type, flags, addr, size in sections(args.elf.read_bytes()):
        if not flags & SHF_ALLOC or size == 0:
            continue
        if flash_origin <= addr < flash_origin + flash_len:
            flash += size
            rows.append((name, addr, size, "flash"))
        elif ram_origin <= addr < ram_origin + ram_len:
            ram += size
            where = "RAM"
            if sh_type != SHT_NOBITS:  # initialised: its image is copied from flash at boot
                flash += size
                where = "RAM + flash image"
            rows.append((name, addr, size, where))
        else:
            rows.append((name, addr, size, "other region (not counted)"))

    print(f"{'section':<16} {'address':>10} {'bytes':>8}  counted in")
    for name, addr, size, where in rows:
        print(f"{name:<16} {addr:#010x} {size:>8}  {where}")
    print(f"flash: {flash} bytes ({flash / 1024:.1f} KiB, {100 * flash / flash_len:.1f} % of "
          f"{flash_len // 1024} KiB)")
    print(f"RAM:   {ram} bytes ({ram / 1024:.1f} KiB, {100 * ram / ram_len:.1f} % of "
          f"{ram_len // 1024} KiB) static; the stack has the other {ram_len - ram} bytes")

    failed = False
    if args.max_flash is not None and flash > args.max_flash:
        print(f"size.py: flash {flash} > budget {args.max_flash}", file=sys.stderr)
        failed = True
    if args.max_ram is not None and ram > args.max_ram:
        print(f"size.py: RAM {ram} > budget {args.max_ram}", file=sys.stderr)
        failed = True
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
