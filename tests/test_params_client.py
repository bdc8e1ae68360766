"""The package's parameter client (`mecanum_drive.params`, `mecanum-drive param`) against
python-canopen's SDO server built from the robot's EDS, on python-can's virtual bus: the
table it reads, reads and writes of each type, and a refusal named. (Against the robot
itself: the core's tests in crates/firmware/tests/control/params.rs.)"""

from __future__ import annotations

import math

import can
import canopen
import pytest

from mecanum_drive import params


@pytest.fixture
def server():
    """A CANopen node 127 serving the robot's object dictionary, with the DJI example's
    values of the parameters the tests read; and a client on the same virtual bus."""
    network = canopen.Network()
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
