#!/usr/bin/env python3
"""MCAP write throughput of the Python `mcap` writer on the frames of
crates/hostsim/examples/mcap_throughput.rs: the same messages (CDR `can_msgs/msg/Frame` on
`/can/rx`, profile `ros2`, the schema text hostsim writes, byte for byte the message data it
writes), zstd chunks of 1 MiB. Prints one JSON line like the Rust example.

usage: scripts/mcap_throughput.py [FRAMES] [FILE]   (run with the project's .venv Python)
"""

from __future__ import annotations

import json
import os
import struct
import sys
import tempfile
import time

from mcap.writer import CompressionType, Writer

#: The `ros2msg` schema of can_msgs/msg/Frame as hostsim writes it (crates/drivelog/src/msg.rs,
#: `MsgDef::schema_text`): the type's fields, then each dependency after a line of 80 `=`.
SCHEMA = (
    "std_msgs/Header header\nuint32 id\nbool is_rtr\nbool is_extended\nbool is_error\nuint8 dlc\n"
    "uint8[8] data\n"
    + "=" * 80
    + "\nMSG: std_msgs/Header\nbuiltin_interfaces/Time stamp\nstring frame_id\n"
    + "=" * 80
    + "\nMSG: builtin_interfaces/Time\nint32 sec\nuint32 nanosec\n"
)

#: A frame's CDR message (36 bytes): the encapsulation header (CDR, little-endian), then
#: header.stamp (int32 sec, uint32 nanosec), header.frame_id (uint32 length 1, its NUL, 3
#: bytes of padding to the uint32 id), id, is_rtr, is_extended, is_error, dlc, data[8].
FRAME = struct.Struct("<4siIIB3xIBBBB8s")
CDR_LE = b"\x00\x01\x00\x00"


def frame(i: int) -> tuple[int, int, bytes]:
    """Frame i: (t_ns, id, data), as the Rust example's `frame`."""
    b = i.to_bytes(8, "little")
    return i * 250_000, 0x201 + i % 4, bytes([b[0], b[1], b[2], b[3], 0x5A, 0xA5, i % 251, 0x19])


def encode(t_ns: int, ident: int, data: bytes) -> bytes:
    """The CDR can_msgs/msg/Frame of a standard data frame of 8 bytes, stamped `t_ns`, with an
    empty frame_id: what hostsim logs."""
    sec, nanosec = divmod(t_ns, 1_000_000_000)
    return FRAME.pack(CDR_LE, sec, nanosec, 1, 0, ident, False, False, False, 8, data)


def main() -> None:
    frames = int(sys.argv[1]) if len(sys.argv) > 1 else 1_000_000
    path = sys.argv[2] if len(sys.argv) > 2 else os.path.join(tempfile.gettempdir(), "mcap_throughput_py.mcap")
    start = time.perf_counter()
    with open(path, "wb") as f:
        writer = Writer(f, compression=CompressionType.ZSTD, chunk_size=1 << 20)
        writer.start(profile="ros2", library="mcap_throughput.py")
        schema = writer.register_schema("can_msgs/msg/Frame", "ros2msg", SCHEMA.encode())
        channel = writer.register_channel("/can/rx", "cdr", schema)
        for i in range(frames):
            t, ident, d = frame(i)
            writer.add_message(channel, log_time=t, data=encode(t, ident, d), publish_time=t, sequence=0)
        writer.finish()
    seconds = time.perf_counter() - start
    print(json.dumps({
        "frames": frames,
        "seconds": round(seconds, 6),
        "frames_per_s": round(frames / seconds, 1),
        "bytes": os.path.getsize(path),
    }))


if __name__ == "__main__":
    main()
