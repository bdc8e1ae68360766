"""A scripted robot on python-can's virtual bus, for the Python package's unit tests.

It plays the firmware's side of the robot protocol, encoded by cantools from
dbc/mecanum_robot.dbc: HEARTBEAT and STATUS every `period_s` (and STATUS at once on
STATUS_REQ, each followed by STATUS_COUNTERS), ODOM_POSITION and ODOM_VELOCITY every
`odom_period_s` integrating the last accepted twist (and after them ODOM_SLIP, as a robot
configured with tracking pods sends it, when `odometry_source` is set), the enable latch (MODE_CMD), the e-stop
latch, a command watchdog that a twist repeating the last accepted `seq` does not feed, and a
fault on demand. It records every frame it receives with its arrival time, so a test can
measure what the package sent and when. It is a test double of the firmware's behaviour on
the bus, not of its control; the real firmware is tested on vcan0 (tests/test_vcan_*.py).

With `parameters=True` it also serves the robot's parameters as the firmware does
(docs/protocol.md, "Parameters"): python-canopen's `LocalNode` built from the robot's EDS on
node 127 of the same channel, holding `PARAMETER_VALUES` (config/dji_m3508_pods2_gyro.toml:
a standard layout and two pods, so the general layout's wheels and the third pod are absent,
read as 0x0609_0011), and refusing writes by the robot's rules: fixed 0x0601_0002, disabled
while ENABLED 0x0800_0022, NaN 0x0609_0030, above or below the EDS's range 0x0609_0031 /
0x0609_0032. A write it takes changes HEARTBEAT.config_id, as the firmware's does.
"""

from __future__ import annotations

import dataclasses
import math
import pathlib
import threading
import time
from typing import Any

import can
import cantools

ROOT = pathlib.Path(__file__).resolve().parent.parent
DB = cantools.database.load_file(str(ROOT / "dbc" / "mecanum_robot.dbc"), strict=True)
IDS = {m.name: m.frame_id for m in DB.messages}
BY_ID = {m.frame_id: m for m in DB.messages}
STATES = {"DISABLED": 0, "ENABLED": 1, "FAULT": 2, "ESTOP": 3}
FAULTS = {str(v): int(k) for k, v in DB.get_message_by_name("STATUS").get_signal_by_name("fault").choices.items()}
#: ODOM_SLIP.source by name: WHEELS, PODS2_GYRO, PODS3, WHEELS_PODS_SILENT.
ODOMETRY_SOURCES = {str(v): int(k)
                    for k, v in DB.get_message_by_name("ODOM_SLIP").get_signal_by_name("source").choices.items()}

#: The parameters of config/dji_m3508_pods2_gyro.toml as the robot serves them (the DJI example
#: with a gyro and two pods); the others (`ABSENT_PARAMETERS`) this configuration does not have.
PARAMETER_VALUES: dict[str, float] = {
    "geometry.lx": 0.20, "geometry.ly": 0.18, "geometry.wheel_radius": 0.076,
    "geometry.forward_effectiveness": 1.0, "geometry.lateral_effectiveness": 1.0, "geometry.yaw_effectiveness": 1.0,
    "limits.max_linear_speed": 3.0, "limits.max_angular_speed": 6.0, "limits.max_linear_accel": 4.0,
    "limits.max_angular_accel": 12.0, "limits.stop_linear_decel": 8.0, "limits.stop_angular_decel": 24.0,
    "limits.max_wheel_speed": 45.0, "limits.max_current": 16.0,
    "gains.kp": 1.2, "gains.ki": 30.0, "gains.kv": 0.0,
    "timing.control_hz": 1000, "timing.odometry_hz": 100, "timing.status_hz": 10, "timing.setpoint_hz": 200,
    "timing.command_timeout_ms": 100, "timing.boot_timeout_ms": 1000, "timing.stale_periods": 3,
    "odometry.heading_source": 1, "odometry.gyro_timeout_ms": 50, "odometry.gyro_standstill_ms": 50,
    "odometry.gyro_bias_estimation": 1, "odometry.source": 1, "odometry.pod_timeout_ms": 50, "odometry.pod_count": 2,
    "drive.protocol": 0, "drive.gear_ratio": 3591 / 187, "drive.ids[0]": 1, "drive.ids[1]": 2, "drive.ids[2]": 3,
    "drive.ids[3]": 4, "drive.inverted": 0b1010,
    "odometry.pods[0].x": 0.0, "odometry.pods[0].y": 0.11, "odometry.pods[0].direction_deg": 0.0,
    "odometry.pods[0].radius": 0.024, "odometry.pods[0].counts_per_turn": 2000,
    "odometry.pods[1].x": 0.12, "odometry.pods[1].y": 0.0, "odometry.pods[1].direction_deg": 90.0,
    "odometry.pods[1].radius": 0.024, "odometry.pods[1].counts_per_turn": 2000,
}
ABSENT_PARAMETERS = ("geometry.wheels[", "odometry.pods[2]")


@dataclasses.dataclass(frozen=True)
class Received:
    """A frame the scripted robot received: arrival time (time.monotonic()), name, signals."""

    t: float
    name: str
    signals: dict


