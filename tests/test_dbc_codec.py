"""Cross-check of the firmware's Rust codecs against the DBC files, through `mecanum-codec`.

(a) Every golden frame the Rust encoders produce decodes with cantools, from the DBC, to the
    values Rust reports (and to the values given to the encoder, within half an LSB).
(b) Frames encoded by cantools from the DBC, for many value sets (extremes, zeros, seeded
    random values) of every message, decode in Rust to the same values.
(c) Malformed frames are rejected by Rust with the right error kind, field and values.

Field names are the DBC signal names; values are physical (scaled) values.
"""

from __future__ import annotations

import math
import pathlib
import random
import re
import struct

import pytest

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
    "fault": list(range(13)),
    "wheel": [0, 1, 2, 3],
    "outcome": [0, 1, 2, 3],
    "heading_source": [0, 1, 2],
    "Axis_State": list(range(15)),
    "Axis_Requested_State": list(range(15)),
    "Control_Mode": [0, 1, 2, 3],
    "Input_Mode": list(range(9)),
}

# Signals Rust reads as a flag (nonzero = true, as ODrive does): generated as 0 or 1 only.
FLAGS = {"Identify": [0, 1]}

SEED = 0x3EC4  # fixed: the random value sets are the same on every run
RANDOM_SETS_PER_MESSAGE = 40


# ------------------------------------------------------------------------------------------
# helpers


def parse_candump(text: str) -> tuple[int, bytes, bool]:
    """`123#DEADBEEF` / `123#R8` -> (id, data, remote)."""
    ident, _, data = text.partition("#")
    if data.startswith("R"):
        return int(ident, 16), b"", True
    return int(ident, 16), bytes.fromhex(data), False


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
    return out


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
        "ESTOP", "TWIST_CMD", "MODE_CMD", "STATUS_REQ", "IMU_YAW_RATE", "WHEEL_TEST",
        "WHEEL_TEST_RESULT", "ODOM_POSITION", "ODOM_VELOCITY", "STATUS", "STATUS_COUNTERS", "HEARTBEAT",
    }
    assert all(0x300 <= m.frame_id <= 0x31F for m in dbs["robot"].messages)
    assert sorted(m.frame_id for m in dbs["dji"].messages) == [0x1FF, *range(0x200, 0x209)]
    assert all(m.frame_id < 0x80 for m in dbs["odrive"].messages)
    for db in dbs.values():
        assert all(not m.is_extended_frame for m in db.messages)


def test_robot_dbc_is_little_endian_and_dji_big_endian(dbs):
    for m in dbs["robot"].messages:
        assert all(s.byte_order == "little_endian" for s in m.signals), m.name
    for m in dbs["dji"].messages:
        multi_byte = [s for s in m.signals if s.length > 8]
        assert multi_byte and all(s.byte_order == "big_endian" for s in multi_byte), m.name


# ------------------------------------------------------------------------------------------
# (a) golden frames from the Rust encoders


@pytest.fixture(scope="module")
def golden(run_codec):
    lines = run_codec("golden")
    assert len(lines) >= 60
    return lines


ROBOT_DBC = pathlib.Path(__file__).resolve().parent.parent / "dbc" / "mecanum_robot.dbc"


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
    assert version == 6
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


# ------------------------------------------------------------------------------------------
# (b) frames encoded by cantools, decoded by Rust


def signal_domain(signal):
    """(kind, values or bounds) of the physical values Rust accepts for a signal."""
    if signal.name in ENUM_VALUES:
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


def value_sets(msg, rng: random.Random):
    """Extremes, zeros and seeded random values for every signal of `msg`."""
    domains = {s.name: (s, *signal_domain(s)) for s in msg.signals}

    def pick(mode: str) -> dict:
        values = {}
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
        for values in value_sets(msg, rng):
            data = msg.encode(values, scaling=True, strict=True)
            assert len(data) == msg.length
            cases.append((proto, msg, values, data))
    lines = [candump(m.frame_id, d, prefix=i % 2 == 0) for i, (_, m, _, d) in enumerate(cases)]
    out = run_codec("decode", lines=lines)
    assert len(out) == len(cases)
    messages = set()
    for (proto, msg, values, data), rust, line in zip(cases, out, lines, strict=True):
        where = line
        assert rust.get("protocol") == proto, f"{where}: {rust}"
        decoded = msg.decode(data, decode_choices=False, scaling=True)
        # Rust = cantools' decoding of the same bytes (up to f32 rounding) ...
        check_decoded(msg, rust, decoded, lambda s, v: f32_slack(v) + 1e-9, where)
        # ... and = the values cantools encoded, within half an LSB.
        check_decoded(msg, rust, values, lambda s, v: half_lsb(s) + f32_slack(v), where)
        messages.add(msg.name)
    assert len(messages) == 12 + 10 + 4 * len(ODRIVE_MESSAGES)
    assert len(cases) >= len(messages) * RANDOM_SETS_PER_MESSAGE


