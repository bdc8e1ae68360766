"""The robot's own parameters as the bridge's ROS 2 parameters, `robot.<name>`
(`ros_parameter_name`): read from the robot over SDO at start and whenever its HEARTBEAT
config_id changes, declared with their ranges (read-only where fixed), and each set forwarded
to the robot, its refusal the set's reason. The bridge's module documentation says what a
user sees; docs/protocol.md, "Parameters", the service. `_SdoTap` shares the bridge's one CAN
bus between the `Robot` and the parameter client (`_SdoPort`): slcan, pcan and gs_usb devices
open once per process, and on SocketCAN one socket and one kernel filter serve both.
"""

from __future__ import annotations

import math
import queue
import re
import threading
import time
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

import can
from rclpy.node import Node
from rclpy.parameter import Parameter

from rcl_interfaces.msg import (  # type: ignore[import-untyped]
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    SetParametersResult,
)

from .. import params as robot_params
from ..robot import Robot

if TYPE_CHECKING:
    from .bridge import Settings

#: The robot's parameters among the node's: `robot.` + the name (`ros_parameter_name`).
ROBOT_PREFIX = "robot."

#: How long a set of a robot parameter waits for the robot's answers, the write's and the
#: read-back's together, s (the robot answers within a control step, 1 ms at 1 kHz); also
#: each read's limit when the bridge reads the parameters.
PARAM_TIMEOUT_S = 0.5

#: After a read of the robot's parameters that got no answer, the next try is this much later, s.
PARAM_RETRY_S = 5.0

#: The EDS's data types as ROS 2 parameter types, and their names.
_ROS_TYPES: dict[int, type] = {0x0001: bool, 0x0005: int, 0x0007: int, 0x0008: float}
_TYPE_NAMES = {0x0001: "BOOLEAN", 0x0005: "UNSIGNED8", 0x0007: "UNSIGNED32", 0x0008: "REAL32"}

#: What each change class lets a set do.
CHANGE_RULES = {
    "live": "live: changes in any state, at the robot's next control step",
    "disabled": "disabled: changes only while the robot is disabled (else refused, SDO abort 0x08000022)",
    "fixed": "fixed: never over CAN (read-only; a new configuration file or image changes it)",
}


def ros_parameter_name(name: str) -> str:
    """The ROS 2 parameter of the robot's parameter `name` (docs/protocol.md, "Parameters"):
    `robot.` + the name with each index `[i]` as `_i`, since ROS 2 parameter names take dots
    (a ROS 2 namespace each) but no brackets: `gains.kp` -> `robot.gains.kp`,
    `odometry.pods[1].x` -> `robot.odometry.pods_1.x`. One-to-one on the robot's table (no
    name of it has `_<digits>` where an index could be)."""
    return ROBOT_PREFIX + re.sub(r"\[(\d+)\]", r"_\1", name)


def ros_value(p: robot_params.Param, value: float) -> bool | int | float:
    """A value of the robot's parameter `p` (as `params.Client.get` gives it) as its ROS 2
    parameter holds it: a bool, an int or a float."""
    kind = _ROS_TYPES[p.data_type]
    if kind is bool:
        return bool(value)
    if kind is int:
        return int(value)
    return float(value)


def robot_parameter_descriptor(p: robot_params.Param, value: bool | int | float) -> ParameterDescriptor:
    """The ROS 2 descriptor of the robot's parameter `p`, whose value is `value`: the EDS's
    description, object, type and change class; its range where the EDS has an upper limit
    (and the value is within it); read-only where the class is fixed."""
    rule = CHANGE_RULES.get(p.change, p.change)
    d = ParameterDescriptor(
        description=(f"{p.doc}. The robot's parameter {p.name}, object 0x{p.index:04X}:{p.sub:02X}, "
                     f"{_TYPE_NAMES.get(p.data_type, hex(p.data_type))}; {rule}"),
        additional_constraints=rule,
        read_only=p.change == "fixed",
    )
    if isinstance(value, bool) or not math.isfinite(p.high) or not p.low <= value <= p.high:
        return d
    if isinstance(value, int):
        d.integer_range = [IntegerRange(from_value=int(p.low), to_value=int(p.high), step=1)]
    else:
        d.floating_point_range = [FloatingPointRange(from_value=p.low, to_value=p.high, step=0.0)]
    d.additional_constraints = f"{rule}; {p.low:g} to {p.high:g}"
    return d