class ScriptedRobot:
    """The robot's side of the protocol on virtual channel `channel`. Use as a context manager."""

    def __init__(
        self,
        channel: str,
        *,
        period_s: float = 0.1,
        odom_period_s: float = 0.01,
        command_timeout_s: float = 0.1,
        protocol_version: int | None = None,
        config_id: int = 0,
        odometry_source: str | None = None,
        slip: tuple[float, float, float] = (0.0, 0.0, 0.0),
        parameters: bool = False,
        node: int = 127,
    ) -> None:
        self.bus = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
        self.channel = channel
        self.node_id = node
        # The SDO server (`parameters`): python-canopen's network and node, made on __enter__.
        self.params_network: Any = None
        self.params_node: Any = None
        self.serve_parameters = parameters
        self.param_writes: list[tuple[str, float]] = []  # the writes it took: (name, value)
        self.param_refusals: list[tuple[str, float, int]] = []  # those it refused: (name, value, abort code)
        self.period_s = period_s
        self.odom_period_s = odom_period_s
        self.command_timeout_s = command_timeout_s
        self.protocol_version = protocol_version if protocol_version is not None else _dbc_version()
        self.config_id = config_id
        self.state = "DISABLED"
        self.fault = "NONE"
        self.twist = (0.0, 0.0, 0.0)
        self.pose = [0.0, 0.0, 0.0]
        self.last_command: float | None = None
        self.last_seq: int | None = None
        self.repeated_seq = 0
        self.heading_source = 0  # STATUS.heading_source: 0 WHEELS, 1 GYRO, 2 WHEELS_GYRO_SILENT
        # ODOM_SLIP.source by name (PODS2_GYRO, PODS3, WHEELS_PODS_SILENT), sent with the slip
        # (vx, vy, wz) after every ODOM_VELOCITY; None: no ODOM_SLIP (a robot without pods).
        # set_odometry_source changes both while the robot runs.
        self.odometry_source = odometry_source
        self.slip = slip
        self.received: list[Received] = []
        self.heartbeats = True  # False: the robot goes silent
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._threads = [
            threading.Thread(target=self._receive, daemon=True),
            threading.Thread(target=self._transmit, daemon=True),
        ]

    def __enter__(self) -> ScriptedRobot:
        if self.serve_parameters:
            self._start_parameters()
        for t in self._threads:
            t.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        for t in self._threads:
            t.join(timeout=2)
        if self.params_network is not None:
            self.params_network.disconnect()
        self.bus.shutdown()

    # --- the parameters (SDO) ----------------------------------------------------------------

    def _start_parameters(self) -> None:
        import canopen
        from mecanum_drive import params

        self.param_table = params.table()
        self._by_object = {(p.index, p.sub): p for p in self.param_table.values()}
        network = canopen.Network()
        network.NOTIFIER_CYCLE = 0.05  # its thread's wait: the teardown's, 1 s by default
        network.connect(interface="virtual", channel=self.channel, receive_own_messages=False,
                        can_filters=[{"can_id": 0x600 + self.node_id, "can_mask": 0x7FF, "extended": False}])
        node = canopen.LocalNode(self.node_id, str(params.eds_path()))
        network.add_node(node)
        self.params_network, self.params_node = network, node
        for name, value in PARAMETER_VALUES.items():
            self.write_parameter(name, value)
        node.add_read_callback(self._on_param_read)
        node.add_write_callback(self._on_param_write)

    def write_parameter(self, name: str, value: float) -> None:
        """Puts `value` into the robot's parameter `name` as another client's write that the
        robot took leaves it: straight into the node's store, without the rules or a new
        config_id (set `config_id` for that)."""
        p = self.param_table[name]
        raw = self.params_node.object_dictionary[p.index][p.sub].encode_raw(
            value if p.data_type == 0x0008 else int(value))
        self.params_node.data_store.setdefault(p.index, {})[p.sub] = raw

    def parameter(self, name: str) -> float:
        """The robot's value of parameter `name` (as the robot's type holds it)."""
        p = self.param_table[name]
        return p.decode(self.params_node.data_store[p.index][p.sub])

    def _on_param_read(self, index: int, subindex: int, od: object) -> None:
        from canopen.sdo import SdoAbortedError

        p = self._by_object.get((index, subindex))
        if p is not None and p.name.startswith(ABSENT_PARAMETERS):
            raise SdoAbortedError(0x0609_0011)

    def _on_param_write(self, index: int, subindex: int, od: object, data: bytes) -> None:
        from canopen.sdo import SdoAbortedError

        p = self._by_object.get((index, subindex))
        if p is None:
            return  # not a parameter: nothing of the robot's to emulate
        value = p.decode(bytes(data))
        with self._lock:
            code = None
            if p.name.startswith(ABSENT_PARAMETERS):
                code = 0x0609_0011
            elif p.change == "fixed":
                code = 0x0601_0002
            elif p.change == "disabled" and self.state == "ENABLED":
                code = 0x0800_0022
            elif math.isnan(value):
                code = 0x0609_0030
            elif value > p.high:
                code = 0x0609_0031
            elif value < p.low:
                code = 0x0609_0032
            if code is not None:
                self.param_refusals.append((p.name, value, code))
                raise SdoAbortedError(code)
            # Taken (python-canopen stores it once this returns, before it answers): another
            # configuration is in force, with another id.
            self.param_writes.append((p.name, value))
            self.config_id = (self.config_id + 1) & 0xFFFF

    def frames(self, name: str) -> list[Received]:
        with self._lock:
            return [r for r in self.received if r.name == name]

    def set_odometry_source(self, source: str | None, slip: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> None:
        """ODOM_SLIP's source (by name) and slip from the next odometry sample on, together;
        None: no more ODOM_SLIP."""
        with self._lock:
            self.odometry_source, self.slip = source, slip

    def set_fault(self, fault: str) -> None:
        with self._lock:
            self.state, self.fault, self.twist = "FAULT", fault, (0.0, 0.0, 0.0)

    def _send(self, name: str, **signals: float) -> None:
        message = DB.get_message_by_name(name)
        self.bus.send(can.Message(arbitration_id=message.frame_id, data=message.encode(signals), is_extended_id=False))

    def _status(self) -> None:
        self._send("STATUS", state=STATES[self.state], fault=FAULTS[self.fault], rx_errors=0, unknown_ids=0,
                   motors_online=0x0F, heading_source=self.heading_source, seq=0)
        self._send("STATUS_COUNTERS", repeated_seq=min(self.repeated_seq, 0xFFFF), wrong_dlc=0, out_of_range=0,
                   non_finite=0)

    def _receive(self) -> None:
        while not self._stop.is_set():
            msg = self.bus.recv(timeout=0.02)
            if msg is None:
                continue
            now = time.monotonic()
            if msg.arbitration_id not in BY_ID:
                continue  # not the robot protocol's (the parameters' SDO, python-canopen's)
            message = BY_ID[msg.arbitration_id]
            signals = message.decode(bytes(msg.data), decode_choices=False) if message.signals else {}
            with self._lock:
                self.received.append(Received(now, message.name, signals))
                if message.name == "TWIST_CMD" and self.state == "ENABLED":
                    # Protocol version 3: a repeat of the last accepted seq is not a command.
                    if signals["seq"] == self.last_seq:
                        self.repeated_seq += 1
                    else:
                        self.last_seq = signals["seq"]
                        self.twist = (signals["vx"], signals["vy"], signals["wz"])
                        self.last_command = now
                elif message.name == "MODE_CMD":
                    request = signals["request"]
                    if request == 1 and self.state == "DISABLED":
                        self.state, self.fault, self.last_command, self.last_seq = "ENABLED", "NONE", now, None
                    elif request == 0 and self.state == "ENABLED":
                        self.state, self.twist = "DISABLED", (0.0, 0.0, 0.0)
                    elif request == 2 and self.state in ("FAULT", "ESTOP"):
                        self.state, self.fault = "DISABLED", "NONE"
                elif message.name == "ESTOP" and signals["magic"] == 0xE5:
                    self.state, self.twist = "ESTOP", (0.0, 0.0, 0.0)
                if message.name == "STATUS_REQ":
                    self._status()

    def _transmit(self) -> None:
        start = time.monotonic()
        next_status = next_odom = start
        while not self._stop.is_set():
            now = time.monotonic()
            with self._lock:
                if self.state == "ENABLED" and self.last_command is not None and now - self.last_command > self.command_timeout_s:
                    self.state, self.fault, self.twist = "DISABLED", "WATCHDOG", (0.0, 0.0, 0.0)
                if now >= next_odom:
                    vx, vy, wz = self.twist
                    c, s = math.cos(self.pose[2]), math.sin(self.pose[2])
                    dt = self.odom_period_s
                    self.pose[0] += (vx * c - vy * s) * dt
                    self.pose[1] += (vx * s + vy * c) * dt
                    self.pose[2] = (self.pose[2] + wz * dt + math.pi) % (2 * math.pi) - math.pi
                    self._send("ODOM_POSITION", x=self.pose[0], y=self.pose[1])
                    self._send("ODOM_VELOCITY", heading=self.pose[2], vx=vx, vy=vy, wz=wz)
                    if self.odometry_source is not None:
                        self._send("ODOM_SLIP", vx=self.slip[0], vy=self.slip[1], wz=self.slip[2],
                                   source=ODOMETRY_SOURCES[self.odometry_source], reserved=0)
                    next_odom += self.odom_period_s
                if now >= next_status:
                    if self.heartbeats:
                        self._status()
                        self._send("HEARTBEAT", uptime_ms=int((now - start) * 1000), state=STATES[self.state],
                                   protocol_version=self.protocol_version, config_id=self.config_id)
                    next_status += self.period_s
            time.sleep(0.002)


def _dbc_version() -> int:
    import re

    text = (ROOT / "dbc" / "mecanum_robot.dbc").read_text()
    return int(re.search(r'CM_ "Mecanum robot CAN protocol, version (\d+)', text).group(1))
