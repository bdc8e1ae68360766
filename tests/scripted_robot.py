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
"""

from __future__ import annotations

import dataclasses
import math
import pathlib
import threading
import time

import can
import cantools

ROOT = pathlib.Path(__file__).resolve().parent.parent
DB = cantools.database.load_file(str(ROOT / "dbc" / "mecanum_robot.dbc"), strict=True)
IDS = {m.name: m.frame_id for m in DB.messages}
STATES = {"DISABLED": 0, "ENABLED": 1, "FAULT": 2, "ESTOP": 3}
FAULTS = {str(v): int(k) for k, v in DB.get_message_by_name("STATUS").get_signal_by_name("fault").choices.items()}
#: ODOM_SLIP.source by name: WHEELS, PODS2_GYRO, PODS3, WHEELS_PODS_SILENT.
ODOMETRY_SOURCES = {str(v): int(k)
                    for k, v in DB.get_message_by_name("ODOM_SLIP").get_signal_by_name("source").choices.items()}


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
    ) -> None:
        self.bus = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
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
        for t in self._threads:
            t.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        for t in self._threads:
            t.join(timeout=2)
        self.bus.shutdown()

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
            message = DB.get_message_by_frame_id(msg.arbitration_id)
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
