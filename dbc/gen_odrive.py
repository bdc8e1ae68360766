#!/usr/bin/env python3
"""Generate dbc/odrive_cansimple.dbc: ODrive's official CAN Simple DBC cut down to nodes 0-3.

The official file, odrive-cansimple-0.6.10.dbc (ODrive firmware 0.6), ships in the MIT-licensed
`odrive-can` PyPI package. It defines every message for nodes 0-7 with ids
node_id << 5 | cmd_id. This script keeps the messages and nodes of axes 0-3 (ids 0x000-0x07F),
unchanged otherwise, and writes them with cantools.

    python -m pip download --no-deps odrive-can==2.1.0 -d odrive-can-dl
    python -m zipfile -e odrive-can-dl/odrive_can-2.1.0-py3-none-any.whl odrive-can-dl/x
    python dbc/gen_odrive.py odrive-can-dl/x/odrive_can/dbc/odrive-cansimple-0.6.10.dbc

Without an argument it looks for the file in an installed `odrive_can` package.
"""

from __future__ import annotations

import argparse
import importlib.util
import pathlib
import sys

import cantools

OFFICIAL_NAME = "odrive-cansimple-0.6.10.dbc"
NODES = range(4)
CMD_BITS = 5
OUT = pathlib.Path(__file__).with_name("odrive_cansimple.dbc")


def find_official() -> pathlib.Path:
    spec = importlib.util.find_spec("odrive_can")
    if spec is None or spec.origin is None:
        sys.exit("odrive_can is not installed; pass the path of " + OFFICIAL_NAME)
    return pathlib.Path(spec.origin).parent / "dbc" / OFFICIAL_NAME


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("official", nargs="?", type=pathlib.Path, help="path of " + OFFICIAL_NAME)
    parser.add_argument("-o", "--output", type=pathlib.Path, default=OUT)
    args = parser.parse_args()
    src = args.official or find_official()

    db = cantools.database.load_file(str(src), strict=True)
    last_id = (max(NODES) + 1) << CMD_BITS
    db.messages[:] = [m for m in db.messages if m.frame_id < last_id]
    keep = {"Master"} | {f"ODrive_Axis{n}" for n in NODES}
    db.nodes[:] = [n for n in db.nodes if n.name in keep]
    text = db.as_dbc_string()
    cantools.database.load_string(text, strict=True)  # the output must load strictly too
    args.output.write_text(text)
    print(f"wrote {args.output} ({len(db.messages)} messages) from {src}")


if __name__ == "__main__":
    main()
