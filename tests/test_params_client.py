"""The package's parameter client (`mecanum_drive.params`, `mecanum-drive param`) against
python-canopen's SDO server built from the robot's EDS, on python-can's virtual bus: the
table it reads, reads and writes of each type, and a refusal named; save, restore and the
configurations' ids (0x1010, 0x1011, 0x2100) against a double of what the robot does with
them; `param dump`'s TOML. (Against the robot itself: the core's tests in
crates/firmware/tests/control/params.rs.)"""

from __future__ import annotations

import json
import math
import struct
import time
import tomllib

import can
import canopen
import pytest
from canopen.sdo import SdoAbortedError

from mecanum_drive import cli, params


@pytest.fixture
def server():
    """A CANopen node 127 serving the robot's object dictionary, with the DJI example's
    values of the parameters the tests read; and a client on the same virtual bus."""
    network = canopen.Network()
    network.NOTIFIER_CYCLE = 0.05  # its thread's wait: the teardown's, 1 s by default
    network.connect(interface="virtual", channel="params-test", receive_own_messages=False)
    node = canopen.LocalNode(127, str(params.eds_path()))
    network.add_node(node)
    for name, value in [("gains.kp", 1.2), ("timing.command_timeout_ms", 100),
                        ("odometry.gyro_bias_estimation", 1), ("drive.protocol", 0)]:
        p = params.table()[name]
        node.sdo[p.index][p.sub].raw = value
    bus = can.Bus(interface="virtual", channel="params-test")
    try:
        yield node, params.Client(bus, node=127, timeout=2.0)
    finally:
        bus.shutdown()
        network.disconnect()


def test_the_table_is_the_eds() -> None:
    table = params.table()
    assert len(table) == 73
    kp = table["gains.kp"]
    assert (kp.index, kp.sub, kp.data_type, kp.low, kp.high, kp.change) == (0x2002, 1, 0x0008, 0, 100, "live")
    assert table["limits.stop_linear_decel"].high == math.inf
    assert table["drive.protocol"].change == "fixed"


def test_reads_and_writes_of_each_type(server) -> None:
    node, client = server
    t = params.table()
    assert client.get(t["gains.kp"]) == pytest.approx(1.2)
    client.set(t["gains.kp"], 1.5)
    assert node.sdo["gains"]["gains.kp"].raw == pytest.approx(1.5)
    assert client.get(t["gains.kp"]) == pytest.approx(1.5)
    client.set(t["timing.command_timeout_ms"], 250)
    assert node.sdo[0x2003][5].raw == 250
    assert client.get(t["odometry.gyro_bias_estimation"]) == 1
    client.set(t["odometry.gyro_bias_estimation"], 0)
    assert node.sdo[0x2004][4].raw == 0


def test_a_refusal_names_the_parameter_and_the_reason(server) -> None:
    _, client = server
    t = params.table()
    with pytest.raises(params.ParamError, match=r"drive.protocol: read-only over CAN \(SDO abort 0x06010002\)"):
        client.set(t["drive.protocol"], 1)
    for bad in (1.5, math.nan, -1.0):
        with pytest.raises(ValueError, match=f"timing.command_timeout_ms: {bad} is not a whole number"):
            client.set(t["timing.command_timeout_ms"], bad)
    silent = params.Client(client.bus, node=5, timeout=0.2)
    with pytest.raises(params.ParamError, match="gains.kp: no answer from node 5 within 0.2 s"):
        silent.get(t["gains.kp"])


#: The double's configurations' ids: the one in force at the start, and the built-in one.
RUNNING, BUILTIN = 0x1A2B, 0x3C4D


