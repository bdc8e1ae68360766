"""Cross-check of the firmware's Rust codecs against the DBC files, through `mecanum-codec`.

(a) Every golden frame the Rust encoders produce decodes with cantools, from the DBC, to the
    values Rust reports (and to the values given to the encoder, within half an LSB).
(b) Frames encoded by cantools from the DBC, for many value sets (extremes, zeros, seeded
    random values) of every message, decode in Rust to the same values.
(c) Malformed frames: tests/test_dbc_codec_malformed.py.

Field names are the DBC signal names; values are physical (scaled) values. CANopen frames
(dbc/cia402.dbc) go through `decode --canopen`: their ids overlap DJI's and ODrive's.
"""

from __future__ import annotations

import math
import pathlib
import random
import re
import struct
import subprocess
import sys

import pytest
from codec_frames import SDO_ABORT, SDO_COMMANDS, SDO_DOWNLOADED, SDO_UPLOAD, canopen_kind, parse_candump

DBC_DIR = pathlib.Path(__file__).resolve().parent.parent / "dbc"

# Messages the Rust codecs implement, per protocol (ODrive: per node 0-3, cmd suffix only).
ODRIVE_NODES = range(4)
ODRIVE_MESSAGES = {
    0x01: "Heartbeat",
    0x02: "Estop",
    0x03: "Get_Error",
    0x07: "Set_Axis_State",
    0x09: "Get_Encoder_Estimates",
    0x0B: "Set_Controller_Mode",
    0x0D: "Set_Input_Vel",
    0x18: "Clear_Errors",
}

# Signals the Rust decoders do not report (reserved, ignored on receipt).
RESERVED = {"reserved"}

# Signals whose raw values form an enum in Rust: other values are rejected (part c).
ENUM_VALUES = {
    "magic": [0xE5],
    "request": [0, 1, 2],
    "state": [0, 1, 2, 3, 4],
    "fault": list(range(14)),
    "wheel": [0, 1, 2, 3],
    "outcome": [0, 1, 2, 3],
    "heading_source": [0, 1, 2],
    "source": [0, 1, 2, 3],
    "Axis_State": list(range(15)),
    "Axis_Requested_State": list(range(15)),
    "Control_Mode": [0, 1, 2, 3],
    "Input_Mode": list(range(9)),
}

# Signals Rust reads as a flag (nonzero = true, as ODrive does): generated as 0 or 1 only.
FLAGS = {"Identify": [0, 1]}

# CANopen (dbc/cia402.dbc, `decode --canopen`): per node 1 and 2 by function code (id = code +
# node), and NMT, SYNC and the master's heartbeat (node 127) once.
CANOPEN_NODES = (1, 2)
CANOPEN_MASTER_NODE = 127
CANOPEN_MESSAGES = {
    0x080: "EMCY",
    0x180: "TPDO1",
    0x280: "TPDO2",
    0x200: "RPDO1",
    0x400: "RPDO3",
    0x580: "SDO_RESPONSE",
    0x600: "SDO_REQUEST",
    0x700: "HEARTBEAT",
}
# docs/protocol.md, "CANopen CiA 402": kind -> (DLC, sent by the drive, [(signal, start bit,
# length, signed)]), little-endian, unscaled.
SDO_SIGNALS = [("command", 0, 8, False), ("index", 8, 16, False), ("subindex", 24, 8, False),
               ("data", 32, 32, False)]
CANOPEN_LAYOUT = {
    "NMT": (2, False, [("command", 0, 8, False), ("node", 8, 8, False)]),
    "SYNC": (0, False, []),
    "EMCY": (8, True, [("error_code", 0, 16, False), ("error_register", 16, 8, False),
                       ("manufacturer", 24, 40, False)]),
    "TPDO1": (6, True, [("statusword", 0, 16, False), ("velocity_actual", 16, 32, True)]),
    "TPDO2": (4, True, [("velocity_actual_2", 0, 32, True)]),
    "RPDO1": (6, False, [("controlword", 0, 16, False), ("target_velocity", 16, 32, True)]),
    "RPDO3": (4, False, [("target_velocity_2", 0, 32, True)]),
    "SDO_RESPONSE": (8, True, SDO_SIGNALS),
    "SDO_REQUEST": (8, False, SDO_SIGNALS),
    "HEARTBEAT": (1, True, [("state", 0, 8, False)]),
}
# The Rust enums firmware::protocol::canopen::NmtCommand and NmtState, by raw value.
NMT_COMMANDS = {0x01: "START", 0x02: "STOP", 0x80: "PRE_OPERATIONAL", 0x81: "RESET_NODE",
                0x82: "RESET_COMMUNICATION"}
NMT_STATES = {0x00: "BOOT_UP", 0x04: "STOPPED", 0x05: "OPERATIONAL", 0x7F: "PRE_OPERATIONAL"}

