"""Malformed frames through `mecanum-codec`: the Rust codecs reject each with the right error
kind, field and values, and the DBC files agree they are malformed (part (c) of the
cross-check in tests/test_dbc_codec.py). Also the input forms `decode` accepts (candump log,
bare lines) and the tool's help.
"""

from __future__ import annotations

import math
import struct
import subprocess
from collections.abc import Callable

from codec_frames import SDO_ABORT, SDO_COMMANDS, SDO_DOWNLOADED, SDO_UPLOAD, canopen_kind, parse_candump


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
    ("307#", "unknown_id", {}),
    ("30F#0000000000000000", "unknown_id", {}),
    ("316#0000000000000000", "unknown_id", {}),
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
    ("312#000E000000000000", "out_of_range", {"field": "fault", "value": 14}),
    ("305#0400000100000000", "out_of_range", {"field": "wheel", "value": 4}),
    ("305#0011270100000000", "out_of_range", {"field": "speed", "value": 10001}),
    ("305#0010270000000000", "out_of_range", {"field": "duration_ms", "value": 0}),
    ("314#0004000000000000", "out_of_range", {"field": "outcome", "value": 4}),
    ("312#0000000000003F00", "out_of_range", {"field": "heading_source", "value": 3}),
    ("312#000000000000F000", "out_of_range", {"field": "heading_source", "value": 15}),
    ("315#0000000000000400", "out_of_range", {"field": "source", "value": 4}),
    ("315#0000000000000F00", "out_of_range", {"field": "source", "value": 15}),
    ("315#0080000000000000", "out_of_range", {"field": "vx", "value": -32768}),
    ("306#00000000000000", "wrong_dlc", {"expected": 8, "got": 7}),
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


def assert_rejected(out: list[dict], table: list[tuple[str, str | None, dict]], good: str,
                    dbc_length: Callable[[int], int]) -> None:
    """`out` decoded each line of `table`, each followed by a valid frame (`interleaved`): every
    bad line is rejected with its kind (None: a parse error) and extra fields, a wrong DLC
    expects the DBC's length (`dbc_length(frame_id)`), and the valid frame after it decodes
    as `good` (a rejected line must not stop the stream)."""
    for i, (line, kind, extra) in enumerate(table):
        rust, after = out[2 * i], out[2 * i + 1]
        assert after.get("message") == good, f"line after {line}: {after}"
        assert "error" in rust, f"{line}: accepted as {rust}"
        err = rust["error"]
        assert err["kind"] == (kind or "parse"), f"{line}: {err}"
        for key, want in extra.items():
            assert err.get(key) == want, f"{line}: {key} = {err.get(key)!r}, want {want!r}"
        if kind == "wrong_dlc":
            frame_id, _, _ = parse_candump(line)
            assert dbc_length(frame_id) == err["expected"], line


def interleaved(table: list[tuple[str, str | None, dict]], good: str) -> list[str]:
    """The lines of `table`, each followed by the valid frame `good`."""
    return [line for bad, _, _ in table for line in (bad, good)]


def test_malformed_frames_are_rejected_with_the_right_kind(run_codec, dbs):
    lines = interleaved(MALFORMED, "301#F40106FFE8030700") + ["hello", "123#ABC", "123##0011",
                                                              "301#F40106FFE8030700"]
    out = run_codec("decode", lines=lines)
    assert len(out) == len(lines)

    def dbc_length(frame_id: int) -> int:
        proto = next(p for p, db in dbs.items() if _has_id(db, frame_id))
        return dbs[proto].get_message_by_frame_id(frame_id).length

    assert_rejected(out, MALFORMED, "TWIST_CMD", dbc_length)
    assert [o["error"]["kind"] for o in out[-4:-1]] == ["parse"] * 3
    assert out[-1]["fields"]["vx"] == 0.5