class RobotDouble:
    """What the robot does with 0x1010:01 (save), 0x1011:01 (restore) and 0x2100 (ids), on
    the LocalNode through its write callback: the right signature is obeyed, anything else
    refused with the robot's abort codes (python-canopen's server answers a callback's
    SdoAbortedError with that abort)."""

    def __init__(self, node: canopen.LocalNode) -> None:
        self.node = node
        self.writes: list[tuple[int, int, bytes]] = []
        self.enabled = False  # a restore is refused while enabled
        self.refusal: int | None = None  # an abort for the right signature (flash full, busy, ...)
        self.delay = 0.0  # seconds before the answer, as a store takes
        self.running, self.saved, self.seq = RUNNING, BUILTIN, 0
        node.add_write_callback(self.on_write)
        self.publish()

    def publish(self) -> None:
        for sub, value in enumerate((self.running, BUILTIN, self.saved, self.seq), start=1):
            self.node.sdo[params.INFO_INDEX][sub].raw = value

    def on_write(self, index: int, subindex: int, od: object, data: bytes) -> None:
        if index not in (params.STORE_INDEX, params.RESTORE_INDEX):
            return
        self.writes.append((index, subindex, bytes(data)))
        time.sleep(self.delay)
        signature = b"save" if index == params.STORE_INDEX else b"load"
        if subindex != 1 or bytes(data) != signature:
            raise SdoAbortedError(0x0800_0020)
        if self.refusal is not None:
            raise SdoAbortedError(self.refusal)
        if index == params.RESTORE_INDEX:
            if self.enabled:
                raise SdoAbortedError(0x0800_0022)
            self.running = BUILTIN
        self.seq += 1
        self.saved = self.running
        self.publish()


@pytest.fixture
def robot(server):
    node, client = server
    return RobotDouble(node), client


def _cli(*argv: str) -> int:
    return cli.main(["--interface", "virtual", "--channel", "params-test", *argv])


def test_save_and_restore_write_their_signatures_and_info_reads_the_ids(robot) -> None:
    double, client = robot
    assert client.info() == params.Info(running_id=RUNNING, builtin_id=BUILTIN, saved_id=BUILTIN, saved_seq=0)
    client.save()
    assert double.writes == [(0x1010, 1, b"save")]
    assert struct.unpack("<I", double.writes[0][2])[0] == 0x6576_6173
    assert client.info() == params.Info(RUNNING, BUILTIN, RUNNING, 1)
    client.restore()
    assert double.writes[1] == (0x1011, 1, b"load")
    assert struct.unpack("<I", double.writes[1][2])[0] == 0x6461_6F6C
    assert client.info() == params.Info(BUILTIN, BUILTIN, BUILTIN, 2)


def test_a_save_is_given_a_second_whatever_the_client_timeout(robot) -> None:
    double, client = robot
    quick = params.Client(client.bus, node=127, timeout=0.1)
    double.delay = 0.4  # the answer comes once stored: longer than the client's own timeout
    t0 = time.monotonic()
    quick.save()
    assert time.monotonic() - t0 >= 0.4
    assert double.seq == 1
    silent = params.Client(client.bus, node=5, timeout=0.1)
    t0 = time.monotonic()
    with pytest.raises(params.ParamError, match="save: no answer from node 5 within 1 s"):
        silent.save()
    # At least the second a save is given (how much longer is the machine's scheduling).
    assert time.monotonic() - t0 >= 1.0


