"""What tests/test_dbc_codec.py and tests/test_dbc_codec_malformed.py share: a candump
frame's parts, a CANopen message's kind, and the SDO command bytes the Rust codec accepts."""

from __future__ import annotations

# SDO command bytes (CiA 301) without data size: upload request, download response, abort.
SDO_UPLOAD, SDO_DOWNLOADED, SDO_ABORT = 0x40, 0x60, 0x80


def sdo_expedited(cs: int) -> list[int]:
    """CiA 301 command bytes of an expedited initiate transfer with command specifier `cs`:
    bits 7-5 cs, bit 4 reserved (0), bits 3-2 n (unused data bytes), bit 1 e (expedited, 1),
    bit 0 s (size indicated); every n and s (without s, n is ignored: 4 bytes)."""
    return [cs << 5 | n << 2 | 0b10 | s for n in range(4) for s in range(2)]


# The SDO command bytes Rust accepts: only expedited transfers (download, client command
# specifier 1; upload response, server command specifier 2) and aborts. Segmented (0x21, 0x41)
# and block transfers are rejected.
SDO_COMMANDS = {
    "SDO_REQUEST": [SDO_UPLOAD, SDO_ABORT, *sdo_expedited(1)],
    "SDO_RESPONSE": [SDO_DOWNLOADED, SDO_ABORT, *sdo_expedited(2)],
}


def parse_candump(text: str) -> tuple[int, bytes, bool]:
    """`123#DEADBEEF` / `123#R8` -> (id, data, remote)."""
    ident, _, data = text.partition("#")
    if data.startswith("R"):
        return int(ident, 16), b"", True
    return int(ident, 16), bytes.fromhex(data), False


def canopen_kind(name: str) -> str:
    """A CANopen message's kind: `TPDO1_2` -> `TPDO1`, `SDO_REQUEST_1` -> `SDO_REQUEST`."""
    base, _, node = name.rpartition("_")
    return base if base and node.isdigit() else name
