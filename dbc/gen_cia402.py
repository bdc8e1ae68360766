#!/usr/bin/env python3
"""Generate dbc/cia402.dbc: the CANopen (CiA 301/402) frames of the firmware's master.

CANopen ids are a function code plus a node id (1..127), so a DBC spells every frame out per
node. This script holds the frames once, as the Rust codec's `layout` table has them
(crates/firmware/src/protocol/canopen/layout.rs; the signal names are its `Field` names), and writes
them for nodes 1 and 2 (DRIVE_1, DRIVE_2) and the master's heartbeat (node 127). The file it
writes must load with cantools, strictly, and decode to the same frames; the script checks that
before writing.

    python dbc/gen_cia402.py            # writes dbc/cia402.dbc
    python dbc/gen_cia402.py --check    # exit 1 if dbc/cia402.dbc is not what it would write

Regenerate rather than edit the .dbc by hand.
"""

from __future__ import annotations

import argparse
import pathlib
import sys
from dataclasses import dataclass

import cantools

OUT = pathlib.Path(__file__).with_name("cia402.dbc")
DRIVES = (1, 2)
MASTER_NODE = 127
MASTER = "MASTER"


def drive(node: int) -> str:
    return f"DRIVE_{node}"


@dataclass(frozen=True)
class Sig:
    name: str
    start: int
    length: int
    signed: bool = False
    comment: str = ""
    # [minimum|maximum]; None: the whole raw range of the type.
    lo: int | None = None
    hi: int | None = None
    choices: tuple[tuple[int, str], ...] = ()

    def bounds(self) -> tuple[int, int]:
        if self.signed:
            lo, hi = -(2 ** (self.length - 1)), 2 ** (self.length - 1) - 1
        else:
            lo, hi = 0, 2**self.length - 1
        return (lo if self.lo is None else self.lo, hi if self.hi is None else self.hi)

    def line(self, receivers: list[str]) -> str:
        lo, hi = self.bounds()
        sign = "-" if self.signed else "+"
        return (f' SG_ {self.name} : {self.start}|{self.length}@1{sign} (1,0) [{lo}|{hi}] "" '
                f"{','.join(receivers)}")


@dataclass(frozen=True)
class Msg:
    """One frame: `name` (with `_<node>` appended for a node's frame), id, DLC, signals."""

    name: str
    function: int
    dlc: int
    from_drive: bool
    comment: str
    signals: tuple[Sig, ...] = ()


# --- the frames (docs/protocol.md, "CANopen CiA 402") ------------------------------------------

NMT_COMMANDS = ((0x01, "START"), (0x02, "STOP"), (0x80, "PRE_OPERATIONAL"), (0x81, "RESET_NODE"),
                (0x82, "RESET_COMMUNICATION"))
NMT_STATES = ((0x00, "BOOT_UP"), (0x04, "STOPPED"), (0x05, "OPERATIONAL"), (0x7F, "PRE_OPERATIONAL"))

NMT = Msg("NMT", 0x000, 2, False,
          "NMT node control, master to all nodes (id 0x000, the highest priority).", (
              Sig("command", 0, 8, lo=0x01, hi=0x82, choices=NMT_COMMANDS,
                  comment="NMT command. Values outside the value table are rejected."),
              Sig("node", 8, 8, lo=0, hi=127, comment="The node addressed, 1..127; 0 addresses every node."),
          ))
SYNC = Msg("SYNC", 0x080, 0, False,
           "SYNC, master to all nodes, once per control cycle, before the RPDOs: each drive answers "
           "with its TPDOs (transmission type 1) and applies its RPDOs on receipt (type 0xFF). The "
           "firmware also accepts CiA 301's counter form (DLC 1, counter 1..240), which this file "
           "does not describe; it sends DLC 0.")