# The SDO command bytes (SDO_UPLOAD, SDO_DOWNLOADED, SDO_ABORT, and SDO_COMMANDS: those Rust
# accepts): tests/codec_frames.py.


def sdo_size(command: int) -> int:
    """The data bytes of an expedited transfer: 4 - n if s is set, else 4."""
    return 4 - (command >> 2 & 3) if command & 1 else 4


# Signals whose raw values form an enum in Rust, per CANopen message kind (part b and c).
CANOPEN_ENUM_VALUES = {
    ("NMT", "command"): sorted(NMT_COMMANDS),
    ("HEARTBEAT", "state"): sorted(NMT_STATES),
    **{(kind, "command"): sorted(commands) for kind, commands in SDO_COMMANDS.items()},
}

SEED = 0x3EC4  # fixed: the random value sets are the same on every run
RANDOM_SETS_PER_MESSAGE = 40


# ------------------------------------------------------------------------------------------
# helpers


def candump(frame_id: int, data: bytes, prefix: bool = False) -> str:
    line = f"{frame_id:03X}#{data.hex().upper()}"
    return f"(1700000000.{frame_id:06d}) vcan0 {line}" if prefix else line


def f32(x: float) -> float:
    """x rounded to the nearest float32, as Rust holds it."""
    return struct.unpack("<f", struct.pack("<f", x))[0]


def half_lsb(signal) -> float:
    return 0.5 * signal.scale * (1 + 1e-9)


def f32_slack(x: float) -> float:
    """Rounding of a value to f32 in Rust (relative 2^-24, and a little for the scaling)."""
    return abs(x) * 2.0**-23


def assert_value(signal, rust: float, want: float, tol: float, where: str) -> None:
    if signal.is_float:
        assert f32(rust) == f32(want), f"{where}: {signal.name} Rust {rust!r} != {want!r}"
        return
    assert math.isfinite(rust), f"{where}: {signal.name} Rust {rust!r}"
    if is_integral(signal):
        # Counters, flags, error bits, enums: exact (a float32 slack would hide a lost bit of
        # a 32-bit error word).
        assert rust == want, f"{where}: {signal.name} Rust {rust!r} != {want!r}"
        return
    assert abs(rust - want) <= tol, (
        f"{where}: {signal.name} Rust {rust!r} vs {want!r} (tolerance {tol:g})"
    )


def implemented_messages(dbs):
    """(protocol, cantools message) for every message the Rust codecs implement."""
    out = [("robot", m) for m in dbs["robot"].messages]
    out += [("dji", m) for m in dbs["dji"].messages]
    for node in ODRIVE_NODES:
        for cmd, name in ODRIVE_MESSAGES.items():
            m = dbs["odrive"].get_message_by_frame_id(node << 5 | cmd)
            assert m.name == f"Axis{node}_{name}", m.name
            out.append(("odrive", m))
    canopen = dbs["canopen"]
    master_heartbeat = 0x700 + CANOPEN_MASTER_NODE
    for frame_id, name in [(0x000, "NMT"), (0x080, "SYNC"),
                           (master_heartbeat, f"HEARTBEAT_{CANOPEN_MASTER_NODE}")]:
        m = canopen.get_message_by_frame_id(frame_id)
        assert m.name == name, m.name
        out.append(("canopen", m))
    for node in CANOPEN_NODES:
        for code, name in CANOPEN_MESSAGES.items():
            m = canopen.get_message_by_frame_id(code + node)
            assert m.name == f"{name}_{node}", m.name
            out.append(("canopen", m))
    return out


def canopen_rust_view(msg, values: dict) -> dict:
    """The values Rust reports for a CANopen frame that carries `values`: an SDO's data as
    CiA 301 reads it (an expedited transfer's size low bytes; the code of an abort; nothing, 0,
    in an upload request or a download response), every other signal as it is."""
    if canopen_kind(msg.name) not in SDO_COMMANDS:
        return values
    command, data = values["command"], values["data"]
    if command in (SDO_UPLOAD, SDO_DOWNLOADED):
        data = 0
    elif command != SDO_ABORT:
        data &= (1 << 8 * sdo_size(command)) - 1
    return {**values, "data": data}


def check_canopen_extras(msg, rust: dict, values: dict, where: str) -> None:
    """`node` (from the id; none for NMT and SYNC) and an SDO's `size` (expedited data only)."""
    kind = canopen_kind(msg.name)
    if kind in ("NMT", "SYNC"):
        assert "node" not in rust, f"{where}: {rust}"
    else:
        assert rust["node"] == msg.frame_id & 0x7F == int(msg.name.rpartition("_")[2]), where
    size = None
    if kind in SDO_COMMANDS and values["command"] not in (SDO_UPLOAD, SDO_DOWNLOADED, SDO_ABORT):
        size = sdo_size(values["command"])
    assert rust.get("size") == size, f"{where}: size {rust.get('size')}, want {size}"