def _refusal(p: robot_params.Param, value: object, err: Exception) -> str:
    """A set's failure as SetParametersResult.reason: the robot's parameter, the value asked and
    the rule (ParamError's text: `timing.status_hz = 20: changes only while disabled (SDO abort
    0x08000022)`)."""
    text = str(err)
    if text.startswith(f"{p.name}: "):
        text = text[len(p.name) + 2:]
    return f"{p.name} = {value!r}: {text}"


class _SdoPort(can.BusABC):
    """The parameter client's side of the bridge's bus (`params.Client` takes a bus): sends go
    out on the bus, and it receives only the robot's SDO responses that `_SdoTap` hands it."""

    def __init__(self, tap: _SdoTap) -> None:
        self._tap = tap
        self._answers: queue.Queue[can.Message] = queue.Queue(maxsize=64)
        self.channel_info = f"{tap.channel_info} (SDO responses)"
        super().__init__(channel=self.channel_info)

    def deliver(self, msg: can.Message) -> None:
        try:
            self._answers.put_nowait(msg)
        except queue.Full:
            pass  # nobody is asking: a stale answer

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        # A request's answer is the next one: answers still queued are a former request's, which
        # gave up waiting for them.
        while True:
            try:
                self._answers.get_nowait()
            except queue.Empty:
                break
        self._tap.send(msg, timeout=timeout if timeout is not None else 0.1)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        try:
            return self._answers.get(timeout=timeout), True
        except queue.Empty:
            return None, True


class _SdoTap(can.BusABC):
    """The bridge's one CAN bus as its `Robot` sees it: each frame received goes to the Robot's
    receiving thread, as from the bus itself, except the robot's SDO responses (0x580 + node),
    which go to `port`, the parameter client's bus. One bus rather than a second one on the
    same channel: an adapter of slcan, pcan, gs_usb and most others opens once per process,
    and on SocketCAN one socket with one kernel filter serves both. Sends from both sides are
    serialised here."""

    def __init__(self, bus: can.BusABC, node: int) -> None:
        self._bus = bus
        self._answer_id = 0x580 + node
        self._send_lock = threading.Lock()
        self.channel_info = bus.channel_info
        super().__init__(channel=bus.channel_info)
        self.port = _SdoPort(self)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        msg = self._bus.recv(timeout)
        if (msg is not None and msg.arbitration_id == self._answer_id and not msg.is_extended_id
                and not msg.is_remote_frame and not msg.is_error_frame):
            self.port.deliver(msg)
            return None, True  # the Robot's recv() waits on for the rest of its timeout
        return msg, True

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        with self._send_lock:
            self._bus.send(msg, timeout)

    def shutdown(self) -> None:
        super().shutdown()
        self.port.shutdown()
        self._bus.shutdown()


