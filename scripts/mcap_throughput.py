#!/usr/bin/env python3
"""MCAP write throughput of the Python `mcap` writer on the frames of
crates/hostsim/examples/mcap_throughput.rs: the same JSON messages (can_msgs/Frame shape,
as hostsim writes them), zstd chunks of 1 MiB. Prints one JSON line like the Rust example.

usage: scripts/mcap_throughput.py [FRAMES] [FILE]   (run with the project's .venv Python)
"""

from __future__ import annotations

import json
import os
import sys
import tempfile
import time

from mcap.writer import CompressionType, Writer

SCHEMA = (
    '{"type":"object","title":"can_msgs/msg/Frame","properties":{"id":{"type":"integer"},'
    '"dlc":{"type":"integer"},"data":{"type":"array","items":{"type":"integer"}}}}'
)


def frame(i: int) -> tuple[int, int, list[int]]:
    """Frame i: (t_ns, id, data), as the Rust example's `frame`."""
    b = i.to_bytes(8, "little")
    return i * 250_000, 0x201 + i % 4, [b[0], b[1], b[2], b[3], 0x5A, 0xA5, i % 251, 0x19]


def main() -> None:
    frames = int(sys.argv[1]) if len(sys.argv) > 1 else 1_000_000
    path = sys.argv[2] if len(sys.argv) > 2 else os.path.join(tempfile.gettempdir(), "mcap_throughput_py.mcap")
    start = time.perf_counter()
    with open(path, "wb") as f:
        writer = Writer(f, compression=CompressionType.ZSTD, chunk_size=1 << 20)
        writer.start(profile="", library="mcap_throughput.py")
        schema = writer.register_schema("can_msgs/msg/Frame", "jsonschema", SCHEMA.encode())
        channel = writer.register_channel("/can/rx", "json", schema)
        for i in range(frames):
            t, ident, d = frame(i)
            data = (
                f'{{"header":{{"stamp":{{"sec":{t // 1_000_000_000},"nsec":{t % 1_000_000_000}}},'
                f'"frame_id":"can0"}},"id":{ident},"is_rtr":false,"is_extended":false,'
                f'"is_error":false,"dlc":8,"data":[{d[0]},{d[1]},{d[2]},{d[3]},{d[4]},{d[5]},'
                f'{d[6]},{d[7]}]}}'
            )
            writer.add_message(channel, log_time=t, data=data.encode(), publish_time=t, sequence=i + 1)
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