def check_decoded(db_msg, rust: dict, expected: dict, tol_of, where: str) -> None:
    assert "error" not in rust, f"{where}: Rust rejected the frame: {rust}"
    assert rust["message"] == db_msg.name, where
    assert rust["id"] == db_msg.frame_id, where
    fields = rust["fields"]
    missing = {s.name for s in db_msg.signals} - set(fields) - RESERVED
    assert not missing, f"{where}: Rust does not report {missing}"
    for name, value in fields.items():
        signal = db_msg.get_signal_by_name(name)
        assert_value(signal, value, expected[name], tol_of(signal, expected[name]), where)


# ------------------------------------------------------------------------------------------
# DBC files


def test_dbc_files_load_strictly(dbs):
    assert {m.name for m in dbs["robot"].messages} == {
        "ESTOP", "TWIST_CMD", "MODE_CMD", "STATUS_REQ", "IMU_YAW_RATE", "WHEEL_TEST", "POD_COUNTS",
        "WHEEL_TEST_RESULT", "ODOM_POSITION", "ODOM_VELOCITY", "STATUS", "STATUS_COUNTERS", "ODOM_SLIP",
        "HEARTBEAT",
    }
    assert all(0x300 <= m.frame_id <= 0x31F for m in dbs["robot"].messages)
    assert sorted(m.frame_id for m in dbs["dji"].messages) == [0x1FF, *range(0x200, 0x209)]
    assert all(m.frame_id < 0x80 for m in dbs["odrive"].messages)
    assert sorted(m.frame_id for m in dbs["canopen"].messages) == sorted(
        [0x000, 0x080, 0x700 + CANOPEN_MASTER_NODE]
        + [code + node for code in CANOPEN_MESSAGES for node in CANOPEN_NODES])
    # No CANopen frame in the robot block: RPDO2 (0x300 + node) is not used.
    assert not any(0x300 <= m.frame_id <= 0x31F for m in dbs["canopen"].messages)
    for db in dbs.values():
        assert all(not m.is_extended_frame for m in db.messages)


def test_robot_dbc_is_little_endian_and_dji_big_endian(dbs):
    for m in dbs["robot"].messages:
        assert all(s.byte_order == "little_endian" for s in m.signals), m.name
    for m in dbs["dji"].messages:
        multi_byte = [s for s in m.signals if s.length > 8]
        assert multi_byte and all(s.byte_order == "big_endian" for s in multi_byte), m.name


def test_canopen_dbc_follows_the_protocol_doc(dbs):
    """dbc/cia402.dbc: the layout of docs/protocol.md (ids, DLCs, senders, signals as the Rust
    layout names them), comments that name the mapping objects and why RPDO2 is not used,
    and the file is what dbc/gen_cia402.py writes."""
    canopen = dbs["canopen"]
    drives = sorted(f"DRIVE_{n}" for n in CANOPEN_NODES)
    assert sorted(n.name for n in canopen.nodes) == sorted(["MASTER", *drives])
    for m in canopen.messages:
        dlc, from_drive, signals = CANOPEN_LAYOUT[canopen_kind(m.name)]
        assert m.length == dlc and not m.is_extended_frame, m.name
        assert [(s.name, s.start, s.length, s.is_signed) for s in m.signals] == signals, m.name
        for s in m.signals:
            assert (s.byte_order, s.scale, s.offset, s.is_float) == ("little_endian", 1, 0, False)
        node = m.frame_id & 0x7F
        if canopen_kind(m.name) in ("NMT", "SYNC") or node == CANOPEN_MASTER_NODE:
            assert m.senders == ["MASTER"], m.name
            assert all(sorted(s.receivers) == drives for s in m.signals), m.name
        else:
            sender, receiver = (f"DRIVE_{node}", "MASTER") if from_drive else ("MASTER", f"DRIVE_{node}")
            assert m.senders == [sender], m.name
            assert all(s.receivers == [receiver] for s in m.signals), m.name
        assert m.comment, m.name
        assert all(s.comment for s in m.signals), m.name
    comment = {kind: canopen.get_message_by_name(f"{kind}_1").comment for kind in CANOPEN_MESSAGES.values()}
    for kind, words in {
        "RPDO1": ("0x6040:00", "0x60FF:00", "0x60FF:01", "0x1600", "0xFF"),
        "RPDO3": ("0x60FF:02", "0x1602", "RPDO2", "0x300 + node", "robot protocol", "disables"),
        "TPDO1": ("0x6041:00", "0x606C:00", "0x606C:01", "0x1A00", "SYNC"),
        "TPDO2": ("0x606C:02", "0x1A01"),
        "SDO_RESPONSE": ("0x41", "abort"),
        "HEARTBEAT": ("BOOT_UP", "boot-up"),
    }.items():
        for word in words:
            assert word in comment[kind], (kind, word)
    proc = subprocess.run([sys.executable, str(DBC_DIR / "gen_cia402.py"), "--check"],
                          capture_output=True, text=True, timeout=60, check=False)
    assert proc.returncode == 0, proc.stdout + proc.stderr