def test_save_and_restore_refusals_say_why(robot) -> None:
    double, client = robot
    with pytest.raises(params.ParamError, match=r"save: not stored: wrong signature, or no erased flash slot left "
                       r"\(reset the board while disabled to compact its parameter flash\) \(SDO abort 0x08000020\)"
                       ) as wrong:
        client._command("save", params.STORE_INDEX, b"evas", {})
    assert wrong.value.code == 0x0800_0020
    assert double.writes == [(0x1010, 1, b"evas")]
    double.refusal = 0x0800_0020  # the right signature, no erased slot left
    with pytest.raises(params.ParamError, match=r"compact its parameter flash\) \(SDO abort 0x08000020\)"):
        client.save()
    double.refusal = 0x0606_0000
    with pytest.raises(params.ParamError, match=r"save: the parameter flash failed: not stored, or its read-back "
                       r"differs \(SDO abort 0x06060000\)"):
        client.save()
    double.refusal = 0x0800_0022
    with pytest.raises(params.ParamError, match=r"save: a save is already being stored; try again when it has "
                       r"answered \(SDO abort 0x08000022\)"):
        client.save()
    double.refusal, double.enabled = None, True
    with pytest.raises(params.ParamError, match=r"restore: refused while the robot is enabled \(restore only while "
                       r"disabled\), or while a save is being stored \(SDO abort 0x08000022\)"):
        client.restore()
    # A parameter's 0x0800_0022 keeps its own text.
    assert params._ABORTS[0x0800_0022] == "changes only while disabled"
    assert len(double.writes) == 5
    assert client.info() == params.Info(RUNNING, BUILTIN, BUILTIN, 0)  # nothing stored


def test_the_cli_says_what_save_and_restore_did(robot, capsys) -> None:
    double, _ = robot
    assert _cli("param", "save") == 0
    assert capsys.readouterr().out == "saved: config 0x1a2b as record 1; a restart runs it\n"
    double.enabled = True
    assert _cli("param", "restore") == 1
    err = capsys.readouterr().err
    assert err == ("mecanum-drive param: restore: refused while the robot is enabled (restore only while disabled), "
                   "or while a save is being stored (SDO abort 0x08000022)\n")
    double.enabled = False
    assert _cli("param", "restore") == 0
    assert capsys.readouterr().out == "restored: the built-in config 0x3c4d is in force, saved as record 2; a restart runs it\n"
    assert _cli("param", "save", "gains.kp") == 1
    assert capsys.readouterr().err == "mecanum-drive param: save takes no names: param save\n"
    assert double.seq == 2

    def no_info(index: int, subindex: int, od: object) -> None:
        if index == params.INFO_INDEX:
            raise SdoAbortedError(0x0602_0000)

    double.node.add_read_callback(no_info)  # stored all the same: status 0, and why no ids
    assert _cli("param", "save") == 0
    assert capsys.readouterr().out == ("saved; the ids could not be read after it: info 0x2100:01: no such object "
                                       "(SDO abort 0x06020000)\n")
    assert double.seq == 3


#: Values for the dump, each parameter the first in turn within its range: doubles that
#: float32 does not hold (1.2, 0.1, 1/3, 6.02e-8), that it does (2.5, -0.75, 0); the two
#: stop decelerations (no upper limit) inf and float32's largest. Integers: their range's top
#: (their type's with none) and one below.
REALS = [1.2, 0.1, 1 / 3, 2.5, -0.75, 6.02e-8, 0.0]
FLOAT32_MAX = 3.4028234663852886e38
#: The parameters this configuration does not have: the robot answers 0x0609_0011.
ABSENT = ("odometry.pods[2]",)


@pytest.fixture
def configured(robot):
    """The double with a value in every parameter but the third pod's; a read of those is
    refused as the robot refuses another configuration's."""
    double, client = robot
    node, t = double.node, params.table()
    tops = {0x0001: 1, 0x0005: 255, 0x0007: 4_000_000_000}
    values: dict[str, float] = {}
    for i, p in enumerate(t.values()):
        if p.name.startswith(ABSENT):
            continue
        if p.data_type != 0x0008:
            values[p.name] = max(p.low, min(p.high, tops[p.data_type]) - i % 2)
            continue
        turn = REALS[i % len(REALS):] + REALS[:i % len(REALS)]
        values[p.name] = next(v for v in turn if p.low <= v <= p.high)
    values.update({"gains.kp": 1.2, "limits.stop_linear_decel": math.inf, "limits.stop_angular_decel": FLOAT32_MAX})
    for name, value in values.items():
        node.sdo[t[name].index][t[name].sub].raw = value

    def on_read(index: int, subindex: int, od: object) -> None:
        if 0x2000 <= index < params.INFO_INDEX and subindex not in node.data_store.get(index, {}):
            raise SdoAbortedError(0x0609_0011)

    node.add_read_callback(on_read)
    double.running, double.saved, double.seq = 0xBEEF, 0xBEEF, 7
    double.publish()
    return double, client, values