def test_dbc_value_tables_match_rust_enums_and_rust_rejects_others(run_codec, dbs):
    """The value tables of the DBC and Rust's enums agree: listed values pass, others fail."""
    robot = dbs["robot"]
    status = robot.get_message_by_name("STATUS")
    table = {int(k): str(v) for k, v in status.get_signal_by_name("fault").choices.items()}
    assert table == {0: "NONE", 1: "MOTOR_STALE", 2: "MOTOR_MISSING", 3: "DRIVE_ERROR",
                     4: "WATCHDOG", 5: "CONFIG", 6: "ENCODER_STUCK", 7: "WHEEL_RUNAWAY", 8: "WHEEL_FIGHT",
                     9: "DRIVE_SILENT", 10: "DRIVE_REBOOTED", 11: "DRIVE_SETUP", 12: "DRIVE_TRANSITION"}
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
    out = run_codec("decode", lines=[candump(0x312, bytes([0, 13, 0, 0, 0, 0, 0, 0]))])
    assert out[0]["error"]["kind"] == "out_of_range"


# ------------------------------------------------------------------------------------------
# (c) malformed frames

NAN = struct.pack("<f", float("nan"))
INF = struct.pack("<f", float("inf"))
ONE = struct.pack("<f", 1.0)

# (candump line, error kind, extra fields the error must carry)
MALFORMED = [
    # wrong DLC (expected = the DBC length, checked below)
    ("301#F40106FFE80307", "wrong_dlc", {"expected": 8, "got": 7}),
    ("300#", "wrong_dlc", {"expected": 1, "got": 0}),
    ("303#00", "wrong_dlc", {"expected": 0, "got": 1}),
    ("312#00000000000000", "wrong_dlc", {"expected": 8, "got": 7}),
    ("313#000000000000", "wrong_dlc", {"expected": 8, "got": 6}),
    ("304#0000003F070000", "wrong_dlc", {"expected": 8, "got": 7}),
    ("304#", "wrong_dlc", {"expected": 8, "got": 0}),
    ("201#1FFF03E8FC1825", "wrong_dlc", {"expected": 8, "got": 7}),
    ("200#0000", "wrong_dlc", {"expected": 8, "got": 2}),
    ("00D#" + ONE.hex(), "wrong_dlc", {"expected": 8, "got": 4}),
    ("007#08000000", "wrong_dlc", {"expected": 8, "got": 4}),
    ("021#0000000008000100FF", None, {}),  # 9 bytes: not a classic frame -> parse error
    ("038#0000", "wrong_dlc", {"expected": 1, "got": 2}),
    # unknown ids
    ("123#00", "unknown_id", {}),
    ("306#", "unknown_id", {}),
    ("30F#0000000000000000", "unknown_id", {}),
    ("315#0000000000000000", "unknown_id", {}),
    ("31E#0000000000000000", "unknown_id", {}),
    ("320#00", "unknown_id", {}),
    ("209#0000000000000000", "unknown_id", {}),
    ("0A1#0000000008000000", "unknown_id", {}),  # ODrive node 5: outside the DBC's nodes
    ("000#0000000000000000", "unknown_id", {}),  # Get_Version: not implemented
    ("00C#0000000000000000", "unknown_id", {}),  # Set_Input_Pos: not implemented
    # extended ids, remote frames where data is expected
    ("00000301#F40106FFE8030700", "extended_id", {}),
    ("00000304#0000003F07000000", "extended_id", {}),
    ("304#R8", "remote", {}),
    ("301#R8", "remote", {}),
    ("02D#R8", "remote", {}),  # Set_Input_Vel carries data: not a request
    # non-finite floats
    ("00D#" + (NAN + ONE).hex(), "non_finite",
     {"field": "Input_Vel", "value": "NaN", "bits": f"{struct.unpack('<I', NAN)[0]:#010x}"}),
    ("02D#" + (ONE + INF).hex(), "non_finite",
     {"field": "Input_Torque_FF", "value": "inf", "bits": "0x7f800000"}),
    ("069#" + (NAN + NAN).hex(), "non_finite", {"field": "Pos_Estimate", "value": "NaN"}),
    ("304#" + NAN.hex() + "01000000", "non_finite",
     {"field": "yaw_rate", "value": "NaN", "bits": f"{struct.unpack('<I', NAN)[0]:#010x}"}),
    ("304#" + INF.hex() + "02000000", "non_finite", {"field": "yaw_rate", "value": "inf", "bits": "0x7f800000"}),
    ("304#" + struct.pack("<f", float("-inf")).hex() + "03000000", "non_finite",
     {"field": "yaw_rate", "value": "-inf", "bits": "0xff800000"}),
    ("049#" + (ONE + struct.pack("<f", float("-inf"))).hex(), "non_finite",
     {"field": "Vel_Estimate", "value": "-inf", "bits": "0xff800000"}),
    # out-of-range values
    ("301#0080000000000000", "out_of_range", {"field": "vx", "value": -32768}),
    ("301#0000008000000000", "out_of_range", {"field": "vy", "value": -32768}),
    ("301#0000000000800000", "out_of_range", {"field": "wz", "value": -32768}),
    ("311#0000000000800000", "out_of_range", {"field": "vy", "value": -32768}),
    ("311#B97A000000000000", "out_of_range", {"field": "heading", "value": 31417}),
    ("203#2000000000000000", "out_of_range", {"field": "rotor_angle", "value": 8192}),
    ("208#FFFF000000000000", "out_of_range", {"field": "rotor_angle", "value": 65535}),
    ("204#0000000040010000", "out_of_range", {"field": "torque_current", "value": 16385}),
    ("200#4001000000000000", "out_of_range", {"field": "current_1", "value": 16385}),
    ("1FF#000000000000BFFF", "out_of_range", {"field": "current_8", "value": -16385}),
    ("300#E4", "out_of_range", {"field": "magic", "value": 0xE4}),
    ("302#03", "out_of_range", {"field": "request", "value": 3}),
    ("312#0500000000000000", "out_of_range", {"field": "state", "value": 5}),
    ("312#000D000000000000", "out_of_range", {"field": "fault", "value": 13}),
    ("305#0400000100000000", "out_of_range", {"field": "wheel", "value": 4}),
    ("305#0011270100000000", "out_of_range", {"field": "speed", "value": 10001}),
    ("305#0010270000000000", "out_of_range", {"field": "duration_ms", "value": 0}),
    ("314#0004000000000000", "out_of_range", {"field": "outcome", "value": 4}),
    ("312#0000000000003F00", "out_of_range", {"field": "heading_source", "value": 3}),
    ("312#000000000000F000", "out_of_range", {"field": "heading_source", "value": 15}),
    # beyond +-35 rad/s (the raw value of a float field is its bits)
    ("304#" + struct.pack("<f", 35.5).hex() + "00000000", "out_of_range",
     {"field": "yaw_rate", "value": struct.unpack("<I", struct.pack("<f", 35.5))[0]}),
    ("304#" + struct.pack("<f", -1e30).hex() + "00000000", "out_of_range",
     {"field": "yaw_rate", "value": struct.unpack("<I", struct.pack("<f", -1e30))[0]}),
    ("31F#0000000005010000", "out_of_range", {"field": "state", "value": 5}),
    ("001#000000000F000000", "out_of_range", {"field": "Axis_State", "value": 15}),
    ("027#0F00000000000000", "out_of_range", {"field": "Axis_Requested_State", "value": 15}),
    ("04B#0400000001000000", "out_of_range", {"field": "Control_Mode", "value": 4}),
    ("06B#0200000009000000", "out_of_range", {"field": "Input_Mode", "value": 9}),
]