# ------------------------------------------------------------------------------------------
# (a) golden frames from the Rust encoders


@pytest.fixture(scope="module")
def golden(run_codec):
    lines = run_codec("golden")
    assert len(lines) >= 60
    return lines


ROBOT_DBC = DBC_DIR / "mecanum_robot.dbc"


def test_dbc_version_line_is_the_firmwares_protocol_version(golden):
    """The DBC's first comment names the protocol version in a fixed form (other packages
    parse it: "Mecanum robot CAN protocol, version N (...)"); N is the version the Rust
    encoder puts in HEARTBEAT, and the HEARTBEAT comment says the same."""
    text = ROBOT_DBC.read_text()
    comments = re.findall(r'^CM_ "(.*)";$', text, re.M)
    assert comments, "no file comment"
    m = re.fullmatch(r"Mecanum robot CAN protocol, version (\d+) \(.+?\)\. .*", comments[0])
    assert m, comments[0][:120]
    version = int(m.group(1))
    assert version == 8
    beats = [g for g in golden if g.get("message") == "HEARTBEAT"]
    assert beats and all(g["fields"]["protocol_version"] == version for g in beats), beats
    assert f'protocol_version "Protocol version: {version} for this file.' in text


def test_twist_seq_is_documented_as_an_alive_counter(dbs):
    """TWIST_CMD.seq's comment tells a host to increment it and what a repeat does, and the
    counter frame that counts repeats follows STATUS in the block."""
    seq = dbs["robot"].get_message_by_name("TWIST_CMD").get_signal_by_name("seq")
    for words in ("Alive counter", "increments", "not apply", "watchdog", "repeated_seq",
                  "255 -> 0", "enable or reset"):
        assert words in seq.comment, (words, seq.comment)
    counters = dbs["robot"].get_message_by_name("STATUS_COUNTERS")
    assert (counters.frame_id, counters.length, counters.senders) == (0x313, 8, ["ROBOT"])
    assert [s.name for s in counters.signals] == ["repeated_seq", "wrong_dlc", "out_of_range", "non_finite"]
    assert all((s.length, s.is_signed, s.minimum, s.maximum) == (16, False, 0, 65535) for s in counters.signals)


def test_imu_yaw_rate_is_an_optional_float_frame_with_an_alive_counter(dbs):
    """IMU_YAW_RATE: host-to-robot block (0x300-0x30F), sent by its own node, a little-endian
    float32 yaw rate in rad/s within the +-35 rad/s a MEMS gyro can read, an alive counter like
    TWIST_CMD's, and the rules (bias, timeout, fallback, counting) in its comments. STATUS
    carries the heading source in the high nibble of motors_online's byte."""
    robot = dbs["robot"]
    imu = robot.get_message_by_name("IMU_YAW_RATE")
    assert (imu.frame_id, imu.length, imu.senders) == (0x304, 8, ["IMU"])
    assert 0x300 <= imu.frame_id <= 0x30F
    rate = imu.get_signal_by_name("yaw_rate")
    assert (rate.start, rate.length, rate.is_float, rate.byte_order) == (0, 32, True, "little_endian")
    assert (rate.minimum, rate.maximum, rate.unit) == (-35, 35, "rad/s")
    assert [s.name for s in imu.signals] == ["yaw_rate", "seq", "reserved"]
    assert imu.get_signal_by_name("seq").start == 32
    for words in ("bias", "standing still", "timeout", "WHEELS_GYRO_SILENT", "not a fault",
                  "non_finite", "out_of_range", "counter-clockwise"):
        assert words in (imu.comment or "") + (rate.comment or ""), words
    assert "repeated_seq" in imu.get_signal_by_name("seq").comment
    status = robot.get_message_by_name("STATUS")
    online, heading = status.get_signal_by_name("motors_online"), status.get_signal_by_name("heading_source")
    assert (online.start, online.length, heading.start, heading.length) == (48, 4, 52, 4)
    assert {int(k): str(v) for k, v in heading.choices.items()} == {
        0: "WHEELS", 1: "GYRO", 2: "WHEELS_GYRO_SILENT"}
    # 0.5 rad/s counter-clockwise, seq 7, as cantools writes it: float32 LE.
    assert imu.encode({"yaw_rate": 0.5, "seq": 7, "reserved": 0}) == bytes.fromhex("0000003F07000000")