def test_dump_writes_toml_that_reads_back_as_the_values_set(configured, tmp_path, capsys) -> None:
    _, _, values = configured
    t = params.table()
    assert _cli("param", "dump") == 0
    text = capsys.readouterr().out
    assert text.startswith("# mecanum-drive param dump of node 127: running config 0xbeef, built-in config 0x3c4d; "
                           "a restart runs the saved set 0xbeef (record 7).\n")
    assert '\n"gains.kp" = 1.2\n' in text
    assert '\n"drive.ids[0]" = ' in text
    dumped = tomllib.loads(text)
    assert len(values) == 73 - 5 == len(dumped)
    assert dumped.keys() == values.keys()  # and in the table's order
    assert list(dumped) == [n for n in t if n in values]
    for name, value in values.items():
        if t[name].data_type == 0x0008:
            assert isinstance(dumped[name], float), name
            assert struct.pack("<f", dumped[name]) == struct.pack("<f", value), name  # the same float32
        else:
            assert type(dumped[name]) is int and dumped[name] == value, name
    # Values float32 holds, or whose shortest float32 text is the double's: equal as doubles.
    assert dumped["gains.kp"] == 1.2
    floats = sorted({v for n, v in dumped.items() if t[n].data_type == 0x0008})
    assert floats == [-0.75, 0.0, 6.02e-8, 0.1, 0.33333334, 1.2, 2.5, 3.4028235e38, math.inf]
    assert dumped["timing.command_timeout_ms"] == values["timing.command_timeout_ms"] >= 1000
    # --output: the same TOML in the file; `get` reads the same parameters.
    out = tmp_path / "robot.toml"
    assert _cli("param", "dump", "--output", str(out)) == 0
    assert capsys.readouterr().out == f"dumped 68 parameters of config 0xbeef to {out}\n"
    assert out.read_text(encoding="utf-8") == text
    assert not (tmp_path / "robot.toml.tmp").exists()
    assert _cli("param", "get", "--json") == 0
    got = json.loads(capsys.readouterr().out)
    assert list(got) == list(dumped)


def test_a_failed_dump_leaves_the_old_file_as_it_was(configured, tmp_path, capsys) -> None:
    double, _, _ = configured
    out = tmp_path / "robot.toml"
    out.write_text("# the old dump\n", encoding="utf-8")
    # No robot: nothing answers 0x2100.
    assert cli.main(["--interface", "virtual", "--channel", "params-test-none", "--timeout", "0.2",
                     "param", "dump", "--output", str(out)]) == 1
    assert capsys.readouterr().err == ("mecanum-drive param: info 0x2100:01: no answer from node 127 within 0.2 s\n")
    # A refusal half-way through the parameters.
    t = params.table()
    kv = t["gains.kv"]

    def refuse_kv(index: int, subindex: int, od: object) -> None:
        if (index, subindex) == (kv.index, kv.sub):
            raise SdoAbortedError(0x0800_0000)

    double.node.add_read_callback(refuse_kv)
    assert _cli("param", "dump", "--output", str(out)) == 1
    assert capsys.readouterr().err == "mecanum-drive param: gains.kv: refused (SDO abort 0x08000000)\n"
    assert out.read_text(encoding="utf-8") == "# the old dump\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["robot.toml"]
    # --output is dump's only.
    assert _cli("param", "get", "--output", str(out)) == 1
    assert capsys.readouterr().err == "mecanum-drive param: --output is for dump: param dump --output robot.toml\n"