SDO_FIELDS = (
    Sig("command", 0, 8, comment="SDO command specifier byte (see the message comment). Other values "
        "(segmented and block transfers, reserved bits set) are rejected."),
    Sig("index", 8, 16, comment="Object index (0x6040 controlword, 0x60FF target velocity, ...)."),
    Sig("subindex", 24, 8, comment="Object sub-index."),
    Sig("data", 32, 32, comment="Expedited data, little-endian; the bytes beyond the transfer's size "
        "are zero and ignored on receipt. An abort carries the abort code (CiA 301 table 22); an "
        "upload request and a download response carry no data (zero, ignored)."),
)

PER_NODE = (
    Msg("EMCY", 0x080, 8, True,
        "Emergency (0x080 + node), drive to master: sent when an error occurs and, with error_code 0, "
        "when the errors are gone. The master decodes and counts them; a drive's fault itself is "
        "seen in the statusword (bit 3).", (
            Sig("error_code", 0, 16, comment="Error code (CiA 301 table 21, CiA 402 for drive errors); "
                "0 = error reset or no error."),
            Sig("error_register", 16, 8, comment="The error register, object 0x1001."),
            Sig("manufacturer", 24, 40, comment="Manufacturer-specific error field, bytes 3-7 (one "
                "little-endian 40-bit number here)."),
        )),
    Msg("TPDO1", 0x180, 6, True,
        "TPDO1 (0x180 + node; 0x1800, mapping 0x1A00), drive to master at every SYNC (transmission "
        "type 1). Mapping: 0x6041:00 statusword (16 bits), then 0x606C:00 on a single-axis node or "
        "0x606C:01 on a dual-axis node (32 bits).", (
            Sig("statusword", 0, 16, comment="Statusword, object 0x6041: the CiA 402 state in bits "
                "0-3, 5 and 6; bit 3 fault."),
            Sig("velocity_actual", 16, 32, signed=True, comment="Velocity actual value, object 0x606C "
                "sub 0 (single-axis) or sub 1 (the first axis of a dual-axis node), drive units: "
                "drive.actual_rpm_per_unit motor rpm per unit."),
        )),
    Msg("RPDO1", 0x200, 6, False,
        "RPDO1 (0x200 + node; 0x1400, mapping 0x1600), master to drive after every SYNC, applied on "
        "receipt (transmission type 0xFF). Mapping: 0x6040:00 controlword (16 bits), then 0x60FF:00 "
        "on a single-axis node or 0x60FF:01 on a dual-axis node (32 bits).", (
            Sig("controlword", 0, 16, comment="Controlword, object 0x6040: 0x06 shutdown, 0x07 switch "
                "on, 0x0F enable operation, 0x02 quick stop, 0x80 fault reset (its rising edge)."),
            Sig("target_velocity", 16, 32, signed=True, comment="Target velocity, object 0x60FF sub 0 "
                "(single-axis) or sub 1 (the first axis of a dual-axis node), drive units: "
                "drive.target_rpm_per_unit motor rpm per unit."),
        )),
    Msg("TPDO2", 0x280, 4, True,
        "TPDO2 (0x280 + node; 0x1801, mapping 0x1A01), dual-axis nodes only, drive to master at every "
        "SYNC. Mapping: 0x606C:02 (32 bits). A single-axis node has it disabled.", (
            Sig("velocity_actual_2", 0, 32, signed=True, comment="Velocity actual value of the second "
                "axis, object 0x606C sub 2, drive units."),
        )),
    Msg("RPDO3", 0x400, 4, False,
        "RPDO3 (0x400 + node; 0x1402, mapping 0x1602), dual-axis nodes only, master to drive after "
        "every SYNC. Mapping: 0x60FF:02 (32 bits). The second axis's target takes RPDO3, not RPDO2: "
        "RPDO2's predefined id, 0x300 + node, is in the robot protocol's block (0x300-0x31F), so "
        "RPDO2 is never used and the master disables it (0x1401:01 bit 31), as every PDO it does "
        "not map: a drive cannot take a robot frame for a PDO.", (
            Sig("target_velocity_2", 0, 32, signed=True, comment="Target velocity of the second axis, "
                "object 0x60FF sub 2, drive units."),
        )),
    Msg("SDO_RESPONSE", 0x580, 8, True,
        "Expedited SDO, server (drive) to client (master), 0x580 + node. command: 0x43, 0x47, 0x4B, "
        "0x4F upload response with 4, 3, 2, 1 data bytes (0x42: size not indicated, 4 bytes); 0x60 "
        "download response; 0x80 abort. Only expedited transfers are implemented: a segmented "
        "upload's response (0x41) is rejected, and the master treats it as a failed transfer.",
        SDO_FIELDS),
    Msg("SDO_REQUEST", 0x600, 8, False,
        "Expedited SDO, client (master) to server (drive), 0x600 + node, one transfer at a time per "
        "node. command: 0x40 upload (read); 0x23, 0x27, 0x2B, 0x2F download (write) of 4, 3, 2, 1 "
        "data bytes (0x22: size not indicated, 4 bytes); 0x80 abort. The master configures each "
        "node with these: 0x1000, 0x6060 = 3 (profile velocity), 0x1017, 0x1016:01, the PDOs.",
        SDO_FIELDS),
    Msg("HEARTBEAT", 0x700, 1, True,
        "Heartbeat (0x700 + node, every 0x1017 ms) and, with state BOOT_UP, the boot-up message. "
        "A boot-up makes the master configure the node (again).", (
            Sig("state", 0, 8, lo=0, hi=0x7F, choices=NMT_STATES, comment="NMT state. Bit 7 is node "
                "guarding's toggle bit, not used by heartbeats; values outside the value table are "
                "rejected."),
        )),
)