def test_pod_counts_and_odom_slip_are_version_7s_optional_frames(dbs):
    """POD_COUNTS: host-to-robot block, from its own node (PODS), three wrapping u16 counts and
    an alive counter, the rules (baseline, timeout, fallback, counting) in its comments.
    ODOM_SLIP: robot-to-host, the slip velocities as ODOM_VELOCITY's and the source in byte 6's
    low nibble; a robot without pods sends none."""
    robot = dbs["robot"]
    pods = robot.get_message_by_name("POD_COUNTS")
    assert (pods.frame_id, pods.length, pods.senders) == (0x306, 8, ["PODS"])
    assert [s.name for s in pods.signals] == ["count0", "count1", "count2", "seq", "reserved"]
    for i, name in enumerate(("count0", "count1", "count2")):
        sig = pods.get_signal_by_name(name)
        assert (sig.start, sig.length, sig.is_signed, sig.byte_order) == (16 * i, 16, False, "little_endian")
    assert pods.get_signal_by_name("seq").start == 48
    for words in ("baseline", "timeout", "WHEELS_PODS_SILENT", "not a fault", "DLC"):
        assert words in pods.comment, words
    assert "signed 16-bit difference" in pods.get_signal_by_name("count0").comment
    assert "repeated_seq" in pods.get_signal_by_name("seq").comment
    assert pods.encode({"count0": 1, "count1": 65535, "count2": 0, "seq": 9, "reserved": 0}) == bytes.fromhex(
        "0100FFFF00000900")
    slip = robot.get_message_by_name("ODOM_SLIP")
    assert (slip.frame_id, slip.length, slip.senders) == (0x315, 8, ["ROBOT"])
    velocity = robot.get_message_by_name("ODOM_VELOCITY")
    for name in ("vx", "vy", "wz"):
        a, b = slip.get_signal_by_name(name), velocity.get_signal_by_name(name)
        assert (a.length, a.is_signed, a.scale, a.minimum, a.maximum, a.unit) == (
            b.length, b.is_signed, b.scale, b.minimum, b.maximum, b.unit), name
    source = slip.get_signal_by_name("source")
    assert (source.start, source.length) == (48, 4)
    assert {int(k): str(v) for k, v in source.choices.items()} == {
        0: "WHEELS", 1: "PODS2_GYRO", 2: "PODS3", 3: "WHEELS_PODS_SILENT"}
    assert "only from a robot configured with pods" in slip.comment


def test_golden_covers_every_implemented_message(golden, dbs):
    seen = {(g.get("protocol"), g.get("message")) for g in golden}
    for proto, m in implemented_messages(dbs):
        assert (proto, m.name) in seen, f"no golden frame for {proto} {m.name}"


def test_golden_frames_decode_with_cantools(golden, dbs):
    checked = 0
    for g in golden:
        assert "error" not in g, f"Rust rejected its own golden frame: {g}"
        frame_id, data, remote = parse_candump(g["candump"])
        db_msg = dbs[g["protocol"]].get_message_by_frame_id(frame_id)
        assert db_msg.name == g["message"], g
        if remote:  # an RTR request (ODrive Heartbeat, Get_Error, Get_Encoder_Estimates)
            assert g["fields"] == {}
            continue
        assert len(data) == db_msg.length, f"{g['candump']}: DLC {len(data)}, DBC {db_msg.length}"
        decoded = db_msg.decode(data, decode_choices=False, scaling=True)
        where = g["candump"]
        if g["protocol"] == "canopen":
            check_canopen_extras(db_msg, g, decoded, where)
        # Rust's decoded values = cantools' values (up to f32 rounding) ...
        check_decoded(db_msg, g, decoded, lambda s, v: f32_slack(v) + 1e-9, where)
        # ... and = the values given to the encoder, within half an LSB.
        for name, value in g["input"].items():
            signal = db_msg.get_signal_by_name(name)
            assert_value(signal, decoded[name], value, half_lsb(signal) + f32_slack(value), where)
        checked += 1
    assert checked >= 60