# Through `decode --canopen`: (candump line, error kind, extra fields the error must carry).
CANOPEN_MALFORMED = [
    # wrong DLC (expected = the DBC length, checked below)
    ("000#01", "wrong_dlc", {"expected": 2, "got": 1}),
    ("000#010100", "wrong_dlc", {"expected": 2, "got": 3}),
    ("080#0000", "wrong_dlc", {"expected": 0, "got": 2}),
    ("081#00000000", "wrong_dlc", {"expected": 8, "got": 4}),
    ("181#3706FEFFFFFF00", "wrong_dlc", {"expected": 6, "got": 7}),
    ("182#3706FEFF", "wrong_dlc", {"expected": 6, "got": 4}),
    ("281#FEFFFFFF00", "wrong_dlc", {"expected": 4, "got": 5}),
    ("201#0F00", "wrong_dlc", {"expected": 6, "got": 2}),
    ("202#0F00D007000000000", None, {}),  # odd number of hex digits: parse error
    ("401#D00700", "wrong_dlc", {"expected": 4, "got": 3}),
    ("581#43001000920102", "wrong_dlc", {"expected": 8, "got": 7}),
    ("602#40001000", "wrong_dlc", {"expected": 8, "got": 4}),
    ("701#", "wrong_dlc", {"expected": 1, "got": 0}),
    ("702#0500", "wrong_dlc", {"expected": 1, "got": 2}),
    # unknown ids: function codes not used (TIME, RPDO2, TPDO3/4, RPDO4, LSS, 0x780+), node 0
    ("100#000000000000", "unknown_id", {}),
    ("341#0F00D0070000", "unknown_id", {}),  # RPDO2 of node 0x41 (0x301-0x31F: robot's)
    ("37F#0F00D0070000", "unknown_id", {}),
    ("381#3706FEFFFFFF", "unknown_id", {}),
    ("481#3706FEFFFFFF", "unknown_id", {}),
    ("501#0F00D0070000", "unknown_id", {}),
    ("7E5#0400000000000000", "unknown_id", {}),
    ("7E4#0400000000000000", "unknown_id", {}),
    ("181#R", "remote", {}),  # a remote frame is checked before the node: RTR on a PDO id
    ("180#3706FEFFFFFF", "unknown_id", {}),
    ("580#4300100092010200", "unknown_id", {}),
    ("700#05", "unknown_id", {}),
    # extended ids, remote frames (node guarding's RTR on the heartbeat id is not used)
    ("00000181#3706FEFFFFFF", "extended_id", {}),
    ("00000000#0100", "extended_id", {}),
    ("701#R1", "remote", {}),
    ("601#R8", "remote", {}),
    ("000#R2", "remote", {}),
    # out-of-range values: unknown NMT commands and states, SYNC counters, segmented and block
    # SDO transfers, bytes of the other direction
    ("000#0300", "out_of_range", {"field": "command", "value": 3}),
    ("000#8300", "out_of_range", {"field": "command", "value": 0x83}),
    ("000#0180", "out_of_range", {"field": "node", "value": 128}),
    ("080#00", "out_of_range", {"field": "counter", "value": 0}),
    ("080#F1", "out_of_range", {"field": "counter", "value": 241}),
    ("701#06", "out_of_range", {"field": "state", "value": 6}),
    ("701#85", "out_of_range", {"field": "state", "value": 0x85}),  # node guarding toggle bit
    ("702#FF", "out_of_range", {"field": "state", "value": 0xFF}),
    ("581#4100100014000000", "out_of_range", {"field": "command", "value": 0x41}),  # segmented
    ("601#2100100014000000", "out_of_range", {"field": "command", "value": 0x21}),  # segmented
    ("602#C600100000000000", "out_of_range", {"field": "command", "value": 0xC6}),  # block
    ("582#A400100000000000", "out_of_range", {"field": "command", "value": 0xA4}),  # block
    ("601#6000100000000000", "out_of_range", {"field": "command", "value": 0x60}),
    ("581#2300100003000000", "out_of_range", {"field": "command", "value": 0x23}),
    ("581#4000100000000000", "out_of_range", {"field": "command", "value": 0x40}),
    ("601#3300100000000000", "out_of_range", {"field": "command", "value": 0x33}),  # bit 4
    ("601#0000100000000000", "out_of_range", {"field": "command", "value": 0x00}),
]


def test_malformed_canopen_frames_are_rejected_with_the_right_kind(run_codec, dbs):
    lines = interleaved(CANOPEN_MALFORMED, "181#3706FEFFFFFF")
    out = run_codec("decode", "--canopen", lines=lines)
    assert len(out) == len(lines)
    assert_rejected(out, CANOPEN_MALFORMED, "TPDO1_1",
                    lambda frame_id: dbs["canopen"].get_message_by_frame_id(frame_id).length)
    for after in out[1::2]:
        assert after["fields"] == {"statusword": 0x0637, "velocity_actual": -2}, after