FILE_COMMENT = (
    "CANopen (CiA 301) frames of CiA 402 velocity drives, as the mecanum firmware's master uses "
    "them (firmware::protocol::canopen; docs/protocol.md, section CANopen CiA 402). Generated by "
    "gen_cia402.py. Every id is a function code plus a node id (1..127): this file spells the "
    "frames out for nodes 1 and 2 (DRIVE_1, DRIVE_2) and the master's heartbeat (node 127); "
    "another node's frames are the same with its id. CAN 2.0A standard ids, little-endian. The PDO "
    "contents are the mapping the master writes into each drive (RPDO1, RPDO3, TPDO1, TPDO2); "
    "RPDO2 (0x300 + node, the robot protocol's block), RPDO4, TPDO3 and TPDO4 are unused and "
    "disabled. The ids overlap the ODrive (NMT 0x000) and DJI (RPDO1 0x201-0x208) protocols: a bus "
    "carries one drive protocol."
)


def frames() -> list[tuple[int, str, Msg, str, list[str], str]]:
    """(id, name, message, sender, receivers, comment) of every frame, by id."""
    drives = [drive(n) for n in DRIVES]
    out = [(NMT.function, NMT.name, NMT, MASTER, drives, NMT.comment),
           (SYNC.function, SYNC.name, SYNC, MASTER, drives, SYNC.comment)]
    for m in PER_NODE:
        for n in DRIVES:
            sender, receivers = (drive(n), [MASTER]) if m.from_drive else (MASTER, [drive(n)])
            out.append((m.function + n, f"{m.name}_{n}", m, sender, receivers, m.comment))
    heartbeat = next(m for m in PER_NODE if m.name == "HEARTBEAT")
    out.append((heartbeat.function + MASTER_NODE, f"HEARTBEAT_{MASTER_NODE}", heartbeat, MASTER, drives,
                "The master's heartbeat (node drive.master_node, 127 by default), operational, every "
                "drive.heartbeat_ms; each drive watches it (0x1016:01 = master node << 16 | "
                "drive.heartbeat_timeout_ms)."))
    return sorted(out, key=lambda f: f[0])


def quote(text: str) -> str:
    assert '"' not in text and "\n" not in text, text
    return f'"{text}"'