def test_golden_inputs_encode_to_the_same_bytes_with_cantools(golden, dbs):
    """The same values through cantools' encoder give Rust's bytes exactly: the same scaling
    and rounding, exact ties included (to even, as Python's round; the golden set has DJI
    currents at k + 1/2 LSB). Saturation is not compared here: the golden inputs are in range
    (cantools refuses an out-of-range value, where Rust saturates it)."""
    checked = ties = 0
    for g in golden:
        frame_id, data, remote = parse_candump(g["candump"])
        if remote:
            continue
        db_msg = dbs[g["protocol"]].get_message_by_frame_id(frame_id)
        # Rust's inputs are f32; JSON carries their shortest decimal form.
        values = {k: f32(v) if isinstance(v, float) else v for k, v in g["input"].items()}
        for signal in db_msg.signals:
            if signal.name in RESERVED:
                values[signal.name] = 0
        # Strict: every golden input is within the DBC's ranges.
        encoded = db_msg.encode(values, scaling=True, strict=True)
        assert encoded == data, (
            f"{g['candump']}: cantools encodes {values} as {encoded.hex().upper()}"
        )
        for name, value in values.items():
            signal = db_msg.get_signal_by_name(name)
            if not signal.is_float and (value / signal.scale) % 1 == 0.5:
                ties += 1
        checked += 1
    assert checked >= 60
    assert ties >= 4, f"only {ties} exact ties in the golden set"


def test_golden_canopen_frames_cover_every_enum_and_sdo_variant(golden):
    """The golden CANopen frames: every NMT command and state, and SDO uploads and downloads of
    1, 2 and 4 bytes and aborts both ways, with the command bytes CiA 301 gives them (the
    encoder always indicates the size) and the unused data bytes zero."""
    canopen = [g for g in golden if g.get("protocol") == "canopen"]
    assert {g["fields"]["command"] for g in canopen if g["message"] == "NMT"} == set(NMT_COMMANDS)
    for node in (*CANOPEN_NODES, CANOPEN_MASTER_NODE):
        assert any(g["message"] == f"HEARTBEAT_{node}" for g in canopen), node
    for node in CANOPEN_NODES:
        states = {g["fields"]["state"] for g in canopen if g["message"] == f"HEARTBEAT_{node}"}
        assert states == set(NMT_STATES), node
    seen = set()
    for g in canopen:
        kind = canopen_kind(g["message"])
        if kind not in SDO_COMMANDS:
            continue
        _, data, _ = parse_candump(g["candump"])
        command = g["fields"]["command"]
        assert data[0] == command, g
        if "size" in g:
            size = g["size"]
            cs = 1 if kind == "SDO_REQUEST" else 2
            assert command == cs << 5 | (4 - size) << 2 | 0b11, g
            assert data[4 + size:] == bytes(4 - size), g
            seen.add((kind, g["node"], f"size {size}"))
        else:
            assert command in (SDO_ABORT, SDO_UPLOAD if kind == "SDO_REQUEST" else SDO_DOWNLOADED), g
            if command != SDO_ABORT:
                assert data[4:] == bytes(4), g
            seen.add((kind, g["node"], hex(command)))
    for node in CANOPEN_NODES:
        for kind, plain in (("SDO_REQUEST", SDO_UPLOAD), ("SDO_RESPONSE", SDO_DOWNLOADED)):
            for variant in ("size 1", "size 2", "size 4", hex(SDO_ABORT), hex(plain)):
                assert (kind, node, variant) in seen, (kind, node, variant)


# ------------------------------------------------------------------------------------------
# (b) frames encoded by cantools, decoded by Rust


def signal_domain(signal, proto: str = "", message: str = ""):
    """(kind, values or bounds) of the physical values Rust accepts for a signal."""
    if proto == "canopen":
        enum = CANOPEN_ENUM_VALUES.get((canopen_kind(message), signal.name))
        if enum is not None:
            return "enum", enum
    elif signal.name in ENUM_VALUES:
        return "enum", ENUM_VALUES[signal.name]
    if signal.name in FLAGS:
        return "enum", FLAGS[signal.name]
    if signal.is_float and (signal.minimum is None or signal.maximum is None):
        return "float", None
    if signal.minimum is not None and signal.maximum is not None and signal.minimum < signal.maximum:
        return "range", (signal.minimum, signal.maximum)
    # ODrive's DBC gives [0|0] (no range): the whole raw type.
    if signal.is_signed:
        lo, hi = -(2 ** (signal.length - 1)), 2 ** (signal.length - 1) - 1
    else:
        lo, hi = 0, 2**signal.length - 1
    return "range", (lo * signal.scale + signal.offset, hi * signal.scale + signal.offset)


def is_integral(signal) -> bool:
    return signal.scale == 1 and signal.offset == 0 and not signal.is_float