def test_malformed_canopen_frames_are_malformed_for_the_dbc_too(dbs):
    """Sanity check of the table: the DBC's value tables do not have those values either, and
    its SDO comments name the command bytes the firmware accepts."""
    canopen = dbs["canopen"]
    nmt = canopen.get_message_by_name("NMT")
    raw = nmt.decode(bytes.fromhex("0300"), decode_choices=False)
    assert raw["command"] not in nmt.get_signal_by_name("command").choices
    assert nmt.decode(bytes.fromhex("0180"))["node"] > nmt.get_signal_by_name("node").maximum
    heartbeat = canopen.get_message_by_name("HEARTBEAT_1")
    assert 0x85 not in heartbeat.get_signal_by_name("state").choices
    for name in ("SDO_REQUEST_1", "SDO_RESPONSE_1"):
        comment = canopen.get_message_by_name(name).comment or ""
        for command in SDO_COMMANDS[canopen_kind(name)]:
            if command & 1 or command in (0x22, 0x42, SDO_UPLOAD, SDO_DOWNLOADED, SDO_ABORT):
                assert f"0x{command:02X}" in comment, (name, hex(command))
    assert "0x41" in canopen.get_message_by_name("SDO_RESPONSE_1").comment


def test_canopen_routing_leaves_the_robot_block_to_the_robot(run_codec):
    """`--canopen` routes every id outside 0x300-0x31F to CANopen. RPDO2's predefined ids
    (0x300 + node) start in the robot block: there a frame is the robot's with or without the
    flag (an RPDO-shaped frame is a robot frame of the wrong length, never a PDO), and beyond
    it no protocol has them. The ids CANopen shares with DJI and ODrive switch with the flag."""
    lines = [
        "301#F40106FFE8030700",  # TWIST_CMD, on RPDO2's id for node 1
        "301#0F00D0070000",  # RPDO2 of node 1 as RPDO1 is mapped: controlword, target
        "31F#0F00D0070000",  # RPDO2 of node 0x1F: the robot's HEARTBEAT id
        "341#0F00D0070000",  # RPDO2 of node 0x41, beyond the robot block
        "201#0F00D0070000",  # RPDO1 of node 1: DJI FEEDBACK_1's id
        "201#1FFF03E8FC182500",  # DJI FEEDBACK_1
        "000#0100",  # NMT start, all nodes: ODrive Axis0_Get_Version's id (not implemented)
        "001#0000000008000000",  # ODrive Axis0_Heartbeat
    ]
    plain = run_codec("decode", lines=lines)
    canopen = run_codec("decode", "--canopen", lines=lines)
    assert plain[0] == canopen[0] and canopen[0]["message"] == "TWIST_CMD"
    for i in (1, 2):
        assert plain[i] == canopen[i], lines[i]
        assert canopen[i]["error"]["kind"] == "wrong_dlc" and canopen[i]["error"]["expected"] == 8
    assert plain[3]["error"]["kind"] == canopen[3]["error"]["kind"] == "unknown_id"
    # DJI (feedback is DLC 8) without the flag, CANopen RPDO1 (DLC 6) with it.
    assert plain[4]["error"]["kind"] == "wrong_dlc" and plain[4]["error"]["expected"] == 8
    assert canopen[4] == {"id": 0x201, "protocol": "canopen", "message": "RPDO1_1", "node": 1,
                          "fields": {"controlword": 0x0F, "target_velocity": 2000}}
    assert plain[5]["message"] == "FEEDBACK_1" and plain[5]["protocol"] == "dji"
    assert canopen[5]["error"] == {"kind": "wrong_dlc", "message": canopen[5]["error"]["message"],
                                   "expected": 6, "got": 8}
    assert plain[6]["error"]["kind"] == "unknown_id"
    assert canopen[6] == {"id": 0, "protocol": "canopen", "message": "NMT",
                          "fields": {"command": 1, "node": 0}}
    assert plain[7]["message"] == "Axis0_Heartbeat"
    assert "error" in canopen[7], canopen[7]  # no CANopen frame has that id and length


def test_canopen_ids_between_nmt_and_sync_are_unknown(run_codec):
    out = run_codec("decode", "--canopen", lines=["001#0500", "07F#7F00", "001#05"])
    assert [o.get("error", {}).get("kind") for o in out] == ["unknown_id"] * 3, out


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
    out = subprocess.run([str(codec_bin), "--help"], capture_output=True, text=True, check=True)
    assert "decode" in out.stdout and "golden" in out.stdout and "candump" in out.stdout
    assert "--canopen" in out.stdout and "cia402.dbc" in out.stdout
    bad = subprocess.run([str(codec_bin), "frobnicate"], capture_output=True, text=True)
    assert bad.returncode == 2