def test_malformed_frames_are_rejected_with_the_right_kind(run_codec, dbs):
    good = "301#F40106FFE8030700"
    # Interleave a valid frame after every bad one: a rejected line must not stop the stream.
    lines = []
    for line, _, _ in MALFORMED:
        lines += [line, good]
    lines += ["hello", "123#ABC", "123##0011", good]
    out = run_codec("decode", lines=lines)
    assert len(out) == len(lines)
    for i, (line, kind, extra) in enumerate(MALFORMED):
        rust, after = out[2 * i], out[2 * i + 1]
        assert after.get("message") == "TWIST_CMD", f"line after {line}: {after}"
        assert "error" in rust, f"{line}: accepted as {rust}"
        err = rust["error"]
        assert err["kind"] == (kind or "parse"), f"{line}: {err}"
        for key, want in extra.items():
            assert err.get(key) == want, f"{line}: {key} = {err.get(key)!r}, want {want!r}"
        if kind == "wrong_dlc":
            frame_id, data, _ = parse_candump(line)
            proto = next(p for p, db in dbs.items() if _has_id(db, frame_id))
            assert dbs[proto].get_message_by_frame_id(frame_id).length == err["expected"], line
    assert [o["error"]["kind"] for o in out[-4:-1]] == ["parse"] * 3
    assert out[-1]["fields"]["vx"] == 0.5