def value_sets(msg, rng: random.Random, proto: str = ""):
    """Extremes, zeros and seeded random values for every signal of `msg`."""
    domains = {s.name: (s, *signal_domain(s, proto, msg.name)) for s in msg.signals}

    def pick(mode: str) -> dict:
        values: dict[str, float] = {}
        for name, (s, kind, dom) in domains.items():
            if name in RESERVED:
                values[name] = 0
            elif kind == "enum":
                values[name] = {"min": dom[0], "max": dom[-1]}.get(mode, rng.choice(dom))
            elif kind == "float":
                if mode == "min":
                    values[name] = -3.0e38
                elif mode == "max":
                    values[name] = 3.0e38
                elif mode == "zero":
                    values[name] = 0.0
                else:
                    values[name] = f32(rng.choice([
                        rng.uniform(-1.0, 1.0),
                        rng.uniform(-1e4, 1e4),
                        rng.uniform(-1e-30, 1e-30),
                    ]))
            else:
                lo, hi = dom
                if mode == "min":
                    values[name] = lo
                elif mode == "max":
                    values[name] = hi
                elif mode == "zero":
                    values[name] = min(max(0, lo), hi)
                elif is_integral(s):
                    values[name] = rng.randint(int(lo), int(hi))
                else:
                    values[name] = rng.uniform(lo, hi)
        return values

    sets = [pick("min"), pick("max"), pick("zero")]
    sets += [pick("random") for _ in range(RANDOM_SETS_PER_MESSAGE)]
    return sets


def test_cantools_encoded_frames_decode_in_rust(run_codec, dbs):
    rng = random.Random(SEED)
    cases = []
    for proto, msg in implemented_messages(dbs):
        for values in value_sets(msg, rng, proto):
            data = msg.encode(values, scaling=True, strict=True)
            assert len(data) == msg.length
            cases.append((proto, msg, values, data))
    messages = set()
    # CANopen's ids overlap DJI's and ODrive's: its frames go through `decode --canopen`, and
    # the robot's through both (the robot block is the robot's either way).
    for canopen in (False, True):
        run = [c for c in cases if (c[0] == "canopen") == canopen or c[0] == "robot"]
        lines = [candump(m.frame_id, d, prefix=i % 2 == 0) for i, (_, m, _, d) in enumerate(run)]
        out = run_codec("decode", *(["--canopen"] if canopen else []), lines=lines)
        assert len(out) == len(run)
        for (proto, msg, values, data), rust, line in zip(run, out, lines, strict=True):
            where = f"{line} (--canopen)" if canopen else line
            assert rust.get("protocol") == proto, f"{where}: {rust}"
            decoded = msg.decode(data, decode_choices=False, scaling=True)
            if proto == "canopen":
                check_canopen_extras(msg, rust, values, where)
                decoded, values = canopen_rust_view(msg, decoded), canopen_rust_view(msg, values)
            # Rust = cantools' decoding of the same bytes (up to f32 rounding) ...
            check_decoded(msg, rust, decoded, lambda s, v: f32_slack(v) + 1e-9, where)
            # ... and = the values cantools encoded, within half an LSB.
            check_decoded(msg, rust, values, lambda s, v: half_lsb(s) + f32_slack(v), where)
            messages.add((proto, msg.name, canopen))
    n_robot, n_canopen = 14, 3 + len(CANOPEN_NODES) * len(CANOPEN_MESSAGES)
    assert len(messages) == 2 * n_robot + 10 + 4 * len(ODRIVE_MESSAGES) + n_canopen
    assert len(cases) >= len({m[:2] for m in messages}) * RANDOM_SETS_PER_MESSAGE
    # The SDO value sets hold every command byte Rust accepts, junk beyond an expedited
    # transfer's size included (Rust ignores it, which canopen_rust_view expects).
    for kind, commands in SDO_COMMANDS.items():
        sent = [v for p, m, v, _ in cases if p == "canopen" and canopen_kind(m.name) == kind]
        assert {v["command"] for v in sent} == set(commands), kind
        assert any(sdo_size(v["command"]) < 4 and v["data"] >> 8 * sdo_size(v["command"])
                   for v in sent if v["command"] not in (SDO_UPLOAD, SDO_DOWNLOADED, SDO_ABORT))


def test_dbc_value_tables_match_rust_enums_and_rust_rejects_others(run_codec, dbs):
    """The value tables of the DBC and Rust's enums agree: listed values pass, others fail."""
    robot = dbs["robot"]
    status = robot.get_message_by_name("STATUS")
    table = {int(k): str(v) for k, v in status.get_signal_by_name("fault").choices.items()}
    assert table == {0: "NONE", 1: "MOTOR_STALE", 2: "MOTOR_MISSING", 3: "DRIVE_ERROR",
                     4: "WATCHDOG", 5: "CONFIG", 6: "ENCODER_STUCK", 7: "WHEEL_RUNAWAY", 8: "WHEEL_FIGHT",
                     9: "DRIVE_SILENT", 10: "DRIVE_REBOOTED", 11: "DRIVE_SETUP", 12: "DRIVE_TRANSITION",
                     13: "DRIVE_NMT"}
    request = robot.get_message_by_name("MODE_CMD").get_signal_by_name("request")
    assert set(request.choices) == set(ENUM_VALUES["request"])
    odrive = dbs["odrive"]
    mode = odrive.get_message_by_name("Axis0_Set_Controller_Mode")
    assert set(mode.get_signal_by_name("Control_Mode").choices) == set(ENUM_VALUES["Control_Mode"])
    assert set(mode.get_signal_by_name("Input_Mode").choices) == set(ENUM_VALUES["Input_Mode"])
    state = odrive.get_message_by_name("Axis0_Heartbeat").get_signal_by_name("Axis_State")
    assert set(state.choices) == set(ENUM_VALUES["Axis_State"])
    requested = odrive.get_message_by_name("Axis0_Set_Axis_State").get_signal_by_name("Axis_Requested_State")
    assert set(requested.choices) == set(ENUM_VALUES["Axis_Requested_State"])
    for message in ("STATUS", "HEARTBEAT"):
        robot_state = robot.get_message_by_name(message).get_signal_by_name("state")
        assert set(robot_state.choices) == set(ENUM_VALUES["state"]), message
    out = run_codec("decode", lines=[candump(0x312, bytes([0, 14, 0, 0, 0, 0, 0, 0]))])
    assert out[0]["error"]["kind"] == "out_of_range"