def dbc_text() -> str:
    lines = [
        'VERSION "1"', "", "",
        "NS_ :", "\tNS_DESC_", "\tCM_", "\tBA_DEF_", "\tBA_", "\tVAL_", "\tBA_DEF_DEF_", "",
        "BS_:", "",
        "BU_: " + " ".join([MASTER, *(drive(n) for n in DRIVES)]), "", "",
    ]
    all_frames = frames()
    for frame_id, name, m, sender, receivers, _ in all_frames:
        lines.append(f"BO_ {frame_id} {name}: {m.dlc} {sender}")
        lines += [s.line(receivers) for s in m.signals]
        lines.append("")
    lines.append("")
    lines.append(f"CM_ {quote(FILE_COMMENT)};")
    lines.append(f'CM_ BU_ {MASTER} "The CANopen master: the mecanum firmware (node {MASTER_NODE} for its '
                 'heartbeat, drive.master_node).";')
    for n in DRIVES:
        lines.append(f'CM_ BU_ {drive(n)} "CiA 402 drive, node {n} (profile velocity mode; one or two '
                     'axes).";')
    for frame_id, _, m, _, _, comment in all_frames:
        lines.append(f"CM_ BO_ {frame_id} {quote(comment)};")
        lines += [f"CM_ SG_ {frame_id} {s.name} {quote(s.comment)};" for s in m.signals if s.comment]
    for frame_id, _, m, _, _, _ in all_frames:
        for s in m.signals:
            if s.choices:
                table = " ".join(f'{value} "{label}"' for value, label in s.choices)
                lines.append(f"VAL_ {frame_id} {s.name} {table} ;")
    return "\n".join(lines) + "\n"


def check(text: str) -> None:
    """The text loads strictly and holds the frames as the tables here describe them."""
    db = cantools.database.load_string(text, database_format="dbc", strict=True)
    assert isinstance(db, cantools.database.can.Database)
    want = frames()
    assert [m.frame_id for m in db.messages] == [f[0] for f in want]
    for frame_id, name, m, sender, receivers, _ in want:
        msg = db.get_message_by_frame_id(frame_id)
        assert (msg.name, msg.length, msg.senders, msg.is_extended_frame) == (name, m.dlc, [sender], False)
        assert [s.name for s in msg.signals] == [s.name for s in m.signals], name
        for sig in m.signals:
            got = msg.get_signal_by_name(sig.name)
            assert (got.start, got.length, got.is_signed, got.byte_order) == (
                sig.start, sig.length, sig.signed, "little_endian"), (name, sig.name)
            assert (got.minimum, got.maximum) == sig.bounds(), (name, sig.name)
            assert sorted(got.receivers) == sorted(receivers), (name, sig.name)
            assert {int(k): str(v) for k, v in (got.choices or {}).items()} == dict(sig.choices)
    # The byte layout: TPDO1 statusword 0x0637, velocity -2 = 37 06 FE FF FF FF.
    tpdo1 = db.get_message_by_name("TPDO1_1")
    assert tpdo1.encode({"statusword": 0x0637, "velocity_actual": -2}) == bytes.fromhex("3706FEFFFFFF")
    sdo = db.get_message_by_name("SDO_REQUEST_2")
    assert sdo.encode({"command": 0x2B, "index": 0x6040, "subindex": 0, "data": 0x0F}) == bytes.fromhex(
        "2B4060000F000000")
    emcy = db.get_message_by_name("EMCY_1")
    assert emcy.encode({"error_code": 0x8130, "error_register": 0x11, "manufacturer": 0x0504030201}) == (
        bytes.fromhex("3081110102030405"))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("-o", "--output", type=pathlib.Path, default=OUT)
    parser.add_argument("--check", action="store_true",
                        help="do not write: exit 1 if the output file differs from what would be written")
    args = parser.parse_args()
    text = dbc_text()
    check(text)
    if args.check:
        current = args.output.read_text() if args.output.exists() else None
        if current != text:
            sys.exit(f"{args.output} is not what {pathlib.Path(__file__).name} writes: regenerate it")
        print(f"{args.output} is up to date")
        return
    args.output.write_text(text)
    print(f"wrote {args.output} ({len(frames())} messages)")


if __name__ == "__main__":
    main()