def _has_id(db, frame_id: int) -> bool:
    try:
        db.get_message_by_frame_id(frame_id)
    except KeyError:
        return False
    return True


def test_malformed_frames_are_malformed_for_the_dbc_too(dbs):
    """Sanity check of the table itself: the DBC agrees these frames are bad."""
    robot, dji = dbs["robot"], dbs["dji"]
    twist = robot.get_message_by_name("TWIST_CMD")
    raw = twist.decode(bytes.fromhex("0080000000000000"), scaling=False)
    assert raw["vx"] == -32768 and twist.get_signal_by_name("vx").minimum == -32.767
    fb = dji.get_message_by_name("FEEDBACK_3")
    raw = fb.decode(bytes.fromhex("2000000000000000"), scaling=False)
    assert raw["rotor_angle"] == 8192 > fb.get_signal_by_name("rotor_angle").maximum
    vel = dbs["odrive"].get_message_by_name("Axis0_Set_Input_Vel")
    assert math.isnan(vel.decode(NAN + ONE)["Input_Vel"])
    imu = robot.get_message_by_name("IMU_YAW_RATE")
    rate = imu.get_signal_by_name("yaw_rate")
    assert imu.decode(struct.pack("<f", 35.5) + bytes(4))["yaw_rate"] > rate.maximum
    assert math.isnan(imu.decode(NAN + bytes(4))["yaw_rate"])
    status = robot.get_message_by_name("STATUS")
    assert status.decode(bytes.fromhex("0000000000003F00"), decode_choices=False)["heading_source"] == 3


def test_decode_accepts_candump_log_and_bare_lines(run_codec):
    out = run_codec(
        "decode",
        lines=[
            "(1700000000.123456) vcan0 301#F40106FFE8030700",
            "301#F4.01.06.FF.E8.03.07.00",
            "  vcan0  303#  ",
            "",
            "023#R8",
            "018#FF",
            "018#",
            "029#R8",
            "021#R",
            "023#",
        ],
    )
    assert [o["message"] for o in out] == [
        "TWIST_CMD", "TWIST_CMD", "STATUS_REQ", "Axis1_Get_Error", "Axis0_Clear_Errors",
        "Axis0_Clear_Errors", "Axis1_Get_Encoder_Estimates", "Axis1_Heartbeat", "Axis1_Get_Error",
    ]
    assert out[0]["fields"] == {"vx": 0.5, "vy": -0.25, "wz": 1.0, "seq": 7}
    # Requests, as the ODrive docs allow them: a remote frame of any DLC, or no data.
    for o in out[3:4] + out[6:]:
        assert o["node"] == 1 and o["request"] == 1 and o["fields"] == {}, o
    # Clear_Errors: Identify is a flag; DLC 0 (ODrive 0.5's form) is accepted as "no identify".
    assert out[4]["fields"] == {"Identify": 1}
    assert out[5]["fields"] == {"Identify": 0}


def test_help_explains_the_tool(codec_bin):
    import subprocess

    out = subprocess.run([str(codec_bin), "--help"], capture_output=True, text=True, check=True)
    assert "decode" in out.stdout and "golden" in out.stdout and "candump" in out.stdout
    bad = subprocess.run([str(codec_bin), "frobnicate"], capture_output=True, text=True)
    assert bad.returncode == 2