def test_canopen_value_tables_match_rust_enums_and_rust_rejects_others(run_codec, dbs) -> None:
    """NMT.command and HEARTBEAT_n.state: the DBC's tables are Rust's NmtCommand and NmtState,
    and of all 256 raw values Rust accepts exactly the table's (others: out_of_range)."""
    canopen = dbs["canopen"]
    command = canopen.get_message_by_name("NMT").get_signal_by_name("command")
    assert {int(k): str(v) for k, v in command.choices.items()} == NMT_COMMANDS
    for node in (*CANOPEN_NODES, CANOPEN_MASTER_NODE):
        state = canopen.get_message_by_name(f"HEARTBEAT_{node}").get_signal_by_name("state")
        assert {int(k): str(v) for k, v in state.choices.items()} == NMT_STATES, node
    # Every raw value, node 2 (NMT) and node 1 (heartbeat).
    cases = [("NMT", "command", raw, candump(0x000, bytes([raw, 2]))) for raw in range(256)]
    cases += [("HEARTBEAT_1", "state", raw, candump(0x701, bytes([raw]))) for raw in range(256)]
    out = run_codec("decode", "--canopen", lines=[line for *_, line in cases])
    accepted: dict[str, set[int]] = {"NMT": set(), "HEARTBEAT_1": set()}
    for (message, field, raw, line), rust in zip(cases, out, strict=True):
        if "error" in rust:
            assert rust["error"]["kind"] == "out_of_range", f"{line}: {rust}"
            assert (rust["error"]["field"], rust["error"]["value"]) == (field, raw), f"{line}: {rust}"
        else:
            assert rust["message"] == message and rust["fields"][field] == raw, f"{line}: {rust}"
            accepted[message].add(raw)
    assert accepted == {"NMT": set(NMT_COMMANDS), "HEARTBEAT_1": set(NMT_STATES)}


def test_canopen_sdo_command_bytes_are_the_expedited_transfers(run_codec, dbs) -> None:
    """All 256 SDO command bytes, both directions: Rust accepts the expedited initiate transfers
    (with their data size), the upload request (requests) or download response (responses) and
    the abort, and rejects every other byte (segmented 0x21/0x41, block transfers, a byte of
    the other direction, reserved bits) as out_of_range on `command`."""
    cases = []
    for kind, code in (("SDO_REQUEST", 0x600), ("SDO_RESPONSE", 0x580)):
        msg = dbs["canopen"].get_message_by_frame_id(code + 2)
        for command in range(256):
            values = {"command": command, "index": 0x60FF, "subindex": 2, "data": 0x8D7C6B5A}
            cases.append((kind, msg, values, msg.encode(values, strict=True)))
    lines = [candump(m.frame_id, data) for _, m, _, data in cases]
    out = run_codec("decode", "--canopen", lines=lines)
    accepted: dict[str, set[int]] = {kind: set() for kind in SDO_COMMANDS}
    for (kind, msg, values, _), rust, line in zip(cases, out, lines, strict=True):
        if values["command"] in SDO_COMMANDS[kind]:
            check_canopen_extras(msg, rust, values, line)
            check_decoded(msg, rust, canopen_rust_view(msg, values), lambda s, v: 0, line)
            accepted[kind].add(values["command"])
        else:
            err = rust.get("error", {})
            assert (err.get("kind"), err.get("field"), err.get("value")) == (
                "out_of_range", "command", values["command"]), f"{line}: {rust}"
    assert accepted == {kind: set(commands) for kind, commands in SDO_COMMANDS.items()}
    assert all(len(commands) == 10 for commands in accepted.values())
    assert 0x21 not in accepted["SDO_REQUEST"] and 0x41 not in accepted["SDO_RESPONSE"]