class RobotParameters(Node):
    """The bridge's part that serves the robot's parameters (see the module documentation).
    The bridge sets `settings`, `robot`, `log` and `_sdo_port` before it calls
    `_start_robot_parameters`."""

    settings: Settings
    robot: Robot
    log: Any
    _sdo_port: _SdoPort

    def _start_robot_parameters(self) -> None:
        """Reads the robot's parameters and declares them (see the module's documentation),
        then starts the thread that reads them again when the robot's config_id changes."""
        self._param_table = robot_params.table()
        # The declared ones: ROS 2 name -> the robot's parameter.
        self.robot_parameters: dict[str, robot_params.Param] = {}
        # One SDO transfer at a time (the start-up read, the re-reads' thread, the sets).
        self._sdo_lock = threading.Lock()
        self._params_lock = threading.Lock()  # what follows, shared with the re-reads' thread
        self._synced: int | None = None  # the config_id whose values were read last
        self._resync = False  # read again whatever the config_id says
        self._sets = 0  # sets sent to the robot: a read that began before one is stale
        self._pending: tuple[dict[str, float], int] | None = None  # values read, for the executor
        # On the executor's thread only: True while the bridge itself puts the robot's values
        # into the parameters (nothing is sent to the robot), and the values in force after a set.
        self._from_robot = False
        self._in_force: dict[str, bool | int | float] = {}
        self._unreadable: set[str] = set()  # refused reads already reported
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self.add_post_set_parameters_callback(self._after_set_parameters)
        # The re-reads' values are put into the parameters on the executor's thread, as every
        # set: this wakes it for that.
        self._params_guard = self.create_guard_condition(self._apply_robot_values)
        self._params_stop = threading.Event()
        node = self.settings.robot_node
        heartbeat = self.robot.heartbeat
        try:
            values = self._read_robot_parameters()
        except robot_params.ParamError as err:
            self.log.warning(f"the robot's parameters are not declared: {err} (node {node}: robot_node). "
                             "They will be once it answers.")
        else:
            self._synced = heartbeat.config_id if heartbeat is not None else None
            self._put_robot_values(values, "at start-up")
            self.log.info(f"robot.*: {len(self.robot_parameters)} parameters of the robot (node {node}) declared")
        self._params_thread = threading.Thread(target=self._params_loop, name="robot parameters", daemon=True)
        self._params_thread.start()

    def robot_parameters_synced(self) -> int | None:
        """The robot's config_id whose values the robot.* parameters hold, once the latest read
        of them is in the parameters and no other is due (None while one is due or under way,
        and before the first)."""
        with self._params_lock:
            if self._pending is not None or self._resync:
                return None
            return self._synced

    def _read_robot_parameters(self) -> dict[str, float]:
        """Every parameter the robot has, by its name: an SDO upload each; those it answers "not
        in this configuration" (0x0609_0011) are left out, and so, with a warning the first
        time, those it refuses otherwise. Raises ParamError when it does not answer."""
        client = robot_params.Client(self._sdo_port, self.settings.robot_node, PARAM_TIMEOUT_S)
        values = {}
        for p in self._param_table.values():
            if self._params_stop.is_set():
                raise robot_params.ParamError("the bridge is closing")
            try:
                with self._sdo_lock:
                    values[p.name] = client.get(p)
            except robot_params.ParamError as err:
                if err.code is None:
                    raise
                if err.code != robot_params.NOT_IN_CONFIGURATION and p.name not in self._unreadable:
                    self._unreadable.add(p.name)
                    self.log.warning(f"{ros_parameter_name(p.name)} not declared: the robot refused to read it: {err}")
        return values

    def _put_robot_values(self, values: Mapping[str, float], why: str, log: bool = True) -> None:
        """The robot's values into the parameters, without sending them back: declares those not
        declared yet, updates those that differ. On the executor's thread (or before it spins)."""
        self._from_robot = True
        try:
            for name, raw in values.items():
                p = self._param_table[name]
                ros_name, value = ros_parameter_name(name), ros_value(p, raw)
                if ros_name not in self.robot_parameters:
                    try:
                        self.declare_parameter(ros_name, value, robot_parameter_descriptor(p, value),
                                               ignore_override=True)
                    except Exception as err:  # noqa: BLE001 - rclpy's exceptions for a value it refuses
                        self.log.warning(f"{ros_name} = {value!r} not declared: {err}")
                        continue
                    self.robot_parameters[ros_name] = p
                    continue
                old = self.get_parameter(ros_name).value
                if old == value and type(old) is type(value):
                    continue
                # A fixed parameter changes only when the robot runs another configuration; its
                # descriptor (the one rclpy keeps) lets it while the robot's value goes in.
                descriptor = self.describe_parameter(ros_name)
                read_only, descriptor.read_only = descriptor.read_only, False
                try:
                    result = self.set_parameters([Parameter(ros_name, value=value)])[0]  # type: ignore[no-untyped-call]
                finally:
                    descriptor.read_only = read_only
                if result.successful and log:
                    self.log.info(f"{ros_name}: {old!r} -> {value!r} ({why})")
                elif not result.successful:
                    self.log.warning(f"{ros_name}: the robot's {value!r} not taken ({why}): {result.reason}")
        finally:
            self._from_robot = False

    def _params_loop(self) -> None:
        """The re-reads' thread: reads the parameters again when the robot's HEARTBEAT says
        another configuration is in force (or a read is due: none yet, or a failed set), and
        hands the values to the executor. Polls the latest HEARTBEAT every status period."""
        next_try = -math.inf
        failing = False
        while not self._params_stop.wait(1.0 / self.settings.status_rate):
            heartbeat = self.robot.heartbeat
            if heartbeat is None or time.monotonic() < next_try:
                continue
            with self._params_lock:
                if heartbeat.config_id == self._synced and not self._resync:
                    continue
                self._resync = False
                sets = self._sets
            try:
                values = self._read_robot_parameters()
            except robot_params.ParamError as err:
                if self._params_stop.is_set():
                    return
                next_try = time.monotonic() + PARAM_RETRY_S
                if not failing:
                    self.log.warning(f"the robot's parameters could not be read: {err}; trying again every "
                                     f"{PARAM_RETRY_S:g} s")
                failing = True
                continue
            except Exception:  # noqa: BLE001 - the bus shut down under a read: closing
                if self._params_stop.is_set():
                    return
                raise
            failing = False
            with self._params_lock:
                self._synced = heartbeat.config_id
                self._pending = (values, sets)
            self._params_guard.trigger()  # type: ignore[no-untyped-call]

    def _apply_robot_values(self) -> None:
        """On the executor's thread: the values the re-reads' thread read into the parameters,
        unless a set went to the robot since that read began (then it reads again)."""
        with self._params_lock:
            pending, self._pending = self._pending, None
            if pending is None:
                return
            values, sets = pending
            if sets != self._sets:
                self._resync = True
                return
        heartbeat = self.robot.heartbeat
        config = f"config 0x{heartbeat.config_id:04x}" if heartbeat is not None else "read again"
        self._put_robot_values(values, f"changed on the robot, {config}")

    def _forward(self, p: robot_params.Param, value: bool | int | float) -> bool | int | float:
        """Writes `value` to the robot's parameter `p` and reads it back, within PARAM_TIMEOUT_S
        in all: the value in force. Raises ParamError (the robot's refusal, or no answer) or
        ValueError (a value its type cannot hold)."""
        if not self.robot.responding:
            raise robot_params.ParamError(f"{p.name}: not sent: the robot sends no HEARTBEAT (is it on the bus?)")
        deadline = time.monotonic() + PARAM_TIMEOUT_S
        node = self.settings.robot_node
        try:
            with self._sdo_lock:
                robot_params.Client(self._sdo_port, node, PARAM_TIMEOUT_S).set(p, float(value))
                try:
                    left = max(0.05, deadline - time.monotonic())
                    return ros_value(p, robot_params.Client(self._sdo_port, node, left).get(p))
                except robot_params.ParamError as err:
                    # Taken, but the read-back got no answer: the value as the robot's type holds it.
                    self.log.warning(f"{ros_parameter_name(p.name)}: set, but not read back ({err})")
                    return ros_value(p, p.decode(p.encode(float(value))[0]))
        finally:
            with self._params_lock:
                self._sets += 1  # after it, so that a read that began before the set is stale

    def _on_set_parameters(self, parameters: list[Parameter]) -> Any:
        """rclpy's on-set callback: a set of a robot.* parameter goes to the robot and succeeds
        only if the robot takes it (the values read back wait in `_in_force` for
        `_after_set_parameters`)."""
        if self._from_robot:
            return SetParametersResult(successful=True)
        sent = False
        for given in parameters:
            p = self.robot_parameters.get(given.name)
            if p is None:
                continue
            try:
                self._in_force[given.name] = self._forward(p, given.value)
                sent = True
            except (robot_params.ParamError, ValueError) as err:
                self._in_force.clear()
                if sent:
                    with self._params_lock:
                        self._resync = True  # those sent before it are in force on the robot
                reason = _refusal(p, given.value, err)
                self.log.warning(f"{given.name}: not set: {reason}")
                return SetParametersResult(successful=False, reason=reason)
        return SetParametersResult(successful=True)

    def _after_set_parameters(self, parameters: list[Parameter]) -> None:
        """rclpy's post-set callback: where the robot holds another value than the one asked (a
        REAL32's float32), the parameter takes the robot's."""
        if self._from_robot:
            return
        in_force = [(given, self._in_force.pop(given.name)) for given in parameters if given.name in self._in_force]
        self._in_force.clear()
        for given, value in in_force:
            self.log.info(f"{given.name} = {value!r} set on the robot"
                          + ("" if value == given.value else f" (asked {given.value!r})"))
        differ = {self.robot_parameters[g.name].name: float(v) for g, v in in_force
                  if v != g.value or type(v) is not type(g.value)}
        if differ:
            self._put_robot_values(differ, "the value in force after the set", log=False)
